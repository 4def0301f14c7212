//! A compiled sketch as a node of the twin: the AVR core stepped on the
//! engine's clock, its UART a port on the bus, its pins wired to the plant.
//!
//! Time: the core runs lazily, cycle by cycle, up to each instant the engine
//! hands the node (a byte's stop bit, a loop tick), so one simulated second
//! is exactly `clock_hz` cycles and the same scenario gives the same run.
//! Nothing here reads the wall clock.
//!
//! The UART's timing comes from the firmware's own registers (UBRR0, U2X0,
//! UCSR0C), not from simavr's UART model: a byte the firmware writes to UDR0
//! leaves on its wire at that baud, and a master at another baud sees what a
//! real receiver would sample (bytes garbled once the two are a few per cent
//! apart). The bytes of one reply go on the bus as one frame once the
//! firmware's line has been quiet for two characters.

use std::collections::VecDeque;
use std::path::{Path, PathBuf};

use nodes::node::{Firmware, MAX_FRAME, Node, NodeEvent};
use plant::params::SensingParams;
use plant::{Actuators, Sensors};
use protocols::time::{SimDuration, SimTime, TICKS_PER_SECOND};
use serde_json::json;
use twin_sim::engine::{FirmwareFile, FirmwareRecord, ObserveError, SimNode, Streamed};

use crate::ffi::{Core, Image, State};
use crate::record::FirmwareLog;
use crate::stepper::Stepper;
use crate::vcd::VcdTrace;
use crate::wiring::{Analog, Input, Output, Pwm, Wiring};

/// The ATmega328P's last flash byte address.
const FLASH_END: u32 = 0x7FFF;
/// Events kept for the engine before the oldest is dropped.
const MAX_PENDING_EVENTS: usize = 64;
/// Pins, ADC inputs and cycles are recorded this often.
const TELEMETRY_EVERY: SimDuration = SimDuration::from_millis(10);
/// A sketch that hears this many bytes (a few requests) over
/// [`SILENT_AFTER`] of its own time and writes nothing is said to be silent:
/// on the lab's buses every board is polled well within a second.
const SILENT_BYTES: u32 = 16;
const SILENT_AFTER: SimDuration = SimDuration::from_secs(1);

/// I/O registers of the ATmega328P (data-space addresses).
mod reg {
    pub const UCSR0A: u16 = 0xC0;
    pub const UCSR0C: u16 = 0xC2;
    pub const UBRR0L: u16 = 0xC4;
    pub const UBRR0H: u16 = 0xC5;
    /// PORTx and DDRx of ports B, C, D.
    pub const PORT: [u16; 3] = [0x25, 0x28, 0x2B];
    pub const DDR: [u16; 3] = [0x24, 0x27, 0x2A];
}

/// Why a firmware node cannot be built.
#[derive(Debug, thiserror::Error)]
pub enum StartError {
    #[error(transparent)]
    Elf(#[from] crate::elf::ElfError),
    #[error("simavr has no MCU `{0}`")]
    NoMcu(String),
}

/// How the firmware's UART is set: its bit time and character length.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UartSetting {
    pub baud: f64,
    pub bits_per_char: u32,
    pub ubrr: u16,
    pub u2x: bool,
}

impl UartSetting {
    /// From the registers: UBRR0, U2X0 (UCSR0A bit 1), UCSR0C's character
    /// size, parity and stop bits.
    fn read(core: &Stepper, clock_hz: u32) -> Self {
        let ubrr = u16::from_le_bytes([core.data(reg::UBRR0L), core.data(reg::UBRR0H) & 0x0F]);
        let u2x = core.data(reg::UCSR0A) & 0b10 != 0;
        let divisor = if u2x { 8.0 } else { 16.0 };
        let baud = f64::from(clock_hz) / (divisor * f64::from(ubrr + 1));
        let c = core.data(reg::UCSR0C);
        let data_bits = 5 + u32::from((c >> 1) & 0b11);
        let parity = u32::from((c >> 4) & 0b11 != 0);
        let stop = 1 + u32::from((c >> 3) & 1);
        Self {
            baud,
            bits_per_char: 1 + data_bits + parity + stop,
            ubrr,
            u2x,
        }
    }
}

/// Whether a receiver at bit time `rx_bit` finds the stop bit of a byte
/// sent at `tx_bit` low (a framing error, the AVR's FE0): it samples it in
/// the middle of its own tenth bit, timed from the start bit's falling edge;
/// after the sender's stop bit the line idles high.
pub fn framing_error(byte: u8, tx_bit: f64, rx_bit: f64) -> bool {
    let t = 9.5 * rx_bit / tx_bit;
    match t.floor() as i64 {
        i64::MIN..=0 => true,
        j @ 1..=8 => byte >> (j - 1) & 1 == 0,
        _ => false,
    }
}

