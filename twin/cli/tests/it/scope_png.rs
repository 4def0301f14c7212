//! `twin scope --png` read back: the trace of a channel, thresholded at each
//! bit's centre along the time axis, is the frame's bytes at the bus's baud
//! (start bit, 8 data bits least significant first, stop bit).

use crate::scope::{run, s};
use crate::support;
use std::path::{Path, PathBuf};
use support::{text, twin};
use twin_lab::scope_png::TRACES;
use twin_recording::read::BusFrame;

fn scratch(name: &str) -> PathBuf {
    support::scratch("scope-png", name)
}

/// An RGB picture.
struct Picture {
    width: usize,
    height: usize,
    rgb: Vec<u8>,
}

impl Picture {
    fn read(path: &Path) -> Picture {
        let file = std::fs::File::open(path).expect("the PNG was written");
        let mut reader = png::Decoder::new(file).read_info().expect("a PNG");
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader.next_frame(&mut buf).expect("a PNG frame");
        assert_eq!(info.color_type, png::ColorType::Rgb, "an RGB picture");
        buf.truncate(info.buffer_size());
        Picture {
            width: info.width as usize,
            height: info.height as usize,
            rgb: buf,
        }
    }

    fn is(&self, x: usize, y: usize, c: [u8; 3]) -> bool {
        let i = 3 * (y * self.width + x);
        self.rgb[i..i + 3] == c
    }

    /// The rows of column `x` in colour `c`.
    fn column(&self, x: usize, c: [u8; 3]) -> Vec<usize> {
        (0..self.height).filter(|&y| self.is(x, y, c)).collect()
    }
}

/// A channel's trace: the columns and rows its colour covers.
struct Trace<'p> {
    picture: &'p Picture,
    color: [u8; 3],
    x0: usize,
    x1: usize,
    /// The high level's top row.
    top: usize,
    /// Between the high and the low level.
    middle: usize,
    /// One level all along (a line nobody drives in the window).
    flat: bool,
}

