//! What is checked of a firmware file before simavr sees it, so that a
//! missing, corrupt or wrong file is refused with the file and the field at
//! fault rather than a crash in C.

use std::path::Path;

use ihex::{ReaderError, Record};
use object::elf::{self, FileFlags};
use object::read::elf::FileHeader;
use object::{Endianness, FileKind};

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

/// The avr-gcc architecture of each MCU this build runs.
fn architecture_of(mcu: &str) -> Option<FileFlags> {
    match mcu {
        "atmega328p" | "atmega328" | "atmega168" | "atmega168p" => Some(elf::EF_AVR_ARCH_AVR5),
        _ => None,
    }
}

fn architecture_name(arch: FileFlags) -> String {
    match arch.0 {
        100 => "avrtiny".into(),
        a @ 101..=107 => format!("xmega{}", a - 100),
        a => format!("avr{a}"),
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
    if bytes.get(..4) != Some(&elf::ELFMAG[..]) {
        return Err(ElfError::NotElf {
            file,
            start: bytes.iter().take(4).copied().collect(),
        });
    }
    // A host program given by mistake is often a 64-bit ELF: it is still
    // named by its machine rather than refused as cut short.
    let header = match FileKind::parse(&bytes[..]) {
        Ok(FileKind::Elf64) => machine_and_flags::<elf::FileHeader64<Endianness>>(&bytes),
        _ => machine_and_flags::<elf::FileHeader32<Endianness>>(&bytes),
    };
    let Some((machine, flags)) = header else {
        return Err(ElfError::Short {
            file,
            len: bytes.len(),
        });
    };
    if machine != elf::EM_AVR {
        return Err(ElfError::NotAvr {
            file,
            machine: machine.0,
        });
    }
    let arch = flags.avr_arch();
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

/// The header's `e_machine` and `e_flags`, if it is whole and well formed.
fn machine_and_flags<H: FileHeader<Endian = Endianness>>(
    bytes: &[u8],
) -> Option<(elf::Machine, FileFlags)> {
    let header = H::parse(bytes).ok()?;
    let endian = header.endian().ok()?;
    Some((header.e_machine(endian), header.e_flags(endian)))
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
    // Record by record rather than ihex's Reader, so an error names its line.
    for (n, line) in text.lines().enumerate().map(|(i, l)| (i + 1, l.trim())) {
        if line.is_empty() {
            continue;
        }
        let record = Record::from_record_string(line).map_err(|e| bad(n, hex_why(&e)))?;
        match record {
            Record::Data { offset, value } => {
                let last = base.saturating_add(u32::from(offset) + value.len() as u32);
                end = end.max(last);
            }
            Record::EndOfFile => saw_eof = true,
            Record::ExtendedSegmentAddress(segment) => base = u32::from(segment) << 4,
            Record::ExtendedLinearAddress(upper) => base = u32::from(upper) << 16,
            Record::StartSegmentAddress { .. } | Record::StartLinearAddress(_) => {}
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

/// What is wrong with a record, in the words this tool has always used.
fn hex_why(e: &ReaderError) -> &'static str {
    match e {
        ReaderError::MissingStartCode => "no ':' at its start",
        ReaderError::ContainsInvalidCharacters => "not hexadecimal",
        ReaderError::RecordTooShort | ReaderError::RecordNotEvenLength => {
            "too short or an odd number of digits"
        }
        ReaderError::RecordTooLong => "more than 255 bytes of data",
        ReaderError::ChecksumMismatch(..) => "bad checksum",
        ReaderError::PayloadLengthMismatch => "its length byte does not match",
        ReaderError::UnsupportedRecordType(_) => "unknown record type",
        ReaderError::InvalidLengthForType => "a length its record type does not allow",
    }
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
    fn a_host_program_and_a_cut_elf_are_named_as_such() {
        // This test's own program: a 64-bit ELF for the host's processor.
        let me = std::env::current_exe().unwrap();
        let err = check(&me, "atmega328p").unwrap_err().to_string();
        assert!(
            err.contains("built for another processor (ELF field e_machine = "),
            "{err}"
        );
        let dir = std::env::temp_dir().join(format!("twin-avr-cut-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("cut.elf");
        std::fs::write(&path, b"\x7fELF\x01\x01\x01\0\0\0").unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(
            err.ends_with("cut.elf: ELF header cut short (10 bytes)"),
            "{err}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
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
        std::fs::write(
            &path,
            ":100000000C945C000C946E000C946E000C946E00CA\n:0000ZZ01FF\n",
        )
        .unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(
            err.contains("line 2: not an Intel HEX record (not hexadecimal)"),
            "{err}"
        );
        // Flash at 64 KiB, through an extended linear address.
        std::fs::write(&path, ":020000040001F9\n:0100000000FF\n:00000001FF\n").unwrap();
        let err = check(&path, "atmega328p").unwrap_err().to_string();
        assert!(
            err.contains("65537 bytes of flash, more than the atmega328p's 32 KB"),
            "{err}"
        );
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
