//! Scope pictures (`twin scope --png`): a bus's lines over a window drawn
//! like the lab's oscilloscope captures of the Controller_network project,
//! one channel above the other on a dark screen, 0/5 V TTL levels, the time
//! axis in milliseconds, each character's byte in hex under the trace and a
//! "bus table" under the screen: who sent each frame, its bytes, what the
//! frame describer says it is, a wrong CRC or an exception marked in red.
//!
//! The trace walks the waveform model's edges ([`twin_scope::Waveform`])
//! onto the picture's pixel columns: each column knows whether the line was
//! high, low or both inside it, so a window of a whole run draws as fast as
//! one frame and nothing is kept per bit.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;
use plotters::style::text_anchor::{HPos, Pos, VPos};
use protocols::modbus::Exception;
use protocols::modbus8::EXCEPTION_BIT;
use twin_recording::describe::{FrameFields, LinkFrameFields, decode_frame, link_frame_fields};
use twin_scope::wave::{Hearing, LineFrame};
use twin_scope::{LineKind, Waveform};

use crate::plot::{PlotError, ensure_font};

/// The picture's width unless asked otherwise (px).
pub const WIDTH: u32 = 1280;
/// The narrowest and widest picture drawn (px): the bus table needs the
/// one, a picture viewer the other.
pub const WIDTHS: std::ops::RangeInclusive<u32> = 640..=16_384;
/// The height of one channel's band unless a height is asked for (px).
const BAND: u32 = 150;
/// The lowest band a trace, its levels and its bytes fit in (px).
const MIN_BAND: u32 = 80;
const MAX_BAND: u32 = 2_000;
const TITLE: u32 = 40;
/// The time axis's labels under the last band.
const X_AXIS: u32 = 44;
const ROW: u32 = 19;
/// Frames listed in the bus table; more are counted in one line.
const TABLE_FRAMES: usize = 8;
/// At most this many channels (a bus of ten modules shows its talkers).
const MAX_CHANNELS: usize = 6;

const SCREEN: RGBColor = RGBColor(14, 16, 22);
const GRID: RGBColor = RGBColor(52, 58, 68);
const TEXT: RGBColor = RGBColor(205, 208, 214);
const DIM: RGBColor = RGBColor(140, 146, 156);
/// A wrong CRC, an exception: no trace is drawn in it.
pub const MARK: RGBColor = RGBColor(255, 60, 60);

/// The channels' colours, as a scope's probes: channel `i` is drawn in
/// `TRACES[i]` and in no other colour, so a picture can be read back.
pub const TRACES: [RGBColor; MAX_CHANNELS] = [
    RGBColor(240, 200, 40),
    RGBColor(40, 200, 235),
    RGBColor(235, 90, 215),
    RGBColor(90, 225, 90),
    RGBColor(250, 140, 40),
    RGBColor(120, 145, 255),
];

/// The TTL levels a UART line swings between (the Arduino's RX and TX).
const HIGH_V: f64 = 5.0;
const LOW_V: f64 = 0.0;

/// What was drawn.
#[derive(Debug, Clone, PartialEq)]
pub struct Drawn {
    /// The channels top to bottom (`ev1 TX`, `bus line`).
    pub channels: Vec<String>,
    pub width: u32,
    pub height: u32,
}

/// The channels of a picture: each node's TX that talks in the window (at
/// least two nodes: the master, then the others in the scenario's order),
/// then the bus line.
pub fn channels(wave: &Waveform) -> Vec<(LineKind, String)> {
    let talks = |n: usize| wave.frames.iter().any(|f| f.node == n);
    let master = match wave.hearing {
        Hearing::MasterSlaves { master } => Some(master),
        Hearing::All => None,
    };
    let mut picked: Vec<usize> = (0..wave.nodes.len()).filter(|&n| talks(n)).collect();
    for n in master.into_iter().chain(0..wave.nodes.len()) {
        if picked.len() >= 2 {
            break;
        }
        if !picked.contains(&n) {
            picked.push(n);
        }
    }
    // The master on top, as its request comes first; then scenario order.
    picked.sort_unstable_by_key(|&n| (Some(n) != master, n));
    picked.truncate(MAX_CHANNELS - 1);
    let mut out: Vec<_> = picked
        .into_iter()
        .map(|n| (LineKind::Tx(n), format!("{} TX", wave.nodes[n])))
        .collect();
    let line = if wave.reconstructed {
        "link"
    } else {
        "bus line"
    };
    out.push((LineKind::Bus, line.to_string()));
    out
}