/// What a receiver at bit time `rx_bit` makes of `byte` sent at `tx_bit`
/// (8 data bits, LSB first): it samples each bit in its own middle, timed
/// from the start bit's falling edge, so a few per cent of mismatch is
/// harmless and more shifts the bits.
pub fn sampled(byte: u8, tx_bit: f64, rx_bit: f64) -> u8 {
    let ratio = rx_bit / tx_bit;
    if (ratio - 1.0).abs() < 1e-9 {
        return byte;
    }
    let level = |t: f64| -> bool {
        match t.floor() as i64 {
            i64::MIN..=0 => false,
            j @ 1..=8 => byte >> (j - 1) & 1 != 0,
            _ => true,
        }
    };
    let mut out = 0u8;
    for k in 1..=8 {
        if level((k as f64 + 0.5) * ratio) {
            out |= 1 << (k - 1);
        }
    }
    out
}

/// What to hand simavr for a pin at `mv` millivolts so that it converts
/// as the chip does. The ATmega's ADC gives floor(Vin · 1024 / Vref)
/// (datasheet, "ADC Conversion Result"); simavr 1.6 computes
/// floor(mV · 1023 / Vref) from whole millivolts, up to two counts low.
/// With AVcc = 5 V as the reference, the smallest millivolt count that
/// simavr turns into the chip's result is handed over instead.
pub fn simavr_millivolts(mv: u32) -> u32 {
    let count = (u64::from(mv) * 1024 / 5000).min(1023);
    (count * 5000).div_ceil(1023) as u32
}

/// 64-bit FNV-1a of the firmware file: names exactly which build ran.
pub fn fingerprint(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0xcbf2_9ce4_8422_2325u64, |h, b| {
        (h ^ u64::from(*b)).wrapping_mul(0x0000_0100_0000_01B3)
    })
}

/// What a firmware node is: its board, its file, and the bus it is on.
#[derive(Debug, Clone, Copy)]
pub struct Board<'a> {
    pub name: &'a str,
    pub elf: &'a Path,
    pub mcu: &'a str,
    pub clock_hz: u32,
    /// The bus's baud and bits per character (its masters' setting).
    pub bus_baud: u32,
    pub bus_bits: u32,
}

/// A compiled sketch running on a simulated ATmega328P.
#[derive(Debug)]
pub struct AvrNode {
    name: String,
    elf: PathBuf,
    core: Stepper,
    clock_hz: u32,
    wiring: Wiring,
    sensing: SensingParams,
    bus_baud: f64,
    bus_bits: u32,
    uart: UartSetting,
    /// Bytes written by the firmware, not yet sent as a frame.
    pending: Vec<u8>,
    /// When the last of them ends on the firmware's wire.
    pending_end: SimTime,
    /// When the firmware's TX line is free for the next byte.
    line_free: SimTime,
    /// Bytes go to the bus one by one, at their own wire times (the
    /// virtual engine), not as frames (the real-time server).
    streaming: bool,
    /// Bytes written, with their wire start and end, not yet streamed.
    stream_out: VecDeque<(u8, SimTime, SimTime)>,
    /// A streamed frame has begun and not yet ended.
    stream_open: bool,
    /// How far the firmware's output has been taken.
    advanced_to: SimTime,
    ready: Vec<u8>,
    /// Inputs as last driven: per wired input pin.
    input_levels: Vec<bool>,
    /// Per PWM pin: (cycle, cycles high) at the last tick, and the filtered volts.
    pwm_state: Vec<(u64, u64, f64)>,
    last_tick: SimTime,
    failure: Option<String>,
    events: VecDeque<NodeEvent>,
    next_telemetry: SimTime,
    adc_mv: [u32; 8],
    actuators: Actuators,
    pub bytes_in: u64,
    pub bytes_out: u64,
    /// Bytes the firmware's receiver took with a framing error (its baud
    /// and the bus's too far apart).
    pub framing_errors_in: u64,
    /// Bytes the firmware sent that the bus's receivers find with one.
    pub framing_errors_out: u64,
    /// Bytes heard since the sketch last wrote one, the first at
    /// `silent_since`; `silent_said` once the silence has been reported.
    heard_since_out: u32,
    silent_since: SimTime,
    silent_said: bool,
    /// The recording's UART bursts, pins and ADC inputs.
    log: FirmwareLog,
    vcd: Option<VcdTrace>,
    /// The firmware file as loaded, for the recording, and its SHA-256.
    elf_bytes: Vec<u8>,
    sha256: String,
    mcu: String,
    /// When the sketch starts: the board is in reset and its bootloader
    /// before, its core at cycle 0 and its UART deaf.
    boot: SimTime,
    /// Bytes the bus sent it before then, which it never heard.
    pub bytes_before_boot: u64,
}

