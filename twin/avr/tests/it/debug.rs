//! The debugging extras simavr users expect, against real peers: a VCD
//! trace of chosen pins read back by a VCD parser we did not write (PyPI
//! `vcdvcd`), its PWM edges one Timer1 period apart; and simavr's GDB stub
//! driven by the real `avr-gdb` (Debian `gdb-avr`) in batch mode: a
//! breakpoint on the sketch's `loop`, a variable and a register read, and
//! the run going on to its end once the debugger lets go.

use crate::common;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

fn elf() -> &'static PathBuf {
    static ELF: OnceLock<PathBuf> = OnceLock::new();
    ELF.get_or_init(|| common::make("dbg", "", &["ev-controller"]).join("ev-controller.elf"))
}

fn dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("avr-debug");
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn scenario(name: &str, duration_s: f64) -> PathBuf {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/ev-meb-avr.toml"),
    )
    .unwrap()
    .replace(
        "twin/avr/firmware/build/ev-controller.elf",
        &elf().display().to_string(),
    )
    .replace("duration_s = 10.0", &format!("duration_s = {duration_s}"));
    let path = dir().join(name);
    std::fs::write(&path, text).unwrap();
    path
}

/// The edges of `signal` in a VCD file as `vcdvcd` reads them: (time in
/// the file's unit, level), and that unit in seconds.
fn vcd_edges(vcd: &Path, signal: &str) -> (Vec<(u64, u8)>, f64) {
    let script = format!(
        "import vcdvcd\n\
         v = vcdvcd.VCDVCD({vcd:?})\n\
         print(float(v.timescale['factor']))\n\
         for t, x in v[{signal:?}].tv: print(t, x)\n",
        vcd = vcd.display().to_string(),
    );
    let o = Command::new("python3")
        .arg("-c")
        .arg(&script)
        .output()
        .expect("python3 runs");
    assert!(
        o.status.success(),
        "vcdvcd cannot read the trace (install it: .ci/install): {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let out = String::from_utf8_lossy(&o.stdout).into_owned();
    let mut lines = out.lines();
    let unit: f64 = lines.next().unwrap().parse().unwrap();
    let edges = lines
        .map(|l| {
            let (t, x) = l.split_once(' ').unwrap();
            (t.parse().unwrap(), x.parse().unwrap())
        })
        .collect();
    (edges, unit)
}

#[test]
fn a_vcd_trace_of_chosen_pins_parses_and_its_pwm_edges_are_one_period_apart() {
    let toml = scenario("vcd.toml", 1.0);
    let vcd = dir().join("pins.vcd");
    let out = dir().join("vcd.mcap");
    let o = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args([
            "run",
            toml.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--vcd", vcd.to_str().unwrap(), "--vcd-pins", "D9,D5,D2"])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));

    // D9: Timer1 fast PWM, 10 bits, no prescaler: a rising edge every 1024
    // cycles of 62.5 ns. simavr toggles the pin at the instruction
    // boundary after the compare, so an edge may fall a cycle late.
    let (d9, unit) = vcd_edges(&vcd, "ev1.D9");
    assert_eq!(unit, 1e-12);
    let rises: Vec<u64> = d9.iter().filter(|e| e.1 == 1).map(|e| e.0).collect();
    assert!(rises.len() > 1000, "{} rising edges on D9", rises.len());
    let cycle_ps = 62_500;
    let gaps: Vec<u64> = rises.windows(2).map(|w| w[1] - w[0]).collect();
    // Every edge on a cycle of its own: the trace's times are exact.
    assert!(gaps.iter().all(|g| g % cycle_ps == 0), "{gaps:?}");
    // While the sketch pulses the pin (it holds it at either end of the
    // range, and a duty change restarts a period), the rising edges are
    // one period apart, and on average exactly one.
    let periods: Vec<u64> = gaps
        .iter()
        .filter(|g| (*g / cycle_ps).abs_diff(1024) <= 4)
        .copied()
        .collect();
    assert!(
        periods.len() * 10 > gaps.len() * 9,
        "{} of {} gaps are a period",
        periods.len(),
        gaps.len()
    );
    let mean = periods.iter().sum::<u64>() as f64 / periods.len() as f64;
    assert!((mean / cycle_ps as f64 - 1024.0).abs() < 0.05, "{mean} ps");

    // D5 (EN): the sketch drives it low to enable the inverter, once.
    let (d5, _) = vcd_edges(&vcd, "ev1.D5");
    assert!(d5.iter().any(|e| e.1 == 0), "{d5:?}");
    // D2 (hall A, an input the plant drives): edges as the wheel turns.
    let (d2, _) = vcd_edges(&vcd, "ev1.D2");
    assert!(d2.len() > 10, "{} edges on D2", d2.len());

    let bad = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args([
            "run",
            toml.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--vcd", vcd.to_str().unwrap(), "--vcd-pins", "D9,D22"])
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&bad.stderr);
    assert!(
        !bad.status.success() && said.contains("--vcd-pins D22: no such pin"),
        "{said}"
    );
}

#[test]
fn avr_gdb_breaks_in_loop_reads_a_variable_and_the_run_finishes() {
    if Command::new("avr-gdb").arg("--version").output().is_err() {
        panic!("avr-gdb is missing: install Debian's gdb-avr (.ci/install)");
    }
    let toml = scenario("gdb.toml", 0.05);
    let out = dir().join("gdb.mcap");
    // A port of our own: this test binary's process id, above 20000.
    let port = 20_000 + std::process::id() % 20_000;
    let mut run = Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args([
            "run",
            toml.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .args(["--gdb", &port.to_string()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    // It says when it waits.
    let mut stderr = BufReader::new(run.stderr.take().unwrap());
    let mut line = String::new();
    stderr.read_line(&mut line).unwrap();
    assert!(line.contains("waits for a debugger"), "{line}");

    let gdb = Command::new("avr-gdb")
        .args(["-batch", "-nx"])
        .args(["-ex", &format!("target remote :{port}")])
        .args(["-ex", "break loop"])
        .args(["-ex", "continue"])
        .args(["-ex", "print stored.ldr_th"])
        .args(["-ex", "info registers r1"])
        // simavr 1.6's stub does not know `detach`: closing the connection
        // is how it lets the core go on.
        .args(["-ex", "disconnect"])
        .arg(elf())
        .output()
        .unwrap();
    let said =
        String::from_utf8_lossy(&gdb.stdout).into_owned() + &String::from_utf8_lossy(&gdb.stderr);
    assert!(said.contains("Breakpoint 1, loop ()"), "{said}");
    // The stored settings' light threshold: 1933 (LDR_TH_DEFAULT).
    assert!(said.contains("$1 = 1933"), "{said}");
    // r1 is avr-gcc's zero register.
    assert!(said.contains("r1             0x0"), "{said}");

    let started = Instant::now();
    loop {
        if let Some(status) = run.try_wait().unwrap() {
            assert!(
                status.success(),
                "twin-avr failed after the debugger let go"
            );
            break;
        }
        assert!(
            started.elapsed() < Duration::from_secs(60),
            "the run did not finish after the debugger let go"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    let mut rest = String::new();
    std::io::Read::read_to_string(&mut run.stdout.take().unwrap(), &mut rest).unwrap();
    assert!(rest.contains("0.050 s simulated"), "{rest}");
}
