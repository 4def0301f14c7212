//! Where a real-time session (`twin serve`, `twin supervise`) records, when
//! it starts a new file and which old ones it keeps: the options of a
//! service that runs for a term, named as logrotate and journald name theirs.

use anyhow::{Result, bail};
use clap::Args;
use std::path::PathBuf;
use twin_realtime::rotate::{self, RecordPlan, Retention};

#[derive(Debug, Args)]
pub struct RecordArgs {
    /// Where to write the recording (replaced if it exists) [default: a file
    /// named by the command and the session's start time in UTC in
    /// --record-dir, e.g. COMMAND-2026-12-03T07-35-44.mcap, so that a restart
    /// never writes over the last one]. Files after a rotation go beside it,
    /// named STEM-START.mcap.
    #[arg(long, value_name = "PATH", conflicts_with = "record_dir")]
    pub out: Option<PathBuf>,
    /// The folder the recordings go to, each named by its start time (UTC)
    /// [default: here].
    #[arg(long, value_name = "DIR")]
    pub record_dir: Option<PathBuf>,
    /// Do not record (for measuring the recording's cost).
    #[arg(long, conflicts_with_all = ["out", "record_dir"])]
    pub no_record: bool,
    /// Close the recording and start a new file after this long: `30m`,
    /// `1h`, `1d`, or seconds. Each file is complete and named by its start
    /// time; SIGHUP starts a new file too.
    #[arg(long, value_name = "TIME", value_parser = duration)]
    pub rotate_every: Option<std::time::Duration>,
    /// Close the recording and start a new file once it holds this much:
    /// `512M`, `2G` (K, M, G are powers of 1024).
    #[arg(long, value_name = "SIZE", value_parser = size)]
    pub rotate_size: Option<u64>,
    /// Keep at most this many recordings of this session's name in the
    /// folder, the one being written included; older ones are deleted
    /// after each rotation.
    #[arg(long, value_name = "N", value_parser = super::numbers::whole::<usize>)]
    pub keep_files: Option<usize>,
    /// Delete recordings of this session's name last written longer ago
    /// than this: `14d`, `12h`.
    #[arg(long, value_name = "TIME", value_parser = duration)]
    pub keep_age: Option<std::time::Duration>,
    /// Keep the recordings of this session's name under this much in all
    /// (`20G`), deleting the oldest. With any --keep option, the disk guard
    /// (TWIN_MIN_FREE_DISK_MB, 256 MB free by default) deletes the oldest
    /// recordings and goes on recording instead of stopping.
    #[arg(long, value_name = "SIZE", value_parser = size)]
    pub keep_size: Option<u64>,
}

/// Names the command's own files in the help of `--out`, shared by
/// `twin serve` and `twin supervise`: `#[command(mut_arg("out", named("serve")))]`.
pub fn named(command: &'static str) -> impl FnOnce(clap::Arg) -> clap::Arg {
    move |arg| {
        let own = |text: &clap::builder::StyledStr| {
            text.to_string()
                .replace("COMMAND-2026", &format!("{command}-2026"))
        };
        let (help, long_help) = (arg.get_help().map(own), arg.get_long_help().map(own));
        let arg = match help {
            Some(help) => arg.help(help),
            None => arg,
        };
        match long_help {
            Some(long_help) => arg.long_help(long_help),
            None => arg,
        }
    }
}

fn duration(text: &str) -> Result<std::time::Duration, String> {
    rotate::parse_duration(text)
        .ok_or_else(|| format!("give a time like 30m, 1h, 7d or seconds above 0, got `{text}`"))
}

fn size(text: &str) -> Result<u64, String> {
    rotate::parse_size(text)
        .ok_or_else(|| format!("give a size like 512M, 2G or bytes above 0, got `{text}`"))
}

impl RecordArgs {
    /// The session's recording plan; `None` with --no-record. `command`
    /// names the files: `serve-START.mcap`.
    pub fn plan(&self, command: &str) -> Result<Option<RecordPlan>> {
        if self.no_record {
            return Ok(None);
        }
        if self.keep_files == Some(0) {
            bail!("--keep-files 0 would delete the recording being written: give 1 or more");
        }
        if let Some(every) = self.rotate_every
            && every.as_secs_f64() < 1.0
        {
            bail!("--rotate-every {} s: give 1 s or more", every.as_secs_f64());
        }
        let mut plan = match &self.out {
            Some(path) => RecordPlan::at_path(path),
            None => RecordPlan::in_folder(
                self.record_dir
                    .clone()
                    .unwrap_or_else(|| PathBuf::from(".")),
                command,
            ),
        };
        plan.every = self
            .rotate_every
            .map(|d| protocols::time::SimDuration::from_secs_f64(d.as_secs_f64()));
        plan.size = self.rotate_size;
        plan.keep = Retention {
            files: self.keep_files,
            age: self.keep_age,
            total: self.keep_size,
        };
        Ok(Some(plan))
    }
}

/// Where and how a session records, in words.
pub fn recorded(plan: Option<&RecordPlan>) -> String {
    use twin_realtime::rotate::{shown_duration, shown_size};
    let Some(plan) = plan else {
        return "not recorded".into();
    };
    let mut text = match &plan.out {
        Some(out) => format!("records to {}", out.display()),
        None => format!(
            "records to {}/{}-START.mcap",
            plan.dir.display(),
            plan.prefix
        ),
    };
    if let Some(every) = plan.every {
        text.push_str(&format!(
            ", a new file every {}",
            shown_duration(every.as_secs_f64())
        ));
    }
    if let Some(size) = plan.size {
        text.push_str(&format!(", a new file at {}", shown_size(size)));
    }
    let keep = &plan.keep;
    let mut kept = Vec::new();
    if let Some(n) = keep.files {
        kept.push(format!("{n} files"));
    }
    if let Some(age) = keep.age {
        kept.push(shown_duration(age.as_secs_f64()));
    }
    if let Some(total) = keep.total {
        kept.push(shown_size(total));
    }
    if !kept.is_empty() {
        text.push_str(&format!(", keeping at most {}", kept.join(", ")));
    }
    text
}