impl AvrNode {
    /// Loads the board's ELF (checked against its MCU) and powers the core up.
    pub fn start(
        board: Board<'_>,
        wiring: Wiring,
        sensing: SensingParams,
    ) -> Result<Self, StartError> {
        Self::start_as(board, wiring, sensing, board.elf)
    }

    /// [`AvrNode::start`], the node naming its file `shown` (a replay runs
    /// the bytes its recording stored, under the name they were recorded by).
    pub fn start_as(
        board: Board<'_>,
        wiring: Wiring,
        sensing: SensingParams,
        shown: &Path,
    ) -> Result<Self, StartError> {
        let Board {
            name,
            elf,
            mcu,
            clock_hz,
            bus_baud,
            bus_bits,
        } = board;
        crate::elf::check(elf, mcu)?;
        let bytes = std::fs::read(elf).unwrap_or_default();
        let image = Image::read(elf).ok_or_else(|| crate::elf::ElfError::Unloadable {
            file: elf.display().to_string(),
        })?;
        if !image.mcu.is_empty() && image.mcu != mcu {
            return Err(crate::elf::ElfError::WrongMcu {
                file: elf.display().to_string(),
                found: image.mcu.clone(),
                mcu: mcu.into(),
            }
            .into());
        }
        let core =
            Core::start(image, mcu, clock_hz).ok_or_else(|| StartError::NoMcu(mcu.into()))?;
        let core = Stepper::new(core, crate::stepper::mode(), name);
        let uart = UartSetting::read(&core, clock_hz);
        let log = crate::record::follow(&wiring, clock_hz);
        let mut node = Self {
            name: name.into(),
            elf: shown.to_path_buf(),
            core,
            clock_hz,
            input_levels: vec![false; wiring.inputs.len()],
            pwm_state: vec![(0, 0, 0.0); wiring.pwm.len()],
            wiring,
            sensing,
            bus_baud: f64::from(bus_baud.max(1)),
            bus_bits,
            uart,
            pending: Vec::with_capacity(MAX_FRAME),
            pending_end: SimTime::ZERO,
            line_free: SimTime::ZERO,
            streaming: false,
            stream_out: VecDeque::with_capacity(MAX_FRAME),
            stream_open: false,
            advanced_to: SimTime::ZERO,
            ready: Vec::with_capacity(MAX_FRAME),
            last_tick: SimTime::ZERO,
            failure: None,
            events: VecDeque::with_capacity(MAX_PENDING_EVENTS),
            next_telemetry: SimTime::ZERO,
            adc_mv: [0; 8],
            actuators: Actuators::from_pins(0x1F, 0x01, 0.0),
            bytes_in: 0,
            bytes_out: 0,
            framing_errors_in: 0,
            framing_errors_out: 0,
            heard_since_out: 0,
            silent_since: SimTime::ZERO,
            silent_said: false,
            log,
            vcd: None,
            sha256: crate::record::sha256_hex(&bytes),
            elf_bytes: Vec::new(),
            mcu: mcu.into(),
            boot: SimTime::ZERO,
            bytes_before_boot: 0,
        };
        node.core.watch(node.log.mask);
        // Inputs the plant holds steady from power-up: a healthy driver's
        // fault line reads high.
        for (i, (pin, input)) in node.wiring.inputs.clone().iter().enumerate() {
            if *input == Input::DriverFault {
                node.core.pin_input(pin.index, true);
                node.input_levels[i] = true;
            }
        }
        let detail = format!(
            "{} ({} bytes, FNV-1a {:016x}) on an {} at {} MHz, wiring {}",
            shown.display(),
            bytes.len(),
            fingerprint(&bytes),
            mcu,
            f64::from(clock_hz) / 1e6,
            node.wiring.origin
        );
        node.push_event(SimTime::ZERO, "state", detail);
        node.elf_bytes = bytes;
        Ok(node)
    }

    /// Holds the board in reset and its bootloader for `boot` from power-up
    /// (a scenario's `boot_ms`): its core runs its first cycle then, and
    /// bytes that reach its UART before are lost, as on a board whose
    /// sketch has not started. Called before the node first runs.
    pub fn hold_in_boot(&mut self, boot: SimDuration) {
        debug_assert_eq!(self.core.cycle(), 0, "the board has started already");
        self.boot = SimTime::ZERO + boot;
        if boot > SimDuration::ZERO {
            let detail = format!(
                "in reset and its bootloader until {:.6} s (boot_ms): the sketch starts then, \
                 and bytes before are not heard",
                self.boot.as_secs_f64()
            );
            self.push_event(SimTime::ZERO, "state", detail);
        }
    }

