//! The EV controller driving the real plant (`PlantParams::vemodule()`) at
//! 1 ms loop ticks, commanded over MEB: the wheel turns, both rpm estimates
//! agree with the true wheel speed where the sensors allow it, and a trip
//! latches and clears as `docs/protocols/meb.md` says.

use nodes::firmware::{EvController, EvControllerConfig, status};
use nodes::node::{Firmware, MAX_FRAME, Node};
use plant::{Actuators, EvModule, PlantParams, Sensors};
use protocols::meb::{MebCmd, MebRepr};
use protocols::time::{SimDuration, SimTime};

const TICK: SimDuration = SimDuration::from_millis(1);

/// A module and its controller, stepped together one loop period at a time.
struct Bench {
    module: EvModule,
    controller: EvController,
    now: SimTime,
    actuators: Actuators,
}

impl Bench {
    fn new(params: &PlantParams) -> Self {
        let module = EvModule::new(params, 7);
        let mut controller = EvController::new(EvControllerConfig::for_plant(params));
        let actuators = controller.loop_tick(SimTime::ZERO, module.sensors());
        Self {
            module,
            controller,
            now: SimTime::ZERO,
            actuators,
        }
    }

    fn tick(&mut self) -> Sensors {
        let sensors = *self.module.step(TICK.as_secs_f64(), &self.actuators);
        self.now += TICK;
        self.actuators = self.controller.loop_tick(self.now, &sensors);
        sensors
    }

    fn run(&mut self, ms: u64) -> Sensors {
        let mut last = *self.module.sensors();
        for _ in 0..ms {
            last = self.tick();
        }
        last
    }

    /// Sends an MEB request (FCS and terminator added) and returns the reply.
    fn meb(&mut self, body: &str) -> Option<MebRepr> {
        let fcs = body.bytes().fold(0u8, |acc, b| acc ^ b);
        let frame = format!("{body}{fcs:02X}*\n");
        self.controller.handle_bytes(self.now, frame.as_bytes());
        let mut buf = [0u8; MAX_FRAME];
        let len = self.controller.poll_transmit(self.now, &mut buf)?;
        Some(MebRepr::parse(&buf[..len]).expect("reply is well formed"))
    }

    fn write(&mut self, body: &str) {
        let reply = self.meb(body).expect("a reply");
        assert_ne!(reply.cmd, MebCmd::ER, "{body} refused: {reply:?}");
    }

    fn read(&mut self, body: &str) -> Vec<u16> {
        let reply = self.meb(body).expect("a reply");
        assert_ne!(reply.cmd, MebCmd::ER, "{body} refused: {reply:?}");
        reply.data.as_slice().to_vec()
    }

    /// RPM_M and RPM_L.
    fn rpms(&mut self) -> (f64, f64) {
        let words = self.read("@01EA0302");
        (f64::from(words[0]), f64::from(words[1]))
    }

    /// Mean true wheel rpm and mean RPM_M, RPM_L read every 10 ms over `ms`.
    fn measure(&mut self, ms: u64) -> (f64, f64, f64) {
        let (mut truth, mut hall, mut light, mut n) = (0.0, 0.0, 0.0, 0.0);
        for _ in 0..ms / 10 {
            let s = self.run(10);
            let (m, l) = self.rpms();
            truth += s.wheel_rpm.abs();
            hall += m;
            light += l;
            n += 1.0;
        }
        (truth / n, hall / n, light / n)
    }
}

/// Enables the module (EN applied, brake released, boost and discharge off,
/// clockwise) with VEL = `vel` counts.
fn start(bench: &mut Bench, vel: u16) {
    bench.write(&format!("@01SA0001{vel:04X}"));
    bench.write("@01SD0001000E");
}

