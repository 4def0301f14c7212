//! One run as rerun entities, whether it comes live from the engine or from
//! an MCAP file afterwards: both feed the same [`RerunLogger`], so the live
//! view and `twin view` show the same entities with the same samples.
//!
//! Per module `<m>` (the scenario's module name, `bench` in open loop):
//!
//! | entity | from | one sample per |
//! |---|---|---|
//! | `<m>/speed/set_point` | the master's loop (`/master/<node>/loop`) | poll cycle |
//! | `<m>/speed/hall_rpm`, `<m>/speed/light_rpm` | the controller's readings (`/controller/<node>/readings`); in a recording without them, RPM_M, RPM_L in the slave's replies | readings sample, or reply carrying them |
//! | `<m>/speed/wheel_rpm` | the plant (`/plant/<m>/sensors`) | sensor sample |
//! | `<m>/voltage/V1`, `V2`, `<m>/current/I`, `<m>/soc/SOC` | the plant | sensor sample |
//! | `<m>/photoresistor/divider`, `threshold` | the plant; the firmware's fixed threshold (none for an adaptive detector) | sensor sample |
//! | `<m>/photoresistor/dips` | the firmware's detector run on the recorded samples | dip |
//! | `<m>/flag/in_beam`, `<m>/flag/detector_dark` | the plant; that detector | sensor sample |
//! | `<m>/motor_shaft/*` | Controller_network motor node (motor shaft rpm) | reply / sample |
//! | `bus/<bus>/frames` | every frame, as text (a real-time session's links: `bus/<link>/frames`) | frame |
//! | `realtime/lateness/p99_us`, `max_us` | a real-time session's `/realtime/lateness` | second |
//! | `events` | every node event | event |
//! | `<node>/firmware/…` | compiled firmware: its UART, pins, ADC inputs, cycles ([`firmware`]) | burst / 10 ms |

use crate::ViewError;
use nodes::firmware::{LightRpm, ea};
use protocols::meb::{MebCmd, MebRepr};
use protocols::modbus::{self, Adu, Request, Response};
use protocols::modbus8;
use protocols::time::{SimDuration, SimTime};
use rerun::components::{InterpolationMode, MarkerShape, TextLogLevel};
use rerun::{Color, RecordingStream, Scalars, SeriesLines, SeriesPoints, TextLog};
use serde::Deserialize;
use std::collections::BTreeMap;

use super::layout::{ControllerNetworkRole, ViewLayout};

pub mod firmware;
use twin_recording::topics::ReadingsSample;

/// The timeline every sample is placed on: simulated seconds.
pub const TIMELINE: &str = "sim_time";

/// What the view takes from one plant sample. Deserialises from the
/// recording's sensor messages and is made from [`plant::Sensors`] live.
#[derive(Debug, Clone, Copy, Default, Deserialize)]
pub struct PlantSample {
    pub battery_volts: f64,
    pub bus_volts: f64,
    pub inverter_current: f64,
    pub soc: f64,
    pub motor_rpm: f64,
    pub wheel_rpm: f64,
    pub ldr_volts: f64,
    pub ldr_counts: u16,
    pub flag_in_beam: bool,
}

impl From<&plant::Sensors> for PlantSample {
    fn from(s: &plant::Sensors) -> Self {
        Self {
            battery_volts: s.battery_volts,
            bus_volts: s.bus_volts,
            inverter_current: s.inverter_current,
            soc: s.soc,
            motor_rpm: s.motor_rpm,
            wheel_rpm: s.wheel_rpm,
            ldr_volts: s.ldr_volts,
            ldr_counts: s.ldr_counts,
            flag_in_beam: s.flag_in_beam,
        }
    }
}

