//! Trial parameters written into a scenario, by their path in a plant
//! parameter file.

use super::CalibrateError;
use plant::PlantParams;
use twin_sim::scenario::Scenario;

/// Whether `path` names a number of the plant's parameters.
pub fn check_path(path: &str) -> Result<(), CalibrateError> {
    let all = toml::Table::try_from(PlantParams::default())?;
    let path_owned = || path.to_string();
    let mut table = &all;
    let parts: Vec<&str> = path.split('.').collect();
    let (last, head) = parts.split_last().expect("split gives one part at least");
    for part in head {
        match table.get(*part) {
            Some(toml::Value::Table(t)) => table = t,
            _ => {
                return Err(CalibrateError::NoTable {
                    path: path_owned(),
                    table: part.to_string(),
                });
            }
        }
    }
    match table.get(*last) {
        Some(toml::Value::Float(_)) => Ok(()),
        Some(toml::Value::Integer(_)) => Err(CalibrateError::WholeNumber { path: path_owned() }),
        Some(_) => Err(CalibrateError::NotANumberParameter { path: path_owned() }),
        None => {
            let near: Vec<&str> = table.keys().map(String::as_str).collect();
            Err(CalibrateError::NoParameter {
                path: path_owned(),
                table: head.join("."),
                has: near.join(", "),
            })
        }
    }
}

/// `scenario` with `values` set at `paths` in every module's parameters.
pub fn with_values(scenario: &Scenario, paths: &[String], values: &[f64]) -> Scenario {
    let mut s = scenario.clone();
    for module in &mut s.modules {
        for (path, v) in paths.iter().zip(values) {
            set(&mut module.params, path, *v);
        }
    }
    s
}

/// Sets a number at a dotted path of a TOML table, making tables on the way.
pub fn set(table: &mut toml::Table, path: &str, value: f64) {
    let mut t = table;
    let mut parts = path.split('.').peekable();
    while let Some(part) = parts.next() {
        if parts.peek().is_none() {
            t.insert(part.to_string(), toml::Value::Float(value));
            return;
        }
        let entry = t
            .entry(part.to_string())
            .or_insert_with(|| toml::Value::Table(toml::Table::new()));
        if !entry.is_table() {
            *entry = toml::Value::Table(toml::Table::new());
        }
        let toml::Value::Table(next) = entry else {
            return;
        };
        t = next;
    }
}
