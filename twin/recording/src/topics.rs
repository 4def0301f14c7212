//! The catalogue of what a recording holds: every channel's topic, who
//! writes it and when, what its messages carry, and the metadata records.
//! Writers name their channels through these functions and readers
//! recognise them with [`Topic::parse`], so no topic is spelt anywhere else.
//!
//! The plant's samples, the frames, the controllers' readings and the
//! supervisors' loop reports are protobuf ([`proto_schema`]); every other
//! channel is JSON (`json` message encoding) with a JSON schema
//! (`jsonschema`) derived from its first message ([`crate::record::schema_of`])
//! and named after the topic ([`schema_name`]: `/plant/ev1/sensors` →
//! `plant.ev1.sensors`). Log time is simulated time (a real-time session's
//! session time).
//!
//! | topic | written by | when | fields |
//! |---|---|---|---|
//! | [`plant_sensors`] `/plant/<module>/sensors` | a virtual run (`twin-sim` `observe.rs`), a real-time session (`twin-realtime` `sink.rs`) | at the scenario's `record_hz` (a session: each plant tick it records) | `plant::Sensors`: `time_s`, `battery_volts` (V1), `bus_volts` (V2), `inverter_current` (I), `battery_current`, `soc`, `charging`, `bms_trip`, `battery_counts`, `bus_counts`, `current_counts`, `motor_current`, `motor_tripped`, `motor_rpm`, `shaft` (hall code, hall and encoder counts), `wheel_rpm`, `wheel_angle`, `brake_applied`, `ldr_volts`, `ldr_counts`, `flag_in_beam`, `energy` (the energy ledger) |
//! | [`PLANT_SENSORS`] `/plant/sensors` | the open-loop bench (`twin run` without a scenario, `twin-sim` `openloop.rs`) | at its `record_hz` | as above |
//! | [`plant_actuators`] `/plant/<module>/actuators` | a virtual run, a real-time session | on every change | `plant::Actuators`: `vel_volts`, `enable`, `brake`, `boost`, `discharge`, `reverse`, `charger` |
//! | [`PLANT_ACTUATORS`] `/plant/actuators` | the open-loop bench | on every change | as above |
//! | [`bus_frames`] `/bus/<bus>/frames` | a virtual run | every frame sent, at its first byte | [`FrameSample`]: `from` (the sending node), `start_s`, `end_s`, `len`, `text` (printable bytes, else empty), `hex` (protobuf keeps the bytes once: `text` when printable, else `hex`; [`complete_frame`] gives back both), `decoded` ([`crate::describe`]; PWM-capture: widths sent and captured per listener, values, pulses lost, values wrong) |
//! | [`bus_line`] `/bus/<bus>/line` | a virtual run | only where the line differed from what was sent (a recording of a bus without noise or collisions has no such channel) | [`LineSample`]: `kind` (`collision`: a character garbled on the wire, alike for every listener; `noise`: data bits flipped at one listener), `from` and `frame_start_s` (the frame's sender and first start bit, as on [`bus_frames`]), `index` (the character's place in the frame), `to` (the listener; empty for a collision), `mask` (the data bits changed, bit 0 first on the wire), `byte` (the character as on the wire, or as the listener got it) |
//! | [`link_frames`] `/link/<link>/frames` | a real-time session (`twin serve`, `twin supervise`) | every frame, both directions | [`FrameSample`], `from` being `twin`, `client N`, or on `twin supervise`'s `bus` the slave that answered (`slave 01`) |
//! | [`EVENTS`] `/events` | a virtual run, a real-time session | as they happen | [`EventSample`]: `node`, `kind` (`timeout`, `bad_check`, `retry`, `exception`, `dropped`, `fault`, `state`, `log`; a session's `connection`, and `slip` from the node `clock` each second real time was lost), `detail` |
//! | [`controller_readings`] `/controller/<node>/readings` | a virtual run, a real-time session (`twin serve`) | beside each plant sample (the scenario's `record_hz`), per EV module controller | [`ReadingsSample`]: what the controller reads, named: `battery_volts` (V1), `bus_volts` (V2), `inverter_amps` (I), `hall_rpm` (RPM_M), `light_rpm` (RPM_L), `flag_dark` (ED0 bit 3), `soc_percent` (SOC), and `meb`, the raw words a master reads by their MEB names (`V2`, `I`, `V1`, `RPM_M`, `RPM_L`, `LDR`, `HALL`, `SOC`, `ERRS`, `STATUS`); its schema describes every field with its unit ([`readings_schema`]; in the protobuf descriptor as the fields' comments) |
//! | [`master_loop`] `/master/<node>/loop` | a virtual run, a real-time session (`twin supervise`) | every poll cycle of a master | [`LoopReport`]: the master's telemetry: set point, measured rpm, error, output, counters (a supervisor: `cycles` and `loops`, one per slave) |
//! | [`REALTIME_LATENESS`] `/realtime/lateness` | a real-time session | each second (and the file is flushed) | `window` and `total`, each `ticks`, `p50_us`, `p99_us`, `p999_us`, `max_us`, `mean_us`, `overruns`: how late the plant's ticks ran; `slips`, `slipped_ms`: how often and by how much the session's clock slipped behind the wall (a stall longer than it catches up) |
//! | [`EXPERIMENT_STEP`] `/experiment/step` | `twin step` (`twin-lab` `step.rs`) | each sample of the experiment | `set_point`, `wheel_rpm`, `motor_rpm`, `light_rpm` |
//! | [`firmware_uart`] `/firmware/<node>/uart` | a virtual run with compiled firmware (`twin-avr`) | each burst of bytes on the firmware's UART, once the line has been quiet for two characters | [`UartBurst`]: `dir` (`rx` to the firmware, `tx` from it), `baud` (the firmware's own, from UBRR0/U2X0), `start_s`, `end_s`, `len`, `text`, `hex`, `cycles` (the CPU cycle each byte started at) |
//! | [`CHECKS`] `/check/checks` | `twin check` (`twin-check` `record.rs`) | each check, at its first step | `index`, `name`, `requirement`, `points`, `result` (`pass`, `fail`), `why`, `at`, `seconds`, `frames` (how many of the frames, in order on every link, are the check's); the frames are on `/link/<role>/frames`, `from` `twin` or the checked program (`slave NN`, `master`); a server check's on `/link/server/frames` (the twin's clients, the `supervisor`) and `/link/bus/frames` (the `supervisor`, the twin's `slave NN`), a client check's on `/link/client/frames` (`client N`, `twin`) |
//! | [`firmware_io`] `/firmware/<node>/io` | a virtual run with compiled firmware | every 10 ms of simulated time | [`FirmwareIo`]: `cycles` (run so far), `pins` (each wired output and PWM pin: `pin`, `signal`, `level`, `duty` over the 10 ms, `period_us` between its rising edges, `edges` in them), `adc` (each analog input fed: `pin`, `signal`, `millivolts`, `counts` as the 10-bit ADC converts them), `edges` (the edges of those pins in the 10 ms, up to 20 per pin: every edge of a line up to 1 kHz; `cycle`, `pin`, `level`) |
//!
//! Metadata records:
//!
//! | name | written by | when | fields |
//! |---|---|---|---|
//! | [`RUN_METADATA`] `twin.run` | every run and session | first, before any message | `kind` (`scenario`, `open-loop`, `serve`, `supervise`, `check`), `twin_version`; a scenario's `scenario`, `scenario_toml`, `seed`, `pwm_calibration`; the open loop's settings and `params_toml`; a step response's `experiment` (`step`), `step_from`, `step_to`, `step_at_s`, and `step_adaptive_light` (open loop) or `step_light_feedback` (closed loop); a session's `links`, `params`, `slaves`, …; a check's `role`, `suite`, `suite_toml`, `link`, `id` |
//! | [`REALTIME_METADATA`] `twin.realtime` | a real-time session | when it ends | the session's totals |
//! | [`firmware_metadata`] `twin.firmware.<node>` | a virtual run with compiled firmware | before any message | `node`, `file` (as the scenario names it), `attachment` (the MCAP attachment holding the file's bytes), `sha256`, `bytes`, `mcu`, `clock_hz`, `wiring` (the map's name or file) and `wiring_toml` (its text) |
//! | [`CHECK_METADATA`] `twin.check` | `twin check` | after the checks | `score`, `points`, `checks`, `checks_passed`, `seconds`, and `hung_up` or `error` when the program hung up or could not be reached; the whole run as JSON is the attachment [`CHECK_RUN_ATTACHMENT`] |
//! | [`PART_METADATA`] `twin.part` | a real-time session's file that another follows (rotation) | when it is closed | `part` (from 1), `ended_by` (`SIGHUP`, `--rotate-every 1h`, …), `next` (the next file's name); the next file's `twin.run` has `part` and `previous` |
//! | [`RECOVERED_METADATA`] `twin.recovered` | `twin recover`'s copy of a run cut short | last, before the summary | `stopped`: where and why the original stops (`after 2 complete chunk(s), its last record is cut off`); replays and comparisons read the copy as the cut run it is |

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};