impl<'p> Trace<'p> {
    fn find(picture: &'p Picture, channel: usize) -> Trace<'p> {
        let c = TRACES[channel];
        let color = [c.0, c.1, c.2];
        let cols: Vec<usize> = (0..picture.width)
            .filter(|&x| !picture.column(x, color).is_empty())
            .collect();
        assert!(!cols.is_empty(), "no trace of channel {channel}");
        let (x0, x1) = (cols[0], *cols.last().unwrap());
        // Every column of the screen holds the trace: the line is drawn
        // from the window's start to its end.
        assert_eq!(
            cols.len(),
            x1 - x0 + 1,
            "channel {channel}: a gap in the trace"
        );
        let rows: Vec<usize> = (x0..=x1).flat_map(|x| picture.column(x, color)).collect();
        let (top, bottom) = (*rows.iter().min().unwrap(), *rows.iter().max().unwrap());
        Trace {
            picture,
            color,
            x0,
            x1,
            top,
            middle: (top + bottom) / 2,
            flat: bottom - top < 4,
        }
    }

    /// The level at `t` (s) of a window `from..to`: high, low, or none when
    /// the column holds an edge.
    fn level(&self, t: f64, (from, to): (f64, f64)) -> Option<bool> {
        let x = self.x0 as f64 + (t - from) / (to - from) * (self.x1 - self.x0) as f64;
        let rows = self.picture.column(x.round() as usize, self.color);
        if rows.iter().all(|&y| y < self.middle) {
            Some(true)
        } else if rows.iter().all(|&y| y > self.middle) {
            Some(false)
        } else {
            None
        }
    }
}

/// The window `twin scope --frame` draws: two characters either side.
fn frame_window(f: &BusFrame, bit_s: f64) -> (f64, f64) {
    let end = f.time_s + f.bytes.len() as f64 * 10.0 * bit_s;
    (f.time_s - 20.0 * bit_s, end + 20.0 * bit_s)
}

/// The levels of `f`'s bits on the wire, 8N1.
fn bits(f: &BusFrame) -> Vec<bool> {
    f.bytes
        .iter()
        .flat_map(|b| {
            std::iter::once(false)
                .chain((0..8).map(move |k| b >> k & 1 == 1))
                .chain(std::iter::once(true))
        })
        .collect()
}

/// Reads frame `f`'s bits off `trace` at each bit's centre.
fn read_bits(trace: &Trace, f: &BusFrame, window: (f64, f64), bit_s: f64) -> Vec<Option<bool>> {
    (0..f.bytes.len() * 10)
        .map(|p| trace.level(f.time_s + (p as f64 + 0.5) * bit_s, window))
        .collect()
}

fn channels(out: &str, png: &Path) -> Vec<String> {
    let line = out
        .lines()
        .find(|l| l.trim_start().starts_with(s(png)))
        .unwrap_or_else(|| panic!("no line about the picture in {out}"));
    let (_, list) = line.split_once("channels ").expect("channels listed");
    list.split(", ").map(str::to_string).collect()
}

#[test]
fn a_frames_picture_reads_back_as_its_bytes_at_the_baud() {
    let (run, frames) = run("ev-meb", "0.2", "png-ev-meb.mcap");
    let bit_s = 1.0 / 115_200.0;
    // A short frame of each node that sends one (the supervisor's requests;
    // the controller's replies are long): at 1280 px a 16-character frame
    // with its idle line is more than six pixels a bit, enough to read each
    // bit's centre. A long reply draws as narrow bits, as on a scope.
    let mut picked: Vec<usize> = Vec::new();
    for (n, f) in frames.iter().enumerate().skip(10) {
        if f.bytes.len() <= 16 && !picked.iter().any(|&p| frames[p].from == f.from) {
            picked.push(n);
        }
    }
    assert!(!picked.is_empty(), "no short frame");
    for n in picked {
        let f = &frames[n];
        let png = scratch(&format!("frame-{n}.png"));
        let o = twin(&[
            "scope",
            s(&run),
            "--frame",
            &n.to_string(),
            "--png",
            s(&png),
        ]);
        assert!(o.status.success(), "{}", text(&o));
        let names = channels(&text(&o), &png);
        assert_eq!(
            names.last().map(String::as_str),
            Some("bus line"),
            "{names:?}"
        );
        let picture = Picture::read(&png);
        let window = frame_window(f, bit_s);
        let want: Vec<Option<bool>> = bits(f).into_iter().map(Some).collect();
        let talker = names
            .iter()
            .position(|name| *name == format!("{} TX", f.from))
            .unwrap_or_else(|| panic!("no channel for {} in {names:?}", f.from));
        let talker_top = Trace::find(&picture, talker).top;
        for (i, name) in names.iter().enumerate() {
            let trace = Trace::find(&picture, i);
            if i == talker || name == "bus line" {
                // The idle line before and after the frame is high.
                for t in [window.0 + bit_s, window.1 - bit_s] {
                    assert_eq!(trace.level(t, window), Some(true), "{name} idle at {t}");
                }
                let got = read_bits(&trace, f, window, bit_s);
                assert_eq!(got, want, "frame {n} on {name}: {:02x?}", f.bytes);
            } else {
                // The other node's TX stays idle: flat at its band's 5 V,
                // where the talker's high level is in its own band.
                assert!(trace.flat, "{name} is not idle");
                let band = 150 * i.abs_diff(talker);
                assert_eq!(trace.top.abs_diff(talker_top), band, "{name} is not high");
            }
        }
    }
}

#[test]
fn a_controller_network_request_and_reply_show_on_the_master_and_the_slave() {
    let (run, frames) = run("controller-network", "0.3", "png-cn.mcap");
    let bit_s = 1.0 / 115_200.0;
    let i = frames
        .iter()
        .position(|f| f.time_s > 0.1 && f.from == "rpi")
        .expect("a request of the master");
    let (request, reply) = (&frames[i], &frames[i + 1]);
    assert_ne!(reply.from, "rpi", "{reply:?}");
    let from = request.time_s - 20.0 * bit_s;
    let to = reply.end_s + 30.0 * bit_s;
    let png = scratch("cn.png");
    let o = twin(&[
        "scope",
        s(&run),
        "--from",
        &format!("{from:.9}"),
        "--to",
        &format!("{to:.9}"),
        "--png",
        s(&png),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let names = channels(&text(&o), &png);
    let picture = Picture::read(&png);
    let window = ((from * 1e9).round() / 1e9, (to * 1e9).round() / 1e9);
    for f in [request, reply] {
        let i = names
            .iter()
            .position(|n| *n == format!("{} TX", f.from))
            .unwrap_or_else(|| panic!("no channel for {} in {names:?}", f.from));
        let trace = Trace::find(&picture, i);
        let want: Vec<Option<bool>> = bits(f).into_iter().map(Some).collect();
        assert_eq!(
            read_bits(&trace, f, window, bit_s),
            want,
            "{}: {:02x?}",
            f.from,
            f.bytes
        );
    }
}

#[test]
fn a_frame_out_of_range_is_an_error_and_draws_nothing() {
    let (run, frames) = run("ev-meb", "0.1", "png-short.mcap");
    let png = scratch("none.png");
    let o = twin(&["scope", s(&run), "--frame", "99999", "--png", s(&png)]);
    assert!(!o.status.success());
    let want = format!(
        "--frame 99999: {} has frames 0 to {} on this bus",
        s(&run),
        frames.len() - 1
    );
    assert!(text(&o).contains(&want), "{}", text(&o));
    assert!(!png.exists(), "a picture was drawn");
}

#[test]
fn a_picture_is_drawn_at_the_size_asked_and_still_reads_back() {
    let (run, frames) = run("ev-meb", "0.2", "png-size.mcap");
    let bit_s = 1.0 / 115_200.0;
    let (n, f) = frames
        .iter()
        .enumerate()
        .skip(10)
        .find(|(_, f)| f.bytes.len() <= 16)
        .expect("a short frame");
    let png = scratch("size.png");
    let o = twin(&[
        "scope",
        s(&run),
        "--frame",
        &n.to_string(),
        "--png",
        s(&png),
        "--width",
        "1920",
        "--height",
        "720",
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("1920×720 px"), "{}", text(&o));
    let picture = Picture::read(&png);
    assert_eq!((picture.width, picture.height), (1920, 720));
    let names = channels(&text(&o), &png);
    let line = names.len() - 1;
    assert_eq!(names[line], "bus line");
    let trace = Trace::find(&picture, line);
    let want: Vec<Option<bool>> = bits(f).into_iter().map(Some).collect();
    let window = frame_window(f, bit_s);
    assert_eq!(read_bits(&trace, f, window, bit_s), want);

    // A size no picture can have is refused, saying what can be.
    let o = twin(&[
        "scope",
        s(&run),
        "--frame",
        "1",
        "--png",
        s(&png),
        "--width",
        "100",
    ]);
    assert!(!o.status.success());
    assert!(
        text(&o).contains("a width of 100 px: give 640 to 16384 px"),
        "{}",
        text(&o)
    );
    let o = twin(&[
        "scope",
        s(&run),
        "--frame",
        "1",
        "--png",
        s(&png),
        "--height",
        "50",
    ]);
    assert!(!o.status.success());
    assert!(text(&o).contains("a height of 50 px: "), "{}", text(&o));
}
