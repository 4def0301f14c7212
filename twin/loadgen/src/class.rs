//! `serve-bench class`: a class of N modules on this machine, served by one
//! `twin serve` process (a configuration file with a `[[module]]` per
//! student) and by one process per student (what the `twin-serve@` unit
//! template runs), measured interleaved in the same run; or, given other
//! builds of `twin` (`--against`), each build serving the class from one
//! process, interleaved the same way. Each module is
//! polled by its own Modbus TCP client at a fixed rate (one request in
//! flight, FC04 and FC03 alternating, every reply checked); reported per
//! module are the reply latency p99 and, from the server's own report, the
//! plant's tick lateness p99.

use anyhow::{Context, Result, bail};
use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use crate::child::{Server, tcp_addr};
use crate::measure::{Dialect, quantile};

/// The two ways to serve a class.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Variant {
    /// One `twin serve --config class.toml` with a `[[module]]` per student.
    OneProcess,
    /// One `twin serve --config studentNN.toml` per student.
    ProcessPerModule,
}

impl Variant {
    pub fn name(self) -> &'static str {
        match self {
            Variant::OneProcess => "one process",
            Variant::ProcessPerModule => "a process each",
        }
    }
}

/// A build of `twin`, and what its lines are headed with.
#[derive(Debug, Clone)]
pub struct Build {
    pub label: String,
    pub path: PathBuf,
}

impl Build {
    /// Labels for `paths`: each binary's folder (`bins/old/twin` is `old`)
    /// where the binaries share a name, else its file name; a label taken
    /// twice gets its place in the list too.
    pub fn labelled(paths: &[PathBuf]) -> Vec<Build> {
        let name = |p: &PathBuf| {
            p.file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default()
        };
        let same_names = paths.iter().all(|p| name(p) == name(&paths[0]));
        let labels: Vec<String> = paths
            .iter()
            .map(|p| {
                let folder = p
                    .parent()
                    .and_then(|d| d.file_name())
                    .map(|n| n.to_string_lossy().into_owned());
                match folder {
                    Some(f) if same_names && !f.is_empty() => f,
                    _ => name(p),
                }
            })
            .collect();
        labels
            .iter()
            .enumerate()
            .map(|(n, label)| Build {
                label: if labels.iter().filter(|l| *l == label).count() > 1 {
                    format!("{label}#{}", n + 1)
                } else {
                    label.clone()
                },
                path: paths[n].clone(),
            })
            .collect()
    }
}

/// One way to serve the class: a build, and one process or a process each.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Way {
    /// Index into [`ClassRun::builds`].
    pub build: usize,
    pub variant: Variant,
}

/// What the class is told and how it is loaded.
#[derive(Debug, Clone)]
pub struct ClassRun {
    /// The builds measured: the first is the one the others are compared with.
    pub builds: Vec<Build>,
    pub modules: usize,
    pub hz: f64,
    pub seconds: f64,
    pub record: bool,
    /// Poll over MEB-TCP instead of Modbus TCP.
    pub meb: bool,
    pub dir: PathBuf,
}

impl ClassRun {
    /// The protocol each module is polled in, its configuration key and
    /// the name the twin prints its links under.
    fn protocol(&self) -> (Dialect, &'static str, &'static str) {
        if self.meb {
            (Dialect::MebTcp, "meb", "meb")
        } else {
            (Dialect::ModbusTcp, "modbus", "modbus-tcp")
        }
    }
}

/// One module's figures.
#[derive(Debug, Clone, Default)]
pub struct ModuleFigures {
    pub answered: u64,
    pub expected: u64,
    pub bad: u64,
    pub lost: u64,
    pub latency_p50_us: f64,
    pub latency_p99_us: f64,
    pub latency_max_us: f64,
    /// Requests sent more than one period after their slot (the client fell behind).
    pub late_sends: u64,
    pub tick_p99_us: Option<f64>,
}

/// A way's figures over its modules, and what the machine did meanwhile.
#[derive(Debug, Clone)]
pub struct ClassFigures {
    pub way: Way,
    /// How the way is named on its lines.
    pub name: String,
    pub modules: Vec<ModuleFigures>,
    /// The servers' CPU time over the run, as a share of one core.
    pub server_cpu: f64,
    /// The whole machine's busy share (all cores) over the run, from /proc/stat.
    pub machine_busy: f64,
    /// 1-minute load average at the end of the run.
    pub load_avg: f64,
    /// Resident memory of the servers at the end, MiB.
    pub rss_mib: f64,
}