/// Message encoding of the JSON channels.
pub const MESSAGE_ENCODING: &str = "json";
/// Schema encoding of the JSON channels.
pub const SCHEMA_ENCODING: &str = "jsonschema";
/// Message and schema encoding of the protobuf channels ([`proto_schema`]).
pub const PROTOBUF: &str = "protobuf";

/// The run's identity: what `twin replay` re-runs and `twin view` lays out.
pub const RUN_METADATA: &str = "twin.run";
/// A real-time session's totals, written when it ends.
pub const REALTIME_METADATA: &str = "twin.realtime";
/// Why a session's file ended and which file goes on (rotation).
pub const PART_METADATA: &str = "twin.part";
/// Where the run a `twin recover` copy was made of stops (it was cut short).
pub const RECOVERED_METADATA: &str = "twin.recovered";

/// A `twin check` run's score and how it ended.
pub const CHECK_METADATA: &str = "twin.check";
/// The attachment holding a `twin check` run as its JSON report.
pub const CHECK_RUN_ATTACHMENT: &str = "check-run.json";
/// A `twin check` run's verdicts, one message per check.
pub const CHECKS: &str = "/check/checks";

/// The open-loop bench's sensors (one module, no name).
pub const PLANT_SENSORS: &str = "/plant/sensors";
/// The open-loop bench's actuators.
pub const PLANT_ACTUATORS: &str = "/plant/actuators";
/// Node events of a run or session.
pub const EVENTS: &str = "/events";
/// A real-time session's tick lateness, each second.
pub const REALTIME_LATENESS: &str = "/realtime/lateness";
/// The step-response experiment's samples.
pub const EXPERIMENT_STEP: &str = "/experiment/step";

