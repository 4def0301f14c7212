//! `POST /api/outputs`: VEL and the switches (EN, BRK, PRO, DES, FR, CHG)
//! set from the page. On `twin panel` the client writes them itself; on
//! `twin supervise` the supervisor forwards the SD words on its bus between
//! its polls, as it does a remote client's writes, in manual mode only (the
//! loop owns the module while it is closed).

use serde_json::{Map, Value, json};
use std::collections::BTreeMap;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use crate::commands::{EngineCommand, Rejected, run_on_engine};
use crate::remote::OutputRequest;
use crate::remote::layout::SWITCHES;
use crate::remote::state::pin_for;
use nodes::master::{LoopMode, StartupOutputs, WriteOutcome, WriteTicket};
use protocols::meb::MebCmd;
use twin_realtime::{Inbound, RtEngine};

/// The SD words the panel last had the supervisor write, per slave (MEB
/// outputs cannot be read back): the start-up outputs until then.
pub type Written = Arc<Mutex<BTreeMap<u8, [u16; 2]>>>;

const FIELDS: &str = "slave, vel, EN, BRK, PRO, DES, FR, CHG";

/// The body: `{"slave": 1, "vel": 2048, "EN": true, "FR": false}`.
pub fn parse(map: &Map<String, Value>) -> Result<(Option<u8>, OutputRequest), Rejected> {
    let mut request = OutputRequest::default();
    let mut slave = None;
    for (key, value) in map {
        let upper = key.to_ascii_uppercase();
        if let Some(i) = SWITCHES.iter().position(|(name, ..)| *name == upper) {
            let on = value
                .as_bool()
                .ok_or_else(|| Rejected::field(key, "must be true (on) or false (off)"))?;
            request.switches.push((i, on));
            continue;
        }
        let number = |lo: f64, hi: f64| {
            value
                .as_f64()
                .filter(|n| n.is_finite() && n.fract() == 0.0)
                .ok_or_else(|| Rejected::field(key, "must be a whole number"))
                .and_then(|n| {
                    (lo..=hi).contains(&n).then_some(n).ok_or_else(|| {
                        Rejected::field(key, format!("{n} is out of range {lo}-{hi}"))
                    })
                })
        };
        match key.as_str() {
            "vel" => request.vel = Some(number(0.0, 4095.0)? as u16),
            "slave" => slave = Some(number(1.0, 99.0)? as u8),
            _ => {
                return Err(Rejected::field(
                    key,
                    format!("unknown field; this command takes {FIELDS}"),
                ));
            }
        }
    }
    if request.vel.is_none() && request.switches.is_empty() {
        return Err(Rejected::body(format!("nothing to set: give {FIELDS}")));
    }
    Ok((slave, request))
}

/// The switches of slaves `ids` as the panel last had them written (the
/// start-up outputs until then), for the stream.
pub fn written_json(written: &Written, ids: impl Iterator<Item = u8>) -> Value {
    let mut w = written.lock().map(|w| w.clone()).unwrap_or_default();
    for id in ids {
        w.entry(id).or_insert_with(start_words);
    }
    let mut out = Map::new();
    for (id, words) in w {
        let mut s = Map::new();
        for &(name, word, bit) in &SWITCHES {
            let pin = words[usize::from(word)] >> bit & 1 == 1;
            s.insert(
                name.into(),
                json!({ "on": pin == pin_for(word, bit, true), "pin": u8::from(pin) }),
            );
        }
        out.insert(id.to_string(), Value::Object(s));
    }
    Value::Object(out)
}

fn start_words() -> [u16; 2] {
    let s = StartupOutputs::ENABLED_BRAKE_RELEASED;
    [s.sd0, s.sd1]
}

