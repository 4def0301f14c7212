//! The firmware in the recording: the ELF stored whole with its SHA-256,
//! the UART bursts with the cycle of every byte, the pins, the ADC inputs
//! and the cycle count; the same seed and firmware giving the same bytes;
//! and `twin-avr replay` running the stored ELF (not the file on disk),
//! refusing in words a recording whose firmware is damaged or missing.

use crate::common;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

use twin_recording::{Recording, attachment, topics};

fn elf() -> &'static PathBuf {
    static ELF: OnceLock<PathBuf> = OnceLock::new();
    ELF.get_or_init(|| {
        common::make("rec", "", &["ev-controller", "echo"]).join("ev-controller.elf")
    })
}

fn dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("avr-recording");
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// The shipped EV scenario for `duration_s`, its sketch at `firmware`.
fn scenario(name: &str, firmware: &Path, duration_s: f64) -> PathBuf {
    let text = std::fs::read_to_string(
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scenarios/ev-meb-avr.toml"),
    )
    .unwrap()
    .replace(
        "twin/avr/firmware/build/ev-controller.elf",
        &firmware.display().to_string(),
    )
    .replace("duration_s = 10.0", &format!("duration_s = {duration_s}"));
    let path = dir().join(name);
    std::fs::write(&path, text).unwrap();
    path
}