/// A module's sensors: `/plant/<module>/sensors`.
pub fn plant_sensors(module: &str) -> String {
    format!("/plant/{module}/sensors")
}

/// A module's actuators: `/plant/<module>/actuators`.
pub fn plant_actuators(module: &str) -> String {
    format!("/plant/{module}/actuators")
}

/// The frames on a simulated bus: `/bus/<bus>/frames`.
pub fn bus_frames(bus: &str) -> String {
    format!("/bus/{bus}/frames")
}

/// Where a simulated bus's line differed from what was sent (collisions,
/// noise): `/bus/<bus>/line`.
pub fn bus_line(bus: &str) -> String {
    format!("/bus/{bus}/line")
}

/// The frames on a real-time session's link: `/link/<link>/frames`.
pub fn link_frames(link: &str) -> String {
    format!("/link/{link}/frames")
}

/// A master's loop reports: `/master/<node>/loop`.
pub fn master_loop(node: &str) -> String {
    format!("/master/{node}/loop")
}

/// An EV module controller's readings: `/controller/<node>/readings`.
pub fn controller_readings(node: &str) -> String {
    format!("/controller/{node}/readings")
}

/// A firmware node's UART traffic: `/firmware/<node>/uart`.
pub fn firmware_uart(node: &str) -> String {
    format!("/firmware/{node}/uart")
}

/// A firmware node's pins, ADC inputs and cycles: `/firmware/<node>/io`.
pub fn firmware_io(node: &str) -> String {
    format!("/firmware/{node}/io")
}

/// The metadata record naming a firmware node's file: `twin.firmware.<node>`.
pub fn firmware_metadata(node: &str) -> String {
    format!("{FIRMWARE_METADATA}.{node}")
}

/// The prefix of [`firmware_metadata`] records.
pub const FIRMWARE_METADATA: &str = "twin.firmware";

/// The attachment holding a firmware node's file: `firmware/<node>/<file name>`.
pub fn firmware_attachment(node: &str, file_name: &str) -> String {
    format!("firmware/{node}/{file_name}")
}

/// The schema name of a topic's channel: `/plant/ev1/sensors` → `plant.ev1.sensors`.
pub fn schema_name(topic: &str) -> String {
    topic.trim_start_matches('/').replace('/', ".")
}