/// The picture's size as asked: its width, and its whole height (the
/// channels' bands share what the title, axis and bus table leave).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Size {
    pub width: u32,
    pub height: Option<u32>,
}

impl Default for Size {
    fn default() -> Self {
        Size {
            width: WIDTH,
            height: None,
        }
    }
}

/// Draws `wave` to a PNG at `path`, `size` as asked.
pub fn draw(wave: &Waveform, path: &Path, size: Size) -> Result<Drawn, PlotError> {
    let channels = channels(wave);
    let listed = wave.frames.len().min(TABLE_FRAMES);
    let table_rows = 1 + 2 * listed as u32 + u32::from(wave.frames.len() > listed);
    let fixed = TITLE + X_AXIS + 16 + ROW * table_rows + 12;
    let bands = channels.len() as u32;
    if !WIDTHS.contains(&size.width) {
        return Err(PlotError::Size(format!(
            "a width of {} px: give {} to {} px",
            size.width,
            WIDTHS.start(),
            WIDTHS.end()
        )));
    }
    let band = match size.height {
        None => BAND,
        Some(h) => {
            let (low, high) = (fixed + MIN_BAND * bands, fixed + MAX_BAND * bands);
            if !(low..=high).contains(&h) {
                return Err(PlotError::Size(format!(
                    "a height of {h} px: {bands} channels and a table of {listed} frames take {low} to {high} px"
                )));
            }
            (h - fixed) / bands
        }
    };
    ensure_font()?;
    let height = size.height.unwrap_or(fixed + band * bands);
    let width = size.width;
    let size = (width, height);
    let drawn = Drawn {
        channels: channels.iter().map(|(_, name)| name.clone()).collect(),
        width,
        height,
    };
    let described: Vec<Described> = wave.frames.iter().map(|f| describe(wave, f)).collect();
    let paint = || -> Result<(), Box<dyn std::error::Error>> {
        let root = BitMapBackend::new(path, size).into_drawing_area();
        root.fill(&SCREEN)?;
        let (head, rest) = root.split_vertically(TITLE);
        head.draw(&Text::new(title(wave), (16, 12), font(17, TEXT)))?;
        let screen_height = band * bands + X_AXIS;
        let (screen, table) = rest.split_vertically(screen_height);
        let bands = screen.split_by_breakpoints(
            [] as [u32; 0],
            (1..channels.len())
                .map(|i| band * i as u32)
                .collect::<Vec<_>>(),
        );
        for (i, ((kind, name), band)) in channels.iter().zip(&bands).enumerate() {
            let last = i + 1 == channels.len();
            channel(&root, band, wave, &described, *kind, name, TRACES[i], last)?;
        }
        bus_table(&table, wave, &described)?;
        root.present()?;
        Ok(())
    };
    paint().map_err(|e| PlotError::Draw {
        path: path.to_path_buf(),
        why: e.to_string(),
    })?;
    Ok(drawn)
}

fn font(size: u32, color: RGBColor) -> TextStyle<'static> {
    ("sans-serif", size).into_font().color(&color)
}

fn title(wave: &Waveform) -> String {
    let parity = match wave.format.parity {
        twin_scope::wave::Parity::None => 'N',
        twin_scope::wave::Parity::Even => 'E',
        twin_scope::wave::Parity::Odd => 'O',
    };
    let mut t = format!(
        "{}   {} baud 8{parity}{}   {:.6} s to {:.6} s",
        wave.name,
        wave.format.baud,
        wave.format.stop_bits,
        seconds(wave.from),
        seconds(wave.to)
    );
    if wave.reconstructed {
        t.push_str("   (reconstructed from the recorded byte times)");
    }
    t
}

