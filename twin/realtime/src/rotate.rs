//! A long session's recordings: one file after another, each complete (its
//! MCAP summary written) and named by the wall-clock time it started, so a
//! service that runs for a term never needs to be stopped to get at its
//! recordings, and old ones are pruned by a retention rule so it never fills
//! its disk.
//!
//! A file is closed and the next one opened ([`Recordings::rotate`]) after
//! `--rotate-every` of session time, once it holds `--rotate-size` bytes, on
//! SIGHUP (as logrotate's `postrotate` sends it), or when the disk guard
//! stops it. The sink thread does it between two messages, so every message,
//! frame or sample is in exactly one file. After each rotation the files
//! beyond `--keep-files`, older than `--keep-age` or past `--keep-size` in
//! total are deleted, oldest first; only files of this session's own name
//! (`PREFIX-YYYY-MM-DDTHH-MM-SS[-N].mcap`) are ever touched.
//!
//! Durations are read by humantime and the names' time stamps made and read
//! by jiff (which adds about 7 s to a debug build of this crate: jiff-core
//! 2.7 s, then jiff 4.3 s). Sizes stay hand-read: bytesize takes `512M` and
//! `512MB` for 512·10⁶ bytes, where these options, like journald's and
//! logrotate's, mean 512·2²⁰ as their help says; and it prints `512.0 MiB`
//! where a session's first line says `512M`.

use protocols::time::{SimDuration, SimTime};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use twin_recording::WriteError;
use twin_recording::disk;
use twin_recording::topics;

type Result<T, E = WriteError> = std::result::Result<T, E>;
use twin_sim::engine::FirmwareFile;
use twin_sim::observe::SimRecorder;

/// Where a session records and when it starts a new file.
#[derive(Debug, Clone)]
pub struct RecordPlan {
    /// The first file's path when one was named (`--out`); `None`: named by
    /// its start time in `dir`, as every later file is.
    pub out: Option<PathBuf>,
    /// The folder of the files named by their start time.
    pub dir: PathBuf,
    /// Their name before the start time: `serve`, `supervise`, or `--out`'s stem.
    pub prefix: String,
    /// Start a new file after this much session time.
    pub every: Option<SimDuration>,
    /// Start a new file once the current one holds this many bytes.
    pub size: Option<u64>,
    pub keep: Retention,
}

impl RecordPlan {
    /// Recordings named by their start time in `dir`, never rotated but on SIGHUP.
    pub fn in_folder(dir: impl Into<PathBuf>, prefix: &str) -> Self {
        Self {
            out: None,
            dir: dir.into(),
            prefix: prefix.into(),
            every: None,
            size: None,
            keep: Retention::default(),
        }
    }

    /// The first recording at `path`; later ones beside it, named after it.
    pub fn at_path(path: &Path) -> Self {
        let dir = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let prefix = path
            .file_stem()
            .map_or_else(|| "recording".into(), |s| s.to_string_lossy().into_owned());
        Self {
            out: Some(path.to_path_buf()),
            ..Self::in_folder(dir, &prefix)
        }
    }
}

/// Which old recordings are kept (all of them, when nothing is set).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Retention {
    /// At most this many files, the one being written included.
    pub files: Option<usize>,
    /// None whose last write is older than this.
    pub age: Option<Duration>,
    /// At most this many bytes in all, the one being written included.
    pub total: Option<u64>,
}

impl Retention {
    /// Whether any rule is set: only then may old recordings be deleted,
    /// by the rules or by the disk guard.
    pub fn any(&self) -> bool {
        self.files.is_some() || self.age.is_some() || self.total.is_some()
    }
}

