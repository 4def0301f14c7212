//! `twin serve` and `twin supervise` as services: configuration files good
//! and broken (`--config`, `--check`), flags over the file, SIGHUP's
//! reread, the allowed client addresses (a client from 127.0.0.2 refused,
//! one from 127.0.0.1 served), systemd's readiness protocol on a socket the
//! test holds, the units in deploy/systemd verified by systemd-analyze
//! against the real binary (with the real-time priority they grant, and
//! what a session without it says), and a class of five modules in one
//! process, each reached by its own pymodbus client.

use std::os::unix::net::UnixDatagram;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use crate::support;
use support::{Proc, text, twin};

fn folder(name: &str) -> PathBuf {
    support::folder("service", name)
}

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn signal(proc: &Proc, name: &str) {
    let pid = proc.child.id().to_string();
    assert!(
        Command::new("kill")
            .args([&format!("-{name}"), &pid])
            .status()
            .expect("kill runs")
            .success()
    );
}

// The example configurations of deploy/config, checked, and flags over
// them: tests/cmd/service-config.trycmd. Broken configurations named by
// file, line and key: tests/cmd/service-broken.trycmd.

/// Runs the pymodbus student client: connects from `source`, writes `vel`.
fn student(source: &str, addr: &str, vel: u16) -> serde_json::Value {
    let (host, port) = addr.rsplit_once(':').expect("host:port");
    let script = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peers/pymodbus_class.py");
    let o = Command::new("python3")
        .arg(script)
        .args([source, host, port, &vel.to_string()])
        .output()
        .expect("python3 runs");
    assert!(o.status.success(), "pymodbus client: {}", text(&o));
    serde_json::from_slice(&o.stdout).expect("one JSON object")
}

