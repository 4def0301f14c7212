//! The MEB FCS model, from the frame rules of `docs/protocols/meb.md` alone: the exact
//! probability that a frame arrives corrupted yet parses, and the same rules as
//! integer counts of error patterns, to hold against the real parser.

use std::collections::HashMap;

use protocols::meb::MebRepr;

/// What a receiver accepts at one position of an MEB frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
enum Accepts {
    /// Only the byte that was sent: `@`, `*`, `\n`, and CNT when DATA is
    /// present (DATA must then be exactly CNT words, so CNT cannot change).
    Same,
    /// A decimal digit: ID, and CNT of a frame without DATA.
    Decimal,
    /// An ASCII letter of either case: CMD (a lower-case command parses).
    Letter,
    /// A hex digit of either case: ADDR, DATA, FCS.
    Hex,
}

impl Accepts {
    fn byte(self, sent: u8, received: u8) -> bool {
        match self {
            Accepts::Same => sent == received,
            Accepts::Decimal => received.is_ascii_digit(),
            Accepts::Letter => received.is_ascii_alphabetic(),
            Accepts::Hex => received.is_ascii_hexdigit(),
        }
    }
}

fn hex_value(digit: u8) -> Option<u8> {
    char::from(digit)
        .to_digit(16)
        .and_then(|v| u8::try_from(v).ok())
}

/// What each byte of a canonical frame (`@ ID CMD ADDR CNT DATA FCS * \n`)
/// may turn into and the frame still parse, FCS aside.
fn meb_layout(frame: &[u8]) -> Vec<Accepts> {
    let n = frame.len();
    assert!(
        n >= 13 && frame[0] == b'@' && frame.ends_with(b"*\n"),
        "{frame:?}"
    );
    let has_data = n > 13;
    (0..n)
        .map(|i| match i {
            1 | 2 => Accepts::Decimal,
            3 | 4 => Accepts::Letter,
            5 | 6 => Accepts::Hex,
            7 | 8 if !has_data => Accepts::Decimal,
            _ if (9..n - 2).contains(&i) => Accepts::Hex,
            _ => Accepts::Same,
        })
        .collect()
}

/// Probability that noise applies the XOR mask `e` to one byte's 8 data bits.
fn mask_probability(e: usize, p: f64) -> f64 {
    let flips = e.count_ones() as i32;
    p.powi(flips) * (1.0 - p).powi(8 - flips)
}

/// In-place Walsh–Hadamard transform: turns XOR-convolution into a product.
fn walsh_hadamard(v: &mut [f64; 256]) {
    let mut half = 1;
    while half < 256 {
        for block in (0..256).step_by(2 * half) {
            for i in block..block + half {
                let (a, b) = (v[i], v[i + half]);
                v[i] = a + b;
                v[i + half] = a - b;
            }
        }
        half *= 2;
    }
}

/// The exact probability that an MEB frame arrives corrupted yet parses, at
/// bit-error rate `p` on its data bits (start and stop bits are not flipped,
/// as on the simulated line).
///
/// A received frame parses when every byte is still of its kind (a digit, a
/// letter, a hex digit, the framing chars untouched) and the received FCS digits
/// equal the XOR of the received covered bytes. Bytes are hit independently, so
/// the XOR of the covered bytes' error masks has the XOR-convolution of their
/// per-byte distributions, computed as a product of Walsh–Hadamard spectra.
/// Ignored: the `*\r\n` terminator a receiver also accepts. A frame of fixed
/// length only ends so if its last FCS digit turns into `*` (2 flips or more)
/// and its `*` into `\r` (4 flips): about 1e-18 at 1e-3.
#[derive(Debug)]
pub(crate) struct MebFcsModel {
    p: f64,
    /// Spectrum of the error-mask distribution of one byte, per kind and byte sent.
    spectra: HashMap<(Accepts, u8), [f64; 256]>,
    /// Per frame content, its probability (replies repeat).
    frames: HashMap<Vec<u8>, f64>,
}

impl MebFcsModel {
    pub(crate) fn new(p: f64) -> Self {
        MebFcsModel {
            p,
            spectra: HashMap::new(),
            frames: HashMap::new(),
        }
    }

    fn spectrum(&mut self, accepts: Accepts, sent: u8) -> &[f64; 256] {
        let p = self.p;
        self.spectra.entry((accepts, sent)).or_insert_with(|| {
            let mut v = [0.0; 256];
            for (e, slot) in v.iter_mut().enumerate() {
                if accepts.byte(sent, sent ^ e as u8) {
                    *slot = mask_probability(e, p);
                }
            }
            walsh_hadamard(&mut v);
            v
        })
    }

