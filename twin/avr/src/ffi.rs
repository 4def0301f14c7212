//! The one place that calls C: the shim over libsimavr (`csrc/shim.c`),
//! wrapped in [`Core`], whose methods are safe. Everything else in the
//! crate is safe Rust.

use std::ffi::{CStr, CString, c_char, c_int, c_void};
use std::path::Path;

#[repr(C)]
struct RawCore {
    _private: [u8; 0],
}

unsafe extern "C" {
    fn twin_avr_read_elf(
        path: *const c_char,
        mcu: *mut c_char,
        mcu_len: usize,
        frequency: *mut u32,
    ) -> *mut c_void;
    fn twin_avr_free_elf(fw: *mut c_void);
    fn twin_avr_start(fw: *mut c_void, mcu: *const c_char, frequency: u32) -> *mut RawCore;
    fn twin_avr_run_until(t: *mut RawCore, target: u64) -> c_int;
    fn twin_avr_cycle(t: *const RawCore) -> u64;
    fn twin_avr_pc(t: *const RawCore) -> u32;
    fn twin_avr_state(t: *const RawCore) -> c_int;
    fn twin_avr_data(t: *const RawCore, addr: u16) -> u8;
    fn twin_avr_uart_input(t: *mut RawCore, byte: u8);
    fn twin_avr_uart_output(t: *mut RawCore, byte: *mut u8, cycle: *mut u64) -> c_int;
    fn twin_avr_adc(t: *mut RawCore, channel: c_int, millivolts: u32);
    fn twin_avr_pin_input(t: *mut RawCore, pin: c_int, level: c_int);
    fn twin_avr_pin_output(
        t: *const RawCore,
        pin: c_int,
        level: *mut u8,
        edges: *mut u64,
        high: *mut u64,
    );
    fn twin_avr_free(t: *mut RawCore);
    fn twin_avr_watch(t: *mut RawCore, pins: u32);
    fn twin_avr_edge(t: *mut RawCore, cycle: *mut u64, pin: *mut u8, level: *mut u8) -> c_int;
    fn twin_avr_edges_dropped(t: *const RawCore) -> u32;
    fn twin_avr_gdb(t: *mut RawCore, port: c_int) -> c_int;
    fn twin_avr_last_log() -> *const c_char;
}

/// simavr's core states (`sim_avr.h`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum State {
    Running,
    Sleeping,
    /// Stopped by itself: asleep with interrupts off.
    Done,
    Crashed,
    Other(i32),
}

impl State {
    fn of(raw: c_int) -> Self {
        match raw {
            2 => State::Running,
            3 => State::Sleeping,
            6 => State::Done,
            7 => State::Crashed,
            n => State::Other(n),
        }
    }
}

/// A firmware image read by simavr, not yet running.
#[derive(Debug)]
pub struct Image {
    raw: *mut c_void,
    /// The MCU the ELF's `.mmcu` section names (empty for Arduino builds).
    pub mcu: String,
}

impl Image {
    /// Reads `path` as simavr does; `None` if it cannot.
    pub fn read(path: &Path) -> Option<Image> {
        let c_path = CString::new(path.as_os_str().as_encoded_bytes()).ok()?;
        let mut mcu = [0 as c_char; 64];
        let mut frequency = 0u32;
        // SAFETY: the path is NUL-terminated, the buffer's length is given.
        let raw = unsafe {
            twin_avr_read_elf(c_path.as_ptr(), mcu.as_mut_ptr(), mcu.len(), &mut frequency)
        };
        if raw.is_null() {
            return None;
        }
        // SAFETY: the shim NUL-terminates within the buffer.
        let mcu = unsafe { CStr::from_ptr(mcu.as_ptr()) }
            .to_string_lossy()
            .into_owned();
        Some(Image { raw, mcu })
    }
}

impl Drop for Image {
    fn drop(&mut self) {
        if !self.raw.is_null() {
            // SAFETY: allocated by twin_avr_read_elf, not yet taken over.
            unsafe { twin_avr_free_elf(self.raw) };
        }
    }
}

/// One simulated microcontroller.
#[derive(Debug)]
pub struct Core {
    raw: *mut RawCore,
}

// SAFETY: a core is owned by one node; simavr keeps no thread-bound state
// but the last log line, which the shim keeps per thread.
unsafe impl Send for Core {}

impl Core {
    /// Starts `image` on `mcu` at `frequency` Hz; `None` if simavr has no such MCU.
    pub fn start(mut image: Image, mcu: &str, frequency: u32) -> Option<Core> {
        let c_mcu = CString::new(mcu).ok()?;
        let fw = std::mem::replace(&mut image.raw, std::ptr::null_mut());
        // SAFETY: `fw` comes from twin_avr_read_elf and is taken over here.
        let raw = unsafe { twin_avr_start(fw, c_mcu.as_ptr(), frequency) };
        (!raw.is_null()).then_some(Core { raw })
    }

