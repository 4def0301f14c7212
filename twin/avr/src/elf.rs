//! What is checked of a firmware file before simavr sees it, so that a
//! missing, corrupt or wrong file is refused with the file and the field at
//! fault rather than a crash in C.

use std::path::Path;

/// Why a firmware file is refused.
#[derive(Debug, thiserror::Error)]
pub enum ElfError {
    #[error("{file}: cannot read it ({why})")]
    Unreadable { file: String, why: String },
    #[error(
        "{file}: not an ELF file (it starts {start:02X?}); give the sketch's .elf, as avr-gcc or the Arduino IDE's \"Export compiled binary\" writes it"
    )]
    NotElf { file: String, start: Vec<u8> },
    #[error("{file}, line {line}: not an Intel HEX record ({why})")]
    BadHex {
        file: String,
        line: usize,
        why: &'static str,
    },
    #[error("{file}: {end} bytes of flash, more than the {mcu}'s 32 KB")]
    HexTooBig { file: String, end: u32, mcu: String },
    #[error("{file}: ELF header cut short ({len} bytes)")]
    Short { file: String, len: usize },
    #[error("{file}: built for another processor (ELF field e_machine = {machine}), not an AVR")]
    NotAvr { file: String, machine: u16 },
    #[error(
        "{file}: built for AVR architecture {found} (ELF field e_flags), not the {mcu}'s {expected}: rebuild it with -mmcu={mcu}"
    )]
    WrongArchitecture {
        file: String,
        found: String,
        expected: String,
        mcu: String,
    },
    #[error("{file}: built for the {found} (its .mmcu section), not the {mcu} the node asks for")]
    WrongMcu {
        file: String,
        found: String,
        mcu: String,
    },
    #[error("{file}: simavr cannot read it as firmware (a corrupt or stripped ELF?)")]
    Unloadable { file: String },
    #[error("mcu `{0}`: this build runs the ATmega328P only (mcu = \"atmega328p\")")]
    UnsupportedMcu(String),
}

/// `EM_AVR`.
const EM_AVR: u16 = 83;

/// The avr-gcc architecture of each MCU this build runs.
fn architecture_of(mcu: &str) -> Option<u32> {
    match mcu {
        "atmega328p" | "atmega328" | "atmega168" | "atmega168p" => Some(5),
        _ => None,
    }
}

fn architecture_name(arch: u32) -> String {
    match arch {
        100..=107 => format!("xmega{}", arch - 100),
        _ => format!("avr{arch}"),
    }
}

/// Checks that `path` is an AVR ELF built for `mcu`.
pub fn check(path: &Path, mcu: &str) -> Result<(), ElfError> {
    let file = path.display().to_string();
    let expected = architecture_of(mcu).ok_or_else(|| ElfError::UnsupportedMcu(mcu.into()))?;
    let bytes = std::fs::read(path).map_err(|e| ElfError::Unreadable {
        file: file.clone(),
        // The usual cause: the lab's sketches ship as sources, not built.
        why: if e.kind() == std::io::ErrorKind::NotFound {
            "no such file; `make -C twin/avr/firmware` builds the lab's sketches".into()
        } else {
            e.kind().to_string()
        },
    })?;
    if bytes.first() == Some(&b':') {
        return check_hex(&file, &bytes, mcu);
    }
    if bytes.get(..4) != Some(b"\x7fELF") {
        return Err(ElfError::NotElf {
            file,
            start: bytes.iter().take(4).copied().collect(),
        });
    }
    // 32-bit little-endian header: e_machine at 18, e_flags at 36.
    let (Some(machine), Some(flags)) = (bytes.get(18..20), bytes.get(36..40)) else {
        return Err(ElfError::Short {
            file,
            len: bytes.len(),
        });
    };
    let machine = u16::from_le_bytes([machine[0], machine[1]]);
    if machine != EM_AVR {
        return Err(ElfError::NotAvr { file, machine });
    }
    let arch = u32::from_le_bytes([flags[0], flags[1], flags[2], flags[3]]) & 0x7f;
    if arch != expected {
        return Err(ElfError::WrongArchitecture {
            file,
            found: architecture_name(arch),
            expected: architecture_name(expected),
            mcu: mcu.into(),
        });
    }
    Ok(())
}