/// Entity paths of one module, made once.
#[derive(Debug)]
struct ModulePaths {
    set_point: String,
    hall_rpm: String,
    light_rpm: String,
    wheel_rpm: String,
    v1: String,
    v2: String,
    current: String,
    soc: String,
    divider: String,
    threshold: String,
    dips: String,
    in_beam: String,
    dark: String,
    shaft_set_point: String,
    shaft_node_rpm: String,
    shaft_rpm: String,
}

impl ModulePaths {
    fn new(m: &str) -> Self {
        let p = |rest: &str| format!("{m}/{rest}");
        Self {
            set_point: p("speed/set_point"),
            hall_rpm: p("speed/hall_rpm"),
            light_rpm: p("speed/light_rpm"),
            wheel_rpm: p("speed/wheel_rpm"),
            v1: p("voltage/V1"),
            v2: p("voltage/V2"),
            current: p("current/I"),
            soc: p("soc/SOC"),
            divider: p("photoresistor/divider"),
            threshold: p("photoresistor/threshold"),
            dips: p("photoresistor/dips"),
            in_beam: p("flag/in_beam"),
            dark: p("flag/detector_dark"),
            shaft_set_point: p("motor_shaft/set_point"),
            shaft_node_rpm: p("motor_shaft/motor_node_rpm"),
            shaft_rpm: p("motor_shaft/motor_rpm"),
        }
    }
}

/// A module's paths and its light detector, fed the recorded samples.
#[derive(Debug)]
struct ModuleState {
    paths: ModulePaths,
    threshold_volts: f64,
    threshold_counts: u16,
    adaptive: bool,
    detector: Option<LightRpm>,
    last_sample_at: Option<f64>,
    config: nodes::firmware::LightDetectorConfig,
    /// The controller's readings are recorded: its speeds come from them,
    /// not from the replies that carry the same words less often.
    has_readings: bool,
}

/// A Modbus read request waiting for its reply: which registers it asked for.
#[derive(Debug, Clone, Copy)]
struct PendingRead {
    unit: u8,
    address: u16,
    quantity: u16,
}

/// Logs one run to a rerun recording stream.
#[derive(Debug)]
pub struct RerunLogger {
    rec: RecordingStream,
    layout: ViewLayout,
    modules: Vec<ModuleState>,
    bus_paths: BTreeMap<String, String>,
    /// Per bus: the last Modbus RTU input-register read sent by a master.
    pending_reads: BTreeMap<String, PendingRead>,
    /// Samples logged per entity, for the summary and the tests.
    pub samples: BTreeMap<String, u64>,
}

impl RerunLogger {
    /// Log the series styles (static) for every module of `layout`.
    pub fn new(rec: RecordingStream, layout: ViewLayout) -> Result<Self, ViewError> {
        // Only simulated time: no wall clock in the view.
        rec.set_log_time_enabled(false);
        rec.set_log_tick_enabled(false);
        let mut modules = Vec::new();
        for (i, m) in layout.modules.iter().enumerate() {
            let state = ModuleState {
                paths: ModulePaths::new(&m.name),
                threshold_volts: m.threshold_volts(),
                threshold_counts: m.light.threshold_counts,
                adaptive: m.light.adaptive,
                detector: None,
                last_sample_at: None,
                config: m.light,
                has_readings: false,
            };
            log_styles(&rec, &state.paths, layout.has_controller_network(i))?;
            modules.push(state);
        }
        if layout.realtime {
            log_lateness_styles(&rec)?;
        }
        Ok(Self {
            rec,
            layout,
            modules,
            bus_paths: BTreeMap::new(),
            pending_reads: BTreeMap::new(),
            samples: BTreeMap::new(),
        })
    }

    pub fn layout(&self) -> &ViewLayout {
        &self.layout
    }

    pub fn stream(&self) -> &RecordingStream {
        &self.rec
    }