    /// Runs until the cycle count reaches `target` or the core stops.
    pub fn run_until(&mut self, target: u64) -> State {
        // SAFETY: `raw` is a live core.
        State::of(unsafe { twin_avr_run_until(self.raw, target) })
    }

    pub fn cycle(&self) -> u64 {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_cycle(self.raw) }
    }

    /// The program counter, as a byte address.
    pub fn pc(&self) -> u32 {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_pc(self.raw) }
    }

    pub fn state(&self) -> State {
        // SAFETY: `raw` is a live core.
        State::of(unsafe { twin_avr_state(self.raw) })
    }

    /// A byte of data space (I/O registers from 0x20).
    pub fn data(&self, addr: u16) -> u8 {
        // SAFETY: `raw` is a live core; the shim bounds the address.
        unsafe { twin_avr_data(self.raw, addr) }
    }

    /// A byte arriving on RXD0.
    pub fn uart_input(&mut self, byte: u8) {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_uart_input(self.raw, byte) }
    }

    /// The next byte the firmware wrote to UDR0, with the cycle it wrote it at.
    pub fn uart_output(&mut self) -> Option<(u8, u64)> {
        let (mut byte, mut cycle) = (0u8, 0u64);
        // SAFETY: `raw` is a live core; both pointers are to locals.
        let got = unsafe { twin_avr_uart_output(self.raw, &mut byte, &mut cycle) };
        (got != 0).then_some((byte, cycle))
    }

    /// The voltage on ADC channel `channel`.
    pub fn adc(&mut self, channel: u8, millivolts: u32) {
        // SAFETY: `raw` is a live core; the shim bounds the channel.
        unsafe { twin_avr_adc(self.raw, c_int::from(channel), millivolts) }
    }

    /// Drives input pin `pin` (port B 0–7, C 8–15, D 16–23).
    pub fn pin_input(&mut self, pin: u8, high: bool) {
        // SAFETY: `raw` is a live core; the shim bounds the pin.
        unsafe { twin_avr_pin_input(self.raw, c_int::from(pin), c_int::from(high)) }
    }

    /// Pin `pin` as the firmware drives it: level, edges since power-up,
    /// cycles spent high since power-up.
    pub fn pin_output(&self, pin: u8) -> (bool, u64, u64) {
        let (mut level, mut edges, mut high) = (0u8, 0u64, 0u64);
        // SAFETY: `raw` is a live core; the pointers are to locals.
        unsafe {
            twin_avr_pin_output(
                self.raw,
                c_int::from(pin),
                &mut level,
                &mut edges,
                &mut high,
            )
        };
        (level != 0, edges, high)
    }

    /// Keep the edges of these pins (bit per pin index) for [`Core::edge`].
    pub fn watch(&mut self, pins: u32) {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_watch(self.raw, pins) }
    }

    /// The next edge of a watched pin: cycle, pin index, new level.
    pub fn edge(&mut self) -> Option<(u64, u8, bool)> {
        let (mut cycle, mut pin, mut level) = (0u64, 0u8, 0u8);
        // SAFETY: `raw` is a live core; the pointers are to locals.
        let got = unsafe { twin_avr_edge(self.raw, &mut cycle, &mut pin, &mut level) };
        (got != 0).then_some((cycle, pin, level != 0))
    }

    /// Edges lost because they were not drained in time.
    pub fn edges_dropped(&self) -> u32 {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_edges_dropped(self.raw) }
    }

    /// Starts simavr's GDB stub on `port`; the core then waits, stopped,
    /// until a debugger connects and continues it. `false` if the port
    /// cannot be listened on.
    pub fn gdb(&mut self, port: u16) -> bool {
        // SAFETY: `raw` is a live core.
        unsafe { twin_avr_gdb(self.raw, c_int::from(port)) == 0 }
    }

    /// simavr's last warning or error (a crash's reason), if any.
    pub fn last_log() -> String {
        // SAFETY: the shim returns its own NUL-terminated buffer.
        let log = unsafe { CStr::from_ptr(twin_avr_last_log()) }.to_string_lossy();
        // The shim keeps the last two lines, `|` between them; simavr's
        // own name for a crash says nothing to a user.
        log.split('|')
            .map(str::trim)
            .filter(|l| !l.is_empty() && !l.contains("avr_sadly_crashed"))
            .collect::<Vec<_>>()
            .join("; ")
    }
}

impl Drop for Core {
    fn drop(&mut self) {
        // SAFETY: `raw` is a live core, freed once.
        unsafe { twin_avr_free(self.raw) }
    }
}
