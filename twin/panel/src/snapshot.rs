//! The engine's state as the panel shows it. A closure sent to the engine
//! copies the few values needed (no JSON on the engine's thread); the panel
//! turns them into the stream's `state` object on its own thread.

use nodes::firmware::{LightDetectorConfig, RegisterImage, ea, sd, status};
use nodes::master::{LoopMode, LoopState};
use serde_json::{Value, json};
use twin_realtime::device::SlaveAddress;
use twin_realtime::engine::RtCounters;
use twin_realtime::{Forces, RtEngine};
use twin_recording::topics::ReadingsSample;

/// One module's plant.
#[derive(Debug, Clone)]
pub struct ModuleState {
    pub name: String,
    pub sensors: plant::Sensors,
    pub actuators: plant::Actuators,
    /// Volts per ADC count at the pin, and each input's divider.
    pub adc_volts_per_count: f64,
    pub dac_full_volts: f64,
}

/// One slave's loop in a supervisor.
#[derive(Debug, Clone, Copy)]
pub struct SlaveLoop {
    pub id: u8,
    pub state: LoopState,
    pub set_point_rpm: Option<f64>,
    pub gains: Option<(f64, f64)>,
    pub mode: Option<LoopMode>,
}

/// One device (the EV controller, a Nano, a supervisor).
#[derive(Debug, Clone)]
pub struct DeviceState {
    pub name: String,
    pub image: Option<RegisterImage>,
    pub forces: Forces,
    pub readings: Option<ReadingsSample>,
    pub loops: Vec<SlaveLoop>,
    /// The light detector in use: its description and the fastest wheel
    /// it sees the flag at, rpm (a controller on a plant only).
    pub light: Option<(String, f64, bool)>,
    /// Its slave id and I/O map, when the page may change them.
    pub address: Option<SlaveAddress>,
}

#[derive(Debug, Clone)]
pub struct LinkState {
    pub name: String,
    pub protocol: &'static str,
    pub address: String,
    pub clients: usize,
    /// The serial line's speed and character format (`None` on TCP, which
    /// has no line): the scope draws every byte's bits at it.
    pub line: Option<protocols::link::SerialSettings>,
}

/// A serial line as the page reads it (`null`: a TCP link).
pub fn line_json(line: Option<&protocols::link::SerialSettings>) -> Value {
    use protocols::link::Parity;
    line.map_or(Value::Null, |l| {
        let parity = match l.parity {
            Parity::None => "N",
            Parity::Even => "E",
            Parity::Odd => "O",
        };
        json!({ "baud": l.baud, "data_bits": l.data_bits, "parity": parity, "stop_bits": l.stop_bits })
    })
}

/// What the engine hands the panel each stream period.
#[derive(Debug, Clone)]
pub struct EngineSnapshot {
    pub t: f64,
    pub modules: Vec<ModuleState>,
    pub devices: Vec<DeviceState>,
    pub links: Vec<LinkState>,
    pub counters: RtCounters,
    /// The fault in force (`bad-check`, `delay 20 ms`, …) and its link.
    pub fault: Option<(String, Option<String>)>,
    pub read_only: bool,
}