    fn scalar(&mut self, path_of: impl Fn(&ModulePaths) -> &String, m: usize, value: f64) {
        let Some(state) = self.modules.get(m) else {
            return;
        };
        let path = path_of(&state.paths);
        // A sink that fails reports it on flush; logging goes on meanwhile.
        let _ = self.rec.log(path.as_str(), &Scalars::single(value));
        if let Some(n) = self.samples.get_mut(path) {
            *n += 1;
        } else {
            self.samples.insert(path.clone(), 1);
        }
    }

    fn at(&self, t: f64) {
        self.rec.set_duration_secs(TIMELINE, t);
    }

    /// One plant sample of module `module` at `t` seconds.
    pub fn plant(&mut self, module: &str, t: f64, s: &PlantSample) {
        let Some(m) = self.layout.module_index(module) else {
            return;
        };
        self.at(t);
        self.scalar(|p| &p.wheel_rpm, m, s.wheel_rpm);
        self.scalar(|p| &p.v1, m, s.battery_volts);
        self.scalar(|p| &p.v2, m, s.bus_volts);
        self.scalar(|p| &p.current, m, s.inverter_current);
        self.scalar(|p| &p.soc, m, s.soc * 100.0);
        self.scalar(|p| &p.divider, m, s.ldr_volts);
        // An adaptive detector's threshold follows the signal: no fixed line.
        if !self.modules[m].adaptive {
            let threshold = self.modules[m].threshold_volts;
            self.scalar(|p| &p.threshold, m, threshold);
        }
        self.scalar(|p| &p.in_beam, m, f64::from(u8::from(s.flag_in_beam)));
        if self.layout.has_controller_network(m) {
            self.scalar(|p| &p.shaft_rpm, m, s.motor_rpm);
        }

        // The firmware's own detector, sampled at the recording's rate (its
        // trackers need that period: it is known from the second sample on).
        let state = &mut self.modules[m];
        let previous = state.last_sample_at.replace(t);
        let mut dark = false;
        let mut dip = false;
        if let Some(previous) = previous {
            let config = state.config;
            let period = SimDuration::from_secs_f64((t - previous).max(1e-6));
            let detector = state
                .detector
                .get_or_insert_with(|| LightRpm::new(config, period));
            let was_dark = detector.dark();
            let now = SimTime::ZERO + SimDuration::from_secs_f64(t);
            detector.tick(now, s.ldr_counts, state.threshold_counts, state.adaptive);
            dark = detector.dark();
            dip = dark && !was_dark;
        }
        self.scalar(|p| &p.dark, m, f64::from(u8::from(dark)));
        if dip {
            self.scalar(|p| &p.dips, m, s.ldr_volts);
        }
    }

    /// An EV controller's readings (`/controller/<node>/readings`) at `t`:
    /// its hall and light rpm, on the speed plot beside the wheel's.
    pub fn readings(&mut self, node: &str, t: f64, r: &ReadingsSample) {
        let Some(m) = self.layout.module_of_node(node) else {
            return;
        };
        self.at(t);
        self.modules[m].has_readings = true;
        self.scalar(|p| &p.hall_rpm, m, f64::from(r.hall_rpm));
        self.scalar(|p| &p.light_rpm, m, f64::from(r.light_rpm));
    }

    /// One frame on bus `bus`, sent by node `from` over `[start, end]`.
    pub fn frame(&mut self, bus: &str, from: &str, start: f64, end: f64, bytes: &[u8]) {
        self.at(start);
        self.speeds_in_frame(bus, from, bytes);
        let shown = match std::str::from_utf8(bytes) {
            Ok(text)
                if bytes
                    .iter()
                    .all(|b| b.is_ascii_graphic() || b.is_ascii_whitespace()) =>
            {
                text.trim_end().to_string()
            }
            _ => bytes
                .iter()
                .map(|b| format!("{b:02x}"))
                .collect::<Vec<_>>()
                .join(" "),
        };
        let decoded = twin_recording::describe::decode_any(bytes);
        let level = if decoded.get("error").is_some() {
            TextLogLevel::WARN
        } else {
            TextLogLevel::INFO
        };
        let line = format!(
            "{from}: {shown}   ({:.3} ms) {decoded}",
            (end - start) * 1e3
        );
        let path = self
            .bus_paths
            .entry(bus.to_string())
            .or_insert_with(|| format!("bus/{bus}/frames"))
            .clone();
        let _ = self
            .rec
            .log(path.as_str(), &TextLog::new(line).with_level(level));
        *self.samples.entry(path).or_default() += 1;
    }

