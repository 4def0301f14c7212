//! The supervisor given a slave's I/O map, against the controller's own MEB
//! front end answering through that map: a map with gaps is read and
//! written in runs of neighbouring addresses, the words land in the loop's
//! inputs in the protocol page's order, and a client's write in the default
//! map is put where the slave has it.

use nodes::firmware::{EvController, EvControllerConfig, Framing, MebMap, SlaveFrontend};
use nodes::master::{
    ForwardError, MebLayout, Protocol, SetPointStep, SlaveLoopConfig, Supervisor, SupervisorConfig,
    TranslateError,
};
use nodes::node::{MAX_FRAME, Node};
use protocols::meb::{MebCmd, MebRepr};
use protocols::time::{SimDuration, SimTime};

/// Inputs in the gaps, the switches in words 3 and 5, VEL at SA 04, SOC at FA 04.
fn gapped_map() -> MebMap {
    let mut map = MebMap::default();
    map.clear_block("EA");
    for (name, address) in [
        ("V2", 0),
        ("I", 1),
        ("V1", 2),
        ("RPM_M", 7),
        ("RPM_L", 8),
        ("LDR", 9),
    ] {
        map.place("EA", name, address, None).unwrap();
    }
    map.clear_block("SA");
    map.place("SA", "VEL", 4, None).unwrap();
    map.clear_block("SD");
    for (name, bit) in [("EN", 0), ("BRK", 1), ("PRO", 2), ("DES", 3), ("FR", 4)] {
        map.place("SD", name, 3, Some(bit)).unwrap();
    }
    map.place("SD", "CHG", 5, Some(0)).unwrap();
    map.clear_block("FA");
    map.place("FA", "SOC", 4, None).unwrap();
    map
}

/// One exchange: the supervisor's next request (waking it as it asks) and
/// the front end's reply handed back 1 ms later. Returns the request.
pub(crate) fn exchange(
    master: &mut Supervisor,
    slave: &mut SlaveFrontend,
    controller: &mut EvController,
    now: &mut SimTime,
) -> MebRepr {
    let mut buf = [0u8; MAX_FRAME];
    for _ in 0..100 {
        if let Some(n) = master.poll_transmit(*now, &mut buf) {
            master.transmit_done(*now);
            let request = MebRepr::parse(&buf[..n]).expect("a well-formed request");
            slave.handle_bytes(controller.image_mut(), *now, &buf[..n]);
            let mut reply = [0u8; MAX_FRAME];
            *now += SimDuration::from_millis(1);
            if let Some(m) = slave.poll_transmit(&mut reply) {
                master.handle_bytes(*now, &reply[..m]);
            }
            return request;
        }
        *now = master.poll_timeout().expect("a next instant");
        master.handle_timeout(*now);
    }
    panic!("no request");
}

#[test]
fn a_mapped_slave_is_read_and_written_in_runs_and_its_words_land_in_the_default_order() {
    let map = gapped_map();
    let mut slave_loop = SlaveLoopConfig::new(1);
    slave_loop.set_points = vec![SetPointStep {
        at: SimTime::ZERO,
        rpm: 1000.0,
    }];
    let mut config = SupervisorConfig::new(Protocol::Meb, vec![slave_loop]);
    config.layout = MebLayout::from_map(&map);
    config.status_every = 1;
    let mut master = Supervisor::new(config).unwrap();
    let mut controller = EvController::new(EvControllerConfig::default());
    controller.image_mut().inputs = [11, 22, 33, 44, 55, 66];
    let mut slave = SlaveFrontend::new(Framing::Meb, 1);
    slave.set_meb_map(Some(map));
    let mut now = SimTime::ZERO;
    let mut requests = Vec::new();
    for _ in 0..10 {
        let r = exchange(&mut master, &mut slave, &mut controller, &mut now);
        requests.push((r.cmd, r.addr, r.cnt, r.data.as_slice().to_vec()));
    }
    let vel = master.loop_state(1).unwrap().output;
    assert_eq!(
        requests,
        vec![
            // Start-up: module enabled, brake released, in SD 03 and SD 05.
            (MebCmd::SD, 3, 1, vec![0x000E]),
            (MebCmd::SD, 5, 1, vec![0x0001]),
            (MebCmd::EA, 0, 3, vec![]),
            (MebCmd::EA, 7, 3, vec![]),
            (MebCmd::SA, 4, 1, vec![vel]),
            // The status round: ED 00, SOC apart from ERRS, then STATUS.
            (MebCmd::ED, 0, 1, vec![]),
            (MebCmd::FA, 4, 1, vec![]),
            (MebCmd::FA, 1, 1, vec![]),
            (MebCmd::FD, 0, 1, vec![]),
            (MebCmd::EA, 0, 3, vec![]),
        ]
    );
    let state = master.loop_state(1).unwrap();
    assert_eq!(state.inputs, [11, 22, 33, 44, 55, 66]);
    assert_eq!(state.measured_rpm, 44.0, "RPM_M, read at EA 07");
    assert_eq!(state.counters.exceptions, 0, "{:?}", state.counters);
    assert_eq!(state.vel_written, Some(vel));
    assert_eq!(controller.image().stored.sd0 & 0x1F, 0x000E);
    assert!(state.status.flags.is_some() && state.status.status.is_some());

    // A client's brake (default SD 00 bit 1 low) goes to SD 03; a write
    // of both default SD words would need SD 03 to 05, and SD 04 is empty.
    master
        .forward_write(now, 1, MebCmd::SD, 0, &[0x000C])
        .unwrap();
    let r = exchange(&mut master, &mut slave, &mut controller, &mut now);
    assert_eq!(
        (r.cmd, r.addr, r.data.as_slice()),
        (MebCmd::SD, 3, &[0x000C][..])
    );
    assert_eq!(
        controller.image().stored.sd0 & 0x1F,
        0x000C,
        "the brake applied"
    );
    assert_eq!(
        master.forward_write(now, 1, MebCmd::SD, 0, &[0x000E, 0x0001]),
        Err(ForwardError::Map(TranslateError::Scattered))
    );
}