    /// Traces `pins` to a VCD file at `path`, from now on.
    pub fn trace_vcd(
        &mut self,
        path: &Path,
        pins: &[crate::wiring::Pin],
    ) -> Result<(), crate::vcd::VcdError> {
        let core = &self.core;
        let trace = VcdTrace::create(path, pins, self.clock_hz, &self.name, |i| {
            core.pin_output(i).0
        })?;
        self.core.watch(self.log.mask | trace.mask);
        self.vcd = Some(trace);
        Ok(())
    }

    /// Starts simavr's GDB stub on `port`: the core waits, stopped, for a
    /// debugger to connect and continue it.
    pub fn debug_gdb(&mut self, port: u16) -> Result<(), crate::debug::DebugError> {
        if !self.core.gdb(port) {
            let log = Core::last_log();
            return Err(crate::debug::DebugError::GdbPort {
                port,
                simavr: (!log.is_empty()).then_some(log),
            });
        }
        Ok(())
    }

    /// The firmware file's SHA-256, as `sha256sum` prints it.
    pub fn sha256(&self) -> &str {
        &self.sha256
    }

    /// The simulated cycles run so far.
    pub fn cycles(&self) -> u64 {
        self.core.cycle()
    }

    /// A byte of the firmware's data space (registers, I/O, RAM: a global
    /// variable at the address `avr-nm` gives, less 0x800000).
    pub fn ram(&self, addr: u16) -> u8 {
        self.core.data(addr)
    }

    /// The firmware's UART setting as its registers hold it now.
    pub fn uart(&self) -> UartSetting {
        self.uart
    }

    /// The core's cycle at `t`: 0 until the sketch starts at `boot`.
    fn to_cycle(&self, t: SimTime) -> u64 {
        let since = t.saturating_since(self.boot);
        (u128::from(since.0) * u128::from(self.clock_hz) / u128::from(TICKS_PER_SECOND)) as u64
    }

    fn to_time(&self, cycle: u64) -> SimTime {
        self.boot
            + SimDuration(
                (u128::from(cycle) * u128::from(TICKS_PER_SECOND) / u128::from(self.clock_hz))
                    as u64,
            )
    }

    fn push_event(&mut self, at: SimTime, kind: &'static str, detail: String) {
        if self.events.len() >= MAX_PENDING_EVENTS {
            self.events.pop_front();
        }
        self.events.push_back(NodeEvent { at, kind, detail });
    }

    /// Runs the core up to `now` and takes what its UART wrote.
    fn advance(&mut self, now: SimTime) {
        if self.failure.is_some() {
            return;
        }
        let state = self.core.run_until(self.to_cycle(now));
        while let Some((cycle, pin, level)) = self.core.edge() {
            self.log.edge(cycle, pin, level);
            if let Some(vcd) = &mut self.vcd {
                vcd.edge(cycle, pin, level);
            }
        }
        if let Some(vcd) = &mut self.vcd {
            vcd.reached(self.core.cycle());
        }
        match state {
            State::Crashed | State::Done => {
                let at = self.to_time(self.core.cycle());
                let pc = self.core.pc();
                let why = if state == State::Crashed {
                    let log = self.core.last_log();
                    let log = if log.is_empty() {
                        String::new()
                    } else {
                        format!(" (simavr: {log})")
                    };
                    let past = if pc > FLASH_END {
                        ", past the end of its 32 KB of flash"
                    } else {
                        ""
                    };
                    format!("crashed{log} at PC 0x{pc:04X}{past}")
                } else {
                    format!("went to sleep with interrupts off at PC 0x{pc:04X} and can never wake")
                };
                let message = format!(
                    "firmware {} of board `{}` {why}, {:.6} s simulated (cycle {}); the node is stopped",
                    self.elf.display(),
                    self.name,
                    at.as_secs_f64(),
                    self.core.cycle()
                );
                self.push_event(at, "trip", message.clone());
                self.failure = Some(message);
            }
            _ => {}
        }
        self.advanced_to = self.to_time(self.core.cycle()).max(now);
        self.take_uart_output();
    }