    pub(crate) fn corrupted_and_passing(&mut self, frame: &[u8]) -> f64 {
        if let Some(&known) = self.frames.get(frame) {
            return known;
        }
        let layout = meb_layout(frame);
        let n = frame.len();
        let covered = n - 4;
        let mut spectrum = [1.0; 256];
        for i in 0..covered {
            let s = *self.spectrum(layout[i], frame[i]);
            for (acc, x) in spectrum.iter_mut().zip(s) {
                *acc *= x;
            }
        }
        walsh_hadamard(&mut spectrum);
        // The distribution of the XOR of the covered bytes' error masks.
        let xor_errors = spectrum.map(|x| x / 256.0);
        let (f1, f2) = (frame[n - 4], frame[n - 3]);
        let fcs_sent = hex_value(f1).unwrap_or(0) << 4 | hex_value(f2).unwrap_or(0);
        let p = self.p;
        let mut passes = 0.0;
        for e1 in 0..256 {
            let Some(high) = hex_value(f1 ^ e1 as u8) else {
                continue;
            };
            for e2 in 0..256 {
                let Some(low) = hex_value(f2 ^ e2 as u8) else {
                    continue;
                };
                let fcs_received = high << 4 | low;
                passes += mask_probability(e1, p)
                    * mask_probability(e2, p)
                    * xor_errors[usize::from(fcs_sent ^ fcs_received)];
            }
        }
        let trailer_clean = (1.0 - p).powi(16);
        let all_clean = (1.0 - p).powi(8 * n as i32);
        let result = passes * trailer_clean - all_clean;
        self.frames.insert(frame.to_vec(), result);
        result
    }
}

/// Number of error patterns of each weight 0..=max that the model lets pass
/// (weight 0 is the clean frame), by the same rules with integer counts.
fn model_passing_patterns(frame: &[u8], max: usize) -> Vec<u64> {
    let layout = meb_layout(frame);
    let n = frame.len();
    let mut counts = vec![[0u64; 256]; max + 1];
    counts[0][0] = 1;
    for i in 0..n - 4 {
        let mut next = vec![[0u64; 256]; max + 1];
        for e in 0..256usize {
            let k = e.count_ones() as usize;
            if k > max || !layout[i].byte(frame[i], frame[i] ^ e as u8) {
                continue;
            }
            for w in 0..=max - k {
                for x in 0..256 {
                    next[w + k][x ^ e] += counts[w][x];
                }
            }
        }
        counts = next;
    }
    let (f1, f2) = (frame[n - 4], frame[n - 3]);
    let fcs_sent = hex_value(f1).unwrap_or(0) << 4 | hex_value(f2).unwrap_or(0);
    let mut total = vec![0u64; max + 1];
    for e1 in 0..256usize {
        for e2 in 0..256usize {
            let k = (e1.count_ones() + e2.count_ones()) as usize;
            let (Some(high), Some(low)) = (hex_value(f1 ^ e1 as u8), hex_value(f2 ^ e2 as u8))
            else {
                continue;
            };
            for w in 0..=max.saturating_sub(k) {
                if w + k <= max {
                    total[w + k] += counts[w][usize::from(fcs_sent ^ (high << 4 | low))];
                }
            }
        }
    }
    total
}

/// Number of error patterns of each weight 0..=max after which the real
/// parser accepts the frame, by trying them all.
fn parser_passing_patterns(frame: &[u8], max: usize) -> Vec<u64> {
    fn walk(frame: &mut Vec<u8>, first_bit: usize, weight: usize, max: usize, total: &mut [u64]) {
        if MebRepr::parse(frame).is_ok() {
            total[weight] += 1;
        }
        if weight == max {
            return;
        }
        for bit in first_bit..frame.len() * 8 {
            frame[bit / 8] ^= 1 << (bit % 8);
            walk(frame, bit + 1, weight + 1, max, total);
            frame[bit / 8] ^= 1 << (bit % 8);
        }
    }
    let mut total = vec![0; max + 1];
    walk(&mut frame.to_vec(), 0, 0, max, &mut total);
    total
}

/// A canonical MEB frame from its text between `@` and the FCS.
fn meb_frame(body: &str) -> Vec<u8> {
    let mut frame = format!("@{body}").into_bytes();
    let fcs = frame.iter().fold(0, |acc, b| acc ^ b);
    frame.extend_from_slice(format!("{fcs:02X}*\n").as_bytes());
    assert!(MebRepr::parse(&frame).is_ok(), "{frame:?}");
    frame
}

#[test]
fn meb_fcs_model_counts_the_same_error_patterns_as_the_parser() {
    // The supervisor's frames (read request, VEL write and its echo) and a
    // read reply, with letters and digits in FCS and DATA.
    let short = [meb_frame("01EA0006"), meb_frame("01SA0001")];
    let reply = meb_frame("01EA000608F2001A0C1B05DC05D60ABC");
    for frame in &short {
        let (model, parser) = (
            model_passing_patterns(frame, 3),
            parser_passing_patterns(frame, 3),
        );
        eprintln!(
            "{}: passing patterns by weight {model:?}",
            String::from_utf8_lossy(frame).trim()
        );
        assert_eq!(model, parser, "{frame:?}");
    }
    for frame in [&meb_frame("01SA00010A3F"), &reply] {
        let (model, parser) = (
            model_passing_patterns(frame, 2),
            parser_passing_patterns(frame, 2),
        );
        eprintln!(
            "{}: passing patterns by weight {model:?}",
            String::from_utf8_lossy(frame).trim()
        );
        assert_eq!(model, parser, "{frame:?}");
    }
    // The exact probability agrees with its low-weight expansion at a small rate.
    let p = 1e-5;
    let mut model = MebFcsModel::new(p);
    let counts = model_passing_patterns(&reply, 3);
    let bits = 8 * reply.len() as i32;
    let expansion: f64 = (1..=3)
        .map(|w| counts[w] as f64 * p.powi(w as i32) * (1.0 - p).powi(bits - w as i32))
        .sum();
    let exact = model.corrupted_and_passing(&reply);
    assert!(
        (exact - expansion).abs() < 1e-6 * expansion,
        "{exact} vs {expansion}"
    );
}