#[test]
fn sighup_rereads_the_allowed_addresses_and_starts_a_new_file() {
    let dir = folder("hup");
    let config = dir.join("serve.toml");
    let body = |allow: &str, seed: u32| {
        format!(
            "modbus = [\"tcp://127.0.0.1:0\"]\nallow = [\"{allow}\"]\nseed = {seed}\nquiet = true\nstatus-every = 0\nrecord-dir = \"{}\"\n",
            dir.display()
        )
    };
    std::fs::write(&config, body("127.0.0.1/32", 1)).unwrap();
    let server = Proc::start(&["serve", "--config", config.to_str().unwrap()]);
    let addr = server.tcp_of("modbus-tcp");
    let from_2 = student("127.0.0.2", &addr, 1000);
    assert!(
        from_2.get("error").is_some(),
        "127.0.0.2 is not allowed: {from_2}"
    );
    assert!(
        server.printed("127.0.0.2")
            && server.printed("refused, not an allowed address (--allow 127.0.0.1/32)"),
        "{}",
        server.output()
    );
    let from_1 = student("127.0.0.1", &addr, 1000);
    assert_eq!(
        from_1["vel_readback"],
        serde_json::json!([1000, 1000]),
        "{from_1}"
    );

    std::fs::write(&config, body("127.0.0.2/32", 7)).unwrap();
    signal(&server, "HUP");
    assert!(
        server.printed(
            "applied `allow`; not reread while serving: `seed` (they take effect at the next start"
        ),
        "{}",
        server.output()
    );
    assert!(server.printed("finished (SIGHUP)"), "{}", server.output());
    let from_2 = student("127.0.0.2", &addr, 1200);
    assert_eq!(
        from_2["vel_readback"],
        serde_json::json!([1200, 1200]),
        "{from_2}"
    );
    let from_1 = student("127.0.0.1", &addr, 1300);
    assert!(
        from_1.get("error").is_some(),
        "127.0.0.1 no longer allowed: {from_1}"
    );

    // A file broken meanwhile is not applied, and says why.
    std::fs::write(&config, "modbus = [\n").unwrap();
    signal(&server, "HUP");
    assert!(
        server.printed("not reread, serving on as before"),
        "{}",
        server.output()
    );
    let printed = server.terminate();
    let refused: u64 = printed
        .split(" refused by --allow")
        .next()
        .and_then(|head| head.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no count of refusals: {printed}"));
    assert!(
        refused >= 2,
        "one from 127.0.0.2, one from 127.0.0.1: {printed}"
    );
    let files: Vec<_> = std::fs::read_dir(&dir)
        .unwrap()
        .filter_map(|e| e.ok())
        .filter(|e| e.file_name().to_string_lossy().starts_with("serve-"))
        .collect();
    assert_eq!(files.len(), 3, "two SIGHUPs, three files: {printed}");
}

/// Receives one datagram on `socket` within 30 s.
fn datagram(socket: &UnixDatagram) -> String {
    socket
        .set_read_timeout(Some(Duration::from_secs(30)))
        .unwrap();
    let mut buf = [0u8; 4096];
    let n = socket.recv(&mut buf).expect("a datagram from twin");
    String::from_utf8_lossy(&buf[..n]).into_owned()
}

#[test]
fn ready_and_stopping_reach_the_notify_socket() {
    let dir = folder("notify");
    let path = dir.join("notify.sock");
    let socket = UnixDatagram::bind(&path).expect("bind the notify socket");
    // An abstract one too, as systemd may hand out.
    let abstract_name = format!("twin-test-notify-{}", std::process::id());
    let abstract_socket = {
        use std::os::linux::net::SocketAddrExt;
        let addr = std::os::unix::net::SocketAddr::from_abstract_name(&abstract_name).unwrap();
        UnixDatagram::bind_addr(&addr).expect("bind the abstract socket")
    };
    for (notify, socket) in [
        (path.to_str().unwrap().to_string(), &socket),
        (format!("@{abstract_name}"), &abstract_socket),
    ] {
        let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
            .args([
                "serve",
                "--meb",
                "tcp://127.0.0.1:0",
                "--quiet",
                "--no-record",
            ])
            .env("NOTIFY_SOCKET", &notify)
            .stdout(std::process::Stdio::piped())
            .spawn()
            .expect("twin starts");
        let ready = datagram(socket);
        assert!(
            ready.starts_with("READY=1\nSTATUS=serving meb tcp://127.0.0.1:"),
            "{ready:?}"
        );
        let started = Instant::now();
        assert!(
            Command::new("kill")
                .args(["-TERM", &child.id().to_string()])
                .status()
                .unwrap()
                .success()
        );
        let stopping = datagram(socket);
        assert_eq!(
            stopping,
            "STOPPING=1\nSTATUS=SIGTERM: finishing the recording"
        );
        let status = child.wait().unwrap();
        assert!(status.success(), "{status}");
        assert!(started.elapsed() < Duration::from_secs(20));
    }
}

#[test]
fn the_systemd_units_verify_against_the_real_binary() {
    let Some(version) = Command::new("systemd-analyze")
        .arg("--version")
        .output()
        .ok()
        .filter(|o| o.status.success())
    else {
        eprintln!(
            "SKIPPED: systemd-analyze is not installed here (Debian: apt-get install systemd; .ci/install does it)"
        );
        return;
    };
    let _ = version;
    let dir = folder("units");
    // The man pages the units' Documentation= names, as `twin man` writes them.
    let man = dir.join("man/man1");
    let o = twin(&["man", "--out", man.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    let binary = env!("CARGO_BIN_EXE_twin");
    let units = repo().join("deploy/systemd");
    let mut written = Vec::new();
    for (file, instance) in [
        ("twin-serve.service", "twin-serve.service"),
        ("twin-serve@.service", "twin-serve@student01.service"),
        ("twin-supervise.service", "twin-supervise.service"),
    ] {
        let unit = std::fs::read_to_string(units.join(file)).expect("unit in deploy/systemd");
        // What a careful administrator's unit says.
        for line in [
            "Type=notify",
            "ExecReload=/bin/kill -HUP $MAINPID",
            "DynamicUser=yes",
            "Restart=on-failure",
            "StandardOutput=journal",
            "Environment=NO_COLOR=1",
            "NoNewPrivileges=yes",
            "ProtectSystem=strict",
        ] {
            assert!(unit.lines().any(|l| l == line), "{file} lacks {line}");
        }
        assert!(unit.contains("ExecStart=/usr/local/bin/twin "), "{file}");
        // Real-time priority where the host allows it: the flag, within the
        // limit the unit sets, and a sandbox that lets the scheduler be asked.
        for line in [
            "RestrictRealtime=no",
            "AmbientCapabilities=CAP_SYS_NICE",
            "CapabilityBoundingSet=CAP_SYS_NICE",
        ] {
            assert!(unit.lines().any(|l| l == line), "{file} lacks {line}");
        }
        let setting = |prefix: &str| -> u8 {
            let line = unit
                .lines()
                .find(|l| l.starts_with(prefix) || l.contains(prefix))
                .unwrap_or_else(|| panic!("{file} lacks {prefix}"));
            let after = &line[line.find(prefix).unwrap() + prefix.len()..];
            let number = after.split_whitespace().next().unwrap_or_default();
            number
                .parse()
                .unwrap_or_else(|_| panic!("{file}: {prefix}{number} is not a priority"))
        };
        let asked = setting("--rt-priority ");
        let limit = setting("LimitRTPRIO=");
        assert!(
            (1..=limit).contains(&asked),
            "{file}: --rt-priority {asked} beyond LimitRTPRIO={limit}"
        );
        let path = dir.join(instance);
        std::fs::write(&path, unit.replace("/usr/local/bin/twin", binary)).unwrap();
        written.push(path);
    }
    let verify = |paths: &[PathBuf]| {
        Command::new("systemd-analyze")
            .arg("verify")
            .args(paths)
            .env("MANPATH", dir.join("man"))
            .output()
            .expect("systemd-analyze runs")
    };
    let o = verify(&written);
    let said = text(&o);
    if !o.status.success() && said.contains("Failed to") && said.contains("bus") {
        eprintln!("SKIPPED: systemd-analyze verify cannot run in this container: {said}");
        return;
    }
    assert!(o.status.success(), "systemd-analyze verify: {said}");
    for path in &written {
        let name = path.file_name().unwrap().to_string_lossy();
        assert!(!said.contains(&*name), "{name}: {said}");
    }
    // It does check ExecStart: a missing binary fails it.
    if !Path::new("/usr/local/bin/twin").exists() {
        let original = dir.join("original/twin-serve.service");
        std::fs::create_dir_all(original.parent().unwrap()).unwrap();
        std::fs::copy(units.join("twin-serve.service"), &original).unwrap();
        let o = verify(&[original]);
        assert!(!o.status.success(), "{}", text(&o));
        assert!(text(&o).contains("/usr/local/bin/twin"), "{}", text(&o));
    }
}

/// Lines of `out` that say the session has no real-time priority.
fn priority_notices(out: &str) -> Vec<&str> {
    out.lines()
        .filter(|l| l.contains("no real-time priority"))
        .collect()
}

#[test]
fn a_session_without_real_time_priority_says_once_what_it_risks_and_how_to_grant_it() {
    let _cores = support::RealTime::share_the_cores();
    let base = [
        "serve",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--no-record",
        "--duration",
        "0.3",
        "--status-every",
        "0",
    ];
    // Under --quiet too: it drops the frame monitor, not the notices.
    for quiet in [false, true] {
        let mut args = base.to_vec();
        if quiet {
            args.push("--quiet");
        }
        let o = twin(&args);
        assert!(o.status.success(), "{}", text(&o));
        let out = text(&o);
        let said = priority_notices(&out);
        assert_eq!(said.len(), 1, "{out}");
        for words in [
            "real time lost",
            "replies come late",
            "--rt-priority N",
            "CAP_SYS_NICE",
            "deploy/systemd",
        ] {
            assert!(said[0].contains(words), "{words}: {}", said[0]);
        }
        // Said before `ready`, where a user reads what the session is.
        let ready = out.lines().position(|l| l == "ready").expect("ready");
        let notice = out.lines().position(|l| l == said[0]).unwrap();
        assert!(notice < ready, "{out}");
    }

    // A class says it once, not once per module.
    let dir = folder("class-priority");
    let mut config =
        "quiet = true\nstatus-every = 0\nno-record = true\nduration = 0.3\n".to_string();
    for n in 1..=3 {
        config.push_str(&format!(
            "\n[[module]]\nname = \"m{n}\"\nmodbus = [\"tcp://127.0.0.1:0\"]\n"
        ));
    }
    let path = dir.join("class.toml");
    std::fs::write(&path, config).unwrap();
    let o = twin(&["serve", "--config", path.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert_eq!(priority_notices(&text(&o)).len(), 1, "{}", text(&o));
}

/// The grant the units give, tried where the test runs as root: an
/// ordinary user holding only CAP_SYS_NICE (as `AmbientCapabilities=`
/// gives the service's user) gets the priority and says nothing; the same
/// user without it is refused, and told once what that risks and how to
/// grant it.
#[test]
fn the_units_grant_is_enough_and_a_refusal_is_said_once() {
    let root = Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0");
    let setpriv = Command::new("setpriv")
        .arg("--version")
        .output()
        .is_ok_and(|o| o.status.success());
    // Root itself may be denied SCHED_FIFO in a container.
    let fifo = Command::new("chrt")
        .args(["-f", "1", "true"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !(root && setpriv && fifo) {
        eprintln!(
            "SKIPPED: needs root allowed SCHED_FIFO, and setpriv (util-linux) to run the twin as another user"
        );
        return;
    }
    let _cores = support::RealTime::share_the_cores();
    let session = |caps: &[&str]| {
        let o = Command::new("setpriv")
            .args(["--reuid=nobody", "--regid=nogroup", "--clear-groups"])
            .args(caps)
            .args([
                env!("CARGO_BIN_EXE_twin"),
                "serve",
                "--modbus",
                "tcp://127.0.0.1:0",
                "--no-record",
                "--quiet",
                "--duration",
                "0.3",
                "--status-every",
                "0",
                "--rt-priority",
                "40",
            ])
            .current_dir("/")
            .output()
            .expect("setpriv runs");
        assert!(o.status.success(), "{}", text(&o));
        text(&o)
    };
    let granted = session(&["--inh-caps=+sys_nice", "--ambient-caps=+sys_nice"]);
    assert!(priority_notices(&granted).is_empty(), "{granted}");
    let refused = session(&["--inh-caps=-all", "--bounding-set=-all"]);
    let said = priority_notices(&refused);
    // The plant's thread and the links' are both refused: one warning.
    assert_eq!(said.len(), 1, "{refused}");
    for words in [
        "delay ticks",
        "CAP_SYS_NICE",
        "rtprio limit to 40",
        "LimitRTPRIO=",
    ] {
        assert!(said[0].contains(words), "{words}: {}", said[0]);
    }
}

/// `--rt-priority N`, granted: the plant's thread runs under SCHED_FIFO
/// at N and every thread of the links' runtime (where the serial ports and
/// listeners are served) at N-1, as the help says; read from `/proc` while
/// the session runs. (The runtime's workers once kept normal priority: only
/// the thread that blocks on the runtime was raised.)
#[test]
fn a_granted_priority_reaches_the_plant_and_every_links_thread() {
    let fifo = Command::new("chrt")
        .args(["-f", "1", "true"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !fifo {
        eprintln!("SKIPPED: needs SCHED_FIFO allowed (root, or CAP_SYS_NICE)");
        return;
    }
    let serve = Proc::start(&[
        "serve",
        "--modbus",
        "tcp://127.0.0.1:0",
        "--no-record",
        "--quiet",
        "--status-every",
        "0",
        "--rt-priority",
        "40",
    ]);
    // Each thread's name, real-time priority and policy (1: SCHED_FIFO),
    // fields 2, 40 and 41 of its stat.
    let pid = serve.child.id();
    let threads = || {
        let mut threads = Vec::new();
        for task in std::fs::read_dir(format!("/proc/{pid}/task")).expect("the twin's threads") {
            let Ok(stat) = std::fs::read_to_string(task.unwrap().path().join("stat")) else {
                continue;
            };
            let (Some(open), Some(close)) = (stat.find('('), stat.rfind(')')) else {
                continue;
            };
            let fields: Vec<&str> = stat[close + 1..].split_whitespace().collect();
            let number = |n: usize| fields.get(n - 3).and_then(|f| f.parse::<u32>().ok());
            threads.push((stat[open + 1..close].to_string(), number(40), number(41)));
        }
        threads
    };
    let of = |threads: &[(String, Option<u32>, Option<u32>)], name: &str| {
        threads
            .iter()
            .filter(|t| t.0 == name)
            .map(|t| (t.1, t.2))
            .collect::<Vec<_>>()
    };
    let raised = |t: &[(String, Option<u32>, Option<u32>)]| {
        let links = of(t, "twin-links");
        of(t, "twin-realtime") == [(Some(40), Some(1))]
            && !links.is_empty()
            && links.iter().all(|&l| l == (Some(39), Some(1)))
    };
    // Each thread raises itself as it starts, a moment after `ready`.
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut seen = threads();
    while !raised(&seen) && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(50));
        seen = threads();
    }
    serve.terminate();
    assert!(raised(&seen), "{seen:?}");
}

#[test]
fn a_class_of_five_modules_each_reached_by_its_own_pymodbus_client() {
    let dir = folder("class");
    let mut config = format!(
        "quiet = true\nstatus-every = 0\nrecord-dir = \"{}\"\nallow = [\"127.0.0.1\"]\n",
        dir.display()
    );
    for n in 1..=5 {
        config.push_str(&format!(
            "\n[[module]]\nname = \"student{n:02}\"\nmodbus = [\"tcp://127.0.0.1:0\"]\nseed = {n}\n"
        ));
    }
    let path = dir.join("class.toml");
    std::fs::write(&path, config).unwrap();
    let server = Proc::start(&["serve", "--config", path.to_str().unwrap()]);
    let links = server.links();
    assert_eq!(links.len(), 5, "{links:?}");
    let mut addrs = Vec::new();
    for n in 1..=5 {
        let name = format!("student{n:02}");
        let link = links
            .iter()
            .find(|l| l.get(3) == Some(&name))
            .unwrap_or_else(|| panic!("{name} not among {links:?}"));
        assert_eq!(link[0], "modbus-tcp");
        addrs.push(support::host_port(&link[1]).to_string());
    }
    // All five at once, each writing its own VEL.
    let students: Vec<_> = addrs
        .iter()
        .enumerate()
        .map(|(n, addr)| {
            let addr = addr.clone();
            std::thread::spawn(move || student("127.0.0.1", &addr, 1000 + 100 * n as u16))
        })
        .collect();
    for (n, s) in students.into_iter().enumerate() {
        let seen = s.join().unwrap();
        let vel = 1000 + 100 * n as u64;
        assert_eq!(
            seen["vel_readback"],
            serde_json::json!([vel, vel]),
            "student{:02} sees only its own module: {seen}",
            n + 1
        );
        assert_eq!(seen["inputs"].as_array().map(Vec::len), Some(6), "{seen}");
    }
    // Another machine (127.0.0.2) reaches none of them.
    let stranger = student("127.0.0.2", &addrs[2], 4000);
    assert!(stranger.get("error").is_some(), "{stranger}");
    assert!(
        server.printed("refused, not an allowed address"),
        "{}",
        server.output()
    );
    let printed = server.terminate();
    for n in 1..=5 {
        let name = format!("student{n:02}");
        assert!(
            printed
                .lines()
                .any(|l| l.starts_with(&format!("{name}: stopped (SIGTERM)"))),
            "{printed}"
        );
        let recordings: Vec<_> = std::fs::read_dir(dir.join(&name))
            .unwrap_or_else(|e| panic!("{name}'s folder: {e}"))
            .filter_map(|e| e.ok())
            .collect();
        assert_eq!(recordings.len(), 1, "{name}: {recordings:?}");
        let bytes = std::fs::read(recordings[0].path()).unwrap();
        let summary = mcap::Summary::read(&bytes).unwrap().expect("finished");
        assert!(summary.stats.unwrap().message_count > 0);
    }
    assert!(
        printed.contains("student03: stopped (SIGTERM)") && printed.contains("1 refused (--allow)"),
        "{printed}"
    );
}

/// CPU time (user and system) `pid` has used so far, in seconds, from
/// `/proc`: only this process's, however busy the machine.
fn cpu_seconds(pid: u32) -> f64 {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("its /proc stat");
    // After the command's name in parentheses: state is field 3, utime 14.
    let rest = &stat[stat.rfind(')').expect("(comm)") + 1..];
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks: f64 = fields[11].parse::<f64>().unwrap() + fields[12].parse::<f64>().unwrap();
    let per_second = Command::new("getconf")
        .arg("CLK_TCK")
        .output()
        .expect("getconf");
    ticks / text(&per_second).trim().parse::<f64>().expect("CLK_TCK")
}

/// A class of 35 modules that no one uses costs little: no client, no
/// recording, nothing moving, the whole process under half a core over 5 s
/// (this debug build; the release build's figure, and its goal, are in the
/// measurements chapter).
#[test]
fn a_class_of_thirty_five_idle_modules_costs_under_half_a_core() {
    let dir = folder("idle-class");
    let mut config = String::from("quiet = true\nstatus-every = 0\n");
    for n in 1..=35 {
        config.push_str(&format!(
            "\n[[module]]\nname = \"student{n:02}\"\nmeb = [\"tcp://127.0.0.1:0\"]\nno-record = true\n"
        ));
    }
    let path = dir.join("class.toml");
    std::fs::write(&path, config).unwrap();
    let server = Proc::start(&["serve", "--config", path.to_str().unwrap()]);
    assert_eq!(server.links().len(), 35, "{}", server.output());
    let pid = server.child.id();
    std::thread::sleep(Duration::from_secs(1));
    let (before, since) = (cpu_seconds(pid), Instant::now());
    std::thread::sleep(Duration::from_secs(5));
    let share = (cpu_seconds(pid) - before) / since.elapsed().as_secs_f64();
    println!(
        "an idle class of 35 modules: {:.1} % of one core",
        share * 100.0
    );
    assert!(share < 0.5, "{:.1} % of one core", share * 100.0);
    server.terminate();
}

/// A class whose module waits for a port (`--wait-for-ports`) stops on
/// SIGTERM: the other module has taken the signal over by then, so the
/// wait itself must listen for it.
#[test]
fn a_class_waiting_for_a_port_stops_on_sigterm() {
    let _cores = support::RealTime::share_the_cores();
    let dir = folder("class-waits");
    let missing = dir.join("ttyV-not-yet");
    let config = format!(
        "quiet = true\nstatus-every = 0\n\n[[module]]\nname = \"student01\"\n\
         meb = [\"tcp://127.0.0.1:0\"]\nno-record = true\n\n[[module]]\nname = \"student02\"\n\
         modbus8 = [\"{}\"]\nno-record = true\n",
        missing.display()
    );
    let path = dir.join("class.toml");
    std::fs::write(&path, config).unwrap();
    let out = dir.join("out.txt");
    let mut child = Command::new(env!("CARGO_BIN_EXE_twin"))
        .args([
            "serve",
            "--config",
            path.to_str().unwrap(),
            "--wait-for-ports",
        ])
        .stdout(std::fs::File::create(&out).unwrap())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("twin starts");
    let waiting = Instant::now() + Duration::from_secs(30);
    while !std::fs::read_to_string(&out)
        .unwrap_or_default()
        .contains("waiting for")
    {
        assert!(Instant::now() < waiting, "never said it waits");
        std::thread::sleep(Duration::from_millis(50));
    }
    // The other module is up and has the signals by now.
    std::thread::sleep(Duration::from_millis(500));
    let _ = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status();
    let until = Instant::now() + Duration::from_secs(10);
    let status = loop {
        if let Some(status) = child.try_wait().expect("try_wait") {
            break status;
        }
        if Instant::now() > until {
            let _ = child.kill();
            panic!("still waiting 10 s after SIGTERM");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    let mut err = String::new();
    let _ = std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err);
    assert!(
        err.contains("stopped (SIGTERM) while waiting for"),
        "{status}: {err}"
    );
}

#[test]
fn check_refuses_a_serial_port_that_is_not_there_unless_told_to_wait() {
    let missing = folder("ports").join("ttyGone");
    let missing = missing.to_str().unwrap();
    for args in [
        vec!["serve", "--modbus-rtu", missing, "--check"],
        vec!["supervise", "--meb", missing, "--check"],
    ] {
        let o = twin(&args);
        assert!(!o.status.success(), "{args:?}: {}", text(&o));
        assert!(
            text(&o).contains(&format!("serial port {missing} does not exist")),
            "{args:?}: {}",
            text(&o)
        );
        assert!(text(&o).contains("--wait-for-ports"), "{}", text(&o));
        let mut waiting = args.clone();
        waiting.push("--wait-for-ports");
        let o = twin(&waiting);
        assert!(o.status.success(), "{waiting:?}: {}", text(&o));
    }
}