    fn take_uart_output(&mut self) {
        while let Some((byte, cycle)) = self.core.uart_output() {
            let setting = UartSetting::read(&self.core, self.clock_hz);
            if setting != self.uart {
                self.uart = setting;
                let at = self.to_time(cycle);
                self.note_baud(at);
            }
            let bit = 1.0 / self.uart.baud;
            let char_time = SimDuration::from_secs_f64(bit * f64::from(self.uart.bits_per_char));
            let start = self.to_time(cycle).max(self.line_free);
            self.line_free = start + char_time;
            let gap = char_time + char_time;
            self.log.sent(
                byte,
                self.to_cycle(start),
                start,
                self.line_free,
                self.uart.baud,
                gap,
            );
            // The bus's receivers sample it at their own baud.
            let seen = sampled(byte, bit, 1.0 / self.bus_baud);
            self.framing_errors_out += u64::from(framing_error(byte, bit, 1.0 / self.bus_baud));
            if self.streaming {
                if self.stream_out.len() < MAX_FRAME {
                    self.stream_out.push_back((seen, start, self.line_free));
                }
            } else if self.pending.len() < MAX_FRAME {
                self.pending.push(seen);
            }
            self.pending_end = self.line_free;
            self.bytes_out += 1;
            self.heard_since_out = 0;
            self.silent_said = false;
        }
    }

    /// A sketch that keeps hearing its bus and never writes (a student's
    /// sketch with the wrong slave id, a parser that never matches, a
    /// `Serial.begin` that never ran) is reported once, with where its
    /// program is, so the master's timeouts have a cause; the node keeps
    /// running, since a board that is not addressed is silent too.
    fn note_silence(&mut self, now: SimTime, heard: usize) {
        if self.heard_since_out == 0 {
            self.silent_since = now;
        }
        let heard = u32::try_from(heard).unwrap_or(u32::MAX);
        self.heard_since_out = self.heard_since_out.saturating_add(heard);
        if self.silent_said
            || self.heard_since_out < SILENT_BYTES
            || now < self.silent_since + SILENT_AFTER
        {
            return;
        }
        self.silent_said = true;
        let at = self.to_time(self.core.cycle());
        let detail = format!(
            "firmware {} of `{}` heard {} bytes since {:.6} s and answered none \
             (it wrote {} bytes in all); it is running, at PC 0x{:04X}, {:.6} s simulated \
             (cycle {}): a sketch that never answers its bus",
            self.elf.display(),
            self.name,
            self.heard_since_out,
            self.silent_since.as_secs_f64(),
            self.bytes_out,
            self.core.pc(),
            at.as_secs_f64(),
            self.core.cycle()
        );
        self.push_event(at, "silent", detail);
    }

    fn note_baud(&mut self, at: SimTime) {
        let u = self.uart;
        let apart = (u.baud / self.bus_baud - 1.0) * 100.0;
        let detail = format!(
            "UART0 at {:.0} baud (UBRR0 {}, U2X0 {}), {} bits per character; the bus runs at {:.0} baud, {} bits, {:+.1} % apart",
            u.baud,
            u.ubrr,
            if u.u2x { "on" } else { "off" },
            u.bits_per_char,
            self.bus_baud,
            self.bus_bits,
            apart
        );
        self.push_event(at, "state", detail);
    }

    /// When the bytes written so far make a frame: the firmware's line quiet
    /// for two characters after the last.
    fn frame_due(&self) -> Option<SimTime> {
        let streamed = self.stream_open || !self.stream_out.is_empty();
        if self.pending.is_empty() && !streamed {
            return None;
        }
        let char_time =
            SimDuration::from_secs_f64(f64::from(self.uart.bits_per_char) / self.uart.baud);
        Some(self.pending_end + char_time + char_time)
    }

    fn flush_if_due(&mut self, now: SimTime) {
        if self.ready.is_empty() && self.frame_due().is_some_and(|due| due <= now) {
            std::mem::swap(&mut self.ready, &mut self.pending);
        }
    }

    /// The voltage at an analog pin for `what` on the plant, in millivolts.
    fn pin_millivolts(&self, what: Analog, s: &Sensors) -> u32 {
        let k = &self.sensing;
        let volts = match what {
            Analog::V1 => s.battery_volts / k.battery_divider,
            Analog::V2 => s.bus_volts / k.bus_divider,
            Analog::I => k.current_zero_volts + s.inverter_current * k.current_volts_per_amp,
            Analog::Ldr => s.ldr_volts,
        };
        (volts.clamp(0.0, 5.0) * 1000.0).round() as u32
    }

    fn input_level(what: Input, s: &Sensors) -> bool {
        match what {
            Input::HallA => s.shaft.hall & 1 != 0,
            Input::HallB => s.shaft.hall & 2 != 0,
            Input::HallC => s.shaft.hall & 4 != 0,
            Input::EncoderA => s.shaft.encoder_a,
            Input::EncoderB => s.shaft.encoder_b,
            // Active low, as the driver's fault output: low while the
            // driver has tripped (or a fault is forced from the console or panel).
            Input::DriverFault => !s.motor_tripped,
        }
    }