/// Writes the configuration files of `way` into `dir`; returns the
/// commands that serve the class.
fn commands(run: &ClassRun, way: Way, dir: &Path) -> Result<Vec<Command>> {
    let twin = &run.builds[way.build].path;
    std::fs::create_dir_all(dir)?;
    let record = if run.record {
        format!(
            "record-dir = \"{}\"\nrotate-every = \"1h\"\n",
            dir.join("rec").display()
        )
    } else {
        "no-record = true\n".to_string()
    };
    let common = format!(
        "quiet = true\nstatus-every = 0\nallow = [\"127.0.0.1\"]\nmax-clients = 4\n{record}"
    );
    let key = run.protocol().1;
    let module = |n: usize| format!("{key} = [\"tcp://127.0.0.1:0\"]\nseed = {}\n", n + 1);
    let mut commands = Vec::new();
    match way.variant {
        Variant::OneProcess => {
            let mut text = common.clone();
            for n in 0..run.modules {
                text.push_str(&format!(
                    "\n[[module]]\nname = \"student{:03}\"\n{}",
                    n + 1,
                    module(n)
                ));
            }
            let path = dir.join("class.toml");
            std::fs::write(&path, text)?;
            let mut cmd = Command::new(twin);
            cmd.args(["serve", "--config"]).arg(&path);
            commands.push(cmd);
        }
        Variant::ProcessPerModule => {
            for n in 0..run.modules {
                let name = format!("student{:03}", n + 1);
                let text = format!("{common}{}", module(n)).replace(
                    &format!("record-dir = \"{}\"", dir.join("rec").display()),
                    &format!("record-dir = \"{}\"", dir.join("rec").join(&name).display()),
                );
                let path = dir.join(format!("{name}.toml"));
                std::fs::write(&path, text)?;
                let mut cmd = Command::new(twin);
                cmd.args(["serve", "--config"]).arg(&path);
                commands.push(cmd);
            }
        }
    }
    Ok(commands)
}

/// Polls `addr` at `hz` until `stop`; every reply checked.
fn poll_module(
    addr: &str,
    dialect: Dialect,
    hz: f64,
    start: Instant,
    stop: &AtomicBool,
) -> Result<(ModuleFigures, Vec<u32>)> {
    let mut stream =
        std::net::TcpStream::connect(addr).with_context(|| format!("connecting to {addr}"))?;
    stream.set_nodelay(true)?;
    stream.set_read_timeout(Some(Duration::from_secs(1)))?;
    let period = Duration::from_secs_f64(1.0 / hz);
    let mut figures = ModuleFigures::default();
    let mut latencies: Vec<u32> = Vec::with_capacity(8192);
    let mut request = [0u8; 16];
    let mut reply = [0u8; 64];
    let mut i = 0usize;
    while !stop.load(Ordering::Relaxed) {
        let slot = start + period.mul_f64(i as f64);
        let now = Instant::now();
        if slot > now {
            std::thread::sleep(slot - now);
        } else if now - slot > period {
            figures.late_sends += 1;
        }
        let len = dialect.request(i, &mut request);
        let want = dialect.reply_len(i);
        figures.expected += 1;
        let sent = Instant::now();
        stream.write_all(&request[..len])?;
        match stream.read_exact(&mut reply[..want]) {
            Ok(()) => {
                let took = sent.elapsed();
                if dialect.check(i, &request[..len], &reply[..want]) {
                    figures.answered += 1;
                    latencies.push(u32::try_from(took.as_micros()).unwrap_or(u32::MAX));
                } else {
                    figures.bad += 1;
                }
            }
            Err(_) => {
                // No reply within a second: the stream is out of step; start afresh.
                figures.lost += 1;
                stream = std::net::TcpStream::connect(addr)?;
                stream.set_nodelay(true)?;
                stream.set_read_timeout(Some(Duration::from_secs(1)))?;
            }
        }
        i += 1;
    }
    Ok((figures, latencies))
}

/// Busy and total jiffies of the whole machine, from /proc/stat.
fn cpu_jiffies() -> Option<(u64, u64)> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let line = stat.lines().next()?;
    let v: Vec<u64> = line
        .split_whitespace()
        .skip(1)
        .filter_map(|x| x.parse().ok())
        .collect();
    let total: u64 = v.iter().sum();
    let idle = v.get(3)? + v.get(4).unwrap_or(&0);
    Some((total - idle, total))
}

fn load_avg() -> f64 {
    std::fs::read_to_string("/proc/loadavg")
        .ok()
        .and_then(|s| s.split_whitespace().next()?.parse().ok())
        .unwrap_or(f64::NAN)
}