/// A topic recognised.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Topic<'a> {
    /// A module's sensors (`None`: the open-loop bench's).
    PlantSensors(Option<&'a str>),
    /// A module's actuators (`None`: the open-loop bench's).
    PlantActuators(Option<&'a str>),
    BusFrames(&'a str),
    /// Where a bus's line differed from what was sent, by bus name.
    BusLine(&'a str),
    LinkFrames(&'a str),
    Events,
    MasterLoop(&'a str),
    /// An EV module controller's readings, by node name.
    ControllerReadings(&'a str),
    /// A firmware node's UART bursts, by node name.
    FirmwareUart(&'a str),
    /// A firmware node's pins, ADC inputs and cycles, by node name.
    FirmwareIo(&'a str),
    RealtimeLateness,
    ExperimentStep,
    /// Anything else (not written by this twin).
    Other(&'a str),
}

impl<'a> Topic<'a> {
    /// Recognise `topic`.
    pub fn parse(topic: &'a str) -> Self {
        let named = |prefix: &str, suffix: &str| {
            topic
                .strip_prefix(prefix)
                .and_then(|t| t.strip_suffix(suffix))
                .filter(|name| !name.is_empty())
        };
        match topic {
            PLANT_SENSORS => return Topic::PlantSensors(None),
            PLANT_ACTUATORS => return Topic::PlantActuators(None),
            EVENTS => return Topic::Events,
            REALTIME_LATENESS => return Topic::RealtimeLateness,
            EXPERIMENT_STEP => return Topic::ExperimentStep,
            _ => {}
        }
        if let Some(m) = named("/plant/", "/sensors") {
            Topic::PlantSensors(Some(m))
        } else if let Some(m) = named("/plant/", "/actuators") {
            Topic::PlantActuators(Some(m))
        } else if let Some(b) = named("/bus/", "/frames") {
            Topic::BusFrames(b)
        } else if let Some(b) = named("/bus/", "/line") {
            Topic::BusLine(b)
        } else if let Some(l) = named("/link/", "/frames") {
            Topic::LinkFrames(l)
        } else if let Some(n) = named("/master/", "/loop") {
            Topic::MasterLoop(n)
        } else if let Some(n) = named("/controller/", "/readings") {
            Topic::ControllerReadings(n)
        } else if let Some(n) = named("/firmware/", "/uart") {
            Topic::FirmwareUart(n)
        } else if let Some(n) = named("/firmware/", "/io") {
            Topic::FirmwareIo(n)
        } else {
            Topic::Other(topic)
        }
    }

    /// Whether the channel's messages are samples at a fixed rate (the
    /// plant's sensors) rather than events: [`crate::signals`] interpolates
    /// between samples and holds an event's value until the next.
    pub fn is_sampled(self) -> bool {
        matches!(self, Topic::PlantSensors(_))
    }
}

/// Where a bus's line differed from what a node sent, as recorded on
/// [`bus_line`]: a character a collision garbled, or bits noise flipped at
/// one listener. Written from [`LineMessage`].
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct LineSample {
    /// `collision` or `noise` ([`LINE_COLLISION`], [`LINE_NOISE`]).
    pub kind: String,
    /// The frame's sender.
    pub from: String,
    /// The frame's first start bit (s), as its [`FrameSample::start_s`].
    pub frame_start_s: f64,
    /// The character's place in its frame (from 0).
    pub index: usize,
    /// Noise: the listener; a collision: empty (every listener gets it so).
    pub to: String,
    /// The data bits changed (bit 0 is the first on the wire).
    pub mask: u8,
    /// The character as it is on the wire (a collision) or as the listener
    /// got it (noise).
    pub byte: u8,
}

/// A [`LineSample`] as written, borrowing its names.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct LineMessage<'a> {
    pub kind: &'a str,
    pub from: &'a str,
    pub frame_start_s: f64,
    pub index: usize,
    pub to: &'a str,
    pub mask: u8,
    pub byte: u8,
}

/// [`LineSample::kind`] of a character garbled by a collision.
pub const LINE_COLLISION: &str = "collision";
/// [`LineSample::kind`] of bits flipped by noise at a listener.
pub const LINE_NOISE: &str = "noise";

/// A frame as recorded on [`bus_frames`] and [`link_frames`] (the fields a
/// reader takes; `len`, `text` and `decoded` are for people and tools).
#[derive(Debug, Clone, PartialEq, Deserialize)]
pub struct FrameSample {
    /// The sending node (a session's link: `twin`, `client N`, or on a
    /// supervisor's bus `slave NN`).
    pub from: String,
    /// When its first and last byte went (s).
    pub start_s: f64,
    pub end_s: f64,
    /// The bytes, two lowercase hex digits each.
    pub hex: String,
}

/// An EV module controller's readings as recorded on [`controller_readings`]:
/// what a master would read from every input block, named so that a plot or
/// a data frame finds them (`light_rpm`), with the raw words under `meb`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ReadingsSample {
    /// V1: battery voltage (V), from its ADC count through the divider.
    pub battery_volts: f64,
    /// V2: DC-bus voltage (V).
    pub bus_volts: f64,
    /// I: inverter input current (A).
    pub inverter_amps: f64,
    /// RPM_M: wheel rpm from the motor's hall sensors.
    pub hall_rpm: u16,
    /// RPM_L: wheel rpm from the photoresistor's dips.
    pub light_rpm: u16,
    /// ED0 bit 3: the light detector sees the flag now.
    pub flag_dark: bool,
    /// SOC: battery state of charge (%).
    pub soc_percent: f64,
    /// The words as a master reads them over MEB (or Modbus input registers).
    pub meb: MebWords,
}

/// The controller's input words by their MEB names (`docs/protocols/meb.md`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct MebWords {
    /// EA0: DC-bus voltage, ADC counts.
    #[serde(rename = "V2")]
    pub v2: u16,
    /// EA1: inverter current, ADC counts.
    #[serde(rename = "I")]
    pub i: u16,
    /// EA2: battery voltage, ADC counts.
    #[serde(rename = "V1")]
    pub v1: u16,
    /// EA3: wheel rpm, hall sensors.
    #[serde(rename = "RPM_M")]
    pub rpm_m: u16,
    /// EA4: wheel rpm, photoresistor.
    #[serde(rename = "RPM_L")]
    pub rpm_l: u16,
    /// EA5: photoresistor divider, ADC counts.
    #[serde(rename = "LDR")]
    pub ldr: u16,
    /// ED0: hall code (bits 0–2), light detector dark (bit 3).
    #[serde(rename = "HALL")]
    pub hall: u16,
    /// FA0: state of charge, 0.1 % per count.
    #[serde(rename = "SOC")]
    pub soc: u16,
    /// FA1: frames dropped for bad form or check.
    #[serde(rename = "ERRS")]
    pub errs: u16,
    /// FD0: status bits.
    #[serde(rename = "STATUS")]
    pub status: u16,
}

/// The JSON schema of [`controller_readings`]: every field with its meaning
/// and unit, so Foxglove and Lichtblick show what a field is.
pub fn readings_schema() -> Value {
    let number = |d: &str| json!({ "type": "number", "description": d });
    let integer = |d: &str| json!({ "type": "integer", "description": d });
    json!({
        "type": "object",
        "title": "EV module controller readings",
        "properties": {
            "battery_volts": number("V1, battery voltage (V)"),
            "bus_volts": number("V2, DC-bus voltage (V)"),
            "inverter_amps": number("I, inverter input current (A)"),
            "hall_rpm": integer("RPM_M, wheel speed from the motor's hall sensors (rpm)"),
            "light_rpm": integer("RPM_L, wheel speed from the photoresistor (rpm)"),
            "flag_dark": { "type": "boolean", "description": "ED0 bit 3, the light detector sees the flag" },
            "soc_percent": number("SOC, battery state of charge (%)"),
            "meb": {
                "type": "object",
                "description": "the words as a master reads them, by their MEB names",
                "properties": {
                    "V2": integer("EA0, DC-bus voltage (ADC counts)"),
                    "I": integer("EA1, inverter current (ADC counts)"),
                    "V1": integer("EA2, battery voltage (ADC counts)"),
                    "RPM_M": integer("EA3, wheel rpm from the hall sensors"),
                    "RPM_L": integer("EA4, wheel rpm from the photoresistor"),
                    "LDR": integer("EA5, photoresistor divider (ADC counts)"),
                    "HALL": integer("ED0, hall code A B C in bits 0-2, light detector dark in bit 3"),
                    "SOC": integer("FA0, state of charge (0.1 % per count)"),
                    "ERRS": integer("FA1, frames dropped for bad form or check"),
                    "STATUS": integer("FD0, bit 0 battery cut-off, 1 over-current, 2 brake, 3 stalled, 4 charging, 5 counter-clockwise"),
                }
            }
        }
    })
}

/// The schema the catalogue gives `topic`'s channel, where it writes one by
/// hand; other channels' schemas are derived from their first message.
pub fn described_schema(topic: &str) -> Option<Value> {
    match Topic::parse(topic) {
        Topic::ControllerReadings(_) => Some(readings_schema()),
        _ => None,
    }
}

/// The protobuf schema of `topic`'s channel, where the catalogue records it
/// as protobuf: the plant's samples, the frames, the controllers' readings
/// and the supervisors' loop reports, nearly all of a recording's messages.
/// Every other channel is JSON. A bus whose frames do not fit (PWM-capture:
/// per-listener captures, values that may be missing) stays JSON too, as does
/// a master's loop report other than a supervisor's:
/// [`crate::record::Recorder::add_channel`] tries the first message.
pub fn proto_schema(topic: &str) -> Option<prost_reflect::MessageDescriptor> {
    let name = match Topic::parse(topic) {
        Topic::PlantSensors(_) => PLANT_SENSORS_SCHEMA,
        Topic::BusFrames(_) | Topic::LinkFrames(_) => FRAME_SCHEMA,
        Topic::ControllerReadings(_) => READINGS_SCHEMA,
        Topic::MasterLoop(_) => SUPERVISOR_LOOP_SCHEMA,
        _ => return None,
    };
    crate::protobuf::message(name)
}

/// The protobuf message type of the plant's samples ([`plant_sensors`]):
/// `twin/recording/proto/twin/plant_sensors.proto`.
pub const PLANT_SENSORS_SCHEMA: &str = "twin.PlantSensors";
/// The protobuf message type of [`controller_readings`], every field's
/// meaning and unit its comment: `controller_readings.proto`.
pub const READINGS_SCHEMA: &str = "twin.ControllerReadings";
/// The protobuf message type of a supervisor's [`master_loop`]:
/// `supervisor_loop.proto`.
pub const SUPERVISOR_LOOP_SCHEMA: &str = "twin.SupervisorLoop";

/// A master's loop report as recorded on [`master_loop`], once per poll
/// cycle: a supervisor's, typed (written without building a JSON value), or
/// another master's fields as it gives them.
#[derive(Debug, Clone, PartialEq)]
pub enum LoopReport {
    Supervisor(SupervisorReport),
    Other(Value),
}

impl Serialize for LoopReport {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        match self {
            LoopReport::Supervisor(report) => report.serialize(serializer),
            LoopReport::Other(value) => value.serialize(serializer),
        }
    }
}

impl LoopReport {
    /// The report as the JSON value a recording reads back.
    pub fn to_value(&self) -> Value {
        match self {
            LoopReport::Supervisor(report) => serde_json::to_value(report).unwrap_or(Value::Null),
            LoopReport::Other(value) => value.clone(),
        }
    }
}

/// A supervisor's poll cycles so far and its loop of every slave it polls.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SupervisorReport {
    pub cycles: u64,
    pub loops: Vec<SlaveLoop>,
}

/// A supervisor's speed loop of one slave, and that slave's bus counters.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct SlaveLoop {
    pub slave: u8,
    pub set_point_rpm: f64,
    pub measured_rpm: f64,
    pub error_rpm: f64,
    /// `VEL`, DAC counts.
    pub output: u16,
    pub integral: f64,
    pub requests: u64,
    pub replies: u64,
    pub timeouts: u64,
    pub bad_checks: u64,
    pub exceptions: u64,
    pub retries: u64,
    pub lost: u64,
}

/// The protobuf message type of the frames ([`bus_frames`],
/// [`link_frames`]): `frame.proto`.
pub const FRAME_SCHEMA: &str = "twin.Frame";

/// `bytes` as two lowercase hex digits each, appended to `hex`: how a
/// frame's or a UART burst's `hex` field spells them.
pub fn put_hex(hex: &mut String, bytes: &[u8]) {
    // Appended a run at a time: a `push` per digit (a capacity check and a
    // UTF-8 encoding each) cost about 30 instructions a byte.
    let appended: Result<(), std::convert::Infallible> = crate::protobuf::hex_runs(bytes, |run| {
        hex.push_str(run);
        Ok(())
    });
    let Ok(()) = appended;
}

/// A frame read from a protobuf channel, with both `text` and `hex` as the
/// JSON recordings (and the protobuf ones before the bytes were kept once)
/// hold them: the file keeps the bytes once, as `text` when they are
/// printable (MEB) and as `hex` otherwise.
pub fn complete_frame(frame: &mut Value) {
    let Value::Object(fields) = frame else {
        return;
    };
    if !fields.get("hex").is_some_and(Value::is_string) {
        let text = fields.get("text").and_then(Value::as_str).unwrap_or("");
        let mut hex = String::with_capacity(2 * text.len());
        put_hex(&mut hex, text.as_bytes());
        fields.insert("hex".into(), Value::String(hex));
    }
    if !fields.get("text").is_some_and(Value::is_string) {
        fields.insert("text".into(), Value::String(String::new()));
    }
}

/// A burst of bytes on a firmware node's UART, as recorded on [`firmware_uart`].
#[derive(Debug, Clone, Copy, Serialize)]
pub struct UartBurst<'a> {
    /// `rx`: to the firmware; `tx`: from it.
    pub dir: &'a str,
    /// The firmware's baud, from its own registers.
    pub baud: f64,
    /// When the first byte started and the last one ended on the wire (s).
    pub start_s: f64,
    pub end_s: f64,
    pub len: usize,
    /// The bytes as text when they are printable ASCII (MEB), else empty.
    pub text: &'a str,
    pub hex: &'a str,
    /// The CPU cycle at which each byte started.
    pub cycles: &'a [u64],
}

/// A firmware node's pins, ADC inputs and cycles, as recorded on [`firmware_io`].
#[derive(Debug, Clone, Copy, Serialize)]
pub struct FirmwareIo<'a> {
    /// CPU cycles run since power-up.
    pub cycles: u64,
    pub pins: &'a [PinState],
    pub adc: &'a [AdcInput],
    /// Every edge of the pins since the last sample, in order.
    pub edges: &'a [PinEdge],
}

/// An output pin over the last sample period.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct PinState {
    /// The Arduino pin (`D9`).
    pub pin: &'static str,
    /// What the wiring map connects it to (`vel`, `en`, `led`).
    pub signal: &'static str,
    pub level: bool,
    /// The fraction of the period it was high.
    pub duty: f64,
    /// The mean time between its rising edges in the period (µs; 0 with
    /// fewer than two).
    pub period_us: f64,
    /// Its edges in the period (all of them; the sample lists the first 20).
    pub edges: u32,
}

