//! `twin replay`: re-run a recording's scenario and check the new run
//! against it; or send its master frames to a live slave.

use anyhow::{Result, bail};
use clap::Args;
use std::path::{Path, PathBuf};
use std::time::Instant;
use twin_lab::step::StepConfig;
use twin_recording::{Encoding, Recording, diff};
use twin_sim::replay::RunSpec;

use super::progress::Progress;

/// Re-run the scenario stored in a recording and check that the new run matches.
///
/// The recording's `twin.run` metadata holds the scenario (with the duration and
/// seed it ran with) and the twin's version. Every run on the virtual clock
/// replays: `twin run` (a scenario or --open-loop), `twin step`, the runs of
/// `twin sweep` and `twin experiment parallel`, baselines. A real-time session
/// (`twin serve`, `twin supervise`) ran with live peers and the machine's clock
/// and cannot be re-run; send its frames to a live slave with --frames-to.
///
/// An unchanged replay must give the same bytes; otherwise the first signal and
/// time where the replay departs are printed, with the value recorded and
/// replayed, and the exit code is non-zero. `--set PATH=VALUE` changes a field of
/// the stored scenario first (dotted as in its TOML, list items by name or
/// index): `--set node.supervisor.kp=0.6`, `--set
/// module.ev1.params.wheel.brake_torque_nm=3`, `--set seed=2`; of a step
/// response, the scenario or the bench it ran on, or the step itself:
/// `--set step.to=300` (`step.from`, `step.at_s`).
///
/// `--frames-to LINK` instead sends the recorded master requests of one bus to a
/// live slave (`tcp://HOST:PORT` carrying the raw bus bytes, or a serial device or
/// pseudo-terminal path) one at a time, and holds each reply against the recorded
/// one. Replies carrying measurements differ in value from a slave whose plant
/// runs on its own clock; missing, malformed or mismatched replies fail.
#[derive(Debug, Args)]
pub struct ReplayArgs {
    /// The recording to replay.
    #[arg(value_name = "RUN.mcap")]
    recording: PathBuf,
    /// Change a field of the stored scenario before re-running (repeatable).
    #[arg(long = "set", value_name = "PATH=VALUE")]
    overrides: Vec<String>,
    /// Where to write the replay's recording, replacing one there [default:
    /// RUN.replay.mcap beside RUN.mcap].
    #[arg(long, value_name = "PATH", conflicts_with = "frames_to")]
    out: Option<PathBuf>,
    /// Send the recorded master frames to a live slave instead of re-running.
    #[arg(long, value_name = "LINK", conflicts_with = "overrides")]
    frames_to: Option<String>,
    /// With --frames-to: the bus whose frames to send [default: the only one].
    #[arg(long, value_name = "NAME", requires = "frames_to")]
    bus: Option<String>,
    /// With --frames-to: how long to wait for each reply.
    #[arg(long, value_name = "MS", default_value_t = 500, requires = "frames_to", value_parser = super::numbers::whole::<u64>)]
    timeout_ms: u64,
    /// With --frames-to: send only the first N requests.
    #[arg(long, value_name = "N", requires = "frames_to", value_parser = super::numbers::whole::<usize>)]
    limit: Option<usize>,
    /// With --frames-to: how many differing replies to print.
    #[arg(long, value_name = "N", default_value_t = 10, requires = "frames_to", value_parser = super::numbers::whole::<usize>)]
    show: usize,
}

impl ReplayArgs {
    /// Whether this replay sends frames to a live slave (in real time).
    pub fn sends_frames(&self) -> bool {
        self.frames_to.is_some()
    }
}