    /// An output pin's level: what PORTx drives where DDRx makes it an
    /// output; an input pin floats high (the module's inputs pull up).
    fn output_level(&self, index: u8) -> bool {
        let port = usize::from(index / 8);
        let bit = 1u8 << (index % 8);
        let driven = self.core.data(reg::DDR[port]) & bit != 0;
        !driven || self.core.data(reg::PORT[port]) & bit != 0
    }

    fn read_outputs(&mut self, now: SimTime) -> Actuators {
        // Lines no pin is wired to rest inactive; FR at 0 is clockwise.
        let mut sd0: u16 = 0x0F;
        let mut sd1: u16 = 0x01;
        for &(pin, what) in &self.wiring.outputs {
            let high = self.output_level(pin.index);
            let (word, bit) = match what {
                Output::En => (&mut sd0, 0),
                Output::Brk => (&mut sd0, 1),
                Output::Pro => (&mut sd0, 2),
                Output::Des => (&mut sd0, 3),
                Output::Fr => (&mut sd0, 4),
                Output::Chg => (&mut sd1, 0),
                // Awake (high) enables the inverter: EN is active low.
                Output::DriverSleep => {
                    if high {
                        sd0 &= !1;
                    } else {
                        sd0 |= 1;
                    }
                    continue;
                }
                Output::Led => continue,
            };
            if high {
                *word |= 1 << bit;
            } else {
                *word &= !(1 << bit);
            }
        }
        let cycle = self.core.cycle();
        let dt = now.saturating_since(self.last_tick).as_secs_f64();
        let tau = self.wiring.board.pwm_filter_ms / 1000.0;
        let mut vel = 0.0;
        for (i, &(pin, Pwm::Vel)) in self.wiring.pwm.iter().enumerate() {
            let (_, _, high) = self.core.pin_output(pin.index);
            let (last_cycle, last_high, filtered) = self.pwm_state[i];
            let span = cycle.saturating_sub(last_cycle);
            // A pin that stays put has no edges: its level is its duty.
            let duty = if span == 0 {
                f64::from(u8::from(self.output_level(pin.index)))
            } else {
                (high.saturating_sub(last_high)) as f64 / span as f64
            };
            let target = duty.clamp(0.0, 1.0) * 5.0;
            let volts = if span == 0 && cycle > 0 {
                // The core has not run since the last look (in real time it
                // may have run ahead of the loop ticks): nothing new to filter.
                filtered
            } else if tau > 0.0 {
                filtered + (target - filtered) * (1.0 - (-dt / tau).exp())
            } else {
                target
            };
            // To the millivolt, as a 12-bit converter would see it: the
            // filter's endless approach is not a change worth recording.
            let volts = (volts * 1000.0).round() / 1000.0;
            self.pwm_state[i] = (cycle, high, volts);
            vel = volts;
        }
        Actuators::from_pins(sd0, sd1, vel)
    }

    /// The edge time the plant reports for `what`, if it has one in (from, to].
    fn edge_time(what: Input, s: &Sensors) -> f64 {
        match what {
            Input::HallA | Input::HallB | Input::HallC => s.shaft.last_hall_edge_at,
            Input::EncoderA | Input::EncoderB => s.shaft.last_encoder_edge_at,
            Input::DriverFault => f64::NAN,
        }
    }
}

impl Node for AvrNode {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        self.advance(now);
        if self.failure.is_some() {
            return;
        }
        if now < self.boot {
            // No sketch yet to enable the receiver: the bytes are lost.
            self.bytes_before_boot += bytes.len() as u64;
            return;
        }
        let setting = UartSetting::read(&self.core, self.clock_hz);
        if setting != self.uart {
            self.uart = setting;
            self.note_baud(now);
        }
        let char_time = SimDuration::from_secs_f64(f64::from(self.bus_bits) / self.bus_baud);
        for &b in bytes {
            // The firmware's receiver samples the bus's bits at its own baud.
            let seen = sampled(b, 1.0 / self.bus_baud, 1.0 / self.uart.baud);
            if framing_error(b, 1.0 / self.bus_baud, 1.0 / self.uart.baud) {
                self.framing_errors_in += 1;
                if self.framing_errors_in == 1 {
                    let detail = format!(
                        "framing error: a byte from the bus at {:.0} baud has no stop bit where UART0 at {:.0} baud samples it",
                        self.bus_baud, self.uart.baud
                    );
                    self.push_event(now, "framing", detail);
                }
            }
            let start = SimTime(now.0.saturating_sub(char_time.0));
            self.log.received(
                seen,
                self.to_cycle(start),
                start,
                now,
                self.uart.baud,
                char_time + char_time,
            );
            self.core.uart_input(seen);
            self.bytes_in += 1;
        }
        self.note_silence(now, bytes.len());
    }

    fn handle_timeout(&mut self, now: SimTime) {
        self.advance(now);
        self.flush_if_due(now);
    }

    fn poll_transmit(&mut self, now: SimTime, buf: &mut [u8]) -> Option<usize> {
        self.flush_if_due(now);
        if self.ready.is_empty() {
            return None;
        }
        let len = self.ready.len().min(buf.len());
        buf[..len].copy_from_slice(&self.ready[..len]);
        self.ready.clear();
        Some(len)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        if self.failure.is_some() {
            return None;
        }
        let due = self.frame_due();
        // While a streamed frame is on the wire, the firmware is run to the
        // end of each byte, so the next one it writes goes out on time.
        if self.streaming && due.is_some() && self.advanced_to < self.pending_end {
            return Some(self.pending_end);
        }
        due
    }

    fn poll_event(&mut self) -> Option<NodeEvent> {
        self.events.pop_front()
    }
}

