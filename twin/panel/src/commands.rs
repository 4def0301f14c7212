//! The panel's commands: JSON bodies checked here, field by field (a
//! mistake names its field and changes nothing), then run on the engine's
//! thread as the console's commands are.

use nodes::firmware::Refusal;
use nodes::link::{Junk, JunkBytes, JunkPlace, MAX_JUNK};
use nodes::master::LoopMode;
use protocols::time::SimDuration;
use serde_json::{Map, Value, json};
use std::sync::Mutex;
use std::sync::mpsc::Sender;
use std::time::Duration;
use twin_realtime::forces::{Input, InputKind};
use twin_realtime::serve;
use twin_realtime::{Forces, Inbound, LinkFault, RtEngine};

/// A command refused: the HTTP status, the field at fault and why.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{message}")]
pub struct Rejected {
    pub status: u16,
    pub field: Option<String>,
    pub message: String,
}

impl Rejected {
    pub fn field(field: &str, message: impl Into<String>) -> Self {
        Self {
            status: 422,
            field: Some(field.into()),
            message: format!("{field}: {}", message.into()),
        }
    }

    pub fn body(message: impl Into<String>) -> Self {
        Self {
            status: 400,
            field: None,
            message: message.into(),
        }
    }

    pub fn to_json(&self) -> Value {
        json!({ "error": self.message, "field": self.field })
    }
}

/// What runs on the engine: the answer, or why it was refused.
pub type EngineCommand = Box<dyn FnOnce(&mut RtEngine) -> Result<Value, Rejected> + Send>;

/// The body as a JSON object, or a 400 that says what is wrong with it.
pub fn object(body: &[u8]) -> Result<Map<String, Value>, Rejected> {
    let value: Value = serde_json::from_slice(body).map_err(|e| {
        Rejected::body(format!(
            "the body is not JSON ({e}); send an object such as {{\"input\": \"v1\", \"value\": 30.5}}"
        ))
    })?;
    match value {
        Value::Object(map) => Ok(map),
        _ => Err(Rejected::body("the body must be a JSON object")),
    }
}

/// Refuses fields the command does not know (a typo would be ignored otherwise).
fn only(map: &Map<String, Value>, known: &[&str]) -> Result<(), Rejected> {
    match map.keys().find(|k| !known.contains(&k.as_str())) {
        Some(k) => Err(Rejected::field(
            k,
            format!("unknown field; this command takes {}", known.join(", ")),
        )),
        None => Ok(()),
    }
}

fn text<'a>(map: &'a Map<String, Value>, field: &str) -> Result<Option<&'a str>, Rejected> {
    match map.get(field) {
        None | Some(Value::Null) => Ok(None),
        Some(Value::String(s)) => Ok(Some(s)),
        Some(_) => Err(Rejected::field(field, "must be a string")),
    }
}

fn number(
    map: &Map<String, Value>,
    field: &str,
    range: std::ops::RangeInclusive<f64>,
) -> Result<Option<f64>, Rejected> {
    match map.get(field) {
        None | Some(Value::Null) => Ok(None),
        Some(v) => {
            let n = v
                .as_f64()
                .filter(|n| n.is_finite())
                .ok_or_else(|| Rejected::field(field, "must be a number"))?;
            if !range.contains(&n) {
                return Err(Rejected::field(
                    field,
                    format!("{n} is out of range {}-{}", range.start(), range.end()),
                ));
            }
            Ok(Some(n))
        }
    }
}

fn required<T>(value: Option<T>, field: &str) -> Result<T, Rejected> {
    value.ok_or_else(|| Rejected::field(field, "missing"))
}