/// The ways a run serves its class: one build one process and a process
/// each, or every build one process.
pub fn ways(run: &ClassRun) -> Vec<Way> {
    if run.builds.len() == 1 {
        [Variant::OneProcess, Variant::ProcessPerModule]
            .map(|variant| Way { build: 0, variant })
            .to_vec()
    } else {
        (0..run.builds.len())
            .map(|build| Way {
                build,
                variant: Variant::OneProcess,
            })
            .collect()
    }
}

/// How `way` is named on its lines: the variant, after the build's label
/// where builds are compared.
pub fn way_name(run: &ClassRun, way: Way) -> String {
    if run.builds.len() == 1 {
        way.variant.name().to_string()
    } else {
        format!("{}, {}", run.builds[way.build].label, way.variant.name())
    }
}

/// Serves and loads the class one way; returns its figures.
pub fn measure(run: &ClassRun, way: Way, round: usize) -> Result<ClassFigures> {
    let dir = run.dir.join(format!(
        "round{round}-{}-{}",
        way.build,
        match way.variant {
            Variant::OneProcess => "one",
            Variant::ProcessPerModule => "each",
        }
    ));
    let _ = std::fs::remove_dir_all(&dir);
    let mut servers = Vec::new();
    for (n, cmd) in commands(run, way, &dir)?.into_iter().enumerate() {
        servers.push(Server::start(
            &format!("twin serve {n}"),
            cmd,
            Duration::from_secs(60),
        )?);
    }
    // Each module's server, name (in a class) and address.
    let mut addrs: Vec<(usize, String, String)> = Vec::new();
    for (si, s) in servers.iter().enumerate() {
        for (n, (protocol, addr)) in s.links.iter().enumerate() {
            if protocol == run.protocol().2 {
                let name = s.link_names.get(n).cloned().unwrap_or_default();
                addrs.push((si, name, tcp_addr(addr)?.to_string()));
            }
        }
    }
    if addrs.len() != run.modules {
        bail!("{} modules printed, {} wanted", addrs.len(), run.modules);
    }
    let cpu_before: Duration = servers.iter().filter_map(Server::cpu_time).sum();
    let machine_before = cpu_jiffies();
    let stop = Arc::new(AtomicBool::new(false));
    let start = Instant::now() + Duration::from_millis(200);
    // An idle class (no rate) has no client.
    let polled = if run.hz > 0.0 { addrs.as_slice() } else { &[] };
    let clients: Vec<_> = polled
        .iter()
        .enumerate()
        .map(|(n, (_, _, addr))| {
            let (addr, stop, hz) = (addr.clone(), stop.clone(), run.hz);
            let dialect = run.protocol().0;
            // Spread the clients over the period, as students' programs would be.
            let offset = Duration::from_secs_f64(n as f64 / run.modules as f64 / hz);
            std::thread::Builder::new()
                .name(format!("client-{n}"))
                .stack_size(256 * 1024)
                .spawn(move || poll_module(&addr, dialect, hz, start + offset, &stop))
        })
        .collect::<std::io::Result<_>>()?;
    std::thread::sleep(Duration::from_secs_f64(run.seconds) + Duration::from_millis(200));
    stop.store(true, Ordering::Relaxed);
    let mut modules = Vec::new();
    if polled.is_empty() {
        modules.resize(addrs.len(), ModuleFigures::default());
    }
    for c in clients {
        let (mut figures, mut latencies) = c
            .join()
            .map_err(|_| anyhow::anyhow!("a client thread failed"))??;
        latencies.sort_unstable();
        let us = |q| quantile(&latencies, q).map_or(f64::NAN, f64::from);
        figures.latency_p50_us = us(0.5);
        figures.latency_p99_us = us(0.99);
        figures.latency_max_us = latencies.last().map_or(f64::NAN, |&m| f64::from(m));
        modules.push(figures);
    }
    let cpu_after: Duration = servers.iter().filter_map(Server::cpu_time).sum();
    let machine_busy = match (machine_before, cpu_jiffies()) {
        (Some((b0, t0)), Some((b1, t1))) if t1 > t0 => (b1 - b0) as f64 / (t1 - t0) as f64,
        _ => f64::NAN,
    };
    let rss_mib = servers.iter().filter_map(Server::rss_kib).sum::<u64>() as f64 / 1024.0;
    let load = load_avg();
    let server_cpu = (cpu_after.saturating_sub(cpu_before)).as_secs_f64() / run.seconds;
    // Tick lateness from each server's last lines.
    let mut ticks: Vec<(usize, String, f64)> = Vec::new();
    for (si, s) in servers.into_iter().enumerate() {
        let lines = s.stop_within(Duration::from_secs(60));
        for line in &lines {
            // One process: `student001: stopped (…) …; tick lateness p99 12 µs, …`
            if let Some((name, rest)) = line.split_once(": stopped (")
                && let Some(p99) = number_after(rest, "tick lateness p99 ")
            {
                ticks.push((si, name.to_string(), p99));
            }
            // A process each: `  tick lateness over N ticks: p50 1 µs, p99 12 µs, …`
            if line.trim_start().starts_with("tick lateness over")
                && let Some(p99) = number_after(line, "p99 ")
            {
                ticks.push((si, String::new(), p99));
            }
        }
    }
    for ((si, name, _), figures) in addrs.iter().zip(&mut modules) {
        figures.tick_p99_us = ticks
            .iter()
            .find(|(s, n, _)| s == si && n == name)
            .map(|(_, _, p)| *p);
    }
    Ok(ClassFigures {
        way,
        name: way_name(run, way),
        modules,
        server_cpu,
        machine_busy,
        load_avg: load,
        rss_mib,
    })
}