/// Reads the engine (run on its thread, the front locked: microseconds).
pub fn read(engine: &mut RtEngine) -> EngineSnapshot {
    let t = engine.clock.now().as_secs_f64();
    let now = engine.clock.now();
    let modules = engine
        .modules
        .iter()
        .map(|m| {
            let p = m.plant.params();
            let full = f64::from((1u32 << p.sensing.adc_bits.min(16)) - 1);
            ModuleState {
                name: m.name.clone(),
                sensors: *m.plant.sensors(),
                actuators: m.actuators,
                adc_volts_per_count: p.sensing.adc_reference_volts / full,
                dac_full_volts: 5.0,
            }
        })
        .collect();
    let light_params = engine
        .modules
        .first()
        .map(|m| m.plant.params().light.clone());
    let devices = engine
        .devices
        .iter_mut()
        .map(|d| {
            let loops = match d.node.supervisor_mut() {
                Some(s) => {
                    let ids: Vec<u8> = s.slave_ids().collect();
                    ids.into_iter()
                        .filter_map(|id| {
                            Some(SlaveLoop {
                                id,
                                state: s.loop_state(id)?,
                                set_point_rpm: s.set_point(id, now),
                                gains: s.gains(id),
                                mode: s.mode(id),
                            })
                        })
                        .collect()
                }
                None => Vec::new(),
            };
            let image = d.node.image_mut().map(|i| i.clone());
            // As the controller runs it now: a master may have changed
            // LDR_TH or LDR_ADAPT since the console said it at start.
            let light = image.as_ref().zip(light_params.as_ref()).map(|(i, p)| {
                let mut detector = LightDetectorConfig::for_sensor(p);
                detector.threshold_counts = i.stored.ldr_threshold;
                detector.adaptive = i.stored.ldr_adaptive & 1 != 0;
                (detector.describe(p), detector.max_rpm(p), detector.adaptive)
            });
            DeviceState {
                name: d.name.clone(),
                image,
                light,
                forces: d.forces,
                address: d.address.clone(),
                readings: d.node.controller_readings(),
                loops,
            }
        })
        .collect();
    let mut clients = vec![0usize; engine.links.len()];
    for (link, _) in engine.connections() {
        if let Some(c) = clients.get_mut(link) {
            *c += 1;
        }
    }
    let links = engine
        .links
        .iter()
        .zip(clients)
        .map(|(l, clients)| LinkState {
            name: l.name.clone(),
            protocol: l.protocol,
            address: l.address.clone(),
            clients,
            line: match l.spec.addr {
                protocols::link::LinkAddr::Serial(_) => Some(l.spec.serial),
                protocols::link::LinkAddr::Tcp(_) => None,
            },
        })
        .collect();
    let fault = engine.fault().map(|(f, link)| {
        (
            f.to_string(),
            link.and_then(|l| engine.links.get(l))
                .map(|l| l.name.clone()),
        )
    });
    EngineSnapshot {
        t,
        modules,
        devices,
        links,
        counters: engine.counters,
        fault,
        read_only: engine.read_only(),
    }
}

/// A digital output as the lab's I/O list names it: active low on the pin.
fn bit(word: u16, mask: u16) -> Value {
    json!({ "on": word & mask == 0, "pin": if word & mask == 0 { 0 } else { 1 } })
}

/// The status word `FD 00` as the lab's lamps.
pub fn lamps(word: u16) -> Value {
    json!({
        "battery_cut_off": word & status::BATTERY_CUT_OFF != 0,
        "over_current": word & status::OVER_CURRENT != 0,
        "brake": word & status::BRAKE != 0,
        "stalled": word & status::STALLED != 0,
        "charging": word & status::CHARGING != 0,
        "ccw": word & status::CCW != 0,
    })
}

/// An MEB word with its engineering value.
fn analog(counts: u16, value: f64, unit: &str) -> Value {
    json!({ "counts": counts, "value": value, "unit": unit })
}

