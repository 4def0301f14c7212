//! The waveform model: a bus's frames over a window, and every line a logic
//! analyzer would probe, as edges computed bit by bit on demand.
//!
//! A frame is kept as the recording has it (sender, first start bit, bytes);
//! a line's edges come from [`Waveform::edges`], an iterator that walks the
//! frames' bit boundaries in time order, so no sample or edge is stored and
//! nothing is allocated per bit. Writers (VCD, sigrok, a picture) read the
//! same edges.
//!
//! Times are the engine's ticks ([`protocols::time::TICKS_PER_SECOND`]): a
//! bit boundary is `start + ⌊p × ticks_per_second / baud⌋` for bit `p` of the
//! frame, as the bus computes its bytes' arrivals, so no rounding accumulates.
//!
//! The TX lines carry the bytes as sent; the pair and the receivers carry
//! them as the engine delivered them: a character a collision garbled
//! ([`Garble`]) as garbled, and bits noise flipped at a listener
//! ([`Flip`]) flipped, on that listener's RX and on the pair. The parity
//! bit stays the talker's, so a decoder that checks parity sees the error
//! a receiver would.

use protocols::time::TICKS_PER_SECOND;

/// Parity of a character.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Parity {
    None,
    Even,
    Odd,
}

/// The character format and speed of a line.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct LineFormat {
    pub baud: u32,
    pub parity: Parity,
    /// 1 or 2.
    pub stop_bits: u8,
}

impl LineFormat {
    /// Bit times per character: start, 8 data bits, parity, stop bits.
    pub fn bits_per_char(&self) -> u32 {
        9 + u32::from(self.parity != Parity::None) + u32::from(self.stop_bits)
    }

    /// The format a simulated bus's `bits_per_char` stands for: 10 is 8N1,
    /// 11 8E1 (Modbus RTU's own), 12 8E2.
    pub fn from_bits_per_char(baud: u32, bits: u32) -> Self {
        let (parity, stop_bits) = match bits {
            11 => (Parity::Even, 1),
            12 => (Parity::Even, 2),
            _ => (Parity::None, 1),
        };
        LineFormat {
            baud,
            parity,
            stop_bits,
        }
    }

    /// How the format reads in the options of sigrok's `uart` decoder
    /// (`baudrate=115200:parity=even`; 8 data bits and one stop bit are its
    /// defaults, and a second stop bit reads as idle line).
    pub fn sigrok_options(&self) -> String {
        let parity = match self.parity {
            Parity::None => "",
            Parity::Even => ":parity=even",
            Parity::Odd => ":parity=odd",
        };
        format!("baudrate={}{parity}", self.baud)
    }

    /// The start of bit `p` counted from a frame's first start bit (ticks).
    pub fn bit_offset(&self, p: u64) -> u64 {
        p * TICKS_PER_SECOND / u64::from(self.baud.max(1))
    }

    /// One bit's time in ticks (rounded down).
    pub fn bit_ticks(&self) -> u64 {
        self.bit_offset(1)
    }

    /// The level of bit `k` of a character carrying `byte` (0: start bit).
    fn level(&self, byte: u8, k: u32) -> bool {
        match k {
            0 => false,
            1..=8 => byte >> (k - 1) & 1 == 1,
            9 => match self.parity {
                Parity::None => true,
                Parity::Even => !byte.count_ones().is_multiple_of(2),
                Parity::Odd => byte.count_ones().is_multiple_of(2),
            },
            _ => true,
        }
    }
}

/// A frame on the line.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LineFrame {
    /// Its place in the recording's frames of this bus (from 0), for
    /// `--frame N` and for the people reading the picture.
    pub number: usize,
    /// The talker's index in [`Waveform::nodes`].
    pub node: usize,
    /// Its first start bit (ticks).
    pub start: u64,
    pub bytes: Vec<u8>,
}

impl LineFrame {
    /// The end of its last stop bit on `format`'s line.
    pub fn end(&self, format: &LineFormat) -> u64 {
        self.start + format.bit_offset(self.bits(format))
    }

    fn bits(&self, format: &LineFormat) -> u64 {
        self.bytes.len() as u64 * u64::from(format.bits_per_char())
    }
}

/// Noise that flipped data bits of one character at one listener, as the
/// engine flipped them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Flip {
    /// Index in [`Waveform::frames`].
    pub frame: usize,
    /// The character's place in its frame.
    pub index: usize,
    /// The listener's index in [`Waveform::nodes`].
    pub to: usize,
    /// The data bits flipped (bit 0: the first data bit on the wire).
    pub mask: u8,
}

/// A character a collision garbled on the wire, as every listener got it.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Garble {
    /// Index in [`Waveform::frames`].
    pub frame: usize,
    /// The character's place in its frame.
    pub index: usize,
    /// The character as it was on the wire.
    pub byte: u8,
}