    /// A node's event (timeout, bad check, retry, state change, log line).
    pub fn event(&mut self, node: &str, t: f64, kind: &str, detail: &str) {
        self.at(t);
        let level = match kind {
            // A real-time session's clients coming and going.
            "log" | "state" | "connection" => TextLogLevel::INFO,
            "fault" | "trip" => TextLogLevel::ERROR,
            _ => TextLogLevel::WARN,
        };
        let line = format!("{node} {kind}: {detail}");
        let _ = self.rec.log(EVENTS, &TextLog::new(line).with_level(level));
        *self.samples.entry(EVENTS.into()).or_default() += 1;
    }

    /// A master's loop report (`/master/<node>/loop`): the set point per slave.
    pub fn master_loop(&mut self, node: &str, t: f64, report: &serde_json::Value) {
        let Some(loops) = report.get("loops").and_then(|l| l.as_array()) else {
            return;
        };
        self.at(t);
        for l in loops {
            let (Some(id), Some(set_point)) = (
                l.get("slave").and_then(serde_json::Value::as_u64),
                l.get("set_point_rpm").and_then(serde_json::Value::as_f64),
            ) else {
                continue;
            };
            let Some(m) = u8::try_from(id)
                .ok()
                .and_then(|id| self.layout.module_of_slave(node, id))
            else {
                continue;
            };
            self.scalar(|p| &p.set_point, m, set_point);
        }
    }

    /// The rpm words a slave's reply carries: RPM_M and RPM_L of an EV
    /// controller (MEB `EA` or Modbus input registers), the Controller_network
    /// nodes' readings, and the Controller_network master's set-point writes.
    fn speeds_in_frame(&mut self, bus: &str, from: &str, bytes: &[u8]) {
        if let Some(m) = self.layout.module_of_node(from) {
            if self.modules[m].has_readings {
                return;
            }
            let words: Option<(usize, Vec<u16>)> = if bytes.first() == Some(&b'@') {
                MebRepr::parse(bytes)
                    .ok()
                    .filter(|r| r.cmd == MebCmd::EA && !r.data.as_slice().is_empty())
                    .map(|r| (usize::from(r.addr), r.data.as_slice().to_vec()))
            } else {
                self.modbus_reply(bus, bytes)
            };
            if let Some((addr, words)) = words {
                let word = |i: usize| i.checked_sub(addr).and_then(|k| words.get(k)).copied();
                if let Some(v) = word(ea::RPM_M) {
                    self.scalar(|p| &p.hall_rpm, m, f64::from(v));
                }
                if let Some(v) = word(ea::RPM_L) {
                    self.scalar(|p| &p.light_rpm, m, f64::from(v));
                }
            }
            return;
        }
        if let Some((m, role)) = self.layout.controller_network_node(from) {
            let Ok(f) = modbus8::Modbus8Repr::parse(bytes, modbus8::CrcOrder::HighFirst) else {
                return;
            };
            match (role, f.function, f.addr) {
                (ControllerNetworkRole::Motor, 3, 5) => {
                    self.scalar(|p| &p.shaft_node_rpm, m, f64::from(f.value));
                }
                // The light node's register holds the smoothed wheel rpm × 100.
                (ControllerNetworkRole::Light, 3, 6) => {
                    self.scalar(|p| &p.light_rpm, m, f64::from(f.value) / 100.0);
                }
                _ => {}
            }
            return;
        }
        // A master's frame: remember a Modbus read so that its reply can
        // be read; the Controller_network master's set-point write to the motor node
        // (register 9; until the first one the node runs its default 10000).
        let read = with_modbus(bytes, |unit, pdu| match Request::parse(pdu) {
            Ok(Request::ReadInputRegisters { address, quantity }) => Some(PendingRead {
                unit,
                address,
                quantity,
            }),
            _ => None,
        });
        if let Some(read) = read {
            self.pending_reads.insert(bus.to_string(), read);
        }
        if let Ok(f) = modbus8::Modbus8Repr::parse(bytes, modbus8::CrcOrder::HighFirst)
            && f.function == 6
            && f.id == 1
            && f.addr == 9
            && let Some(m) = self.layout.controller_network_motor_module()
        {
            self.scalar(|p| &p.shaft_set_point, m, f64::from(f.value));
        }
    }