fn seconds(ticks: u64) -> f64 {
    ticks as f64 / protocols::time::TICKS_PER_SECOND as f64
}

fn ms(ticks: u64) -> f64 {
    seconds(ticks) * 1e3
}

/// A frame as the describer reads it.
struct Described {
    what: String,
    /// A wrong CRC or a frame that does not read.
    broken: bool,
    exception: bool,
    /// Its bytes are text (MEB): show the characters too.
    text: bool,
}

impl Described {
    fn marked(&self) -> bool {
        self.broken || self.exception
    }
}

fn describe(wave: &Waveform, frame: &LineFrame) -> Described {
    let bytes = &frame.bytes;
    let fields = match wave.name.strip_prefix("link.") {
        Some(protocol) => link_frame_fields(protocol, bytes),
        None => LinkFrameFields::Bus(decode_frame(bytes)),
    };
    let exception_name = |code: Option<u8>| {
        code.map_or("exception", |c| Exception::from_code(c).name())
            .to_string()
    };
    let plain = |what: String| Described {
        what,
        broken: false,
        exception: false,
        text: false,
    };
    match fields {
        LinkFrameFields::Bus(FrameFields::Meb {
            addr,
            cmd,
            cnt,
            data,
            id,
            ..
        }) => {
            let mut what = format!("MEB {cmd}: id {id}, address {addr}, count {cnt}");
            if !data.as_slice().is_empty() {
                let words: Vec<String> = data.as_slice().iter().map(|w| w.to_string()).collect();
                what.push_str(&format!(", data {}", words.join(" ")));
            }
            Described {
                text: true,
                ..plain(what)
            }
        }
        LinkFrameFields::Bus(FrameFields::Modbus8 {
            addr,
            function,
            id,
            value,
            ..
        }) => {
            if function & EXCEPTION_BIT != 0 {
                Described {
                    exception: true,
                    ..plain(format!(
                        "exception {value:02X}: {} (function {:02X}, id {id}, register {addr})",
                        exception_name(u8::try_from(value).ok()),
                        function & !EXCEPTION_BIT
                    ))
                }
            } else {
                let verb = match function {
                    3 => " (read)",
                    6 => " (write)",
                    _ => "",
                };
                plain(format!(
                    "8-byte Modbus: id {id}, function {function:02X}{verb}, register {addr}, value {value}"
                ))
            }
        }
        LinkFrameFields::Bus(FrameFields::ModbusRtu { function, unit, .. })
        | LinkFrameFields::Modbus {
            function: Some(function),
            unit,
            ..
        } => {
            let protocol = match wave.name.strip_prefix("link.") {
                Some(p) => p.to_string(),
                None => "Modbus RTU".to_string(),
            };
            if function & EXCEPTION_BIT != 0 {
                // The code follows the function: byte 2 of an RTU frame.
                let code = if protocol == "modbus-tcp" {
                    bytes.get(8)
                } else {
                    bytes.get(2)
                };
                Described {
                    exception: true,
                    ..plain(format!(
                        "{protocol} exception: {} (function {:02X}, unit {unit})",
                        exception_name(code.copied()),
                        function & !EXCEPTION_BIT
                    ))
                }
            } else {
                plain(format!("{protocol}: unit {unit}, function {function:02X}"))
            }
        }
        LinkFrameFields::Modbus {
            function: None,
            unit,
            protocol,
            ..
        } => plain(format!("{protocol}: unit {unit}")),
        LinkFrameFields::Bus(FrameFields::Broken { error, protocol })
        | LinkFrameFields::Broken { error, protocol } => {
            let what = match protocol {
                "modbus8" => format!("8-byte Modbus: {error}"),
                // Of no known kind: the describer's reason says it all.
                "unknown" => error,
                p => format!("{p}: {error}"),
            };
            Described {
                broken: true,
                text: bytes.first() == Some(&b'@'),
                ..plain(what)
            }
        }
    }
}