/// An analog input as fed to the ADC.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct AdcInput {
    pub pin: &'static str,
    pub signal: &'static str,
    pub millivolts: u32,
    /// What the 10-bit converter reads at AVcc = 5 V.
    pub counts: u16,
}

/// One edge of a pin.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub struct PinEdge {
    pub cycle: u64,
    pub pin: &'static str,
    pub level: bool,
}

/// An event as recorded on [`EVENTS`].
#[derive(Debug, Clone, PartialEq, Eq, Deserialize)]
pub struct EventSample {
    pub node: String,
    pub kind: String,
    pub detail: String,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn hex_spells_every_byte_in_two_lowercase_digits_at_any_length() {
        let every: Vec<u8> = (0..=255).collect();
        for len in [0, 1, 63, 64, 65, 256] {
            let bytes = &every[..len];
            let mut hex = String::from("kept:");
            put_hex(&mut hex, bytes);
            let expected: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
            assert_eq!(hex, format!("kept:{expected}"), "{len} bytes");
        }
    }

    #[test]
    fn every_topic_parses_back_to_what_named_it() {
        for (topic, parsed) in [
            (plant_sensors("ev1"), Topic::PlantSensors(Some("ev1"))),
            (PLANT_SENSORS.to_string(), Topic::PlantSensors(None)),
            (plant_actuators("m2"), Topic::PlantActuators(Some("m2"))),
            (PLANT_ACTUATORS.to_string(), Topic::PlantActuators(None)),
            (bus_frames("rs485"), Topic::BusFrames("rs485")),
            (link_frames("modbus-tcp"), Topic::LinkFrames("modbus-tcp")),
            (EVENTS.to_string(), Topic::Events),
            (master_loop("supervisor"), Topic::MasterLoop("supervisor")),
            (controller_readings("ev1"), Topic::ControllerReadings("ev1")),
            (REALTIME_LATENESS.to_string(), Topic::RealtimeLateness),
            (EXPERIMENT_STEP.to_string(), Topic::ExperimentStep),
            (firmware_uart("ev1"), Topic::FirmwareUart("ev1")),
            (firmware_io("motor"), Topic::FirmwareIo("motor")),
        ] {
            assert_eq!(Topic::parse(&topic), parsed, "{topic}");
        }
        assert_eq!(Topic::parse("/bus//frames"), Topic::Other("/bus//frames"));
        assert_eq!(Topic::parse("/camera/image"), Topic::Other("/camera/image"));
        assert!(Topic::parse("/plant/ev1/sensors").is_sampled());
        assert!(!Topic::parse("/plant/ev1/actuators").is_sampled());
        assert_eq!(schema_name("/plant/ev1/sensors"), "plant.ev1.sensors");
    }