/// The files of a session: the one being written and what makes the next.
#[derive(Debug)]
pub struct Recordings {
    plan: RecordPlan,
    kind: &'static str,
    /// The `twin.run` fields every file starts with.
    metadata: BTreeMap<String, String>,
    /// Compiled firmware the session runs, stored whole in every file (its
    /// `twin.firmware.<node>` record and the ELF as an attachment).
    firmware: Vec<FirmwareFile>,
    current: PathBuf,
    /// Session time at which the current file started.
    started: SimTime,
    /// The current file's number in the session, from 1.
    part: u32,
    /// Files finished before the current one.
    pub finished: Vec<PathBuf>,
    /// When the recording stopped for want of disk space and waits for it.
    paused_since: Option<SimTime>,
    /// The name promised to the finishing file's `twin.part` record, which
    /// the next file must then have (the clock may have moved on since).
    promised_next: Option<PathBuf>,
}

/// How often a recording stopped for want of disk space looks for it again.
const DISK_RETRY: SimDuration = SimDuration::from_secs(10);

/// Room above the disk guard's floor before a stopped recording goes on: a
/// new file gets at least this far before the guard stops it again.
const RESUME_ABOVE_FLOOR: u64 = 64 * 1024 * 1024;

/// The free space at which a recording the disk guard stopped goes on.
pub fn resume_free() -> u64 {
    disk::min_free_bytes().saturating_add(RESUME_ABOVE_FLOOR)
}

impl Recordings {
    /// Stores the session's compiled firmware in the current file and in
    /// every file started after it.
    pub fn keep_firmware(
        &mut self,
        files: Vec<FirmwareFile>,
        current: &mut SimRecorder,
    ) -> Result<()> {
        store_firmware(current, &files)?;
        self.firmware = files;
        Ok(())
    }

    /// Creates the first file, with its `twin.run` metadata (`kind` and the
    /// twin's version added to `metadata`).
    pub fn start(
        plan: RecordPlan,
        kind: &'static str,
        mut metadata: BTreeMap<String, String>,
    ) -> Result<(Self, SimRecorder)> {
        metadata.insert("kind".into(), kind.into());
        metadata.insert("twin_version".into(), env!("CARGO_PKG_VERSION").into());
        let path = plan
            .out
            .clone()
            .unwrap_or_else(|| next_name(&plan.dir, &plan.prefix, SystemTime::now()));
        let recorder = create(&path, metadata.clone())?;
        Ok((
            Self {
                plan,
                kind,
                metadata,
                firmware: Vec::new(),
                current: path,
                started: SimTime::ZERO,
                part: 1,
                finished: Vec::new(),
                paused_since: None,
                promised_next: None,
            },
            recorder,
        ))
    }

    /// The file being written (or the last one, once paused).
    pub fn current(&self) -> &Path {
        &self.current
    }