    /// The registers of a Modbus reply (RTU, TCP or ASCII) to the last read
    /// on `bus`.
    fn modbus_reply(&mut self, bus: &str, bytes: &[u8]) -> Option<(usize, Vec<u16>)> {
        let pending = self.pending_reads.get(bus).copied()?;
        let words = with_modbus(bytes, |unit, pdu| {
            if unit != pending.unit {
                return None;
            }
            let Ok(Ok(Response::ReadInputRegisters(registers))) = Response::parse(pdu) else {
                return None;
            };
            let words = registers.as_slice();
            (words.len() == usize::from(pending.quantity)).then(|| words.to_vec())
        })?;
        self.pending_reads.remove(bus);
        Some((usize::from(pending.address), words))
    }

    /// One second of a real-time session's tick lateness (`/realtime/lateness`).
    pub fn lateness(&mut self, t: f64, window: &LatenessSample) {
        self.at(t);
        for (path, value) in [(LATENESS_P99, window.p99_us), (LATENESS_MAX, window.max_us)] {
            let _ = self.rec.log(path, &Scalars::single(value));
            *self.samples.entry(path.to_string()).or_default() += 1;
        }
    }

    /// Push everything logged so far to the sink.
    pub fn flush(&self) -> Result<(), ViewError> {
        self.rec.flush_blocking().map_err(ViewError::SinkRefused)
    }
}

/// Entities of a real-time session's tick lateness.
pub const LATENESS_P99: &str = "realtime/lateness/p99_us";
pub const LATENESS_MAX: &str = "realtime/lateness/max_us";
/// The entity the tick lateness plots sit under (rerun entity paths, not
/// recording topics).
pub const LATENESS: &str = "realtime/lateness";
/// The entity of every node event, as text.
pub const EVENTS: &str = "events";

/// What the view takes from one second of tick lateness (the `window` of a
/// `/realtime/lateness` message).
#[derive(Debug, Clone, Copy, Default, Deserialize)]
pub struct LatenessSample {
    pub p99_us: f64,
    pub max_us: f64,
}

/// `f` applied to the unit id and PDU of `bytes` read as a Modbus frame in
/// whichever framing it checks as: RTU (serial links, the simulated bus), TCP
/// or ASCII.
fn with_modbus<R>(bytes: &[u8], f: impl FnOnce(u8, &[u8]) -> Option<R>) -> Option<R> {
    if let Ok(frame) = modbus::rtu::RtuFrame::new_checked(bytes) {
        return f(frame.unit(), frame.pdu());
    }
    if let Ok(frame) = modbus::tcp::TcpFrame::new_checked(bytes) {
        return f(frame.unit(), frame.pdu());
    }
    let mut scratch = [0; modbus::ascii::MAX_BINARY_LEN];
    match modbus::ascii::AsciiFrame::decode_line(bytes, &mut scratch) {
        Ok(frame) => f(frame.unit(), frame.pdu()),
        Err(_) => None,
    }
}

