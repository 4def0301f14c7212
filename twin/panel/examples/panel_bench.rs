//! The panel's benchmark: does the plant tick notice it? Runs `twin serve`
//! (the real-time engine, an MEB TCP link polled by a master at 100 Hz) for
//! a few seconds with no panel, then with a panel and 0, 1 and 30 stream
//! clients, interleaved, and prints each run's plant tick lateness (p50,
//! p99, max) and the update rate the clients got.
//!
//! `cargo run -p twin-panel --example panel_bench -- [SECONDS] [ROUNDS]`
//! (`--release` for figures nearer an installed `twin`).

#![allow(
    clippy::disallowed_methods,
    reason = "a benchmark of a real-time server times it by the wall clock"
)]

use std::io::{BufRead, BufReader, Write};
use std::net::{SocketAddr, TcpStream};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::channel;
use std::time::{Duration, Instant};

use plant::PlantParams;
use protocols::meb::MebCmd;
use twin_panel::{AccessOptions, Panel, PanelOptions, PanelRole};
use twin_realtime::client::MebClient;
use twin_realtime::io::LinkDefaults;
use twin_realtime::serve::{self, ServeOptions, ServeProtocol};
use twin_realtime::session::SessionOptions;
use twin_realtime::sink::ViewOpener;

struct Run {
    p50: f64,
    p99: f64,
    max: f64,
    /// Updates per second per client (mean), if any client.
    rate: Option<f64>,
    polls: u64,
}

fn run(clients: Option<usize>, seconds: f64) -> Run {
    let panel = clients.map(|_| {
        Panel::bind(PanelOptions {
            role: PanelRole::Serve,
            addr: "127.0.0.1:0".parse().unwrap(),
            access: AccessOptions::default(),
            rate_hz: 20.0,
        })
        .unwrap()
    });
    let view = panel
        .clone()
        .map(|p| ViewOpener::new(move |_| Some(p.view())));
    let options = ServeOptions {
        session: SessionOptions {
            duration: Some(seconds + 1.0),
            record: None,
            monitor: false,
            status_every: 0.0,
            wait_for_ports: false,
            record_hz: 200.0,
            rt_priority: None,
            view,
            command_line: "panel_bench".into(),
            allow: Default::default(),
            on_hangup: None,
        },
        links: vec![(ServeProtocol::Meb, "tcp://127.0.0.1:0".into())],
        defaults: LinkDefaults::default(),
        id: 1,
        meb_map: None,
        params: PlantParams::preset("vemodule").unwrap(),
        seed: 1,
        max_clients: Some(8),
        partial_timeout: None,
        rate_limit: None,
        idle_timeout: None,
        room_after_idle: None,
        read_only: false,
        light_adaptive: true,
        firmware: Vec::new(),
    };
    let (ready_tx, ready_rx) = channel();
    let addr = panel.as_ref().map(|p| p.running().addr);
    let session = std::thread::spawn(move || {
        serve::serve(
            &options,
            move |links| {
                let _ = ready_tx.send(links[0].address.clone());
            },
            move |engine| {
                if let Some(p) = &panel {
                    p.start(engine).unwrap();
                }
            },
        )
        .unwrap()
    });
    let meb = ready_rx.recv().unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    // A master polling the inputs at 100 Hz, as a supervisor does.
    let master = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let mut c = MebClient::connect(&meb, Duration::from_secs(2)).unwrap();
            let _ = c.write(1, MebCmd::SA, 0, &[1500]);
            let _ = c.write(1, MebCmd::SD, 0, &[0x001E]);
            let mut polls = 0;
            while !stop.load(Ordering::Relaxed) {
                if c.read(1, MebCmd::EA, 0, 6).is_ok() {
                    polls += 1;
                }
                std::thread::sleep(Duration::from_millis(10));
            }
            polls
        })
    };
    let readers: Vec<_> = (0..clients.unwrap_or(0))
        .map(|_| {
            let addr = addr.unwrap();
            std::thread::spawn(move || updates(addr, seconds))
        })
        .collect();
    std::thread::sleep(Duration::from_secs_f64(seconds));
    stop.store(true, Ordering::Relaxed);
    let polls = master.join().unwrap();
    let got: Vec<usize> = readers.into_iter().map(|r| r.join().unwrap()).collect();
    let outcome = session.join().unwrap();
    let l = outcome.lateness;
    Run {
        p50: l.p50_us,
        p99: l.p99_us,
        max: l.max_us,
        rate: (!got.is_empty())
            .then(|| got.iter().sum::<usize>() as f64 / got.len() as f64 / seconds),
        polls,
    }
}

fn updates(addr: SocketAddr, seconds: f64) -> usize {
    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    s.write_all(b"GET /api/stream HTTP/1.1\r\nHost: bench\r\n\r\n")
        .unwrap();
    let mut r = BufReader::new(s);
    let end = Instant::now() + Duration::from_secs_f64(seconds);
    let (mut n, mut line) = (0, String::new());
    while Instant::now() < end {
        line.clear();
        if r.read_line(&mut line).is_ok() && line.starts_with("event: update") {
            n += 1;
        }
    }
    n
}

fn main() {
    let mut args = std::env::args().skip(1);
    let seconds: f64 = args.next().and_then(|a| a.parse().ok()).unwrap_or(8.0);
    let rounds: usize = args.next().and_then(|a| a.parse().ok()).unwrap_or(2);
    println!("panel_bench: {seconds} s per run, {rounds} rounds, MEB master polling at 100 Hz");
    println!(
        "{:<18} {:>8} {:>8} {:>9} {:>14} {:>7}",
        "run", "p50 µs", "p99 µs", "max µs", "updates/s/client", "polls"
    );
    for round in 1..=rounds {
        for (label, clients) in [
            ("no panel", None),
            ("panel, 0 clients", Some(0)),
            ("panel, 1 client", Some(1)),
            ("panel, 30 clients", Some(30)),
        ] {
            let r = run(clients, seconds);
            println!(
                "{:<18} {:>8.0} {:>8.0} {:>9.0} {:>14} {:>7}   (round {round})",
                label,
                r.p50,
                r.p99,
                r.max,
                r.rate.map_or("-".into(), |x| format!("{x:.1}")),
                r.polls
            );
        }
    }
}