#[test]
fn vel_2048_turns_the_wheel_and_rpm_m_tracks_it() {
    let params = PlantParams::vemodule();
    let mut bench = Bench::new(&params);
    bench.run(100);
    assert_eq!(bench.module.sensors().wheel_rpm, 0.0, "off at power-up");
    start(&mut bench, 2048);
    // The write is stored at once and applied at the next tick.
    assert!(!bench.actuators.enable);
    bench.tick();
    assert!(bench.actuators.enable);
    assert!((bench.actuators.vel_volts - 2048.0 / 4095.0 * 5.0).abs() < 1e-12);
    bench.run(4000);
    let (truth, hall, _) = bench.measure(1000);
    assert!(bench.module.sensors().wheel_rpm > 0.0, "clockwise");
    eprintln!("VEL 2048: wheel {truth:.1} rpm, RPM_M {hall:.1}");
    assert!(truth > 500.0, "the wheel turns: {truth}");
    assert!(
        (hall - truth).abs() < 0.01 * truth,
        "RPM_M {hall} vs {truth}"
    );
    let status = bench.read("@01FD0001")[0];
    assert_eq!(status & status::STALLED, 0);
    assert_eq!(status & status::CCW, 0, "FR low: clockwise");
}

#[test]
fn rpm_l_follows_the_wheel_below_the_light_limit_and_misses_dips_above() {
    let params = PlantParams::vemodule();
    let config = EvControllerConfig::for_plant(&params);
    let light = &params.light;
    let threshold_volts =
        f64::from(config.light.threshold_counts) / 4096.0 * light.adc_reference_volts;
    let limit = plant::light::fixed_threshold_max_rpm(light, threshold_volts);
    eprintln!("light limit {limit:.1} rpm at {threshold_volts:.3} V");

    // 80 % of the limit: every dip reaches the threshold.
    let mut bench = Bench::new(&params);
    start(&mut bench, 200);
    bench.run(6000);
    let (truth, hall, light_rpm) = bench.measure(3000);
    eprintln!("slow: wheel {truth:.1}, RPM_M {hall:.1}, RPM_L {light_rpm:.1}");
    assert!(
        truth > 0.5 * limit && truth < 0.9 * limit,
        "slow speed {truth}"
    );
    assert!(
        (light_rpm - truth).abs() < 0.02 * truth,
        "RPM_L {light_rpm} vs {truth}"
    );
    assert!(
        (hall - truth).abs() < 0.01 * truth,
        "RPM_M {hall} vs {truth}"
    );
    // The adaptive detector (VD0 bit 0) sees the same dips.
    bench.write("@01VD00010001");
    bench.run(3000);
    let (truth, _, light_rpm) = bench.measure(3000);
    eprintln!("adaptive: wheel {truth:.1}, RPM_L {light_rpm:.1}");
    assert!(
        (light_rpm - truth).abs() < 0.02 * truth,
        "adaptive RPM_L {light_rpm} vs {truth}"
    );

    // Just above the limit and far above it: every RPM_L reading over two
    // seconds is 0 or a sub-multiple of the speed, never the speed itself.
    for vel in [300, 2048] {
        let mut bench = Bench::new(&params);
        start(&mut bench, vel);
        bench.run(5000);
        let (truth, _, _) = bench.measure(200);
        assert!(truth > 1.1 * limit, "VEL {vel}: speed {truth}");
        let mut seen_zero = false;
        for _ in 0..200 {
            let s = bench.run(10);
            let (_, l) = bench.rpms();
            let wheel = s.wheel_rpm.abs();
            seen_zero |= l == 0.0;
            let sub_multiple = (2..=50).any(|k| {
                let k = f64::from(k);
                (l - wheel / k).abs() < 0.05 * wheel / k
            });
            assert!(
                (l == 0.0 || sub_multiple) && l < limit,
                "VEL {vel}: RPM_L {l} at {wheel:.1} rpm (limit {limit:.1})"
            );
        }
        eprintln!("VEL {vel}: wheel {truth:.1} rpm, RPM_L was 0 at times: {seen_zero}");
    }
}

/// FD0 and the reply to an enabling write.
fn status_word(bench: &mut Bench) -> u16 {
    bench.read("@01FD0001")[0]
}