#[test]
fn a_map_without_the_measured_speed_or_vel_is_refused_and_modbus_takes_no_map() {
    let mut map = MebMap::default();
    map.clear_block("EA");
    map.place("EA", "V1", 0, None).unwrap();
    let mut config = SupervisorConfig::new(Protocol::Meb, vec![SlaveLoopConfig::new(1)]);
    config.layout = MebLayout::from_map(&map);
    let e = Supervisor::new(config.clone()).unwrap_err().to_string();
    assert_eq!(
        e,
        "the I/O map places no RPM_M, which the supervisor measures the speed with"
    );
    config.protocol = Protocol::ModbusRtu;
    let e = Supervisor::new(config).unwrap_err().to_string();
    assert!(e.contains("Modbus RTU"), "{e}");
}

/// A remote client that writes VEL back to back (two writes always waiting)
/// does not starve the supervisor's own polls: each forwarded write goes
/// out between two of them, and the inputs and the status word are still
/// read.
#[test]
fn forwarded_writes_back_to_back_leave_the_polls_their_turn() {
    let mut config = SupervisorConfig::new(Protocol::Meb, vec![SlaveLoopConfig::new(1)]);
    config.status_every = 1;
    let mut master = Supervisor::new(config).unwrap();
    let mut controller = EvController::new(EvControllerConfig::default());
    let mut slave = SlaveFrontend::new(Framing::Meb, 1);
    let mut now = SimTime::ZERO;
    // Start-up and a first cycle.
    for _ in 0..8 {
        exchange(&mut master, &mut slave, &mut controller, &mut now);
    }
    // The client's writes carry 3000 and up; the loop's own VEL is its PI
    // output (0 at a set point of 0).
    let mut seen = Vec::new();
    for n in 0..40u16 {
        while master.forwards_in_flight() < 2 {
            master
                .forward_write(now, 1, MebCmd::SA, 0, &[3000 + n])
                .unwrap();
        }
        let r = exchange(&mut master, &mut slave, &mut controller, &mut now);
        let client = r.cmd == MebCmd::SA && r.data.as_slice().first() >= Some(&3000);
        seen.push(if client {
            "client"
        } else if r.cmd == MebCmd::EA {
            "EA"
        } else if r.cmd == MebCmd::FD {
            "FD"
        } else {
            "another poll"
        });
    }
    let count = |what: &str| seen.iter().filter(|&&c| c == what).count();
    assert!(
        count("client") >= 15,
        "the client's writes go out: {seen:?}"
    );
    assert!(count("EA") >= 3, "the inputs are still read: {seen:?}");
    assert!(count("FD") >= 3, "the status word is still read: {seen:?}");
    // Never two of the client's writes in a row while a poll waits.
    assert!(
        seen.windows(2).all(|w| w != ["client", "client"]),
        "{seen:?}"
    );
}