/// The link named `name` (its name or protocol), or a 404 naming the links.
fn link_index(engine: &RtEngine, name: &str) -> Result<usize, Rejected> {
    engine
        .links
        .iter()
        .position(|l| l.name == name || l.protocol == name)
        .ok_or_else(|| {
            let names: Vec<&str> = engine.links.iter().map(|l| l.name.as_str()).collect();
            Rejected {
                status: 404,
                field: Some("link".into()),
                message: format!("link: no link `{name}` (links: {})", names.join(", ")),
            }
        })
}

/// `POST /api/force {"input": "v1", "value": 30.5}`: the controller measures
/// this value (V, A, rpm or counts for the words, a code for the hall
/// sensors, `true`/`false` or 1/0 for the flag and the driver fault) until
/// released. The range is the console's (`twin_realtime::forces::Input`).
pub fn force(map: &Map<String, Value>) -> Result<EngineCommand, Rejected> {
    only(map, &["input", "value"])?;
    let name = required(text(map, "input")?, "input")?;
    let input = Input::parse(name).map_err(|e| Rejected::field("input", e.to_string()))?;
    let value = match map.get("value") {
        None | Some(Value::Null) => return Err(Rejected::field("value", "missing")),
        Some(Value::Bool(b)) if input.kind() == InputKind::Switch => f64::from(u8::from(*b)),
        Some(v) => v.as_f64().ok_or_else(|| {
            Rejected::field("value", format!("must be a number: {}", input.takes()))
        })?,
    };
    let forced = input
        .value(value)
        .map_err(|e| Rejected::field("value", e.to_string()))?;
    Ok(Box::new(move |e: &mut RtEngine| {
        e.force(forced);
        let name = input.name();
        e.say(format!("panel: forced {name} = {forced}"));
        Ok(json!({ "forced": name }))
    }))
}

/// `POST /api/release {"input": "v1" | "all"}`.
pub fn release(map: &Map<String, Value>) -> Result<EngineCommand, Rejected> {
    only(map, &["input"])?;
    let name = required(text(map, "input")?, "input")?.to_ascii_lowercase();
    let input = match name.as_str() {
        "all" => None,
        other => Some(Input::parse(other).map_err(|_| {
            Rejected::field(
                "input",
                format!(
                    "cannot release `{other}`: v1, v2, i, rpm_m, rpm_l, ldr, hall, flag, driver_fault or all"
                ),
            )
        })?),
    };
    Ok(Box::new(move |e: &mut RtEngine| {
        for d in &mut e.devices {
            match input {
                Some(input) => d.forces.release(input),
                None => d.forces = Forces::default(),
            }
        }
        e.say(format!("panel: released {name}"));
        Ok(json!({ "released": name }))
    }))
}

/// The inputs the panel can force, with what each takes: the page builds
/// its sliders and switches from this (`GET /api/info`, `inputs`).
pub fn inputs_json() -> Value {
    Value::Array(
        Input::ALL
            .iter()
            .map(|i| {
                let r = i.range();
                json!({
                    "name": i.name(),
                    "label": i.label(),
                    "kind": match i.kind() {
                        InputKind::Analog => "analog",
                        InputKind::Code => "code",
                        InputKind::Switch => "switch",
                    },
                    "unit": i.unit(),
                    "min": r.start(),
                    "max": r.end(),
                    "step": i.step(),
                    "takes": i.takes(),
                })
            })
            .collect(),
    )
}