pub fn execute(args: &ReplayArgs) -> Result<()> {
    if let Some(link) = &args.frames_to {
        return frames_to(args, link);
    }
    let recorded = Recording::read(&args.recording)?;
    refuse_empty(&recorded)?;
    let as_recorded = Rerun::of(&recorded, &[])?;
    let version = recorded.run_field("twin_version").unwrap_or("unknown");
    println!(
        "twin replay: {} ({}, recorded by twin {version})",
        args.recording.display(),
        as_recorded.describe()
    );
    if version != env!("CARGO_PKG_VERSION") {
        println!(
            "  note: this is twin {}; a different version may run differently",
            env!("CARGO_PKG_VERSION")
        );
    }
    if let Some(why) = &recorded.truncated {
        println!("  note: the recording is cut short ({why}); only what it holds is compared");
    } else if let Some(why) = recorded.recovered_from_cut() {
        println!(
            "  note: the recording was recovered from a run cut short ({why}); only what it \
             holds is compared"
        );
    }
    let rerun = match args.overrides.is_empty() {
        true => as_recorded,
        false => Rerun::of(&recorded, &args.overrides)?,
    };
    for o in &args.overrides {
        println!("  changed: {o}");
    }
    let out = args.out.clone().unwrap_or_else(|| {
        let stem = args
            .recording
            .file_stem()
            .map_or_else(|| "run".into(), |s| s.to_string_lossy().into_owned());
        args.recording.with_file_name(format!("{stem}.replay.mcap"))
    });
    if out == args.recording {
        bail!("--out must not be the recording being replayed");
    }
    let earlier = super::output::Earlier::at(&out);
    let started = Instant::now();
    let progress = Progress::simulated("replay", rerun.duration_s());
    let path = rerun.run(&out, |done| progress.show(done))?;
    progress.clear();
    println!(
        "  replayed in {:.2} s wall time into {}{}",
        started.elapsed().as_secs_f64(),
        path.display(),
        super::output::Earlier::note(earlier.as_ref())
    );
    if diff::same_bytes(&args.recording, &path)? {
        println!(
            "  byte-identical: the replay matches the recording exactly ({} bytes, {} messages)",
            std::fs::metadata(&path)?.len(),
            recorded.message_count()
        );
        return Ok(());
    }
    let replayed = Recording::read(&path)?;
    match diff::first_departure(&recorded, &replayed)? {
        Some(d) => {
            println!(
                "  DEPARTS at {:.6} s on {}: recorded {}, replayed {}",
                d.time_s, d.signal, d.recorded, d.replayed
            );
            if !d.other_fields.is_empty() {
                let shown: Vec<&str> = d.other_fields.iter().take(8).map(String::as_str).collect();
                println!(
                    "    {} other field(s) of that message differ too: {}{}",
                    d.other_fields.len(),
                    shown.join(", "),
                    if d.other_fields.len() > shown.len() {
                        ", …"
                    } else {
                        ""
                    }
                );
            }
            println!("    {} channel(s) depart in all", d.channels_departing);
            bail!(
                "the replay departs from the recording at {:.6} s on {}",
                d.time_s,
                d.signal
            );
        }
        None if recorded.ends_early() => {
            println!(
                "  every message the cut-short recording holds matches the replay ({} messages)",
                recorded.message_count()
            );
            Ok(())
        }
        None if written_as_json_before(&recorded, &replayed) => {
            println!(
                "  every message matches ({} messages); the recording is from a twin that \
                 wrote as JSON channels the replay writes as protobuf (the plant's samples, \
                 the frames, the readings, a supervisor's loop), so their bytes differ",
                recorded.message_count()
            );
            Ok(())
        }
        None if frames_stored_twice(&args.recording)? => {
            println!(
                "  every message matches ({} messages); the recording is from a twin that \
                 stored each frame's bytes twice (as text and as hex), where the replay \
                 stores them once, so their bytes differ",
                recorded.message_count()
            );
            Ok(())
        }
        None if schemas_written_by_hand(&recorded, &replayed) => {
            println!(
                "  every message matches ({} messages); the recording is from a twin that \
                 wrote its protobuf schemas by hand, before the .proto files \
                 (twin/recording/proto/), and a frame's decoded fields in another order, so \
                 their bytes differ",
                recorded.message_count()
            );
            Ok(())
        }
        None => {
            let keys = metadata_differences(&recorded, &replayed);
            println!(
                "  every message matches, but the files differ{}",
                if keys.is_empty() {
                    " in their layout".to_string()
                } else {
                    format!(" in metadata: {}", keys.join(", "))
                }
            );
            bail!("the replay is not byte-identical to the recording");
        }
    }
}

/// Whether `recorded` holds as JSON a channel `replayed` holds as protobuf
/// (a recording made before the twin wrote protobuf).
fn written_as_json_before(recorded: &Recording, replayed: &Recording) -> bool {
    recorded.channels.iter().any(|c| {
        c.encoding == Encoding::Json
            && replayed
                .channel(&c.topic)
                .is_some_and(|r| matches!(r.encoding, Encoding::Protobuf(_)))
    })
}

/// Whether a protobuf channel of `recorded` has another schema than the
/// replay's: a recording made before the messages were `.proto` files,
/// whose schemas (and a frame's field order) the twin wrote by hand.
fn schemas_written_by_hand(recorded: &Recording, replayed: &Recording) -> bool {
    recorded.channels.iter().any(|c| {
        let Encoding::Protobuf(old) = &c.encoding else {
            return false;
        };
        replayed.channel(&c.topic).is_some_and(|r| {
            matches!(&r.encoding, Encoding::Protobuf(new)
                if new.parent_file().file_descriptor_proto()
                    != old.parent_file().file_descriptor_proto())
        })
    })
}

/// Whether the recording at `path` holds a protobuf frame with both its
/// `text` and its `hex` (a recording made before frames kept their bytes
/// once). Read as stored, since the reader fills in the missing one.
fn frames_stored_twice(path: &Path) -> Result<bool> {
    let mut twice = false;
    Recording::scan(path, |m| {
        if twice {
            return Ok(());
        }
        if let Encoding::Protobuf(schema) = m.encoding
            && schema.full_name() == twin_recording::topics::FRAME_SCHEMA
            && let Ok(serde_json::Value::Object(fields)) =
                twin_recording::protobuf::to_value(schema, m.data)
        {
            let present = |k: &str| {
                fields
                    .get(k)
                    .and_then(|v| v.as_str())
                    .is_some_and(|t| !t.is_empty())
            };
            twice = present("text") && present("hex");
        }
        Ok(())
    })?;
    Ok(twice)
}

