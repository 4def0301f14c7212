//! The end-of-run lines of `twin run` for each node that reports a state:
//! every figure with what it is, never the raw JSON the nodes hand over.

use serde_json::Value;

/// A node's end-of-run state in words.
pub fn print(node: &str, state: &Value, simulated_s: f64) {
    if let (Some(slaves), Some(updates)) = (state["slaves"].as_array(), state["updates"].as_u64()) {
        print_parallel_master(node, state, slaves, updates, simulated_s);
        return;
    }
    if let Some(taken) = state["frames_taken"].as_u64() {
        // A slave that never took a frame holds no VEL at all.
        let vel = match &state["vel"] {
            Value::Null => "none".to_string(),
            v => v.to_string(),
        };
        println!(
            "  {node}: VEL {vel} from {taken} frames taken, {} for others, {} bad, {} cut short, {} answers",
            state["frames_ignored"],
            state["bad_frames"],
            state["incomplete_frames"],
            state["answers"]
        );
        return;
    }
    if print_controller_network(node, state) {
        return;
    }
    let Some(loops) = state["loops"].as_array() else {
        println!("  {node}: {}", plain(state));
        return;
    };
    let cycles = state["cycles"].as_f64().unwrap_or(0.0);
    println!(
        "  {node}: {cycles} poll cycles ({:.1} per second)",
        cycles / simulated_s.max(1e-9)
    );
    for l in loops {
        let n = |k: &str| l[k].as_f64().unwrap_or(f64::NAN);
        println!(
            "    slave {}: set point {:.0} rpm, measured {:.0} rpm, error {:.0} rpm, VEL {:.0}; \
             {} requests, {} replies, {} timeouts, {} bad checks, {} retries, {} lost",
            l["slave"],
            n("set_point_rpm"),
            n("measured_rpm"),
            n("error_rpm"),
            n("output"),
            l["requests"],
            l["replies"],
            l["timeouts"],
            l["bad_checks"],
            l["retries"],
            l["lost"]
        );
    }
}

/// A parallel-module master: its own loop, then each exchange's tally.
fn print_parallel_master(
    node: &str,
    state: &Value,
    slaves: &[Value],
    updates: u64,
    simulated_s: f64,
) {
    let n = |v: &Value, k: &str| v[k].as_f64().unwrap_or(f64::NAN);
    let cycles = n(state, "cycles");
    println!(
        "  {node}: set point {:.0} rpm, measured {:.0} rpm, VEL {}; {updates} references issued, \
         {cycles} send cycles ({:.0} per second)",
        n(state, "set_point_rpm"),
        n(state, "measured_rpm"),
        state["vel"],
        cycles / simulated_s.max(1e-9)
    );
    for s in slaves {
        let who = match s["slave"].as_u64() {
            Some(0) => "broadcast".to_string(),
            Some(id) => format!("slave {id}"),
            None => "?".to_string(),
        };
        println!(
            "    {who}: {} frames, {} answers, {} timeouts, {} bad answers, {} retries, {} lost",
            s["requests"], s["replies"], s["timeouts"], s["bad_replies"], s["retries"], s["lost"]
        );
    }
}

/// The Controller_network project's three nodes. Four rpm figures meet in
/// its summary (the wheel's true speed on the module's line, the motor
/// node's encoder, the Raspberry Pi's last reads, the light-sensor node's),
/// so each says which it is. `false` if `state` is none of them.
fn print_controller_network(node: &str, state: &Value) -> bool {
    let n = |k: &str| state[k].as_f64();
    if let (Some(latched), Some(kind)) = (n("latched_rpm"), state["state"].as_str()) {
        println!(
            "  {node} (motor node): {kind}, set point {} rpm, PWM duty {:.0} %; \
             its encoder: motor shaft {latched:.0} rpm over the last 20 ms window",
            state["set_point"],
            n("duty").unwrap_or(0.0) * 100.0
        );
        return true;
    }
    if let (Some(rpm), Some(raw)) = (n("rpm"), n("raw_rpm")) {
        println!(
            "  {node} (light-sensor node): wheel {rpm:.1} rpm by the paper flag, smoothed \
             ({raw:.1} rpm from the last turn alone); the flag passed {} times",
            state["edges"]
        );
        return true;
    }
    if let Some(phase) = state["phase"].as_str() {
        let scripted = &state["scripted"];
        let (sent, of) = (scripted["sent"].as_u64(), scripted["of"].as_u64());
        if state["program"] == "requests" {
            println!(
                "  {node} (Raspberry Pi master): only its scripted requests, {} of {} sent; \
                 {} bad CRCs, {} timeouts",
                sent.unwrap_or(0),
                of.unwrap_or(0),
                state["crc_errors"],
                state["timeouts"]
            );
            return true;
        }
        let scripted = match (sent, of) {
            (Some(sent), Some(of)) => format!("; scripted requests: {sent} of {of} sent"),
            _ => String::new(),
        };
        let motor = n("motor_rpm").map_or_else(
            || "nothing yet from the motor node".into(),
            |v| format!("motor shaft {v:.0} rpm from the motor node"),
        );
        let wheel = n("sensor_value").map_or_else(
            || "nothing yet from the light-sensor node".into(),
            |v| {
                format!(
                    "wheel {:.2} rpm ({v:.0}) from the light-sensor node",
                    v / 100.0
                )
            },
        );
        println!(
            "  {node} (Raspberry Pi master): {phase}, {} cycles, set point {} rpm; last read: \
             {motor}, {wheel}; {} bad CRCs, {} timeouts{scripted}",
            state["cycles"], state["set_point"], state["crc_errors"], state["timeouts"]
        );
        return true;
    }
    false
}

/// Any other state as `name value` pairs, in the words of its keys.
fn plain(state: &Value) -> String {
    match state {
        Value::Object(map) => map
            .iter()
            .map(|(k, v)| format!("{} {}", k.replace('_', " "), plain(v)))
            .collect::<Vec<_>>()
            .join(", "),
        Value::Array(items) => items.iter().map(plain).collect::<Vec<_>>().join(", "),
        Value::String(s) => s.clone(),
        Value::Null => "none".into(),
        other => other.to_string(),
    }
}