/// `POST /api/slave {"id": 5, "map": "[EA]\nV1 = 0\n..."}`: the module's
/// device number and I/O map, as `twin serve --id` and `--map` set them at
/// start, with their checks (the map's text is a map file's; empty: the
/// default map). Either may be left out.
pub fn slave(map: &Map<String, Value>) -> Result<EngineCommand, Rejected> {
    only(map, &["id", "map"])?;
    let id = match map.get("id") {
        None | Some(Value::Null) => None,
        Some(v) => {
            let n = v.as_f64().ok_or_else(|| {
                Rejected::field("id", "must be a number: a slave id takes 1 to 99 (as --id)")
            })?;
            Some(serve::check_id(n).map_err(|e| Rejected::field("id", e))?)
        }
    };
    let meb_map = match text(map, "map")? {
        None => None,
        Some(t) if t.trim().is_empty() => Some(nodes::firmware::MebMap::default()),
        Some(t) => {
            Some(serve::map::parse_text(t).map_err(|e| Rejected::field("map", e.to_string()))?)
        }
    };
    if id.is_none() && meb_map.is_none() {
        return Err(Rejected::body("nothing to change: give id, map or both"));
    }
    Ok(Box::new(move |e: &mut RtEngine| {
        let changed_map = meb_map.is_some();
        let a = serve::readdress(e, id, meb_map).map_err(|why| Rejected {
            status: 409,
            field: None,
            message: why.to_string(),
        })?;
        let mut said = format!("panel: the module answers as slave {:02}", a.id);
        if changed_map {
            said += match a.meb_map {
                Some(_) => " with the I/O map set on the page",
                None => " with the default I/O map",
            };
        }
        e.say(said);
        Ok(json!({ "id": a.id, "map_is_default": a.meb_map.is_none() }))
    }))
}

/// `POST /api/fault {"fault": "bad-check", "link": "meb"}`; `"off"` clears it.
/// One fault is in force at a time, on one link or (no `link`) on all.
pub fn fault(map: &Map<String, Value>) -> Result<EngineCommand, Rejected> {
    only(
        map,
        &[
            "fault",
            "link",
            "delay_ms",
            "code",
            "id",
            "gap_ms",
            "junk_count",
            "junk_hex",
            "junk_place",
        ],
    )?;
    let kind = required(text(map, "fault")?, "fault")?;
    let link = text(map, "link")?.map(str::to_string);
    let fault = match kind {
        "off" => None,
        "bad-check" => Some(LinkFault::BadCheck),
        "no-reply" => Some(LinkFault::NoReply),
        "delay" => {
            let ms = required(number(map, "delay_ms", 0.0..=60_000.0)?, "delay_ms")?;
            Some(LinkFault::Delay(SimDuration::from_secs_f64(ms / 1000.0)))
        }
        "exception" => {
            let code = number(map, "code", 1.0..=4.0)?.unwrap_or(4.0);
            Some(LinkFault::Exception(
                Refusal::from_code(code.round() as u8).unwrap_or(Refusal::DeviceFailure),
            ))
        }
        "wrong-id" => {
            let id = number(map, "id", 1.0..=247.0)?.map(|id| id.round() as u8);
            Some(LinkFault::WrongId(id))
        }
        "split" => {
            let ms = required(number(map, "gap_ms", 0.0..=10_000.0)?, "gap_ms")?;
            Some(LinkFault::Split(SimDuration::from_secs_f64(ms / 1000.0)))
        }
        "junk" => Some(LinkFault::Junk(junk(map)?)),
        other => {
            return Err(Rejected::field(
                "fault",
                format!(
                    "no fault `{other}`: bad-check, no-reply, delay, exception, wrong-id, split, \
                     junk or off"
                ),
            ));
        }
    };
    Ok(Box::new(move |e: &mut RtEngine| {
        let index = link.as_deref().map(|l| link_index(e, l)).transpose()?;
        e.set_fault(fault, index);
        let on = link.as_deref().unwrap_or("every link");
        match fault {
            Some(f) => e.say(format!("panel: fault {f} on {on}")),
            None => e.say("panel: fault off"),
        }
        Ok(json!({ "fault": fault.map(|f| f.to_string()), "link": link }))
    }))
}