/// An Intel HEX file (avr-objcopy's or the Arduino IDE's `.hex`): every
/// record well formed with its checksum, and the flash it fills within the
/// MCU's. A `.hex` names no MCU: the node's `mcu` and `clock_hz` are taken.
fn check_hex(file: &str, bytes: &[u8], mcu: &str) -> Result<(), ElfError> {
    let bad = |line, why| ElfError::BadHex {
        file: file.into(),
        line,
        why,
    };
    let text = std::str::from_utf8(bytes).map_err(|_| bad(1, "not text"))?;
    let (mut base, mut end, mut saw_eof) = (0u32, 0u32, false);
    for (n, line) in text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())) {
        if line.is_empty() {
            continue;
        }
        let hex = line
            .strip_prefix(':')
            .ok_or_else(|| bad(n, "no ':' at its start"))?;
        if hex.len() % 2 != 0 || hex.len() < 10 {
            return Err(bad(n, "too short or an odd number of digits"));
        }
        let record: Vec<u8> = (0..hex.len() / 2)
            .map(|i| u8::from_str_radix(&hex[2 * i..2 * i + 2], 16))
            .collect::<Result<_, _>>()
            .map_err(|_| bad(n, "not hexadecimal"))?;
        if record.len() != usize::from(record[0]) + 5 {
            return Err(bad(n, "its length byte does not match"));
        }
        if record.iter().fold(0u8, |a, b| a.wrapping_add(*b)) != 0 {
            return Err(bad(n, "bad checksum"));
        }
        let addr = u32::from(u16::from_be_bytes([record[1], record[2]]));
        let data = &record[4..record.len() - 1];
        match record[3] {
            0x00 => end = end.max(base + addr + data.len() as u32),
            0x01 => saw_eof = true,
            0x02 if data.len() == 2 => {
                base = u32::from(u16::from_be_bytes([data[0], data[1]])) << 4
            }
            0x04 if data.len() == 2 => {
                base = u32::from(u16::from_be_bytes([data[0], data[1]])) << 16
            }
            0x03 | 0x05 => {}
            _ => return Err(bad(n, "unknown record type")),
        }
    }
    if !saw_eof {
        return Err(bad(
            text.lines().count().max(1),
            "no end-of-file record (cut short?)",
        ));
    }
    if end > 0x8000 {
        return Err(ElfError::HexTooBig {
            file: file.into(),
            end,
            mcu: mcu.into(),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_text_file_is_not_taken_for_firmware() {
        let dir = std::env::temp_dir().join(format!("twin-avr-elf-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("sketch.hex");
        std::fs::write(&path, "MEB @01EA000643*\n").unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(err.contains("sketch.hex: not an ELF file"), "{err}");
        let err = check(&dir.join("missing.elf"), "atmega328p")
            .unwrap_err()
            .to_string();
        assert!(err.contains("missing.elf: cannot read it"), "{err}");
        let err = check(&path, "atmega2560").unwrap_err().to_string();
        assert!(err.contains("ATmega328P only"), "{err}");
    }

    #[test]
    fn an_intel_hex_file_is_checked_record_by_record() {
        let dir = std::env::temp_dir().join(format!("twin-avr-hex-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("sketch.hex");
        let good = ":100000000C945C000C946E000C946E000C946E00CA\n:00000001FF\n";
        std::fs::write(&path, good).unwrap();
        check(&path, "atmega328p").expect("a good .hex");
        std::fs::write(&path, good.replace("CA", "CB")).unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(
            err.contains("sketch.hex, line 1: not an Intel HEX record (bad checksum)"),
            "{err}"
        );
        std::fs::write(&path, ":100000000C945C000C946E000C946E000C946E00CA\n").unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(err.contains("no end-of-file record"), "{err}");
    }
}