/// A line a logic analyzer probes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LineKind {
    /// What a node's UART transmits (idle high).
    Tx(usize),
    /// A node's RS-485 driver enable (high while it drives the pair).
    DriverEnable(usize),
    /// What a node's UART receives: the pair as it hears it (its receiver is
    /// off while it drives, so the line idles high then), with the noise
    /// the engine flipped at this listener.
    Rx(usize),
    /// The pair itself, as the receivers got it: each character a
    /// collision garbled as the engine garbled it (where two drive at once,
    /// low wherever either is low), and the bits noise flipped at any
    /// listener flipped.
    Bus,
}

/// Who hears whom on the bus.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Hearing {
    /// Every node hears every other.
    All,
    /// The Controller_network wiring: the master hears every slave, a slave
    /// only the master.
    MasterSlaves { master: usize },
}

impl Hearing {
    fn hears(self, listener: usize, talker: usize) -> bool {
        listener != talker
            && match self {
                Hearing::All => true,
                Hearing::MasterSlaves { master } => listener == master || talker == master,
            }
    }
}

/// A bus (or a real-time link) over a window of time.
#[derive(Debug, Clone, PartialEq)]
pub struct Waveform {
    /// `bus.rs485` or `link.meb`: the prefix of every line's name.
    pub name: String,
    pub format: LineFormat,
    /// The talkers and listeners, in the scenario's order.
    pub nodes: Vec<String>,
    pub hearing: Hearing,
    /// Frames overlapping the window, by start.
    pub frames: Vec<LineFrame>,
    /// Sorted.
    pub flips: Vec<Flip>,
    /// Sorted.
    pub garbled: Vec<Garble>,
    /// The window (ticks).
    pub from: u64,
    pub to: u64,
    /// Idle line drawn before `from` (ticks), so that a frame whose first
    /// start bit opens the window starts with a falling edge a decoder
    /// sees: a character time when one does, else 0.
    pub lead_in: u64,
    /// Reconstructed from a real-time session's byte times: no driver
    /// enable or receiver lines, only what each side sent and the link.
    pub reconstructed: bool,
}

/// One line: its kind and name (`bus.rs485.ev1.tx`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Line {
    pub kind: LineKind,
    pub name: String,
}

/// At most this many frames overlapping at one instant are drawn; more
/// (never seen on a bus whose nodes wait for each other) are left out.
const MAX_OVERLAP: usize = 8;

impl Waveform {
    /// The lines a logic analyzer would probe, in the order it lists them:
    /// the pair first, then per node TX, driver enable and RX.
    pub fn lines(&self) -> Vec<Line> {
        let mut lines = vec![Line {
            kind: LineKind::Bus,
            name: format!("{}.line", self.name),
        }];
        for (i, node) in self.nodes.iter().enumerate() {
            let node = wire_name(node);
            lines.push(Line {
                kind: LineKind::Tx(i),
                name: format!("{}.{node}.tx", self.name),
            });
            if !self.reconstructed {
                lines.push(Line {
                    kind: LineKind::DriverEnable(i),
                    name: format!("{}.{node}.de", self.name),
                });
                lines.push(Line {
                    kind: LineKind::Rx(i),
                    name: format!("{}.{node}.rx", self.name),
                });
            }
        }
        lines
    }

    /// A line's level when nothing is sent.
    pub fn idle(kind: LineKind) -> bool {
        !matches!(kind, LineKind::DriverEnable(_))
    }

