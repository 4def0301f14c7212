//! A class: one suite run against every student's program, each on its
//! own link, several at once (students that share a link one after the
//! other), and the scores side by side. The roster is a CSV file
//! (`student,link[,id][,bus][,bench]`, as a spreadsheet exports it) or
//! TOML (`[[student]] name, link, id, bus, bench`).

use crate::bench::Bench;
use crate::framing::Protocol;
use crate::run::{SuiteRun, run_suite_on};
use crate::suite::Suite;
use crate::wire::Wire;
use serde::Deserialize;
use std::collections::VecDeque;
use std::path::Path;
use std::sync::{Condvar, Mutex, PoisonError};
use twin_realtime::io::{LinkDefaults, LinkSpec};

/// One student of the roster.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Student {
    pub name: String,
    pub link: String,
    pub id: u8,
    /// A supervisor's bus, where the twin plays its slave (`twin check
    /// server`), if the roster gives one.
    pub bus: Option<String>,
    /// The panel of the bench the student's slave is wired to (`twin
    /// check slave`'s `--bench`), if the roster gives one.
    pub bench: Option<String>,
    /// The roster's line, for messages.
    pub line: usize,
}

impl Student {
    /// The student's reports' file name, without extension: the name with
    /// anything a file system might refuse or read as a folder replaced.
    pub fn file_stem(&self) -> String {
        let stem: String = self
            .name
            .chars()
            .map(|c| {
                if c.is_alphanumeric() || matches!(c, '-' | '_' | '.') {
                    c
                } else {
                    '_'
                }
            })
            .collect();
        match stem.strip_prefix('.') {
            Some(rest) => format!("_{rest}"),
            None => stem,
        }
    }
}

/// A roster that cannot be used, with the file and the line.
#[derive(Debug, thiserror::Error)]
pub enum RosterError {
    #[error("cannot read the roster {path}: {why}")]
    Read { path: String, why: std::io::Error },
    #[error("{path}, line {line}: {why}")]
    At {
        path: String,
        line: usize,
        why: String,
    },
    #[error("{path}: {why}")]
    Whole { path: String, why: String },
}

/// Reads a roster: TOML if the file's name ends in `.toml`, CSV otherwise.
/// `default_id` is the slave id of a student whose line gives none; an id
/// the line gives must be one of `protocol`'s.
pub fn load_roster(
    path: &Path,
    default_id: u8,
    protocol: Protocol,
) -> Result<Vec<Student>, RosterError> {
    let shown = path.display().to_string();
    let text = std::fs::read_to_string(path).map_err(|why| RosterError::Read {
        path: shown.clone(),
        why,
    })?;
    if path.extension().is_some_and(|e| e == "toml") {
        parse_toml(&text, &shown, default_id, protocol)
    } else {
        parse_csv(&text, &shown, default_id, protocol)
    }
}

/// A CSV roster: a header naming `student` and `link` (and `id`, if some
/// students' slaves have another device number); other columns are left
/// alone, `#` starts a comment line.
pub fn parse_csv(
    text: &str,
    path: &str,
    default_id: u8,
    protocol: Protocol,
) -> Result<Vec<Student>, RosterError> {
    let at = |line: usize, why: String| RosterError::At {
        path: path.into(),
        line,
        why,
    };
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_reader(text.as_bytes());
    let header = reader.headers().map_err(|e| csv_error(&e, path))?.clone();
    let column = |name: &str| header.iter().position(|h| h.eq_ignore_ascii_case(name));
    let header_line = text
        .lines()
        .position(|l| !l.trim().is_empty() && !l.starts_with('#'))
        .map_or(1, |i| i + 1);
    let missing = |name: &str| {
        at(
            header_line,
            format!(
                "no `{name}` column: the first line names the columns, student,link[,id] (this one: {})",
                header.iter().collect::<Vec<_>>().join(",")
            ),
        )
    };
    let (Some(name_at), Some(link_at)) = (column("student"), column("link")) else {
        return Err(missing(if column("student").is_none() {
            "student"
        } else {
            "link"
        }));
    };
    let id_at = column("id");
    let bus_at = column("bus");
    let bench_at = column("bench");
    let mut students = Vec::new();
    for record in reader.records() {
        let record = record.map_err(|e| csv_error(&e, path))?;
        let line = record.position().map_or(0, |p| p.line() as usize);
        let field = |i: usize| record.get(i).unwrap_or("").to_string();
        let id = match id_at.map(field).filter(|s| !s.is_empty()) {
            None => default_id,
            Some(text) => id(&text, protocol).map_err(|why| at(line, why))?,
        };
        students.push(Student {
            name: field(name_at),
            link: field(link_at),
            id,
            bus: bus_at.map(field).filter(|s| !s.is_empty()),
            bench: bench_at.map(field).filter(|s| !s.is_empty()),
            line,
        });
    }
    checked(students, path)
}