fn image_json(image: &RegisterImage, readings: Option<&ReadingsSample>, forces: &Forces) -> Value {
    let w = &image.inputs;
    let r = readings;
    let stored = &image.stored;
    json!({
        "inputs": {
            "V1": analog(w[ea::V1], r.map_or(f64::NAN, |r| r.battery_volts), "V"),
            "V2": analog(w[ea::V2], r.map_or(f64::NAN, |r| r.bus_volts), "V"),
            "I": analog(w[ea::I], r.map_or(f64::NAN, |r| r.inverter_amps), "A"),
            "RPM_M": analog(w[ea::RPM_M], f64::from(w[ea::RPM_M]), "rpm"),
            "RPM_L": analog(w[ea::RPM_L], f64::from(w[ea::RPM_L]), "rpm"),
            "LDR": analog(w[ea::LDR], f64::from(w[ea::LDR]), "counts"),
            "SOC": analog(image.soc, f64::from(image.soc) / 10.0, "%"),
        },
        "ED0": image.hall,
        "ERRS": image.errs,
        "status": lamps(image.status),
        // The power-up outputs (SD0 = 0x001F, every pin high) for the page
        // to explain FR and CCW before any master wrote them.
        "sd0": stored.sd0,
        "outputs": {
            "VEL": { "counts": stored.vel, "max": image.dac_max(),
                     "value": f64::from(stored.vel) * 5.0 / f64::from(image.dac_max().max(1)), "unit": "V" },
            "EN": bit(stored.sd0, sd::EN),
            "BRK": bit(stored.sd0, sd::BRK),
            "PRO": bit(stored.sd0, sd::PRO),
            "DES": bit(stored.sd0, sd::DES),
            // FR is no active-low switch: its high pin turns the wheel
            // counter-clockwise, so "on" is reverse.
            "FR": { "on": stored.sd0 & sd::FR != 0, "pin": u8::from(stored.sd0 & sd::FR != 0) },
            "CHG": bit(stored.sd1, sd::CHG),
        },
        "variables": {
            "LDR_TH": stored.ldr_threshold,
            "RPM_WIN": stored.rpm_window_ms,
            "LDR_ADAPT": stored.ldr_adaptive & 1 != 0, // VD0 bit 0
        },
        "forced": forces_json(forces),
    })
}

fn forces_json(f: &Forces) -> Value {
    json!({
        "v1": f.v1, "v2": f.v2, "i": f.i,
        "rpm_m": f.rpm_m, "rpm_l": f.rpm_l, "ldr": f.ldr,
        "hall": f.hall, "flag": f.flag.map(|f| f.in_beam), "driver_fault": f.driver_fault,
    })
}

/// V1, V2 and I from the words a master read, through the lab module's
/// dividers (the master has no plant to ask).
fn volts(words: &[u16]) -> Value {
    let s = plant::params::SensingParams::default();
    let full = f64::from((1u32 << s.adc_bits.min(16)) - 1);
    let pin =
        |i: usize| f64::from(words.get(i).copied().unwrap_or(0)) / full * s.adc_reference_volts;
    json!({
        "V2": pin(ea::V2) * s.bus_divider,
        "I": (pin(ea::I) - s.current_zero_volts) / s.current_volts_per_amp,
        "V1": pin(ea::V1) * s.battery_divider,
    })
}

fn loop_json(l: &SlaveLoop) -> Value {
    let s = &l.state;
    let c = &s.counters;
    json!({
        "volts": volts(&s.inputs),
        "id": l.id,
        "set_point_rpm": l.set_point_rpm,
        "measured_rpm": s.measured_rpm,
        "error_rpm": s.error_rpm,
        "output": s.output,
        "vel_written": s.vel_written,
        "inputs": s.inputs,
        "kp": l.gains.map(|g| g.0),
        "ki": l.gains.map(|g| g.1),
        "mode": match l.mode {
            Some(LoopMode::Closed) => json!("loop"),
            Some(LoopMode::Open { vel }) => json!({ "manual": vel }),
            None => Value::Null,
        },
        "measured_at": s.measured_at.map(|t| crate::seconds(t.as_secs_f64())),
        "started": s.started,
        "counters": {
            "requests": c.requests, "replies": c.replies, "timeouts": c.timeouts,
            "bad_checks": c.bad_checks, "exceptions": c.exceptions, "retries": c.retries,
            "lost": c.lost,
        },
        "status": { "hall": s.status.hall, "flags": s.status.flags, "status": s.status.status,
                    "lamps": s.status.status.map(lamps) },
    })
}