/// One channel's band: its axes, its trace, the bytes under it.
#[allow(clippy::too_many_arguments)]
fn channel(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    band: &DrawingArea<BitMapBackend<'_>, Shift>,
    wave: &Waveform,
    described: &[Described],
    kind: LineKind,
    name: &str,
    color: RGBColor,
    last: bool,
) -> Result<(), Box<dyn std::error::Error>> {
    let (t0, t1) = (ms(wave.from) - ms(wave.lead_in), ms(wave.to));
    let mut chart = ChartBuilder::on(band)
        .margin_left(8)
        .margin_right(24)
        .margin_top(6)
        .y_label_area_size(96)
        .x_label_area_size(if last { X_AXIS } else { 0 })
        .build_cartesian_2d(t0..t1, -3.2f64..7.0)?;
    let decimals = decimals(t1 - t0);
    chart
        .configure_mesh()
        .x_labels(11)
        .y_labels(0)
        .disable_y_mesh()
        .bold_line_style(GRID)
        .light_line_style(TRANSPARENT)
        .axis_style(GRID)
        .label_style(font(13, DIM))
        .axis_desc_style(font(15, shade(color)))
        .x_label_formatter(&|v| format!("{v:.decimals$}"))
        .x_desc(if last { "time (ms)" } else { "" })
        .y_desc(name)
        .draw()?;
    let at = |t_ms: f64, v: f64| chart.backend_coord(&(t_ms, v));
    let (x0, y_hi) = at(t0, HIGH_V);
    let (x1, y_lo) = at(t1, LOW_V);
    // The levels, dashed as a scope's cursors, and their voltages.
    for (v, y) in [(HIGH_V, y_hi), (LOW_V, y_lo)] {
        let mut x = x0;
        while x < x1 {
            root.draw(&PathElement::new(vec![(x, y), ((x + 3).min(x1), y)], GRID))?;
            x += 8;
        }
        root.draw(&Text::new(
            format!("{v:.0} V"),
            (x0 - 8, y),
            font(13, DIM).pos(Pos::new(HPos::Right, VPos::Center)),
        ))?;
    }
    // Frames marked: a red bar over the frame, on every channel it shapes.
    for (f, d) in wave.frames.iter().zip(described) {
        if !d.marked() || !shapes(kind, f) {
            continue;
        }
        let (a, _) = at(ms(f.start.max(wave.from)), 0.0);
        let (b, y) = at(ms(f.end(&wave.format).min(wave.to)), 6.4);
        root.draw(&Rectangle::new([(a, y - 2), (b, y + 2)], MARK.filled()))?;
        let label = match (d.broken, d.what.contains("CRC")) {
            (true, true) => "wrong CRC",
            (true, false) => "does not read",
            (false, _) => "exception",
        };
        root.draw(&Text::new(label, (a, y - 17), font(13, MARK)))?;
    }
    trace(root, wave, kind, color, (x0, x1), (y_hi, y_lo))?;
    // The bytes under the trace, where a character is wide enough to read.
    let format = &wave.format;
    let bpc = u64::from(format.bits_per_char());
    let char_px = (x1 - x0) as f64 * format.bit_offset(bpc) as f64
        / (wave.to - wave.from + wave.lead_in) as f64;
    let (_, y_hex) = at(t0, -1.2);
    let (_, y_ascii) = at(t0, -2.4);
    for (n, (f, d)) in wave.frames.iter().zip(described).enumerate() {
        if !shapes(kind, f) {
            continue;
        }
        let ink = if d.marked() { MARK } else { TEXT };
        if char_px < 22.0 {
            let (a, _) = at(ms(f.start.max(wave.from)), 0.0);
            let (b, _) = at(ms(f.end(format).min(wave.to)), 0.0);
            if b - a > 40 {
                root.draw(&Text::new(
                    format!("#{}", f.number),
                    ((a + b) / 2, y_hex),
                    font(12, ink).pos(Pos::new(HPos::Center, VPos::Center)),
                ))?;
            }
            continue;
        }
        for (i, sent) in f.bytes.iter().enumerate() {
            let mid = f.start + format.bit_offset(i as u64 * bpc) + format.bit_offset(bpc) / 2;
            if mid < wave.from || mid > wave.to {
                continue;
            }
            let (x, _) = at(ms(mid), 0.0);
            // The bus line shows a character as the receivers got it: one
            // a collision garbled or noise flipped, in red.
            let byte = &wave.line_byte(kind, n, i);
            let ink = if byte == sent { ink } else { MARK };
            let centred = |size| font(size, ink).pos(Pos::new(HPos::Center, VPos::Center));
            root.draw(&Text::new(format!("{byte:02X}"), (x, y_hex), centred(13)))?;
            if d.text && byte.is_ascii_graphic() {
                root.draw(&Text::new(
                    char::from(*byte).to_string(),
                    (x, y_ascii),
                    font(12, DIM).pos(Pos::new(HPos::Center, VPos::Center)),
                ))?;
            }
        }
    }
    Ok(())
}