    pub fn kind(&self) -> &'static str {
        self.kind
    }

    /// From now on, rotate and keep as `plan` says (its folder and name
    /// stay those the session started with).
    pub fn update(&mut self, plan: RecordPlan) {
        self.plan.every = plan.every;
        self.plan.size = plan.size;
        self.plan.keep = plan.keep;
    }

    /// Whether a retention rule lets old recordings be deleted.
    pub fn keeps_some(&self) -> bool {
        self.plan.keep.any()
    }

    /// Whether the current file is due to be closed at session time `now`:
    /// the reason, in the words the log shows.
    pub fn due(&self, now: SimTime) -> Option<String> {
        if self.paused_since.is_some() {
            return None;
        }
        if let Some(every) = self.plan.every
            && now.saturating_since(self.started) >= every
        {
            return Some(format!(
                "--rotate-every {}",
                shown_duration(every.as_secs_f64())
            ));
        }
        if let Some(limit) = self.plan.size {
            let size = std::fs::metadata(&self.current).map_or(0, |m| m.len());
            if size >= limit {
                return Some(format!("--rotate-size {}", shown_size(limit)));
            }
        }
        None
    }

    /// After the current file was finished: the next one, with the
    /// current's name in its metadata as `previous`. Prunes what the
    /// retention rules say may go, and returns what it deleted too.
    pub fn rotate(&mut self, now: SimTime) -> Result<(SimRecorder, Vec<Pruned>)> {
        let finished = std::mem::take(&mut self.current);
        let path = self
            .promised_next
            .take()
            .unwrap_or_else(|| next_name(&self.plan.dir, &self.plan.prefix, SystemTime::now()));
        let mut metadata = self.metadata.clone();
        metadata.insert("part".into(), (self.part + 1).to_string());
        if let Some(name) = finished.file_name() {
            metadata.insert("previous".into(), name.to_string_lossy().into_owned());
        }
        self.finished.push(finished);
        let mut recorder = create(&path, metadata)?;
        store_firmware(&mut recorder, &self.firmware)?;
        self.current = path;
        self.started = now;
        self.part += 1;
        self.paused_since = None;
        let pruned = self.prune(0);
        Ok((recorder, pruned))
    }

    /// The `twin.part` metadata a file ends with when the next one follows.
    pub fn part_end(&self, reason: &str, next: &Path) -> BTreeMap<String, String> {
        BTreeMap::from([
            ("part".into(), self.part.to_string()),
            ("ended_by".into(), reason.to_string()),
            (
                "next".into(),
                next.file_name()
                    .map(|n| n.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            ),
        ])
    }

    /// The name the next file will have (for the `twin.part` record, written
    /// before that file exists); `rotate` then creates exactly that file.
    pub fn next_path(&mut self) -> PathBuf {
        let path = next_name(&self.plan.dir, &self.plan.prefix, SystemTime::now());
        self.promised_next = Some(path.clone());
        path
    }

    /// The disk guard stopped the current file (closed whole) at `now`.
    /// With a retention rule, the oldest recordings are deleted until the
    /// disk has [`resume_free`] bytes free, and recording goes on in a new
    /// file; without one, or when that is not enough, recording waits for
    /// space (see [`Recordings::retry`]).
    pub fn disk_full(&mut self, now: SimTime) -> DiskOutcome {
        let want = resume_free();
        let mut pruned = Vec::new();
        if self.plan.keep.any() {
            pruned = self.prune(want);
        }
        let enough = disk::free_bytes(&self.plan.dir).is_none_or(|free| free >= want);
        if enough {
            match self.rotate(now) {
                Ok((recorder, more)) => {
                    pruned.extend(more);
                    return DiskOutcome::Resumed(Box::new(recorder), pruned);
                }
                Err(e) => {
                    self.paused_since = Some(now);
                    return DiskOutcome::Paused(pruned, Some(e));
                }
            }
        }
        self.paused_since = Some(now);
        DiskOutcome::Paused(pruned, None)
    }

    /// While paused for want of space: a new file once the disk has
    /// [`resume_free`] bytes free again (looked at every 10 s).
    pub fn retry(&mut self, now: SimTime) -> Option<Result<SimRecorder>> {
        let since = self.paused_since?;
        if now.saturating_since(since) < DISK_RETRY {
            return None;
        }
        self.paused_since = Some(now);
        if disk::free_bytes(&self.plan.dir).is_some_and(|free| free < resume_free()) {
            return None;
        }
        Some(self.rotate(now).map(|(recorder, _)| recorder))
    }

    /// Deletes, oldest first, the finished recordings the retention rules
    /// do not keep, then (for `want_free` above 0) more until the disk has
    /// that much free. Never the current file, never a file of another name.
    fn prune(&mut self, want_free: u64) -> Vec<Pruned> {
        let keep = &self.plan.keep;
        if !keep.any() {
            return Vec::new();
        }
        let mut files = session_files(&self.plan.dir, &self.plan.prefix);
        // Newest first; the current file counts towards the rules.
        files.sort_by(|a, b| b.0.cmp(&a.0));
        let now = SystemTime::now();
        let current = std::fs::canonicalize(&self.current).unwrap_or(self.current.clone());
        let current_size = std::fs::metadata(&self.current).map_or(0, |m| m.len());
        let mut count = 1;
        let mut total = current_size;
        let mut doomed = Vec::new();
        for (_, path) in files {
            if std::fs::canonicalize(&path).unwrap_or(path.clone()) == current {
                continue;
            }
            let Ok(meta) = std::fs::metadata(&path) else {
                continue;
            };
            count += 1;
            total += meta.len();
            let age = meta
                .modified()
                .ok()
                .and_then(|m| now.duration_since(m).ok())
                .unwrap_or_default();
            let reason = if keep.files.is_some_and(|n| count > n) {
                Some(format!("--keep-files {}", keep.files.unwrap_or_default()))
            } else if keep.age.is_some_and(|a| age > a) {
                Some(format!(
                    "--keep-age {}",
                    shown_duration(keep.age.unwrap_or_default().as_secs_f64())
                ))
            } else if keep.total.is_some_and(|t| total > t) {
                Some(format!(
                    "--keep-size {}",
                    shown_size(keep.total.unwrap_or_default())
                ))
            } else {
                None
            };
            doomed.push((path, meta.len(), reason));
        }
        let mut pruned = Vec::new();
        // Oldest first: the rules' victims, then, for the disk, the rest.
        for (path, bytes, reason) in doomed.iter().rev() {
            if let Some(reason) = reason
                && std::fs::remove_file(path).is_ok()
            {
                pruned.push(Pruned {
                    path: path.clone(),
                    bytes: *bytes,
                    reason: reason.clone(),
                });
            }
        }
        if want_free > 0 {
            for (path, bytes, reason) in doomed.iter().rev() {
                if reason.is_some() {
                    continue;
                }
                if disk::free_bytes(&self.plan.dir).is_none_or(|free| free >= want_free) {
                    break;
                }
                if std::fs::remove_file(path).is_ok() {
                    pruned.push(Pruned {
                        path: path.clone(),
                        bytes: *bytes,
                        reason: "the disk was nearly full".into(),
                    });
                }
            }
        }
        pruned
    }
}