/// Sets VEL (manual mode) and the switches through the supervisor.
pub async fn supervise(
    engine: &Mutex<Sender<Inbound>>,
    written: &Written,
    slave: Option<u8>,
    request: OutputRequest,
) -> Result<Value, Rejected> {
    // The words are computed and kept on the engine's thread, where the
    // commands run one after the other: two clicks in quick succession each
    // start from the other's words, and the bus gets them in that order.
    let shadow = written.clone();
    let switches = request.switches.clone();
    let vel = request.vel;
    let queue: EngineCommand = Box::new(move |e: &mut RtEngine| {
        let now = e.clock.now();
        let Some(s) = e.devices.iter_mut().find_map(|d| d.node.supervisor_mut()) else {
            return Err(Rejected {
                status: 409,
                field: None,
                message: "this session has no supervisor (twin supervise has one)".into(),
            });
        };
        let id = match slave {
            Some(id) => id,
            None => s.slave_ids().next().unwrap_or(1),
        };
        let Some(mode) = s.mode(id) else {
            return Err(Rejected {
                status: 404,
                field: Some("slave".into()),
                message: format!("slave: the supervisor polls no slave {id}"),
            });
        };
        if let Some(vel) = vel {
            s.set_mode(id, LoopMode::Open { vel });
        } else if !switches.is_empty() && mode == LoopMode::Closed {
            return Err(Rejected {
                status: 409,
                field: None,
                message: "the speed loop is closed: switch it to manual (loop off) before setting the switches".into(),
            });
        }
        let mut kept = shadow
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let before = kept.get(&id).copied().unwrap_or_else(start_words);
        let mut words = before;
        let mut touched = [false; 2];
        for &(i, on) in &switches {
            let (_, word, bit) = SWITCHES[i];
            let at = usize::from(word);
            touched[at] = true;
            if pin_for(word, bit, on) {
                words[at] |= 1 << bit;
            } else {
                words[at] &= !(1 << bit);
            }
        }
        let mut tickets = Vec::new();
        for (addr, word) in words.iter().enumerate() {
            if !touched[addr] {
                continue;
            }
            let ticket = s
                .forward_write(now, id, MebCmd::SD, addr as u8, &[*word])
                .map_err(|e| Rejected {
                    status: 409,
                    field: None,
                    message: format!("the supervisor cannot write the switches: {e}"),
                })?;
            tickets.push(ticket.0);
        }
        kept.insert(id, words);
        Ok(json!({ "slave": id, "words": words, "before": before, "tickets": tickets }))
    });
    let queued = run_on_engine(engine, queue).await?;
    let id = queued["slave"].as_u64().unwrap_or(1) as u8;
    let tickets: Vec<u64> = queued["tickets"]
        .as_array()
        .into_iter()
        .flatten()
        .filter_map(Value::as_u64)
        .collect();
    let pair = |v: &Value| {
        [
            v[0].as_u64().unwrap_or(0) as u16,
            v[1].as_u64().unwrap_or(0) as u16,
        ]
    };
    for ticket in tickets {
        if let Err(e) = wait_outcome(engine, WriteTicket(ticket)).await {
            // Not written: the switches are shown as they were, unless a
            // later click has changed them since.
            if let Ok(mut w) = written.lock()
                && w.get(&id) == Some(&pair(&queued["words"]))
            {
                w.insert(id, pair(&queued["before"]));
            }
            return Err(e);
        }
    }
    Ok(json!({ "ok": true, "slave": id }))
}

/// Waits for the slave's answer to a forwarded write.
async fn wait_outcome(
    engine: &Mutex<Sender<Inbound>>,
    ticket: WriteTicket,
) -> Result<(), Rejected> {
    let start = Instant::now();
    loop {
        let ask: EngineCommand = Box::new(move |e: &mut RtEngine| {
            let outcome = e
                .devices
                .iter_mut()
                .find_map(|d| d.node.supervisor_mut())
                .and_then(|s| s.take_write_outcome(ticket));
            Ok(match outcome {
                None => Value::Null,
                Some(WriteOutcome::Acknowledged) => json!("ok"),
                Some(WriteOutcome::Refused(code)) => {
                    json!(format!("the slave refused the switches with ER {code:02}"))
                }
                Some(WriteOutcome::NoAnswer) => {
                    json!("the slave did not answer the write of the switches")
                }
            })
        });
        match run_on_engine(engine, ask).await? {
            Value::Null if start.elapsed() < Duration::from_secs(3) => {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Value::Null => {
                return Err(Rejected {
                    status: 504,
                    field: None,
                    message: "the switches' write got no answer in 3 s".into(),
                });
            }
            Value::String(s) if s == "ok" => return Ok(()),
            Value::String(s) => {
                return Err(Rejected {
                    status: 502,
                    field: None,
                    message: s,
                });
            }
            _ => return Ok(()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(text: &str) -> Map<String, Value> {
        crate::commands::object(text.as_bytes()).unwrap()
    }

    #[test]
    fn outputs_name_their_field() {
        let (slave, r) = parse(&map(r#"{"EN":true,"fr":false,"vel":2048,"slave":1}"#)).unwrap();
        assert_eq!(slave, Some(1));
        assert_eq!(r.vel, Some(2048));
        assert_eq!(r.switches, vec![(0, true), (4, false)]);
        for (body, field) in [
            (r#"{"vel":5000}"#, "vel"),
            (r#"{"vel":1.5}"#, "vel"),
            (r#"{"EN":"yes"}"#, "EN"),
            (r#"{"TURBO":true}"#, "TURBO"),
        ] {
            let e = parse(&map(body)).unwrap_err();
            assert_eq!(e.field.as_deref(), Some(field), "{body}: {e}");
            assert!(e.message.starts_with(field), "{e}");
        }
        assert_eq!(parse(&map("{}")).unwrap_err().status, 400);
    }

    #[test]
    fn switches_are_active_low_but_fr_whose_high_pin_is_reverse() {
        let w: Written = Arc::default();
        let j = written_json(&w, [1].into_iter());
        assert_eq!(j["1"]["EN"]["on"], true, "the start-up outputs enable");
        assert_eq!(j["1"]["BRK"]["on"], false, "and release the brake");
        assert_eq!(j["1"]["FR"]["on"], false, "forward");
        assert_eq!(j["1"]["CHG"]["on"], false);
    }
}