fn number_after(text: &str, label: &str) -> Option<f64> {
    let rest = text.split_once(label)?.1;
    rest.split_whitespace()
        .next()?
        .trim_end_matches(',')
        .parse()
        .ok()
}

/// Median of the finite `values` (NaN if none).
pub fn median(values: &[f64]) -> f64 {
    crate::measure::median(values.iter().copied()).unwrap_or(f64::NAN)
}

/// One line of the report: the variant's modules summed up.
pub fn summary(f: &ClassFigures) -> String {
    let pick = |g: fn(&ModuleFigures) -> f64| -> Vec<f64> {
        f.modules.iter().map(g).filter(|v| v.is_finite()).collect()
    };
    let lat = pick(|m| m.latency_p99_us);
    let tick = pick(|m| m.tick_p99_us.unwrap_or(f64::NAN));
    let lat_max = lat.iter().copied().fold(f64::NAN, f64::max);
    let tick_max = tick.iter().copied().fold(f64::NAN, f64::max);
    let answered: u64 = f.modules.iter().map(|m| m.answered).sum();
    let expected: u64 = f.modules.iter().map(|m| m.expected).sum();
    let bad: u64 = f.modules.iter().map(|m| m.bad).sum();
    let lost: u64 = f.modules.iter().map(|m| m.lost).sum();
    let late: u64 = f.modules.iter().map(|m| m.late_sends).sum();
    let replies = if expected == 0 {
        "idle: no client".to_string()
    } else {
        format!(
            "reply p99 per module: median {:>6.0} µs, worst {:>6.0} µs",
            median(&lat),
            lat_max
        )
    };
    format!(
        "{:<15} {replies} | tick lateness p99 per module: median {:>5.0} µs, worst {:>6.0} µs | {answered}/{expected} answered, {lost} lost, {bad} wrong, {late} sent late | server CPU {:.1} % of a core, RSS {:.0} MiB ({:.1} per module) | machine busy {:.0} %, load {:.1}",
        f.name,
        median(&tick),
        tick_max,
        f.server_cpu * 100.0,
        f.rss_mib,
        f.rss_mib / f.modules.len().max(1) as f64,
        f.machine_busy * 100.0,
        f.load_avg
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    fn run(paths: &[&str]) -> ClassRun {
        ClassRun {
            builds: Build::labelled(&paths.iter().map(PathBuf::from).collect::<Vec<_>>()),
            modules: 2,
            hz: 0.0,
            seconds: 1.0,
            record: false,
            meb: false,
            dir: PathBuf::from("class"),
        }
    }

    #[test]
    fn builds_are_named_by_their_folder_where_the_binaries_share_a_name() {
        let labels = |paths: &[&str]| {
            run(paths)
                .builds
                .into_iter()
                .map(|b| b.label)
                .collect::<Vec<_>>()
        };
        assert_eq!(
            labels(&["bins/head/twin", "bins/old/twin"]),
            ["head", "old"]
        );
        assert_eq!(labels(&["twin", "twin-old"]), ["twin", "twin-old"]);
        assert_eq!(labels(&["a/x/twin", "b/x/twin"]), ["x#1", "x#2"]);
    }

    #[test]
    fn one_build_is_served_both_ways_and_several_one_process_each() {
        let one = run(&["head/twin"]);
        assert_eq!(
            ways(&one)
                .into_iter()
                .map(|w| way_name(&one, w))
                .collect::<Vec<_>>(),
            ["one process", "a process each"]
        );
        let three = run(&["head/twin", "old/twin", "fix/twin"]);
        assert_eq!(
            ways(&three)
                .into_iter()
                .map(|w| way_name(&three, w))
                .collect::<Vec<_>>(),
            ["head, one process", "old, one process", "fix, one process"]
        );
    }
}