/// A recording deleted by the retention rules or the disk guard.
#[derive(Debug, Clone)]
pub struct Pruned {
    pub path: PathBuf,
    pub bytes: u64,
    pub reason: String,
}

/// What the disk guard's stop led to.
#[derive(Debug)]
pub enum DiskOutcome {
    /// A new file, after deleting these.
    Resumed(Box<SimRecorder>, Vec<Pruned>),
    /// Waiting for space (having deleted these); the error if a new file
    /// could not be made.
    Paused(Vec<Pruned>, Option<WriteError>),
}

/// Writes each firmware's record and its bytes into `recorder`.
fn store_firmware(recorder: &mut SimRecorder, files: &[FirmwareFile]) -> Result<()> {
    for file in files {
        let node = file.fields.get("node").map_or("firmware", String::as_str);
        recorder.write_metadata(&topics::firmware_metadata(node), file.fields.clone())?;
        recorder.attach(
            &file.attachment,
            "application/x-elf",
            0.0,
            file.bytes.clone(),
        )?;
    }
    Ok(())
}

/// A new recording at `path` with `metadata` as its `twin.run` record.
fn create(path: &Path, metadata: BTreeMap<String, String>) -> Result<SimRecorder> {
    let mut recorder = SimRecorder::create_inline(path)?;
    recorder.write_metadata(topics::RUN_METADATA, metadata)?;
    Ok(recorder)
}

/// `DIR/PREFIX-2026-12-03T07-35-44.mcap` for a file started at `at` (UTC),
/// with `-2`, `-3`, … should that name be taken.
pub fn next_name(dir: &Path, prefix: &str, at: SystemTime) -> PathBuf {
    let secs = at.duration_since(UNIX_EPOCH).map_or(0, |d| d.as_secs());
    let stem = format!("{prefix}-{}", utc_stamp(secs));
    // Here: shown as `serve-….mcap`, not `./serve-….mcap`.
    let join = |name: String| {
        if dir == Path::new(".") {
            PathBuf::from(name)
        } else {
            dir.join(name)
        }
    };
    let mut path = join(format!("{stem}.mcap"));
    let mut n = 2;
    while path.exists() {
        path = join(format!("{stem}-{n}.mcap"));
        n += 1;
    }
    path
}