/// A junk fault's bytes (`junk_count` random ones, or `junk_hex` these) and
/// place (`junk_place`: `before`, the default, or `after` each reply).
fn junk(map: &Map<String, Value>) -> Result<Junk, Rejected> {
    let count = number(map, "junk_count", 1.0..=MAX_JUNK as f64)?;
    let hex = text(map, "junk_hex")?;
    let bytes = match (count, hex) {
        (Some(_), Some(_)) => {
            return Err(Rejected::field(
                "junk_hex",
                "give junk_count (random bytes) or junk_hex (these bytes), not both",
            ));
        }
        (Some(n), None) => JunkBytes::random(n.round() as usize),
        (None, Some(hex)) => {
            let digits: Vec<char> = hex.chars().filter(|c| !c.is_whitespace()).collect();
            let bytes: Option<Vec<u8>> = digits
                .chunks(2)
                .map(|pair| {
                    let pair: String = pair.iter().collect();
                    (pair.len() == 2).then(|| u8::from_str_radix(&pair, 16).ok())?
                })
                .collect();
            bytes.and_then(|b| JunkBytes::given(&b))
        }
        (None, None) => JunkBytes::random(1),
    };
    let Some(bytes) = bytes else {
        return Err(Rejected::field(
            "junk_hex",
            format!("junk_hex takes 1 to {MAX_JUNK} bytes in hex, e.g. \"00ff7e\""),
        ));
    };
    let place = match text(map, "junk_place")? {
        None | Some("before") => JunkPlace::Before,
        Some("after") => JunkPlace::After,
        Some(other) => {
            return Err(Rejected::field(
                "junk_place",
                format!("junk_place is `before` or `after`, not `{other}`"),
            ));
        }
    };
    Ok(Junk { bytes, place })
}

/// `POST /api/loop {"slave": 1, "set_point_rpm": 2000, "kp": .., "ki": ..,
/// "mode": "loop" | "manual", "vel": counts}`: the supervisor's controls;
/// `manual` without `vel` holds the VEL the slave has.
pub fn supervise_loop(map: &Map<String, Value>) -> Result<EngineCommand, Rejected> {
    only(map, &["slave", "set_point_rpm", "kp", "ki", "mode", "vel"])?;
    let slave = number(map, "slave", 1.0..=99.0)?;
    let set_point = number(map, "set_point_rpm", 0.0..=20_000.0)?;
    let kp = number(map, "kp", 0.0..=1000.0)?;
    let ki = number(map, "ki", 0.0..=1000.0)?;
    let vel = number(map, "vel", 0.0..=nodes::master::VEL_MAX)?.map(|v| v.round() as u16);
    // `Some(None)`: manual at the VEL the slave holds, as a client's
    // `VD 10 0` does (a switch ticked off must not stop a turning wheel).
    let mode: Option<Option<LoopMode>> = match text(map, "mode")? {
        None => vel.map(|vel| Some(LoopMode::Open { vel })),
        Some("loop") => Some(Some(LoopMode::Closed)),
        Some("manual") => Some(vel.map(|vel| LoopMode::Open { vel })),
        Some(other) => {
            return Err(Rejected::field(
                "mode",
                format!("no mode `{other}`: loop or manual"),
            ));
        }
    };
    if set_point.is_none() && kp.is_none() && ki.is_none() && mode.is_none() {
        return Err(Rejected::body(
            "nothing to change: give set_point_rpm, kp, ki, mode or vel",
        ));
    }
    Ok(Box::new(move |e: &mut RtEngine| {
        let now = e.clock.now();
        for d in &mut e.devices {
            let Some(s) = d.node.supervisor_mut() else {
                continue;
            };
            let ids: Vec<u8> = match slave {
                Some(id) => vec![id as u8],
                None => s.slave_ids().collect(),
            };
            for id in &ids {
                if s.set_point(*id, now).is_none() {
                    return Err(Rejected {
                        status: 404,
                        field: Some("slave".into()),
                        message: format!("slave: the supervisor polls no slave {id}"),
                    });
                }
            }
            for id in ids {
                if let Some(rpm) = set_point {
                    s.set_set_point(id, Some(rpm));
                }
                if kp.is_some() || ki.is_some() {
                    let (old_kp, old_ki) = s.gains(id).unwrap_or((0.0, 0.0));
                    s.set_gains(id, kp.unwrap_or(old_kp), ki.unwrap_or(old_ki));
                }
                let held = || {
                    s.loop_state(id).map(|st| LoopMode::Open {
                        vel: st.vel_written.unwrap_or(st.output),
                    })
                };
                if let Some(mode) = mode.and_then(|m| m.or_else(held)) {
                    s.set_mode(id, mode);
                }
            }
            return Ok(json!({ "ok": true, "t": crate::seconds(now.as_secs_f64()) }));
        }
        Err(Rejected {
            status: 409,
            field: None,
            message: "this session has no supervisor (twin supervise has one)".into(),
        })
    }))
}

