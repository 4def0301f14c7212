//! The step button of `twin supervise --web`: steps the set point, takes
//! every measurement the supervisor's polls bring (session time, hall and
//! light rpm as read) from half a second before the step to its end, and
//! computes the figures as `twin step` does (`twin_sim::step_metrics`), on
//! those samples instead of a recording's.

use serde_json::{Map, Value, json};
use std::time::Duration;

use std::sync::Mutex;
use std::sync::mpsc::Sender;

use crate::commands::{self, Rejected, run_on_engine};
use crate::hub::Hub;
use nodes::firmware::ea;
use twin_realtime::Inbound;

/// Longest step the button waits for, s.
const MAX_SECONDS: f64 = 25.0;

/// `POST /api/step {"to_rpm": 1500, "seconds": 6, "slave": 1}`.
pub async fn step(
    hub: &Hub,
    engine: &Mutex<Sender<Inbound>>,
    map: &Map<String, Value>,
) -> Result<Value, Rejected> {
    if let Some(k) = map
        .keys()
        .find(|k| !["to_rpm", "seconds", "slave"].contains(&k.as_str()))
    {
        return Err(Rejected::field(
            k,
            "unknown field; this command takes to_rpm, seconds, slave",
        ));
    }
    let field = |name: &str, lo: f64, hi: f64| -> Result<Option<f64>, Rejected> {
        match map.get(name) {
            None | Some(Value::Null) => Ok(None),
            Some(v) => match v.as_f64().filter(|n| n.is_finite()) {
                Some(n) if (lo..=hi).contains(&n) => Ok(Some(n)),
                Some(n) => Err(Rejected::field(
                    name,
                    format!("{n} is out of range {lo}-{hi}"),
                )),
                None => Err(Rejected::field(name, "must be a number")),
            },
        }
    };
    let to = field("to_rpm", 0.0, 20_000.0)?.ok_or_else(|| Rejected::field("to_rpm", "missing"))?;
    let seconds = field("seconds", 2.0, MAX_SECONDS)?.unwrap_or(6.0);
    let slave = field("slave", 1.0, 99.0)?;
    let before: Value = serde_json::from_str(&hub.latest()).unwrap_or(Value::Null);
    let stepped = before["state"]["devices"]
        .as_array()
        .into_iter()
        .flatten()
        .flat_map(|d| d["loops"].as_array().into_iter().flatten())
        .find(|l| slave.is_none_or(|s| l["id"].as_f64() == Some(s)));
    let from = stepped
        .and_then(|l| l["set_point_rpm"].as_f64())
        .unwrap_or(0.0);
    // A set point moves nothing while the loop is open: say so rather
    // than measure a signal that cannot follow.
    if let Some(vel) = stepped.and_then(|l| l["mode"]["manual"].as_u64()) {
        return Err(Rejected {
            status: 409,
            field: None,
            message: format!(
                "the loop is off (manual VEL {vel}): tick \"loop on\" to step the set point"
            ),
        });
    }
    let mut body = Map::new();
    body.insert("set_point_rpm".into(), json!(to));
    if let Some(s) = slave {
        body.insert("slave".into(), json!(s));
    }
    let command = commands::supervise_loop(&body)?;
    let id = slave.map(|s| s as u8);
    let mut rows: Vec<[f64; 4]> = Vec::new();
    collect(engine, id, Duration::from_millis(500), &mut rows).await?;
    // The step's instant: the session time the engine stepped it at.
    let answer = run_on_engine(engine, command).await?;
    let at = answer["t"].as_f64().unwrap_or(0.0);
    collect(
        engine,
        id,
        Duration::from_secs_f64(seconds + 0.2),
        &mut rows,
    )
    .await?;
    let t: Vec<f64> = rows.iter().map(|r| r[0]).collect();
    let col = |k: usize| -> Vec<f64> { rows.iter().map(|r| r[k]).collect() };
    let (hall, light, wheel) = (col(1), col(2), col(3));
    let options = twin_sim::step_metrics::StepOptions::default();
    let mut signals = Map::new();
    // The loop closes on one of the two readings: its own figures would
    // repeat that reading's, so it is named instead.
    let closes_on = if wheel == hall {
        Some("hall rpm")
    } else if wheel == light {
        Some("light rpm")
    } else {
        None
    };
    let mut shown = vec![("hall rpm", &hall), ("light rpm", &light)];
    if closes_on.is_none() {
        shown.insert(0, ("wheel (loop)", &wheel));
    }
    for (name, y) in shown {
        let figures = twin_sim::step_metrics::step_metrics(&t, y, at, Some(to), &options);
        let delay = (name == "light rpm")
            .then(|| twin_sim::step_metrics::delay(&t, &hall, y, at, 2.0).ok())
            .flatten();
        signals.insert(
            name.into(),
            match figures {
                Ok(m) => json!({ "metrics": m, "delay_s": delay }),
                Err(e) => json!({ "error": e.to_string() }),
            },
        );
    }
    Ok(json!({
        "from_rpm": from,
        "to_rpm": to,
        "step_at_s": at,
        "seconds": seconds,
        "samples": t.len(),
        // A busy machine delays the polls, and the figures with them.
        "largest_gap_ms": t.windows(2).map(|w| (w[1] - w[0]) * 1000.0).fold(0.0, f64::max),
        "signals": signals,
        "loop_closes_on": closes_on,
        "note": "figures as `twin step` computes them, on every measurement the supervisor's polls brought; the light reading's delay is measured behind the hall reading",
    }))
}

/// The loop's last measurement: session time, hall rpm, light rpm, and the
/// rpm the loop closes on.
async fn sample(
    engine: &Mutex<Sender<Inbound>>,
    slave: Option<u8>,
) -> Result<Option<[f64; 4]>, Rejected> {
    let read: commands::EngineCommand = Box::new(move |e| {
        let state = e
            .devices
            .iter_mut()
            .find_map(|d| d.node.supervisor_mut())
            .and_then(|s| {
                let id = slave.or_else(|| s.slave_ids().next())?;
                s.loop_state(id)
            });
        Ok(match state {
            Some(l) => match l.measured_at {
                Some(at) => json!([
                    at.as_secs_f64(),
                    l.inputs[ea::RPM_M],
                    l.inputs[ea::RPM_L],
                    l.measured_rpm
                ]),
                None => Value::Null,
            },
            None => Value::Null,
        })
    });
    let v = run_on_engine(engine, read).await?;
    Ok(v.as_array().and_then(|a| {
        let n = |i: usize| a.get(i).and_then(Value::as_f64);
        Some([n(0)?, n(1)?, n(2)?, n(3)?])
    }))
}

/// Every new measurement for `how_long`: the engine is asked more often
/// than the supervisor polls, so none is missed.
async fn collect(
    engine: &Mutex<Sender<Inbound>>,
    slave: Option<u8>,
    how_long: Duration,
    rows: &mut Vec<[f64; 4]>,
) -> Result<(), Rejected> {
    let end = tokio::time::Instant::now() + how_long;
    let mut tick = tokio::time::interval(Duration::from_millis(3));
    while tokio::time::Instant::now() < end {
        tick.tick().await;
        if let Some(row) = sample(engine, slave).await?
            && rows.last().is_none_or(|last| row[0] > last[0])
        {
            rows.push(row);
        }
    }
    Ok(())
}
