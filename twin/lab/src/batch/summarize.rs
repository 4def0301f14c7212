//! A batch's summaries gathered: one CSV row per entry, and a plot of one
//! column against another (a figure against a `--set` parameter, or against
//! another figure: light-sensor rpm against the true wheel rpm).

use super::BatchError;

type Result<T, E = BatchError> = std::result::Result<T, E>;
use std::collections::BTreeSet;
use std::path::Path;

use super::summary::{Status, Summary};
use crate::plot::{self, Axes, Series};

/// The columns every row starts with.
const FIRST: [&str; 7] = [
    "entry",
    "name",
    "status",
    "scenario",
    "seed",
    "simulated_s",
    "wall_s",
];

/// Every summary in `dir` (its `*.json` files), in manifest order.
pub fn gather(dir: &Path) -> Result<Vec<Summary>> {
    let unreadable = |source| BatchError::ReadDir {
        dir: dir.to_path_buf(),
        source,
    };
    let listing = std::fs::read_dir(dir).map_err(unreadable)?;
    let mut summaries = Vec::new();
    for item in listing {
        let path = item.map_err(unreadable)?.path();
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        // Temporary files start with a dot.
        if !name.ends_with(".json") || name.starts_with('.') {
            continue;
        }
        if let Some(s) = Summary::read(&path)? {
            summaries.push(s);
        }
    }
    if summaries.is_empty() {
        return Err(BatchError::NoSummaries {
            dir: dir.to_path_buf(),
        });
    }
    summaries.sort_by(|a, b| (a.entry, &a.name).cmp(&(b.entry, &b.name)));
    Ok(summaries)
}

/// The CSV's columns: the fixed ones, each `--set` path as `set.PATH`, each
/// figure, then where the recording is and why a run failed.
pub fn columns(summaries: &[Summary]) -> Vec<String> {
    let set: BTreeSet<&String> = summaries.iter().flat_map(|s| s.set.keys()).collect();
    let figures: BTreeSet<&String> = summaries
        .iter()
        .flat_map(|s| s.figures.keys())
        .filter(|k| !FIRST.contains(&k.as_str()))
        .collect();
    FIRST
        .iter()
        .map(|c| c.to_string())
        .chain(set.into_iter().map(|p| format!("set.{p}")))
        .chain(figures.into_iter().cloned())
        .chain(["recording".to_string(), "error".to_string()])
        .collect()
}

/// The text of `column` in a row; empty when the run has no such value.
pub fn cell(s: &Summary, column: &str) -> String {
    let number = |v: Option<f64>| v.map_or_else(String::new, |v| v.to_string());
    match column {
        "entry" => s.entry.to_string(),
        "name" => s.name.clone(),
        "status" => match s.status {
            Status::Ok => "ok".into(),
            Status::Failed => "failed".into(),
        },
        "scenario" => s.scenario.clone(),
        "seed" => s.seed.map_or_else(String::new, |v| v.to_string()),
        "simulated_s" => number(s.simulated_s),
        "wall_s" => number(Some(s.wall_s)),
        "recording" => s.recording.clone().unwrap_or_default(),
        "error" => s.error.clone().unwrap_or_default(),
        _ => match column.strip_prefix("set.").and_then(|p| s.set.get(p)) {
            Some(serde_json::Value::String(text)) => text.clone(),
            Some(v) => v.to_string(),
            None => number(s.figures.get(column).copied().flatten()),
        },
    }
}

/// The CSV text of `summaries`.
pub fn csv(summaries: &[Summary]) -> String {
    let columns = columns(summaries);
    let mut out = String::new();
    let line = |cells: Vec<String>, out: &mut String| {
        let quoted: Vec<String> = cells.iter().map(|c| quote(c)).collect();
        out.push_str(&quoted.join(","));
        out.push('\n');
    };
    line(columns.clone(), &mut out);
    for s in summaries {
        line(columns.iter().map(|c| cell(s, c)).collect(), &mut out);
    }
    out
}

/// A CSV field, quoted when it must be (RFC 4180).
fn quote(field: &str) -> String {
    if field.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", field.replace('"', "\"\""))
    } else {
        field.to_string()
    }
}

/// The column a user's name for it means: a column as the CSV heads it, or
/// a `--set` path without its `set.` prefix.
pub fn find_column(summaries: &[Summary], name: &str) -> Result<String> {
    let columns = columns(summaries);
    let set = format!("set.{name}");
    if let Some(c) = columns.iter().find(|c| *c == name || **c == set) {
        return Ok(c.clone());
    }
    let numeric: Vec<&str> = columns
        .iter()
        .map(String::as_str)
        .filter(|c| !["name", "status", "scenario", "recording", "error"].contains(c))
        .collect();
    Err(BatchError::NoColumn {
        name: name.to_string(),
        numeric: numeric.join(", "),
    })
}