    /// The line's edges in time order, `(tick, level)`, each a change from
    /// the level before (starting from [`Waveform::idle`]); edges may fall
    /// before the window's start (of a frame already on the wire).
    pub fn edges(&self, kind: LineKind) -> Edges<'_> {
        Edges {
            wave: self,
            kind,
            next_frame: 0,
            cluster: [Member::default(); MAX_OVERLAP],
            len: 0,
            level: Self::idle(kind),
        }
    }

    /// Whether frame `f` shapes line `kind` at all.
    fn shapes(&self, kind: LineKind, f: &LineFrame) -> bool {
        match kind {
            LineKind::Tx(n) | LineKind::DriverEnable(n) => f.node == n,
            LineKind::Rx(n) => f.node == n || self.hearing.hears(n, f.node),
            LineKind::Bus => true,
        }
    }

    /// The noise mask on character `index` of frame `frame` at listener `to`.
    fn flip(&self, frame: usize, index: usize, to: usize) -> u8 {
        let key = (frame, index, to);
        self.flips
            .binary_search_by(|f| (f.frame, f.index, f.to).cmp(&key))
            .map_or(0, |i| self.flips[i].mask)
    }

    /// The bits noise flipped on character `index` of frame `frame` at any
    /// listener.
    fn flip_anywhere(&self, frame: usize, index: usize) -> u8 {
        let key = (frame, index);
        let first = self.flips.partition_point(|f| (f.frame, f.index) < key);
        self.flips[first..]
            .iter()
            .take_while(|f| (f.frame, f.index) == key)
            .fold(0, |mask, f| mask | f.mask)
    }

    /// Character `index` of frame `frame` as line `kind` carries it: as
    /// sent on a TX line; as garbled by a collision on the pair and the RX
    /// lines, with the bits noise flipped at that listener (the pair: at
    /// any listener).
    pub fn line_byte(&self, kind: LineKind, frame: usize, index: usize) -> u8 {
        let sent = self
            .frames
            .get(frame)
            .and_then(|f| f.bytes.get(index))
            .copied()
            .unwrap_or(0xff);
        if self.garbled.is_empty() && self.flips.is_empty() {
            return sent;
        }
        let wire = || {
            let key = (frame, index);
            self.garbled
                .binary_search_by(|g| (g.frame, g.index).cmp(&key))
                .map_or(sent, |i| self.garbled[i].byte)
        };
        match kind {
            LineKind::Tx(_) | LineKind::DriverEnable(_) => sent,
            LineKind::Rx(n) => wire() ^ self.flip(frame, index, n),
            LineKind::Bus => wire() ^ self.flip_anywhere(frame, index),
        }
    }
}

/// A node's name as a VCD identifier allows it (no spaces).
pub fn wire_name(name: &str) -> String {
    name.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A frame being walked: its index and how many bit boundaries passed.
#[derive(Debug, Clone, Copy, Default)]
struct Member {
    frame: usize,
    passed: u64,
}

/// The edges of one line (see [`Waveform::edges`]).
#[derive(Debug)]
pub struct Edges<'w> {
    wave: &'w Waveform,
    kind: LineKind,
    /// The next frame not yet taken into a cluster.
    next_frame: usize,
    /// Frames overlapping one another, walked together.
    cluster: [Member; MAX_OVERLAP],
    len: usize,
    level: bool,
}

impl Edges<'_> {
    /// Takes the next frame that shapes the line, and every later one that
    /// overlaps the cluster, into the cluster.
    fn gather(&mut self) -> bool {
        let w = self.wave;
        let mut end = 0;
        while let Some(f) = w.frames.get(self.next_frame) {
            if self.len > 0 && f.start >= end {
                break;
            }
            let i = self.next_frame;
            self.next_frame += 1;
            if !w.shapes(self.kind, f) || f.bytes.is_empty() {
                continue;
            }
            if self.len < MAX_OVERLAP {
                self.cluster[self.len] = Member {
                    frame: i,
                    passed: 0,
                };
                self.len += 1;
            }
            end = end.max(f.end(&w.format));
        }
        self.len > 0
    }

    /// The tick of member `m`'s next bit boundary, if any is left.
    fn boundary(&self, m: &Member) -> Option<u64> {
        let f = &self.wave.frames[m.frame];
        let format = &self.wave.format;
        (m.passed <= f.bits(format)).then(|| f.start + format.bit_offset(m.passed))
    }

    /// The line's level once every member is at its bit.
    fn level_now(&self) -> bool {
        let w = self.wave;
        let format = &w.format;
        let bpc = u64::from(format.bits_per_char());
        let mut driving_self = false;
        let mut low = false;
        let mut any = false;
        for m in &self.cluster[..self.len] {
            let f = &w.frames[m.frame];
            // Driving during bits 1..=bits boundaries passed (inside the frame).
            if m.passed == 0 || m.passed > f.bits(format) {
                continue;
            }
            any = true;
            if matches!(self.kind, LineKind::Rx(n) if f.node == n) {
                driving_self = true;
                continue;
            }
            let p = m.passed - 1;
            let (index, k) = ((p / bpc) as usize, (p % bpc) as u32);
            let sent = f.bytes.get(index).copied().unwrap_or(0xff);
            let bit = match k {
                // The data bits as this line carries them; start, parity
                // and stop bits as the talker made them.
                1..=8 => w.line_byte(self.kind, m.frame, index) >> (k - 1) & 1 == 1,
                _ => format.level(sent, k),
            };
            low |= !bit;
        }
        match self.kind {
            LineKind::DriverEnable(_) => any,
            LineKind::Rx(_) if driving_self => true,
            _ => !low,
        }
    }
}