/// The recordings in `dir` named `PREFIX-STAMP[-N].mcap`, each with the key
/// that orders them by start (stamp, then N).
fn session_files(dir: &Path, prefix: &str) -> Vec<((String, u32), PathBuf)> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Vec::new();
    };
    entries
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            let key = session_key(&name, prefix)?;
            Some((key, e.path()))
        })
        .collect()
}

/// `(stamp, n)` of `PREFIX-YYYY-MM-DDTHH-MM-SS[-N].mcap`; `None` for any
/// other name.
fn session_key(name: &str, prefix: &str) -> Option<(String, u32)> {
    let rest = name.strip_prefix(prefix)?.strip_prefix('-')?;
    let rest = rest.strip_suffix(".mcap")?;
    let stamp = rest.get(..19)?;
    // A date that exists, digits where digits belong (strptime alone would
    // take `2026-1-3` too).
    if !stamp
        .bytes()
        .all(|b| b.is_ascii_digit() || b == b'-' || b == b'T')
        || jiff::civil::DateTime::strptime(STAMP, stamp).is_err()
    {
        return None;
    }
    let n = match rest.get(19..)? {
        "" => 1,
        more => more.strip_prefix('-')?.parse().ok()?,
    };
    Some((stamp.to_string(), n))
}

/// `2026-12-03T07-35-44` for a time in seconds since 1970 (UTC), with
/// hyphens for colons, which some file systems refuse.
pub fn utc_stamp(secs: u64) -> String {
    let at = i64::try_from(secs)
        .ok()
        .and_then(|s| jiff::Timestamp::from_second(s).ok())
        .unwrap_or(jiff::Timestamp::MAX);
    at.strftime(STAMP).to_string()
}

/// The file names' time stamp, for jiff's strftime and strptime.
const STAMP: &str = "%Y-%m-%dT%H-%M-%S";

/// A duration as the options take it: `90s`, `30m`, `1h`, `7d`, `2w`,
/// `1h 30m`, `1.5s` (humantime's spellings), or plain seconds. `None` for
/// anything else, or not above 0.
pub fn parse_duration(text: &str) -> Option<Duration> {
    let text = text.trim();
    let duration = match text.parse::<f64>() {
        // humantime wants a unit; a bare number has always meant seconds.
        Ok(seconds) if seconds.is_finite() && seconds > 0.0 && seconds <= 3.2e9 => {
            Duration::from_secs_f64(seconds)
        }
        Ok(_) => return None,
        Err(_) => humantime::parse_duration(text).ok()?,
    };
    (duration > Duration::ZERO && duration.as_secs_f64() <= 3.2e9).then_some(duration)
}

/// A size as the options take it: `512M`, `512MB`, `2G`, `100k`, or plain
/// bytes; K, M, G and T are powers of 1024, as in journald and logrotate.
pub fn parse_size(text: &str) -> Option<u64> {
    let text = text.trim();
    let split = text
        .find(|c: char| c.is_ascii_alphabetic())
        .unwrap_or(text.len());
    let (number, unit) = text.split_at(split);
    let number: f64 = number.trim().parse().ok()?;
    let unit = unit.trim().to_ascii_uppercase();
    let unit = unit
        .strip_suffix("IB")
        .or(unit.strip_suffix('B'))
        .unwrap_or(&unit);
    let scale = match unit {
        "" => 1.0,
        "K" => 1024.0,
        "M" => 1024.0 * 1024.0,
        "G" => 1024.0 * 1024.0 * 1024.0,
        "T" => 1024.0 * 1024.0 * 1024.0 * 1024.0,
        _ => return None,
    };
    let bytes = number * scale;
    (1.0..1.8e19).contains(&bytes).then_some(bytes as u64)
}