#[test]
fn an_over_current_trip_latches_and_clears_after_release_and_enable() {
    let mut params = PlantParams::vemodule();
    // A gate driver that trips below the current limit: accelerating from rest trips it.
    params.motor.overcurrent_trip_amps = 5.0;
    let mut bench = Bench::new(&params);
    start(&mut bench, 2048);
    let mut ticks = 0;
    while status_word(&mut bench) & status::OVER_CURRENT == 0 {
        bench.tick();
        ticks += 1;
        assert!(ticks < 100, "no trip");
    }
    assert!(!bench.actuators.enable, "outputs forced off");
    assert_eq!(bench.actuators.vel_volts, 0.0);
    // FR is a direction, not a function: the trip leaves it forward, as set.
    assert!(!bench.actuators.reverse, "FR kept");
    assert_eq!(
        status_word(&mut bench) & status::CCW,
        0,
        "not counter-clockwise"
    );
    let trip = bench.controller.poll_event().expect("a trip event");
    assert_eq!(trip.kind, "trip");

    // The winding current is still decaying: enabling is refused with 04.
    assert!(bench.module.sensors().motor_current.abs() > 1.0);
    let refused = bench.meb("@01SD0001000E").expect("a reply");
    assert_eq!(refused.cmd, MebCmd::ER);
    assert_eq!(refused.data.as_slice(), &[4]);

    // Outputs are still stored meanwhile: a gentle speed for later.
    bench.write("@01SA00010064");
    bench.run(50);
    assert!(
        bench.module.sensors().motor_current.abs() < 1.0,
        "cause gone"
    );
    // Enabling without releasing first is stored but does not clear the trip.
    bench.write("@01SD0001000E");
    bench.run(10);
    assert!(!bench.actuators.enable);
    assert_ne!(
        status_word(&mut bench) & status::OVER_CURRENT,
        0,
        "still latched"
    );
    // EN released, then applied: cleared at the next tick, stored outputs take effect.
    bench.write("@01SD0001000F");
    bench.run(10);
    assert!(!bench.actuators.enable);
    bench.write("@01SD0001000E");
    bench.tick();
    assert!(bench.actuators.enable);
    assert!((bench.actuators.vel_volts - 100.0 / 4095.0 * 5.0).abs() < 1e-12);
    bench.run(3000);
    assert_eq!(status_word(&mut bench) & 0b11, 0, "no trip flag");
    assert!(!bench.module.sensors().motor_tripped);
    assert!(bench.module.sensors().wheel_rpm > 20.0, "turning again");
}

#[test]
fn a_battery_cut_off_latches_and_enabling_stays_refused_while_it_persists() {
    let mut params = PlantParams::vemodule();
    // An under-voltage limit above the pack's voltage: the BMS opens after its delay and stays open.
    params.bms.uv_trip_volts = 45.0;
    params.bms.uv_release_volts = 46.0;
    let mut bench = Bench::new(&params);
    start(&mut bench, 500);
    bench.run(500);
    assert!(bench.actuators.enable);
    assert_eq!(status_word(&mut bench) & status::BATTERY_CUT_OFF, 0);
    bench.run(1000);
    assert_ne!(status_word(&mut bench) & status::BATTERY_CUT_OFF, 0);
    assert!(!bench.actuators.enable, "outputs forced off");
    bench.write("@01SD0001000F");
    for _ in 0..3 {
        bench.run(100);
        let reply = bench.meb("@01SD0001000E").expect("a reply");
        assert_eq!(
            (reply.cmd, reply.data.as_slice()),
            (MebCmd::ER, &[4][..]),
            "04 while the cause persists"
        );
    }
    assert!(!bench.actuators.enable);
}

#[test]
fn stall_is_flagged_after_half_a_second_with_the_brake_on() {
    let params = PlantParams::vemodule();
    let mut bench = Bench::new(&params);
    // Brake applied (BRK low), enabled, small speed set: the wheel cannot turn.
    bench.write("@01SA00010064");
    bench.write("@01SD0001000C");
    bench.run(400);
    let early = status_word(&mut bench);
    assert_eq!(early & status::STALLED, 0, "not yet: {early:#x}");
    assert_ne!(early & status::BRAKE, 0);
    bench.run(300);
    assert_ne!(status_word(&mut bench) & status::STALLED, 0);
    assert_eq!(bench.rpms().0, 0.0);
}