/// Runs `command` on the engine and waits for its answer.
pub async fn run_on_engine(
    engine: &Mutex<Sender<Inbound>>,
    command: EngineCommand,
) -> Result<Value, Rejected> {
    let (tx, rx) = tokio::sync::oneshot::channel();
    let sent = engine
        .lock()
        .map_err(|_| Rejected::body("the session is ending"))?
        .send(Inbound::Command(Box::new(move |e| {
            let _ = tx.send(command(e));
        })));
    if sent.is_err() {
        return Err(Rejected {
            status: 503,
            field: None,
            message: "the session has ended".into(),
        });
    }
    match tokio::time::timeout(Duration::from_secs(2), rx).await {
        Ok(Ok(answer)) => answer,
        _ => Err(Rejected {
            status: 503,
            field: None,
            message: "the engine did not answer (the session is ending?)".into(),
        }),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn map(text: &str) -> Map<String, Value> {
        object(text.as_bytes()).unwrap()
    }

    fn field_of(r: Result<EngineCommand, Rejected>) -> Option<String> {
        r.err().and_then(|e| e.field)
    }

    #[test]
    fn mistakes_name_their_field() {
        assert_eq!(object(b"{nope").unwrap_err().status, 400);
        assert!(force(&map(r#"{"input":"v1","value":30.5}"#)).is_ok());
        assert_eq!(
            field_of(force(&map(r#"{"input":"v9","value":1}"#))),
            Some("input".into())
        );
        assert_eq!(
            field_of(force(&map(r#"{"input":"v1","value":"x"}"#))),
            Some("value".into())
        );
        assert_eq!(
            field_of(force(&map(r#"{"input":"v1","value":1e9}"#))),
            Some("value".into())
        );
        assert_eq!(
            field_of(force(&map(r#"{"input":"v1","valu":3}"#))),
            Some("valu".into())
        );
        assert_eq!(
            field_of(fault(&map(r#"{"fault":"smoke"}"#))),
            Some("fault".into())
        );
        assert_eq!(
            field_of(fault(&map(r#"{"fault":"delay"}"#))),
            Some("delay_ms".into())
        );
        assert_eq!(
            field_of(supervise_loop(&map(r#"{"vel":99999}"#))),
            Some("vel".into())
        );
        assert!(supervise_loop(&map(r#"{"mode":"manual"}"#)).is_ok());
        assert!(force(&map(r#"{"input":"hall","value":5}"#)).is_ok());
        assert!(force(&map(r#"{"input":"flag","value":true}"#)).is_ok());
        assert_eq!(
            field_of(force(&map(r#"{"input":"hall","value":true}"#))),
            Some("value".into())
        );
        assert!(slave(&map(r#"{"id":7,"map":""}"#)).is_ok());
        assert_eq!(field_of(slave(&map(r#"{"id":0}"#))), Some("id".into()));
        assert_eq!(
            field_of(slave(&map(r#"{"map":"[EA]\nV1 = 0\nV2 = 0\n"}"#))),
            Some("map".into())
        );
        assert_eq!(slave(&map("{}")).err().map(|e| e.status), Some(400));
    }
}