    #[test]
    fn readings_and_a_supervisors_loop_read_back_from_protobuf_as_their_json() {
        let readings = ReadingsSample {
            battery_volts: 40.684,
            bus_volts: 40.683,
            inverter_amps: 0.104,
            hall_rpm: 1500,
            light_rpm: 1498,
            flag_dark: false,
            soc_percent: 90.0,
            meb: MebWords {
                v2: 3029,
                rpm_l: 1498,
                status: 4,
                ..MebWords::default()
            },
        };
        let slave = SlaveLoop {
            slave: 1,
            set_point_rpm: 1500.0,
            measured_rpm: 1490.5,
            error_rpm: 9.5,
            output: 1375,
            integral: 1374.75,
            requests: 1239,
            replies: 1238,
            timeouts: 1,
            bad_checks: 0,
            exceptions: 0,
            retries: 1,
            lost: 0,
        };
        let report = LoopReport::Supervisor(SupervisorReport {
            cycles: 1000,
            loops: vec![slave, SlaveLoop { slave: 2, ..slave }],
        });
        let json_of = |v: &dyn erased::Json| v.json();
        for (topic, value) in [
            (controller_readings("ev1"), json_of(&readings)),
            (master_loop("supervisor"), json_of(&report)),
        ] {
            let schema = proto_schema(&topic).expect("a protobuf schema");
            let mut bytes = Vec::new();
            match &report {
                LoopReport::Supervisor(report) if schema.full_name() == SUPERVISOR_LOOP_SCHEMA => {
                    crate::protobuf::Protobuf::write_protobuf(report, &mut bytes);
                }
                _ => crate::protobuf::Protobuf::write_protobuf(&readings, &mut bytes),
            }
            assert_eq!(crate::protobuf::to_value(&schema, &bytes).unwrap(), value);
            // The same report as a JSON value (a map) gives the same bytes.
            let mut from_map = Vec::new();
            crate::protobuf::transcode(&schema, &value, &mut from_map).unwrap();
            assert_eq!(from_map, bytes, "{topic}");
        }
        // Another master's report does not fit a supervisor's: JSON.
        let other = LoopReport::Other(json!({ "set_point_rpm": 1500.0, "vel": 3 }));
        let schema = proto_schema(&master_loop("master")).unwrap();
        assert!(crate::protobuf::transcode(&schema, &other, &mut Vec::new()).is_err());
        assert_eq!(other.to_value()["vel"], 3);
        // The readings' descriptor carries every field's meaning, as the
        // JSON schema has it.
        let set =
            crate::protobuf::descriptor_set(&proto_schema(&controller_readings("ev1")).unwrap());
        let text = String::from_utf8_lossy(&set);
        let described = readings_schema();
        for (name, field) in described["properties"].as_object().unwrap().iter().chain(
            described["properties"]["meb"]["properties"]
                .as_object()
                .unwrap(),
        ) {
            let meaning = field["description"].as_str().unwrap();
            assert!(text.contains(meaning), "{name}: {meaning}");
        }
    }

    /// Any serialisable value as the JSON value it is.
    mod erased {
        pub trait Json {
            fn json(&self) -> serde_json::Value;
        }
        impl<T: serde::Serialize> Json for T {
            fn json(&self) -> serde_json::Value {
                serde_json::to_value(self).unwrap()
            }
        }
    }
}