impl EngineSnapshot {
    /// The stream's `state` object.
    pub fn to_json(&self) -> Value {
        let modules: Vec<Value> = self
            .modules
            .iter()
            .map(|m| {
                let s = &m.sensors;
                let a = &m.actuators;
                json!({
                    "name": m.name,
                    // The time the plant has reached: behind `t` while the
                    // engine catches up on late ticks.
                    "plant_t": crate::seconds(s.time_s),
                    "battery_volts": s.battery_volts,
                    "bus_volts": s.bus_volts,
                    "inverter_current": s.inverter_current,
                    "soc_percent": s.soc * 100.0,
                    "wheel_rpm": s.wheel_rpm,
                    "motor_rpm": s.motor_rpm,
                    "ldr_counts": s.ldr_counts,
                    "flag_in_beam": s.flag_in_beam,
                    "bms_trip": s.bms_trip.map(|t| t.to_string()),
                    "motor_tripped": s.motor_tripped,
                    "brake_applied": s.brake_applied,
                    "charging": s.charging,
                    "actuators": {
                        "vel_volts": a.vel_volts, "enable": a.enable, "brake": a.brake,
                        "boost": a.boost, "discharge": a.discharge, "reverse": a.reverse,
                        "charger": a.charger,
                    },
                })
            })
            .collect();
        let devices: Vec<Value> = self
            .devices
            .iter()
            .map(|d| {
                let mut v = json!({ "name": d.name });
                if let Some(image) = &d.image {
                    v["controller"] = image_json(image, d.readings.as_ref(), &d.forces);
                    if let Some((description, max_rpm, adaptive)) = &d.light {
                        v["controller"]["light_detector"] = json!({
                            "description": description, "max_rpm": max_rpm.round(), "adaptive": adaptive,
                        });
                    }
                }
                if let Some(r) = &d.readings {
                    v["readings"] = json!({
                        "hall_rpm": r.hall_rpm, "light_rpm": r.light_rpm,
                        "flag_dark": r.flag_dark, "soc_percent": r.soc_percent,
                        "battery_volts": r.battery_volts,
                    });
                }
                if let Some(a) = &d.address {
                    let map = a.meb_map.clone().unwrap_or_default();
                    v["slave"] = json!({
                        "id": a.id,
                        "map": twin_realtime::serve::map::to_text(&map),
                        "map_is_default": map.is_default(),
                    });
                }
                if !d.loops.is_empty() {
                    v["loops"] = Value::Array(d.loops.iter().map(loop_json).collect());
                }
                v
            })
            .collect();
        let links: Vec<Value> = self
            .links
            .iter()
            .map(|l| {
                json!({ "name": l.name, "protocol": l.protocol, "address": l.address,
                        "clients": l.clients, "line": line_json(l.line.as_ref()) })
            })
            .collect();
        json!({
            "t": crate::seconds(self.t),
            "modules": modules,
            "devices": devices,
            "links": links,
            "counters": self.counters,
            "fault": self.fault.as_ref().map(|(f, link)| json!({ "fault": f, "link": link })),
            "read_only_links": self.read_only,
        })
    }

    /// The trend point: set point, hall, light and true wheel rpm.
    pub fn trend(&self) -> [Option<f64>; 5] {
        let lp = self.devices.iter().flat_map(|d| d.loops.first()).next();
        let readings = self.devices.iter().find_map(|d| d.readings);
        let set_point = lp.and_then(|l| l.set_point_rpm);
        let (hall, light) = match (readings, lp) {
            (Some(r), _) => (Some(f64::from(r.hall_rpm)), Some(f64::from(r.light_rpm))),
            (None, Some(l)) => (
                Some(f64::from(l.state.inputs[ea::RPM_M])),
                Some(f64::from(l.state.inputs[ea::RPM_L])),
            ),
            _ => (None, None),
        };
        // The plant's true wheel; a supervisor has none: its loop's measurement.
        let wheel = self
            .modules
            .first()
            .map(|m| m.sensors.wheel_rpm.abs())
            .or(lp.map(|l| l.state.measured_rpm));
        [Some(self.t), set_point, hall, light, wheel]
    }
}