impl Firmware for AvrNode {
    fn loop_period(&self) -> SimDuration {
        SimDuration::from_micros(u64::from(self.wiring.board.tick_us))
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &Sensors) -> Actuators {
        if self.failure.is_some() {
            return Actuators::from_pins(0x1F, 0x01, 0.0);
        }
        // Digital inputs change at the plant's own edge times, so the
        // firmware's interrupts see them when the bench would.
        let from_s = self.to_time(self.core.cycle()).as_secs_f64();
        for i in 0..self.wiring.inputs.len() {
            let (pin, what) = self.wiring.inputs[i];
            let level = Self::input_level(what, sensors);
            if level == self.input_levels[i] {
                continue;
            }
            let edge = Self::edge_time(what, sensors);
            if edge.is_finite() && edge > from_s && edge <= now.as_secs_f64() {
                self.advance(SimTime::ZERO + SimDuration::from_secs_f64(edge));
            }
            self.core.pin_input(pin.index, level);
            self.input_levels[i] = level;
        }
        self.advance(now);
        for i in 0..self.wiring.analog.len() {
            let (pin, what) = self.wiring.analog[i];
            let mv = self.pin_millivolts(what, sensors);
            let channel = pin.adc.unwrap_or(0);
            if self.adc_mv[usize::from(channel)] != mv {
                self.adc_mv[usize::from(channel)] = mv;
                self.core.adc(channel, simavr_millivolts(mv));
            }
        }
        if now < self.boot {
            // Its pins float until the sketch sets them: the driver rests, as
            // for a board that has stopped.
            self.actuators = Actuators::from_pins(0x1F, 0x01, 0.0);
            self.last_tick = now;
            return self.actuators;
        }
        self.actuators = self.read_outputs(now);
        self.last_tick = now;
        if now >= self.next_telemetry {
            self.next_telemetry = now + TELEMETRY_EVERY;
            let core = &self.core;
            let adc = &self.adc_mv;
            self.log.sample(
                now,
                core.cycle(),
                |i| core.pin_output(i),
                |i| {
                    let port = usize::from(i / 8);
                    let bit = 1u8 << (i % 8);
                    core.data(reg::DDR[port]) & bit == 0 || core.data(reg::PORT[port]) & bit != 0
                },
                |c| adc[usize::from(c)],
            );
        }
        self.actuators
    }
}

impl SimNode for AvrNode {
    fn firmware(&mut self) -> Option<&mut dyn Firmware> {
        Some(self)
    }

    fn drives_plant(&self) -> bool {
        self.wiring.board.drives_plant
    }

    fn final_state(&self) -> Option<serde_json::Value> {
        Some(json!({
            "firmware": self.elf.display().to_string(),
            "firmware_cycles": self.core.cycle(),
            "uart_baud": self.uart.baud.round(),
            "bytes_in": self.bytes_in,
            "bytes_out": self.bytes_out,
            "framing_errors_in": self.framing_errors_in,
            "framing_errors_out": self.framing_errors_out,
        }))
        .map(|mut state| {
            // Only for a board that boots, so earlier recordings read the same.
            if self.boot > SimTime::ZERO {
                state["boot_s"] = json!(self.boot.as_secs_f64());
                state["bytes_before_boot"] = json!(self.bytes_before_boot);
            }
            state
        })
    }

    fn failure(&self) -> Option<String> {
        self.failure.clone()
    }

    fn not_answering(&mut self, now: SimTime, since: SimTime, asked: u32) {
        self.advance(now);
        if self.failure.is_some() {
            return;
        }
        let at = self.to_time(self.core.cycle());
        let message = format!(
            "firmware {} of board `{}` answered none of the {asked} requests for it since {:.6} s \
             (it wrote {} bytes in all) and is still running, at PC 0x{:04X}, {:.6} s simulated \
             (cycle {}); the node is marked dead",
            self.elf.display(),
            self.name,
            since.as_secs_f64(),
            self.bytes_out,
            self.core.pc(),
            at.as_secs_f64(),
            self.core.cycle()
        );
        self.push_event(at, "trip", message.clone());
        self.failure = Some(message);
    }