/// A channel's label colour: a shade off its trace's, so that only the
/// trace has the trace's exact colour and a picture reads back unambiguously.
fn shade(c: RGBColor) -> RGBColor {
    RGBColor(
        c.0.saturating_sub(8),
        c.1.saturating_sub(8),
        c.2.saturating_sub(8),
    )
}

/// Whether frame `f` is seen on channel `kind`.
fn shapes(kind: LineKind, f: &LineFrame) -> bool {
    match kind {
        LineKind::Tx(n) | LineKind::DriverEnable(n) | LineKind::Rx(n) => f.node == n,
        LineKind::Bus => true,
    }
}

/// Tick marks' decimals for a window of `span` ms.
fn decimals(span: f64) -> usize {
    match span {
        s if s >= 100.0 => 0,
        s if s >= 10.0 => 1,
        s if s >= 1.0 => 2,
        s if s >= 0.1 => 3,
        _ => 4,
    }
}

/// The line's level per pixel column: high, low or both (an edge inside).
const WAS_HIGH: u8 = 1;
const WAS_LOW: u8 = 2;

/// Draws one line's trace two pixels thick between the columns `x0..=x1`.
fn trace(
    root: &DrawingArea<BitMapBackend<'_>, Shift>,
    wave: &Waveform,
    kind: LineKind,
    color: RGBColor,
    (x0, x1): (i32, i32),
    (y_hi, y_lo): (i32, i32),
) -> Result<(), Box<dyn std::error::Error>> {
    let columns = (x1 - x0).max(0) as usize + 1;
    // The screen starts with the window's idle lead-in, if it has one.
    let span = (wave.to - wave.from + wave.lead_in).max(1);
    let column = |t: u64| -> usize {
        let since = wave.lead_in + t.saturating_sub(wave.from);
        let c = u128::from(since) * (columns as u128 - 1) / u128::from(span);
        (c as usize).min(columns - 1)
    };
    let mut seen = vec![0u8; columns];
    let mut mark = |from: usize, to: usize, high: bool| {
        for s in &mut seen[from..=to] {
            *s |= if high { WAS_HIGH } else { WAS_LOW };
        }
    };
    let mut level = Waveform::idle(kind);
    let mut at = 0usize;
    for (t, new) in wave.edges(kind) {
        if t >= wave.to {
            break;
        }
        if t > wave.from || (wave.lead_in > 0 && t == wave.from) {
            let c = column(t);
            mark(at, c, level);
            at = c;
        }
        level = new;
    }
    mark(at, columns - 1, level);
    for (c, s) in seen.iter().enumerate() {
        let x = x0 + c as i32;
        let (top, bottom) = match *s {
            WAS_HIGH => (y_hi - 1, y_hi),
            WAS_LOW => (y_lo - 1, y_lo),
            _ => (y_hi - 1, y_lo),
        };
        root.draw(&PathElement::new(vec![(x, top), (x, bottom)], color))?;
    }
    Ok(())
}