/// What a plot drew.
#[derive(Debug, Clone, PartialEq)]
pub struct Plotted {
    /// Points drawn: one per run that succeeded and has both values.
    pub points: usize,
    /// Runs left out: failed, or without one of the values.
    pub left_out: usize,
}

/// Plot `y` against `x` (column names, see [`find_column`]) to a PNG: a
/// dot per run, and a line through the mean of the runs at each `x` (the
/// seeds of one setting, say).
pub fn plot(summaries: &[Summary], y: &str, x: &str, path: &Path) -> Result<Plotted> {
    let (x, y) = (find_column(summaries, x)?, find_column(summaries, y)?);
    let mut points = Vec::new();
    for s in summaries.iter().filter(|s| s.status == Status::Ok) {
        if let (Ok(a), Ok(b)) = (cell(s, &x).parse::<f64>(), cell(s, &y).parse::<f64>())
            && a.is_finite()
            && b.is_finite()
        {
            points.push((a, b));
        }
    }
    if points.is_empty() {
        return Err(BatchError::NothingToPlot { x, y });
    }
    points.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let mut means: Vec<(f64, f64)> = Vec::new();
    for group in points.chunk_by(|a, b| a.0 == b.0) {
        let mean = group.iter().map(|p| p.1).sum::<f64>() / group.len() as f64;
        means.push((group[0].0, mean));
    }
    let title = format!("{y} against {x}");
    let axes = Axes {
        title: &title,
        x_label: &x,
        y_label: &y,
        x_range: plot::fit_range(points.iter().map(|p| p.0), 0.05),
        y_range: plot::fit_range(points.iter().map(|p| p.1), 0.08),
        legend_upper_left: false,
    };
    let repeated = means.len() < points.len();
    let runs = Series {
        name: "each run",
        color: plot::MOTOR,
        points: points.clone(),
        dots: true,
        width: 0,
    };
    let mean = Series {
        name: if repeated { "mean of the runs" } else { "" },
        color: plot::WHEEL,
        points: means,
        dots: false,
        width: 2,
    };
    plot::line_plot(path, &axes, &[mean, runs], (900, 560))?;
    Ok(Plotted {
        points: points.len(),
        left_out: summaries.len() - points.len(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::collections::BTreeMap;

    fn summary(entry: usize, kp: f64, settling: Option<f64>) -> Summary {
        Summary {
            entry,
            name: format!("kp-{kp}"),
            status: Status::Ok,
            scenario: "ev-meb".into(),
            seed: Some(1),
            set: BTreeMap::from([("node.supervisor.kp".into(), serde_json::json!(kp))]),
            simulated_s: Some(2.0),
            wall_s: 0.5,
            recording: Some(format!("kp-{kp}.mcap")),
            figures: BTreeMap::from([("step.settling_s".into(), settling)]),
            error: None,
        }
    }

    #[test]
    fn csv_has_a_column_per_parameter_and_figure() {
        let mut failed = summary(2, 0.9, None);
        failed.status = Status::Failed;
        failed.error = Some("no scenario `x, y`".into());
        failed.figures.clear();
        let rows = [summary(0, 0.3, Some(1.25)), summary(1, 0.6, None), failed];
        let text = csv(&rows);
        let lines: Vec<&str> = text.lines().collect();
        assert_eq!(
            lines[0],
            "entry,name,status,scenario,seed,simulated_s,wall_s,set.node.supervisor.kp,step.settling_s,recording,error"
        );
        assert_eq!(lines[1], "0,kp-0.3,ok,ev-meb,1,2,0.5,0.3,1.25,kp-0.3.mcap,");
        assert_eq!(lines[2], "1,kp-0.6,ok,ev-meb,1,2,0.5,0.6,,kp-0.6.mcap,");
        assert!(
            lines[3].ends_with(",failed,ev-meb,1,2,0.5,0.9,,kp-0.9.mcap,\"no scenario `x, y`\""),
            "{}",
            lines[3]
        );
        assert_eq!(
            find_column(&rows, "node.supervisor.kp").unwrap(),
            "set.node.supervisor.kp"
        );
        let e = find_column(&rows, "kd").unwrap_err().to_string();
        assert!(e.contains("step.settling_s"), "{e}");
    }
}