fn twin_avr(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_twin-avr"))
        .args(args)
        .output()
        .expect("twin-avr runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn sha256(bytes: &[u8]) -> String {
    twin_avr::record::sha256_hex(bytes)
}

/// A copy of the sketch that the test may overwrite.
fn own_copy(name: &str) -> PathBuf {
    let copy = dir().join(name);
    std::fs::copy(elf(), &copy).unwrap();
    copy
}

#[test]
fn a_firmware_run_stores_its_elf_uart_pins_adc_and_cycles_the_same_way_twice() {
    let firmware = own_copy("stored.elf");
    let toml = scenario("stored.toml", &firmware, 1.0);
    let (a, b) = (dir().join("stored-a.mcap"), dir().join("stored-b.mcap"));
    for out in [&a, &b] {
        let o = twin_avr(&[
            "run",
            toml.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", text(&o));
    }
    let bytes = std::fs::read(&a).unwrap();
    assert!(
        bytes == std::fs::read(&b).unwrap(),
        "the same seed and firmware gave two different recordings"
    );
    std::fs::remove_file(&b).unwrap();

    // The file, whole, and its hash in the metadata.
    let elf_bytes = std::fs::read(&firmware).unwrap();
    let stored = attachment::read(&a).unwrap();
    let recording = Recording::read(&a).unwrap();
    let meta = &recording.metadata[&topics::firmware_metadata("ev1")];
    assert_eq!(meta["sha256"], sha256(&elf_bytes));
    assert_eq!(meta["file"], firmware.display().to_string());
    assert_eq!(meta["wiring"], "wiring map ev-controller");
    assert!(meta["wiring_toml"].contains("D9 = \"vel\""));
    assert_eq!(stored.get(&meta["attachment"]).unwrap().data, elf_bytes);

    // UART: the supervisor's requests in, the sketch's MEB replies out, one
    // byte every 1360 cycles (117 647 baud, 8N1).
    let mut replies = 0;
    let mut requests = 0;
    let mut pwm_period = Vec::new();
    let mut v1_counts = Vec::new();
    let mut cycles = Vec::new();
    Recording::scan(&a, |m| {
        match topics::Topic::parse(m.topic) {
            topics::Topic::FirmwareUart("ev1") => {
                let v = m.value()?;
                let dir = v["dir"].as_str().unwrap_or("");
                let text = v["text"].as_str().unwrap_or("");
                if dir == "tx" && text.starts_with("@01EA") {
                    replies += 1;
                    let c: Vec<u64> = v["cycles"]
                        .as_array()
                        .unwrap()
                        .iter()
                        .map(|c| c.as_u64().unwrap())
                        .collect();
                    assert_eq!(c.len(), text.len());
                    // No byte before the last one's stop bit; back to back
                    // (the sketch writes faster than the line) 1360 apart.
                    let gaps: Vec<u64> = c.windows(2).map(|w| w[1] - w[0]).collect();
                    assert!(gaps.iter().all(|g| *g >= 1359), "{c:?}");
                    let back_to_back = gaps.iter().filter(|g| (1359..=1361).contains(*g)).count();
                    assert!(back_to_back * 10 > gaps.len() * 8, "{c:?}");
                    assert_eq!(v["baud"].as_f64(), Some(117_647.0));
                }
                if dir == "rx" && text.starts_with("@01") {
                    requests += 1;
                }
            }
            topics::Topic::FirmwareIo("ev1") => {
                let v = m.value()?;
                cycles.push((m.time_s(), v["cycles"].as_u64().unwrap()));
                for p in v["pins"].as_array().unwrap() {
                    if p["pin"] == "D9" && p["duty"].as_f64().unwrap() > 0.05 {
                        pwm_period.push(p["period_us"].as_f64().unwrap());
                    }
                }
                for a in v["adc"].as_array().unwrap() {
                    if a["signal"] == "v1" {
                        v1_counts.push(a["counts"].as_u64().unwrap());
                    }
                }
            }
            _ => {}
        }
        Ok(())
    })
    .unwrap();
    assert!(replies > 50, "{replies} replies");
    assert!(
        requests >= replies,
        "{requests} requests, {replies} replies"
    );
    // Timer1's 10-bit fast PWM with no prescaler: 1024 cycles, 64 µs (a
    // sample where the duty changed holds a shortened period, or one rise).
    let at_64 = pwm_period
        .iter()
        .filter(|p| (*p - 64.0).abs() < 0.002)
        .count();
    assert!(at_64 * 10 > pwm_period.len() * 8, "{pwm_period:?}");
    // V1 ≈ 40.7 V through the 10:1 divider: 4.07 V, 833 counts of 1024 at 5 V.
    assert!(
        v1_counts.iter().all(|c| (820..=840).contains(c)),
        "{v1_counts:?}"
    );
    // One simulated second is 16 M cycles, to the instruction: a run stops
    // after the instruction that reaches its target, an interrupt's entry
    // (4 cycles) and the jump at its vector (3) included.
    for (t, c) in cycles {
        assert!((c as f64 - t * 16e6).abs() <= 7.0, "{c} cycles at {t} s");
    }
}

#[test]
fn replay_runs_the_stored_elf_and_refuses_a_damaged_or_missing_one() {
    let firmware = own_copy("replayed.elf");
    let toml = scenario("replayed.toml", &firmware, 0.5);
    let run = dir().join("replayed.mcap");
    let o = twin_avr(&[
        "run",
        toml.to_str().unwrap(),
        "--out",
        run.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));

    // The file on disk changes (another sketch): the replay still runs the
    // recorded one, and matches.
    std::fs::copy(elf().with_file_name("echo.elf"), &firmware).unwrap();
    let o = twin_avr(&["replay", run.to_str().unwrap()]);
    let said = text(&o);
    assert!(o.status.success(), "{said}");
    assert!(said.contains("as the recording stored it"), "{said}");
    assert!(said.contains("byte-identical"), "{said}");

    // A byte of the stored ELF flipped.
    let bytes = std::fs::read(&run).unwrap();
    let at = bytes
        .windows(4)
        .position(|w| w == b"\x7fELF")
        .expect("the ELF is in the recording");
    let mut damaged = bytes.clone();
    damaged[at + 2000] ^= 0x10;
    let bad = dir().join("damaged.mcap");
    std::fs::write(&bad, damaged).unwrap();
    let o = twin_avr(&["replay", bad.to_str().unwrap()]);
    let said = text(&o);
    assert!(!o.status.success(), "{said}");
    assert!(
        said.contains("stored for node `ev1`") && said.contains("is damaged"),
        "{said}"
    );

    // Cut short inside the stored file: its metadata is there, the file not.
    let cut = dir().join("cut.mcap");
    std::fs::write(&cut, &bytes[..at + 100]).unwrap();
    let o = twin_avr(&["replay", cut.to_str().unwrap()]);
    let said = text(&o);
    assert!(!o.status.success(), "{said}");
    assert!(said.contains("does not hold it"), "{said}");
}