/// The styles of the lateness series (static, logged once).
fn log_lateness_styles(rec: &RecordingStream) -> Result<(), ViewError> {
    let line = |name: &str, rgb: [u8; 3]| {
        SeriesLines::new()
            .with_names([name])
            .with_colors([Color::from_rgb(rgb[0], rgb[1], rgb[2])])
            .with_widths([1.5])
            .with_interpolation_mode(InterpolationMode::StepAfter)
    };
    rec.log_static(
        LATENESS_P99,
        &line("tick lateness p99 (µs)", [60, 120, 220]),
    )?;
    rec.log_static(LATENESS_MAX, &line("tick lateness max (µs)", [220, 40, 40]))?;
    Ok(())
}

/// Names, colours and line styles of a module's series (static, logged once).
fn log_styles(
    rec: &RecordingStream,
    p: &ModulePaths,
    controller_network: bool,
) -> Result<(), ViewError> {
    let line = |name: &str, rgb: [u8; 3], width: f32| {
        SeriesLines::new()
            .with_names([name])
            .with_colors([Color::from_rgb(rgb[0], rgb[1], rgb[2])])
            .with_widths([width])
    };
    let step = |l: SeriesLines| l.with_interpolation_mode(InterpolationMode::StepAfter);
    // Drawn on the viewer's dark background.
    const WHITE: [u8; 3] = [235, 235, 235];
    const ORANGE: [u8; 3] = [230, 120, 20];
    const GREEN: [u8; 3] = [40, 170, 60];
    const BLUE: [u8; 3] = [60, 120, 220];
    const GREY: [u8; 3] = [150, 150, 150];
    const RED: [u8; 3] = [220, 40, 40];
    const PURPLE: [u8; 3] = [150, 80, 200];
    let styles = [
        (&p.set_point, step(line("set point", WHITE, 2.0))),
        (
            &p.hall_rpm,
            step(line("motor (hall) rpm, RPM_M", ORANGE, 2.0)),
        ),
        (
            &p.light_rpm,
            step(line("light-sensor rpm, RPM_L", GREEN, 2.0)),
        ),
        (&p.wheel_rpm, line("true wheel rpm (plant)", GREY, 1.0)),
        (&p.v1, line("V1 battery (V)", BLUE, 1.5)),
        (&p.v2, line("V2 DC bus (V)", ORANGE, 1.5)),
        (&p.current, line("I inverter (A)", RED, 1.5)),
        (&p.soc, line("SOC (%)", GREEN, 1.5)),
        (&p.divider, line("photoresistor divider (V)", PURPLE, 1.0)),
        (&p.threshold, line("dark threshold (V)", GREY, 1.0)),
        (
            &p.in_beam,
            step(line("flag in the beam (plant)", GREY, 1.5)),
        ),
        (
            &p.dark,
            step(line("detector sees dark (ED0 bit 3)", RED, 1.5)),
        ),
    ];
    let shaft = [
        (&p.shaft_set_point, step(line("set point", WHITE, 2.0))),
        (&p.shaft_node_rpm, step(line("motor node rpm", ORANGE, 2.0))),
        (&p.shaft_rpm, line("true motor rpm (plant)", GREY, 1.0)),
    ];
    for (path, style) in styles {
        rec.log_static(path.as_str(), &style)?;
    }
    if controller_network {
        for (path, style) in shaft {
            rec.log_static(path.as_str(), &style)?;
        }
    }
    rec.log_static(
        p.dips.as_str(),
        &SeriesPoints::new()
            .with_names(["dip detected"])
            .with_colors([Color::from_rgb(RED[0], RED[1], RED[2])])
            .with_markers([MarkerShape::Down])
            .with_marker_sizes([4.0]),
    )?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::layout::{OPEN_LOOP_MODULE, ViewLayout};

    fn logger() -> RerunLogger {
        let (rec, _storage) = rerun::RecordingStreamBuilder::new("test")
            .memory()
            .expect("memory stream");
        let params = plant::PlantParams::preset("vemodule").expect("preset");
        RerunLogger::new(rec, ViewLayout::open_loop(&params)).expect("logger")
    }

    #[test]
    fn every_flag_pass_below_the_threshold_is_one_dip() {
        let mut log = logger();
        let threshold = log.layout().modules[0].light.threshold_counts;
        // 1 s at 200 Hz; the flag darkens the cell for 3 samples every 100 ms.
        for k in 0..200 {
            let dark = k % 20 >= 10 && k % 20 < 13;
            let counts = if dark {
                threshold - 400
            } else {
                threshold + 400
            };
            let s = PlantSample {
                ldr_counts: counts,
                flag_in_beam: dark,
                ..PlantSample::default()
            };
            log.plant(OPEN_LOOP_MODULE, f64::from(k) * 0.005, &s);
        }
        assert_eq!(log.samples["bench/photoresistor/dips"], 10);
        assert_eq!(log.samples["bench/flag/detector_dark"], 200);
        assert_eq!(log.samples["bench/speed/wheel_rpm"], 200);
    }

    #[test]
    fn rpm_words_come_from_the_slaves_ea_replies_only() {
        let scenario = twin_sim::scenario::Scenario::load("ev-meb").expect("scenario");
        let layout = ViewLayout::of_scenario(&scenario).expect("layout");
        let (rec, _storage) = rerun::RecordingStreamBuilder::new("test")
            .memory()
            .expect("memory stream");
        let mut log = RerunLogger::new(rec, layout).expect("logger");
        // The supervisor's read request carries no data: no speed.
        log.frame("rs485", "supervisor", 0.0, 0.001, b"@01EA000643*\n");
        assert!(!log.samples.contains_key("ev1/speed/hall_rpm"));
        // The controller's reply, as recorded: V2, I, V1, RPM_M, RPM_L, LDR.
        log.frame(
            "rs485",
            "ev1",
            0.002,
            0.005,
            b"@01EA00060BD608000D05000000000CCF4C*\n",
        );
        assert_eq!(log.samples["ev1/speed/hall_rpm"], 1);
        assert_eq!(log.samples["ev1/speed/light_rpm"], 1);
        // Garbage is logged as a frame, and feeds nothing.
        log.frame("rs485", "ev1", 0.006, 0.007, &[0xff, 0x00, 0x40]);
        assert_eq!(log.samples["bus/rs485/frames"], 3);
        assert_eq!(log.samples["ev1/speed/hall_rpm"], 1);
        // The master's loop report gives the set point of slave 1.
        let report = serde_json::json!({ "loops": [{ "slave": 1, "set_point_rpm": 1500.0 }] });
        log.master_loop("supervisor", 0.01, &report);
        log.master_loop("someone-else", 0.01, &report);
        assert_eq!(log.samples["ev1/speed/set_point"], 1);
    }

    #[test]
    fn the_controllers_readings_put_hall_and_light_rpm_beside_the_wheel() {
        let scenario = twin_sim::scenario::Scenario::load("ev-meb").expect("scenario");
        let layout = ViewLayout::of_scenario(&scenario).expect("layout");
        // The default scenario's detector is adaptive: no fixed threshold line.
        assert!(layout.modules[0].light.adaptive);
        let (rec, _storage) = rerun::RecordingStreamBuilder::new("test")
            .memory()
            .expect("memory stream");
        let mut log = RerunLogger::new(rec, layout).expect("logger");
        let readings = ReadingsSample {
            battery_volts: 40.0,
            bus_volts: 40.0,
            inverter_amps: 0.2,
            hall_rpm: 1500,
            light_rpm: 1463,
            flag_dark: false,
            soc_percent: 90.0,
            meb: twin_recording::topics::MebWords::default(),
        };
        for k in 0..3 {
            let t = f64::from(k) * 0.005;
            log.plant("ev1", t, &PlantSample::default());
            log.readings("ev1", t, &readings);
        }
        // A node that is no module's controller feeds nothing.
        log.readings("supervisor", 0.0, &readings);
        assert_eq!(log.samples["ev1/speed/hall_rpm"], 3);
        assert_eq!(log.samples["ev1/speed/light_rpm"], 3);
        assert_eq!(log.samples["ev1/speed/wheel_rpm"], 3);
        assert!(!log.samples.contains_key("ev1/photoresistor/threshold"));
        // With the readings recorded, the replies carrying the same words
        // are not plotted twice.
        log.frame(
            "rs485",
            "ev1",
            0.02,
            0.023,
            b"@01EA00060BD608000D05000000000CCF4C*\n",
        );
        assert_eq!(log.samples["ev1/speed/hall_rpm"], 3);
    }

    /// Writes a request and its reply in one framing; returns both lengths.
    type EmitBoth = fn(&Request, &Response, &mut [u8], &mut [u8]) -> (usize, usize);

    #[test]
    fn input_register_replies_give_rpm_in_rtu_tcp_and_ascii_framing() {
        use protocols::modbus::{Registers, ascii, rtu, tcp};
        let params = plant::PlantParams::default();
        let (rec, _storage) = rerun::RecordingStreamBuilder::new("test")
            .memory()
            .expect("memory stream");
        let mut log = RerunLogger::new(rec, ViewLayout::of_serve(&params, true, false, false))
            .expect("logger");
        let read = Request::ReadInputRegisters {
            address: 2,
            quantity: 3,
        };
        // V1, RPM_M, RPM_L: registers 2-4 as the EA block's.
        let reply = Response::ReadInputRegisters(
            Registers::from_slice(&[3333, 1500, 1490]).expect("registers"),
        );
        let mut request_bytes = [0u8; 300];
        let mut reply_bytes = [0u8; 300];
        let framings: [(&str, EmitBoth); 3] = [
            ("rtu", |q, r, a, b| {
                (
                    rtu::RtuRepr { unit: 1, pdu: q }.emit(a).unwrap(),
                    rtu::RtuRepr { unit: 1, pdu: r }.emit(b).unwrap(),
                )
            }),
            ("tcp", |q, r, a, b| {
                (
                    tcp::TcpRepr {
                        transaction_id: 7,
                        unit: 1,
                        pdu: q,
                    }
                    .emit(a)
                    .unwrap(),
                    tcp::TcpRepr {
                        transaction_id: 7,
                        unit: 1,
                        pdu: r,
                    }
                    .emit(b)
                    .unwrap(),
                )
            }),
            ("ascii", |q, r, a, b| {
                (
                    ascii::AsciiRepr { unit: 1, pdu: q }.emit(a).unwrap(),
                    ascii::AsciiRepr { unit: 1, pdu: r }.emit(b).unwrap(),
                )
            }),
        ];
        for (k, (link, emit)) in framings.into_iter().enumerate() {
            let (n, m) = emit(&read, &reply, &mut request_bytes, &mut reply_bytes);
            // A reply nobody asked for is not read.
            log.frame(link, "ev1", 0.0, 0.001, &reply_bytes[..m]);
            log.frame(link, "client 1", 0.0, 0.001, &request_bytes[..n]);
            log.frame(link, "ev1", 0.002, 0.003, &reply_bytes[..m]);
            let k = k as u64 + 1;
            assert_eq!(log.samples["ev1/speed/hall_rpm"], k, "{link}");
            assert_eq!(log.samples["ev1/speed/light_rpm"], k, "{link}");
        }
        log.lateness(
            1.0,
            &LatenessSample {
                p99_us: 20.0,
                max_us: 900.0,
            },
        );
        assert_eq!(log.samples[LATENESS_P99], 1);
        assert_eq!(log.samples[LATENESS_MAX], 1);
    }
}