/// The frames under the screen, as the lab's bus table: number, start,
/// sender, what it is, and its bytes.
fn bus_table(
    area: &DrawingArea<BitMapBackend<'_>, Shift>,
    wave: &Waveform,
    described: &[Described],
) -> Result<(), Box<dyn std::error::Error>> {
    let columns = [16, 76, 186, 330];
    let mut y = 8;
    for (x, head) in columns
        .iter()
        .zip(["frame", "start (s)", "from", "what it is"])
    {
        area.draw(&Text::new(head, (*x, y), font(14, DIM)))?;
    }
    y += ROW as i32;
    for (f, d) in wave.frames.iter().zip(described).take(TABLE_FRAMES) {
        let ink = if d.marked() { MARK } else { TEXT };
        let node = wave.nodes.get(f.node).map_or("?", String::as_str);
        let cells = [
            format!("#{}", f.number),
            format!("{:.6}", seconds(f.start)),
            node.to_string(),
            d.what.clone(),
        ];
        for (x, cell) in columns.iter().zip(cells) {
            area.draw(&Text::new(cell, (*x, y), font(14, ink)))?;
        }
        y += ROW as i32;
        let mut hex: Vec<String> = f
            .bytes
            .iter()
            .take(48)
            .map(|b| format!("{b:02X}"))
            .collect();
        if f.bytes.len() > 48 {
            hex.push(format!("… {} bytes", f.bytes.len()));
        }
        area.draw(&Text::new(hex.join(" "), (columns[3], y), font(13, DIM)))?;
        y += ROW as i32;
    }
    if wave.frames.len() > TABLE_FRAMES {
        area.draw(&Text::new(
            format!(
                "… and {} more frames in the window",
                wave.frames.len() - TABLE_FRAMES
            ),
            (columns[0], y),
            font(14, DIM),
        ))?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use protocols::modbus8::{CrcOrder, Modbus8Repr};
    use twin_scope::LineFormat;

    fn wave(frames: Vec<Vec<u8>>) -> Waveform {
        Waveform {
            name: "bus.serial".into(),
            format: LineFormat::from_bits_per_char(115_200, 10),
            nodes: vec!["rpi".into(), "motor".into(), "sensor".into()],
            hearing: Hearing::MasterSlaves { master: 0 },
            frames: frames
                .into_iter()
                .enumerate()
                .map(|(number, bytes)| LineFrame {
                    number,
                    node: number % 2,
                    start: 1_000 * number as u64,
                    bytes,
                })
                .collect(),
            flips: vec![],
            garbled: vec![],
            from: 0,
            to: 10_000,
            lead_in: 0,
            reconstructed: false,
        }
    }

    #[test]
    fn the_describer_marks_a_wrong_crc_and_an_exception() {
        let read = Modbus8Repr {
            id: 1,
            function: 3,
            addr: 2,
            value: 1,
        }
        .to_bytes(CrcOrder::HighFirst);
        let mut bad = read;
        bad[7] ^= 0xff;
        let refused = Modbus8Repr::exception(1, 6, 1, Exception::IllegalDataValue)
            .to_bytes(CrcOrder::HighFirst);
        let w = wave(vec![read.to_vec(), bad.to_vec(), refused.to_vec()]);
        let d: Vec<Described> = w.frames.iter().map(|f| describe(&w, f)).collect();
        assert!(!d[0].marked(), "{}", d[0].what);
        assert!(d[0].what.contains("function 03 (read)"), "{}", d[0].what);
        assert!(d[1].broken && d[1].what.contains("CRC"), "{}", d[1].what);
        assert!(d[2].exception, "{}", d[2].what);
        assert!(
            d[2].what.contains(Exception::IllegalDataValue.name()),
            "{}",
            d[2].what
        );
    }

    #[test]
    fn a_picture_shows_the_master_and_a_slave_over_the_line() {
        let w = wave(vec![vec![1, 3, 0, 2, 0, 1, 0, 0]]);
        let names: Vec<String> = channels(&w).into_iter().map(|(_, n)| n).collect();
        // Only the master talks in the window: a slave is shown beside it.
        assert_eq!(names, ["rpi TX", "motor TX", "bus line"]);
    }
}