fn csv_error(e: &csv::Error, path: &str) -> RosterError {
    let line = e.position().map_or(0, |p| p.line() as usize);
    let why = match e.kind() {
        csv::ErrorKind::UnequalLengths {
            expected_len, len, ..
        } => format!("{len} fields where the header has {expected_len}"),
        csv::ErrorKind::Utf8 { .. } => "not UTF-8 text (save the roster as UTF-8 CSV)".into(),
        _ => e.to_string(),
    };
    if line == 0 {
        return RosterError::Whole {
            path: path.into(),
            why,
        };
    }
    RosterError::At {
        path: path.into(),
        line,
        why,
    }
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RosterToml {
    #[serde(default)]
    student: Vec<toml::Spanned<StudentToml>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct StudentToml {
    name: String,
    link: String,
    /// Any integer, so that one out of range is said with its line.
    id: Option<i64>,
    bus: Option<String>,
    bench: Option<String>,
}

/// A TOML roster: `[[student]]` tables of `name`, `link` and `id` (and
/// `bus`, `bench`).
pub fn parse_toml(
    text: &str,
    path: &str,
    default_id: u8,
    protocol: Protocol,
) -> Result<Vec<Student>, RosterError> {
    let raw: RosterToml = toml::from_str(text).map_err(|e| RosterError::Whole {
        path: path.into(),
        why: e.to_string().trim_end().to_string(),
    })?;
    // A table's span may begin on the blank line before its header.
    let line_of = |offset: usize| {
        let rest = text.get(offset..).unwrap_or("");
        let start = offset + (rest.len() - rest.trim_start().len());
        text.get(..start).unwrap_or(text).matches('\n').count() + 1
    };
    let mut students = Vec::new();
    for spanned in raw.student {
        let line = line_of(spanned.span().start);
        let s = spanned.into_inner();
        let id = match s.id {
            None => default_id,
            Some(n) => id(&n.to_string(), protocol).map_err(|why| RosterError::At {
                path: path.into(),
                line,
                why,
            })?,
        };
        students.push(Student {
            name: s.name.trim().into(),
            link: s.link.trim().into(),
            id,
            bus: s
                .bus
                .map(|b| b.trim().to_string())
                .filter(|b| !b.is_empty()),
            bench: s
                .bench
                .map(|b| b.trim().to_string())
                .filter(|b| !b.is_empty()),
            line,
        });
    }
    checked(students, path)
}

/// A line's `id`, in `protocol`'s range (its broadcast address is none).
fn id(text: &str, protocol: Protocol) -> Result<u8, String> {
    let ids = protocol.ids();
    match text.parse::<u8>() {
        Ok(n) if ids.contains(&n) => Ok(n),
        _ => Err(format!(
            "id `{text}`: {} is {} to {}",
            match protocol {
                Protocol::Meb => "an MEB slave's device number",
                _ => "a Modbus unit id",
            },
            ids.start(),
            ids.end()
        )),
    }
}

/// Every student named once, with a link the twin can open.
fn checked(students: Vec<Student>, path: &str) -> Result<Vec<Student>, RosterError> {
    let at = |line: usize, why: String| RosterError::At {
        path: path.into(),
        line,
        why,
    };
    if students.is_empty() {
        return Err(RosterError::Whole {
            path: path.into(),
            why: "no students in it".into(),
        });
    }
    for (i, s) in students.iter().enumerate() {
        if s.name.is_empty() {
            return Err(at(s.line, "the student's name is empty".into()));
        }
        if let Some(first) = students[..i].iter().find(|o| {
            o.name == s.name || o.file_stem().to_lowercase() == s.file_stem().to_lowercase()
        }) {
            let why = if first.name == s.name {
                format!("`{}` is on line {} already", s.name, first.line)
            } else {
                format!(
                    "`{}` and `{}` (line {}) would share a report file: name them apart",
                    s.name, first.name, first.line
                )
            };
            return Err(at(s.line, why));
        }
        if s.link.is_empty() {
            return Err(at(s.line, format!("`{}` has no link", s.name)));
        }
        if let Err(e) = LinkSpec::parse(&s.link, &LinkDefaults::default()) {
            return Err(at(s.line, format!("`{}`'s link: {e}", s.name)));
        }
        if let Some(bus) = &s.bus
            && let Err(e) = LinkSpec::parse(bus, &LinkDefaults::default())
        {
            return Err(at(s.line, format!("`{}`'s bus: {e}", s.name)));
        }
        if let Some(bench) = &s.bench
            && let Err(why) = crate::bench::check_url(bench)
        {
            return Err(at(s.line, format!("`{}`'s bench: {why}", s.name)));
        }
    }
    Ok(students)
}

/// Plays `suite` against every student, `jobs` at once (each on its own
/// link, so they do not wait for one another), and calls `done` with each
/// run as it ends, on the caller's thread. A student whose program cannot
/// be reached gets a run whose checks all fail with why
/// ([`SuiteRun::unreachable`]); one that hangs up keeps the checks run
/// before it did ([`SuiteRun::hung_up`]); the others go on. The runs come back in
/// the roster's order.
pub fn run_class(
    suite: &Suite,
    students: &[Student],
    jobs: usize,
    done: impl FnMut(&Student, &SuiteRun),
) -> Vec<SuiteRun> {
    run_each(students, jobs, |student| check(suite, student), done)
}

/// [`run_class`] with any check: `check` makes a student's run (a master's
/// suite, say), `jobs` at once; `done` is called as each ends. Students
/// that share a link (or a bus) are never checked at once: the line is
/// one program's at a time.
pub fn run_each(
    students: &[Student],
    jobs: usize,
    check: impl Fn(&Student) -> SuiteRun + Sync,
    mut done: impl FnMut(&Student, &SuiteRun),
) -> Vec<SuiteRun> {
    let queue = Queue {
        state: Mutex::new(((0..students.len()).collect(), Vec::new())),
        freed: Condvar::new(),
    };
    let (tx, rx) = std::sync::mpsc::channel();
    let mut runs: Vec<Option<SuiteRun>> = vec![None; students.len()];
    std::thread::scope(|scope| {
        for _ in 0..jobs.clamp(1, students.len().max(1)) {
            let (tx, queue, check) = (tx.clone(), &queue, &check);
            scope.spawn(move || {
                while let Some(i) = queue.take(students) {
                    let Some(student) = students.get(i) else {
                        break;
                    };
                    let run = check(student);
                    queue.give_back(student);
                    if tx.send((i, run)).is_err() {
                        break;
                    }
                }
            });
        }
        drop(tx);
        for (i, run) in rx {
            if let (Some(student), Some(slot)) = (students.get(i), runs.get_mut(i)) {
                done(student, &run);
                *slot = Some(run);
            }
        }
    });
    runs.into_iter().flatten().collect()
}

/// The students still to check, and the links in use.
struct Queue {
    state: Mutex<(VecDeque<usize>, Vec<String>)>,
    freed: Condvar,
}

/// The links a student's check holds while it runs (a bench too: two
/// slaves driving one plant at once would spoil each other's checks).
fn links(student: &Student) -> impl Iterator<Item = &str> {
    std::iter::once(student.link.as_str())
        .chain(student.bus.as_deref())
        .chain(student.bench.as_deref())
}

impl Queue {
    /// The next student whose links are free (waiting while every one left
    /// shares a link in use); `None` when none is left.
    fn take(&self, students: &[Student]) -> Option<usize> {
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        loop {
            let (left, busy) = &mut *state;
            if left.is_empty() {
                return None;
            }
            let free = left.iter().position(|&i| {
                students
                    .get(i)
                    .is_some_and(|s| links(s).all(|l| !busy.iter().any(|b| b == l)))
            });
            if let Some(at) = free
                && let Some(i) = left.remove(at)
            {
                if let Some(student) = students.get(i) {
                    busy.extend(links(student).map(str::to_string));
                }
                return Some(i);
            }
            state = self
                .freed
                .wait(state)
                .unwrap_or_else(PoisonError::into_inner);
        }
    }

    /// `student`'s links free again.
    fn give_back(&self, student: &Student) {
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        for link in links(student) {
            if let Some(at) = state.1.iter().position(|b| b == link) {
                state.1.swap_remove(at);
            }
        }
        drop(state);
        self.freed.notify_all();
    }
}

/// One student's slave checked with `suite` over their link, on their
/// bench if the roster gives one (unreachable, or a bench that cannot be
/// reached: a run whose checks all fail with why).
pub fn check(suite: &Suite, student: &Student) -> SuiteRun {
    let bench = match student.bench.as_deref().map(Bench::connect) {
        None => None,
        Some(Ok(bench)) => Some(bench),
        Some(Err(why)) => {
            return SuiteRun::unreachable(
                suite,
                &student.link,
                student.id,
                format!("bench: {why}"),
            );
        }
    };
    match Wire::open(&student.link) {
        Ok(mut wire) => run_suite_on(suite, &mut wire, student.id, bench.as_ref()),
        Err(e) => SuiteRun::unreachable(suite, &student.link, student.id, e.to_string()),
    }
}

/// Refuses a roster that gives a bench to a role that has none (only a
/// slave is checked on a bench), with the file and the line.
pub fn no_bench(students: &[Student], path: &Path, role: &str) -> Result<(), RosterError> {
    match students.iter().find(|s| s.bench.is_some()) {
        None => Ok(()),
        Some(s) => Err(RosterError::At {
            path: path.display().to_string(),
            line: s.line,
            why: format!(
                "`{}` has a bench: a bench holds a slave to what its registers mean (twin check slave), not a {role}",
                s.name
            ),
        }),
    }
}

/// The class's scores as CSV, one row per student in the roster's order:
/// the score, the points, the checks passed, the checks, and the first
/// failing check or why the program could not be checked.
pub fn scores_csv(students: &[Student], runs: &[SuiteRun]) -> String {
    let mut out = csv::Writer::from_writer(Vec::new());
    let _ = out.write_record([
        "student",
        "score",
        "points",
        "checks_passed",
        "checks",
        "first_failure",
        "not_applicable",
    ]);
    for (student, run) in students.iter().zip(runs) {
        let first = match (&run.error, run.first_failure()) {
            (Some(why), _) => why.clone(),
            (None, Some(check)) => check.name.clone(),
            (None, None) => String::new(),
        };
        let _ = out.write_record([
            student.name.clone(),
            run.score().to_string(),
            run.points().to_string(),
            run.passed().count().to_string(),
            (run.checks.len() - run.not_applicable()).to_string(),
            first,
            run.not_applicable().to_string(),
        ]);
    }
    String::from_utf8(out.into_inner().unwrap_or_default()).unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn csv_err(text: &str) -> String {
        parse_csv(text, "class.csv", 1, Protocol::Meb)
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn a_csv_roster_reads_names_links_and_ids() {
        let students = parse_csv(
            "student,link,id\n# the morning group\nAnna Müller, tcp://127.0.0.1:5701 ,\nBen,/dev/ttyUSB0?baud=9600,3\n",
            "class.csv",
            1,
            Protocol::Meb,
        )
        .unwrap();
        assert_eq!(students.len(), 2);
        assert_eq!(students[0].name, "Anna Müller");
        assert_eq!(students[0].link, "tcp://127.0.0.1:5701");
        assert_eq!((students[0].id, students[1].id), (1, 3));
        assert_eq!(students[1].line, 4);
        assert_eq!(students[0].file_stem(), "Anna_Müller");
    }

    #[test]
    fn roster_mistakes_name_the_file_and_line() {
        assert_eq!(
            csv_err("name,link\nAnna,tcp://127.0.0.1:1\n"),
            "class.csv, line 1: no `student` column: the first line names the columns, student,link[,id] (this one: name,link)"
        );
        assert_eq!(
            csv_err("student,link\nAnna,tcp://127.0.0.1:1\n,tcp://127.0.0.1:2\n"),
            "class.csv, line 3: the student's name is empty"
        );
        assert_eq!(
            csv_err(
                "student,link\nAnna,tcp://127.0.0.1:1\nBen,tcp://127.0.0.1:2\nAnna,tcp://127.0.0.1:3\n"
            ),
            "class.csv, line 4: `Anna` is on line 2 already"
        );
        assert_eq!(
            csv_err("student,link\nAnna/B,tcp://127.0.0.1:1\nanna_b,tcp://127.0.0.1:2\n"),
            "class.csv, line 3: `anna_b` and `Anna/B` (line 2) would share a report file: name them apart"
        );
        assert!(
            csv_err("student,link\nAnna,tcp://127.0.0.1\n")
                .starts_with("class.csv, line 2: `Anna`'s link: "),
            "{}",
            csv_err("student,link\nAnna,tcp://127.0.0.1\n")
        );
        assert_eq!(
            csv_err("student,link,id\nAnna,tcp://127.0.0.1:1,100\n"),
            "class.csv, line 2: id `100`: an MEB slave's device number is 1 to 99"
        );
        assert_eq!(
            csv_err("student,link,bench\nAnna,tcp://127.0.0.1:1,127.0.0.1:8080\n"),
            "class.csv, line 2: `Anna`'s bench: `127.0.0.1:8080` is not a panel's address: it is http://HOST:PORT, as `twin serve --web` prints it"
        );
        assert_eq!(
            csv_err("student,link\nAnna,tcp://127.0.0.1:1,3\n"),
            "class.csv, line 2: 3 fields where the header has 2"
        );
        assert_eq!(csv_err("student,link\n"), "class.csv: no students in it");
    }

    #[test]
    fn students_that_share_a_link_or_a_bus_are_never_checked_at_once() {
        use std::sync::atomic::{AtomicUsize, Ordering};
        let students = parse_csv(
            "student,link,bus\nA,tcp://127.0.0.1:1,/tmp/b1\nB,tcp://127.0.0.1:1,/tmp/b2\nC,tcp://127.0.0.1:3,/tmp/b1\nD,tcp://127.0.0.1:4,/tmp/b4\nE,tcp://127.0.0.1:5,\n",
            "class.csv",
            1,
            Protocol::Meb,
        )
        .unwrap();
        assert_eq!(students[4].bus, None);
        let suite = Suite::load("meb-slave").unwrap();
        let (on_1, on_b1, most) = (
            AtomicUsize::new(0),
            AtomicUsize::new(0),
            AtomicUsize::new(0),
        );
        let runs = run_each(
            &students,
            5,
            |s| {
                let shares = |c: &AtomicUsize, yes: bool| {
                    if yes {
                        let now = c.fetch_add(1, Ordering::SeqCst) + 1;
                        most.fetch_max(now, Ordering::SeqCst);
                    }
                };
                let (a, b) = (s.link.ends_with(":1"), s.bus.as_deref() == Some("/tmp/b1"));
                shares(&on_1, a);
                shares(&on_b1, b);
                std::thread::sleep(std::time::Duration::from_millis(30));
                if a {
                    on_1.fetch_sub(1, Ordering::SeqCst);
                }
                if b {
                    on_b1.fetch_sub(1, Ordering::SeqCst);
                }
                SuiteRun::unreachable(&suite, &s.link, s.id, s.name.clone())
            },
            |_, _| {},
        );
        assert_eq!(most.load(Ordering::SeqCst), 1);
        let names: Vec<_> = runs.iter().map(|r| r.error.clone().unwrap()).collect();
        assert_eq!(names, ["A", "B", "C", "D", "E"], "in the roster's order");
    }

    #[test]
    fn a_toml_roster_reads_the_same_and_names_its_lines() {
        let text = "[[student]]\nname = \"Anna\"\nlink = \"tcp://127.0.0.1:5701\"\n\n[[student]]\nname = \"Ben\"\nlink = \"tcp://127.0.0.1:5702\"\nid = 4\n";
        let students = parse_toml(text, "class.toml", 1, Protocol::Meb).unwrap();
        assert_eq!(students[1].id, 4);
        let dup = text.replace("Ben", "Anna");
        assert_eq!(
            parse_toml(&dup, "class.toml", 1, Protocol::Meb)
                .unwrap_err()
                .to_string(),
            "class.toml, line 5: `Anna` is on line 1 already"
        );
        let missing = "[[student]]\nname = \"Anna\"\n";
        let e = parse_toml(missing, "class.toml", 1, Protocol::Meb)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing field `link`"), "{e}");
    }

    #[test]
    fn an_id_is_held_to_the_protocols_range_with_its_line() {
        let csv = "student,link,id\nAnna,tcp://127.0.0.1:1,120\nBen,tcp://127.0.0.1:2,0\n";
        assert_eq!(
            parse_csv(csv, "class.csv", 1, Protocol::Meb)
                .unwrap_err()
                .to_string(),
            "class.csv, line 2: id `120`: an MEB slave's device number is 1 to 99"
        );
        // 120 is a Modbus unit id; 0, the broadcast, is no one's.
        assert_eq!(
            parse_csv(csv, "class.csv", 1, Protocol::ModbusTcp)
                .unwrap_err()
                .to_string(),
            "class.csv, line 3: id `0`: a Modbus unit id is 1 to 247"
        );
        let toml = "[[student]]\nname = \"Anna\"\nlink = \"tcp://127.0.0.1:1\"\n\n[[student]]\nname = \"Ben\"\nlink = \"tcp://127.0.0.1:2\"\nid = 300\n";
        assert_eq!(
            parse_toml(toml, "class.toml", 1, Protocol::ModbusRtu)
                .unwrap_err()
                .to_string(),
            "class.toml, line 5: id `300`: a Modbus unit id is 1 to 247"
        );
        let ok = toml.replace("300", "120");
        let students = parse_toml(&ok, "class.toml", 1, Protocol::ModbusRtu).unwrap();
        assert_eq!(students[1].id, 120);
    }

    #[test]
    fn a_bench_per_student_in_csv_and_toml() {
        let csv = "student,link,bench\nAnna,tcp://127.0.0.1:1,http://127.0.0.1:8080/?token=abc\nBen,tcp://127.0.0.1:2,\n";
        let students = parse_csv(csv, "class.csv", 1, Protocol::Meb).unwrap();
        assert_eq!(
            students[0].bench.as_deref(),
            Some("http://127.0.0.1:8080/?token=abc")
        );
        assert_eq!(students[1].bench, None);
        let toml = "[[student]]\nname = \"Anna\"\nlink = \"tcp://127.0.0.1:1\"\nbench = \"http://127.0.0.1:8080\"\n";
        let students = parse_toml(toml, "class.toml", 1, Protocol::Meb).unwrap();
        assert_eq!(students[0].bench.as_deref(), Some("http://127.0.0.1:8080"));
        assert_eq!(
            no_bench(&students, Path::new("class.toml"), "server")
                .unwrap_err()
                .to_string(),
            "class.toml, line 1: `Anna` has a bench: a bench holds a slave to what its registers mean (twin check slave), not a server"
        );
    }
}
