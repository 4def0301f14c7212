//! The client panel's `state` object: the words its polls read, in
//! engineering units, shaped as the simulated controller's own (so the page
//! draws both the same), with where each signal sits under the map.

use serde_json::{Value, json};

use super::layout::{INPUTS, SWITCHES};
use super::{LINK, Remote};
use nodes::firmware::status;

/// Whether the pin is high with the switch `on`. Every switch is active low
/// (on = pin 0) but FR, whose high pin turns the wheel counter-clockwise:
/// FR "on" is reverse.
pub fn pin_for(home_word: u8, home_bit: u8, on: bool) -> bool {
    if (home_word, home_bit) == (0, 4) {
        on
    } else {
        !on
    }
}

/// EA counts to volts and amps through the lab module's dividers (the
/// panel has no plant to ask).
fn engineering(name: &str, counts: u16) -> (f64, &'static str) {
    let s = plant::params::SensingParams::default();
    let full = f64::from((1u32 << s.adc_bits.min(16)) - 1);
    let pin = f64::from(counts) / full * s.adc_reference_volts;
    match name {
        "V1" => (pin * s.battery_divider, "V"),
        "V2" => (pin * s.bus_divider, "V"),
        "I" => ((pin - s.current_zero_volts) / s.current_volts_per_amp, "A"),
        "RPM_M" | "RPM_L" => (f64::from(counts), "rpm"),
        _ => (f64::from(counts), "counts"),
    }
}

/// The 12-bit DAC's full scale, counts and volts.
const DAC_MAX: u16 = 4095;
const DAC_VOLTS: f64 = 5.0;

/// The stream's `state` for the client panel, and its trend point.
pub fn message_state(remote: &Remote) -> (Value, [Option<f64>; 5]) {
    let s = remote.state();
    let l = &remote.layout;
    let t = remote.now();
    let word = |i: usize| l.inputs[i].and_then(|a| s.ea.get(usize::from(a)).copied());
    let mut inputs = serde_json::Map::new();
    for (i, (name, _)) in INPUTS.iter().enumerate() {
        let counts = word(i);
        let (value, unit) = counts.map_or((f64::NAN, ""), |c| engineering(name, c));
        inputs.insert(
            (*name).into(),
            json!({ "counts": counts, "value": value.is_finite().then_some(value), "unit": unit, "at": l.input_label(i) }),
        );
    }
    let soc = l.soc.and_then(|a| s.fa.get(usize::from(a)).copied());
    inputs.insert(
        "SOC".into(),
        json!({ "counts": soc, "value": soc.map(|c| f64::from(c) / 10.0), "unit": "%",
                "at": l.soc.map(|a| format!("FA {a:02X}")) }),
    );
    let flags = s.status.unwrap_or(0);
    let lamp = |bit: u16| s.status.map(|_| flags & bit != 0);
    let mut outputs = serde_json::Map::new();
    outputs.insert(
        "VEL".into(),
        json!({ "counts": s.vel, "max": DAC_MAX,
                "value": s.vel.map(|v| f64::from(v) * DAC_VOLTS / f64::from(DAC_MAX)), "unit": "V",
                "at": l.vel.map(|a| format!("SA {a:02X}")), "written": s.vel.is_some() }),
    );
    for (i, &(name, home_word, home_bit)) in SWITCHES.iter().enumerate() {
        let written = l.switches[i].and_then(|p| {
            s.sd.iter()
                .find(|(w, _)| *w == p.word)
                .and_then(|(_, v)| *v)
                .map(|v| v >> p.bit & 1 == 1)
        });
        let on = written.map(|pin| pin == pin_for(home_word, home_bit, true));
        outputs.insert(
            name.into(),
            json!({ "on": on, "pin": written.map(u8::from), "at": l.switch_label(i), "written": written.is_some() }),
        );
    }
    let hall_rpm = word(3);
    let light_rpm = word(4);
    let controller = json!({
        "inputs": inputs,
        "ED0": l.hall.and_then(|a| s.ed.get(usize::from(a)).copied()),
        "ERRS": s.fa.get(1).copied(),
        "status": {
            "battery_cut_off": lamp(status::BATTERY_CUT_OFF),
            "over_current": lamp(status::OVER_CURRENT),
            "brake": lamp(status::BRAKE),
            "stalled": lamp(status::STALLED),
            "charging": lamp(status::CHARGING),
            "ccw": lamp(status::CCW),
        },
        "outputs": outputs,
        "forced": { "v1": null, "v2": null, "i": null, "rpm_m": null, "rpm_l": null, "ldr": null,
                    "hall": null, "flag": null, "driver_fault": null },
    });
    let o = &remote.options;
    let state = json!({
        "t": crate::seconds(t),
        "modules": [],
        "devices": [{
            "name": format!("slave {:02}", o.id),
            "controller": controller,
            "readings": { "hall_rpm": hall_rpm, "light_rpm": light_rpm },
        }],
        "links": [{ "name": LINK, "protocol": "meb", "address": o.url, "clients": usize::from(s.connected),
                    "line": null }],
        "connection": {
            "url": o.url,
            "id": o.id,
            "connected": s.connected,
            "error": s.error,
            "last_reply_age_s": s.read_at.map(|r| (t - r).max(0.0)),
            "counters": s.counters,
            "map_is_default": o.map.is_default(),
        },
        "fault": null,
    });
    let trend = [
        Some(t),
        None,
        hall_rpm.map(f64::from),
        light_rpm.map(f64::from),
        None,
    ];
    (state, trend)
}