/// `90s`, `30m`, `1h`, `14d`: the shortest exact way to say `seconds` (days at most,
/// as retention periods are usually given). Not humantime's printer: its
/// month is 30.44 days, so it writes `--keep-age 90d` as `2months 29days 2h
/// 52m 48s`.
pub fn shown_duration(seconds: f64) -> String {
    for (unit, scale) in [("d", 86_400.0), ("h", 3600.0), ("m", 60.0)] {
        if seconds >= scale && (seconds / scale).fract() == 0.0 {
            return format!("{}{unit}", seconds / scale);
        }
    }
    format!("{seconds}s")
}

/// `512M`, `2G`, `100K`: the shortest exact way to say `bytes`.
pub fn shown_size(bytes: u64) -> String {
    for (unit, shift) in [("T", 40), ("G", 30), ("M", 20), ("K", 10)] {
        if bytes >= 1 << shift && bytes.is_multiple_of(1 << shift) {
            return format!("{}{unit}", bytes >> shift);
        }
    }
    format!("{bytes}")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stamps_are_utc_dates() {
        assert_eq!(utc_stamp(0), "1970-01-01T00-00-00");
        assert_eq!(utc_stamp(951_782_400), "2000-02-29T00-00-00");
        assert_eq!(utc_stamp(1_796_283_344), "2026-12-03T07-35-44");
    }

    #[test]
    fn durations_and_sizes_read_as_an_administrator_writes_them() {
        assert_eq!(parse_duration("1h"), Some(Duration::from_secs(3600)));
        assert_eq!(parse_duration("30m"), Some(Duration::from_secs(1800)));
        assert_eq!(parse_duration("90"), Some(Duration::from_secs(90)));
        assert_eq!(parse_duration("1.5s"), Some(Duration::from_millis(1500)));
        assert_eq!(parse_duration("1 h"), Some(Duration::from_secs(3600)));
        assert_eq!(parse_duration("1h 30m"), Some(Duration::from_secs(5400)));
        assert_eq!(parse_duration("2w"), Some(Duration::from_secs(1_209_600)));
        assert_eq!(parse_duration("90 sec"), Some(Duration::from_secs(90)));
        assert_eq!(parse_duration("0s"), None);
        assert_eq!(parse_duration("inf"), None);
        assert_eq!(parse_duration("7d"), Some(Duration::from_secs(604_800)));
        assert_eq!(parse_duration("0"), None);
        assert_eq!(parse_duration("-1h"), None);
        assert_eq!(parse_duration("1 fortnight"), None);
        assert_eq!(parse_size("512MB"), Some(512 << 20));
        assert_eq!(parse_size("512M"), Some(512 << 20));
        assert_eq!(parse_size("2 GiB"), Some(2 << 30));
        assert_eq!(parse_size("1.5k"), Some(1536));
        assert_eq!(parse_size("4096"), Some(4096));
        assert_eq!(parse_size("0"), None);
        assert_eq!(parse_size("lots"), None);
        assert_eq!(shown_size(512 << 20), "512M");
        assert_eq!(shown_duration(3600.0), "1h");
        assert_eq!(shown_duration(90.0), "90s");
    }

    #[test]
    fn only_this_sessions_names_are_its_files() {
        assert_eq!(
            session_key("serve-2026-12-03T07-35-44.mcap", "serve"),
            Some(("2026-12-03T07-35-44".into(), 1))
        );
        assert_eq!(
            session_key("serve-2026-12-03T07-35-44-3.mcap", "serve"),
            Some(("2026-12-03T07-35-44".into(), 3))
        );
        assert_eq!(session_key("serve-notes.mcap", "serve"), None);
        assert_eq!(
            session_key("serve-2026-12-03T07-35-44.mcap", "supervise"),
            None
        );
        assert_eq!(session_key("serve-2026-12-03T07-35-44.txt", "serve"), None);
        assert_eq!(
            session_key("serve-2026-12-03T07-35-44-x.mcap", "serve"),
            None
        );
        assert_eq!(session_key("serve-2026-13-03T07-35-44.mcap", "serve"), None);
        assert_eq!(session_key("serve-2026-12-03T07:35:44.mcap", "serve"), None);
    }
}