/// What a replay runs again: a run, or an experiment on one.
enum Rerun {
    Run(RunSpec),
    Step(Box<StepConfig>),
}

impl Rerun {
    /// The run `recorded` holds, changed by `overrides`.
    fn of(recorded: &Recording, overrides: &[String]) -> Result<Self> {
        if let Some(step) = StepConfig::of_recording(recorded, overrides)? {
            return Ok(Self::Step(Box::new(step)));
        }
        if recorded
            .channel(twin_recording::topics::EXPERIMENT_STEP)
            .is_some()
        {
            bail!(
                "{} is a step response recorded by an earlier twin, which did not store the \
                 step's settings: it cannot be run again; run the `twin step` again to get one \
                 that can",
                recorded.path.display()
            );
        }
        Ok(Self::Run(
            RunSpec::from_recording(recorded)?.with_overrides(overrides)?,
        ))
    }

    fn describe(&self) -> String {
        match self {
            Rerun::Run(spec) => spec.describe(),
            Rerun::Step(step) => step.describe(),
        }
    }

    fn duration_s(&self) -> f64 {
        match self {
            Rerun::Run(spec) => spec.duration_s(),
            Rerun::Step(step) => step.duration_s,
        }
    }

    fn run(&self, out: &Path, progress: impl FnMut(f64)) -> Result<PathBuf> {
        match self {
            Rerun::Run(spec) => Ok(spec.run(out, progress)?),
            Rerun::Step(step) => Ok(twin_lab::step::run(step, out, progress)?.recording),
        }
    }
}

/// A recording with no message cannot show that a replay matches it.
fn refuse_empty(recorded: &Recording) -> Result<()> {
    if recorded.message_count() == 0 {
        bail!(
            "{}: there is nothing to hold a replay against",
            recorded.holds_no_messages()
        );
    }
    Ok(())
}

fn metadata_differences(a: &Recording, b: &Recording) -> Vec<String> {
    let mut keys = Vec::new();
    for (name, fields) in a.metadata.iter().chain(&b.metadata) {
        for k in fields.keys() {
            let get = |r: &Recording| r.metadata.get(name).and_then(|m| m.get(k)).cloned();
            let key = format!("{name}.{k}");
            if get(a) != get(b) && !keys.contains(&key) {
                keys.push(key);
            }
        }
    }
    keys
}

fn frames_to(args: &ReplayArgs, link_spec: &str) -> Result<()> {
    use twin_realtime::frames_to::{Link, Verdict, replay_frames, show};
    let recorded = Recording::read(&args.recording)?;
    refuse_empty(&recorded)?;
    if let Some(why) = &recorded.truncated {
        println!("note: {}: {why}", args.recording.display());
    }
    let mut link = Link::open(link_spec)?;
    let started = Instant::now();
    let progress = Progress::fraction("sending the recorded requests");
    let report = replay_frames(
        &recorded,
        &mut link,
        args.bus.as_deref(),
        std::time::Duration::from_millis(args.timeout_ms),
        args.limit,
        |done| progress.show(done),
    )?;
    progress.clear();
    let n = report.exchanges.len();
    println!(
        "twin replay --frames-to {link_spec}: {n} requests of {} on bus {} from {}, in {:.2} s",
        report.masters.join(", "),
        report.bus,
        args.recording.display(),
        started.elapsed().as_secs_f64()
    );
    let [same, values, missing, unexpected, different] = [
        Verdict::Same,
        Verdict::ValuesDiffer,
        Verdict::Missing,
        Verdict::Unexpected,
        Verdict::Different,
    ]
    .map(|v| report.count(v));
    println!("  {same} replies as recorded, byte for byte");
    println!(
        "  {values} replies differ in their values only (same id, command and length: \
         a live plant's measurements and timing differ from the recorded run's)"
    );
    println!(
        "  {missing} missing (no reply within {} ms), {unexpected} unexpected, {different} different \
         (fail their check or answer something else)",
        args.timeout_ms
    );
    if report.cut_off > 0 && args.limit.is_none_or(|l| l >= n + report.cut_off) {
        println!(
            "  the last request was not sent: the recorded run ended before its reply could come"
        );
    }
    if report.stray_bytes > 0 {
        println!(
            "  {} stray bytes arrived between exchanges",
            report.stray_bytes
        );
    }
    let differing: Vec<_> = report
        .exchanges
        .iter()
        .filter(|e| e.verdict != Verdict::Same)
        .take(args.show)
        .collect();
    if !differing.is_empty() {
        println!("  first differences (recorded time, request, recorded reply, live reply):");
    }
    for e in differing {
        println!("    [{:9.3} s] {}", e.time_s, e.verdict);
        println!("      request   {}", show(&e.request));
        println!(
            "      recorded  {}",
            e.recorded.as_deref().map_or_else(|| "(none)".into(), show)
        );
        println!(
            "      live      {}",
            if e.live.is_empty() {
                "(none)".into()
            } else {
                show(&e.live)
            }
        );
    }
    if missing + unexpected + different > 0 {
        bail!(
            "{} of {n} replies are missing, unexpected or different",
            missing + unexpected + different
        );
    }
    Ok(())
}