impl Iterator for Edges<'_> {
    type Item = (u64, bool);

    fn next(&mut self) -> Option<(u64, bool)> {
        loop {
            if self.len == 0 && !self.gather() {
                return None;
            }
            // The earliest boundary among the members, then every member
            // that has one there moves past it.
            let Some(at) = self.cluster[..self.len]
                .iter()
                .filter_map(|m| self.boundary(m))
                .min()
            else {
                self.len = 0;
                continue;
            };
            for i in 0..self.len {
                let m = self.cluster[i];
                if self.boundary(&m) == Some(at) {
                    self.cluster[i].passed += 1;
                }
            }
            let level = self.level_now();
            if self.cluster[..self.len]
                .iter()
                .all(|m| self.boundary(m).is_none())
            {
                self.len = 0;
            }
            if level != self.level {
                self.level = level;
                return Some((at, level));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn wave(frames: Vec<LineFrame>) -> Waveform {
        Waveform {
            name: "bus.rs485".into(),
            format: LineFormat::from_bits_per_char(115_200, 10),
            nodes: vec!["a".into(), "b".into()],
            hearing: Hearing::All,
            frames,
            flips: vec![],
            garbled: vec![],
            from: 0,
            to: TICKS_PER_SECOND,
            lead_in: 0,
            reconstructed: false,
        }
    }

    #[test]
    fn a_byte_is_start_data_lsb_first_and_stop() {
        let w = wave(vec![LineFrame {
            number: 0,
            node: 0,
            start: 0,
            bytes: vec![0x0f],
        }]);
        let bit = w.format.bit_ticks();
        let edges: Vec<_> = w.edges(LineKind::Tx(0)).collect();
        // start (low), four ones, four zeros, stop (high).
        assert_eq!(
            edges,
            vec![(0, false), (bit, true), (5 * bit, false), (9 * bit, true)]
        );
        let de: Vec<_> = w.edges(LineKind::DriverEnable(0)).collect();
        assert_eq!(de, vec![(0, true), (10 * bit, false)]);
        // b hears it; a's receiver is off while it drives.
        assert_eq!(w.edges(LineKind::Rx(1)).collect::<Vec<_>>(), edges);
        assert_eq!(w.edges(LineKind::Rx(0)).count(), 0);
    }

    #[test]
    fn two_talkers_at_once_pull_the_pair_low_wherever_either_does() {
        let bit = LineFormat::from_bits_per_char(115_200, 10).bit_ticks();
        let w = wave(vec![
            LineFrame {
                number: 0,
                node: 0,
                start: 0,
                bytes: vec![0xff],
            },
            LineFrame {
                number: 1,
                node: 1,
                start: 3 * bit,
                bytes: vec![0xff],
            },
        ]);
        let bus: Vec<_> = w.edges(LineKind::Bus).collect();
        assert_eq!(
            bus,
            vec![(0, false), (bit, true), (3 * bit, false), (4 * bit, true)]
        );
    }

    #[test]
    fn noise_flips_a_data_bit_at_one_listener_only() {
        let mut w = wave(vec![LineFrame {
            number: 0,
            node: 0,
            start: 0,
            bytes: vec![0xff],
        }]);
        w.nodes.push("c".into());
        w.flips.push(Flip {
            frame: 0,
            index: 0,
            to: 1,
            mask: 0b100,
        });
        let bit = w.format.bit_ticks();
        let rx: Vec<_> = w.edges(LineKind::Rx(1)).collect();
        assert_eq!(
            rx,
            vec![(0, false), (bit, true), (3 * bit, false), (4 * bit, true)]
        );
        assert_eq!(w.edges(LineKind::Rx(2)).count(), 2);
        // The pair shows it too; the talker's TX does not.
        assert_eq!(w.edges(LineKind::Bus).collect::<Vec<_>>(), rx);
        assert_eq!(w.edges(LineKind::Tx(0)).count(), 2);
    }

    #[test]
    fn a_garbled_character_is_on_the_pair_and_the_receivers_as_the_engine_garbled_it() {
        let mut w = wave(vec![LineFrame {
            number: 0,
            node: 0,
            start: 0,
            bytes: vec![0xff, 0xff],
        }]);
        w.garbled.push(Garble {
            frame: 0,
            index: 1,
            byte: 0xfe,
        });
        let bit = w.format.bit_ticks();
        let garbled = vec![(0, false), (bit, true), (10 * bit, false), (12 * bit, true)];
        assert_eq!(w.edges(LineKind::Bus).collect::<Vec<_>>(), garbled);
        assert_eq!(w.edges(LineKind::Rx(1)).collect::<Vec<_>>(), garbled);
        assert_eq!(w.line_byte(LineKind::Bus, 0, 1), 0xfe);
        assert_eq!(w.line_byte(LineKind::Tx(0), 0, 1), 0xff);
        assert_eq!(
            w.edges(LineKind::Tx(0)).collect::<Vec<_>>(),
            vec![(0, false), (bit, true), (10 * bit, false), (11 * bit, true)]
        );
    }
}