    /// A sketch whose only inputs are analog and its UART: its core can run
    /// ahead of the bench to the next tick or byte. A digital input's edge
    /// lands on the core at its own time, in the past of the tick that
    /// reads it, so such a core stays at its last tick.
    fn can_run_ahead(&self) -> bool {
        self.wiring.inputs.is_empty() && self.failure.is_none()
    }

    fn streams_bytes(&self) -> bool {
        true
    }

    fn start_streaming(&mut self) -> bool {
        self.streaming = true;
        true
    }

    fn poll_stream(&mut self, now: SimTime) -> Option<Streamed> {
        if let Some((byte, start, end)) = self.stream_out.pop_front() {
            self.stream_open = true;
            return Some(Streamed::Byte { byte, start, end });
        }
        let quiet = self
            .frame_due()
            .is_some_and(|due| due <= now && due <= self.advanced_to);
        if self.stream_open && quiet {
            self.stream_open = false;
            return Some(Streamed::End);
        }
        None
    }

    fn run_ahead(&mut self, horizon: SimTime) {
        if self.can_run_ahead() {
            self.core.run_ahead(self.to_cycle(horizon));
        }
    }

    fn firmware_file(&self) -> Option<FirmwareFile> {
        let file_name = self.elf.file_name().map_or_else(
            || "firmware.elf".into(),
            |n| n.to_string_lossy().into_owned(),
        );
        let attachment = twin_recording::topics::firmware_attachment(&self.name, &file_name);
        let fields = [
            ("node", self.name.clone()),
            ("file", self.elf.display().to_string()),
            ("attachment", attachment.clone()),
            ("sha256", self.sha256.clone()),
            ("bytes", self.elf_bytes.len().to_string()),
            ("mcu", self.mcu.clone()),
            ("clock_hz", self.clock_hz.to_string()),
            ("wiring", self.wiring.origin.clone()),
            ("wiring_toml", self.wiring.text.clone()),
        ];
        Some(FirmwareFile {
            fields: fields.into_iter().map(|(k, v)| (k.into(), v)).collect(),
            attachment,
            bytes: self.elf_bytes.clone(),
        })
    }

    fn firmware_records(
        &mut self,
        record: &mut dyn FnMut(FirmwareRecord<'_>) -> Result<(), ObserveError>,
    ) -> Result<(), ObserveError> {
        let gap =
            SimDuration::from_secs_f64(2.0 * f64::from(self.uart.bits_per_char) / self.uart.baud);
        let now = self.to_time(self.core.cycle());
        self.log.drain(now, gap, record)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simavr_is_handed_the_millivolts_that_give_the_chips_count() {
        for mv in (0..=5000).step_by(7) {
            let chip = (u64::from(mv) * 1024 / 5000).min(1023);
            let simavr = u64::from(simavr_millivolts(mv)) * 1023 / 5000;
            assert_eq!(simavr, chip, "{mv} mV");
        }
    }

    #[test]
    fn a_receiver_a_few_per_cent_off_still_reads_every_byte() {
        let bus = 1.0 / 115_200.0;
        let firmware = 1.0 / 117_647.0; // UBRR0 16 with U2X0 at 16 MHz
        for b in 0..=255u8 {
            assert_eq!(sampled(b, bus, firmware), b);
        }
    }

    #[test]
    fn a_receiver_a_few_per_cent_off_finds_every_stop_bit_and_a_far_one_does_not() {
        let (bus, firmware) = (1.0 / 115_200.0, 1.0 / 117_647.0);
        assert!((0..=255u8).all(|b| !framing_error(b, bus, firmware)));
        assert!((0..=255u8).all(|b| !framing_error(b, firmware, bus)));
        // A fast receiver samples the stop bit inside the slow sender's byte.
        assert!((0..=255u8).all(|b| framing_error(b, 1.0 / 9600.0, 1.0 / 115_200.0)));
        let at_half = (0..=255u8)
            .filter(|b| framing_error(*b, 1.0 / 57_600.0, firmware))
            .count();
        assert_eq!(at_half, 128);
    }

    #[test]
    fn a_receiver_at_another_baud_garbles_the_bytes() {
        let garbled = (0..=255u8)
            .filter(|b| sampled(*b, 1.0 / 9600.0, 1.0 / 115_200.0) != *b)
            .count();
        assert!(garbled > 200, "{garbled}");
    }
}
