//! The two measurements: reply latency (one request at a time, from the
//! request's last byte written to the reply's first byte read) and request
//! rate (clients sending back to back for a fixed time). Both check every
//! reply, so a server that answers garbage fast does not win.

use anyhow::{Context, Result, bail};
use protocols::crc::crc16_modbus;
use protocols::meb::{MebCmd, MebRepr, MebWords};
use rustix::event::{PollFd, PollFlags, Timespec, poll};
use std::io::{Read, Write};
use std::os::fd::AsFd;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Barrier};
use std::time::{Duration, Instant};

/// A broken server fails the run instead of hanging it.
pub const REPLY_TIMEOUT: Duration = Duration::from_secs(2);
const WARMUP: usize = 200;

/// What goes on the wire: requests alternate FC04 (the ten input registers)
/// and FC03 (the three holding registers), the two reads a poller sends.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Dialect {
    ModbusTcp,
    ModbusRtu,
    /// The Modbus TCP requests, echoed back unchanged.
    EchoTcp,
    /// The Modbus RTU requests, echoed back unchanged.
    EchoRtu,
    /// MEB over TCP (the M3CVME tool's protocol): slave 01's six analog
    /// inputs (`EA`) and two analog flags (`FA`) alternating.
    MebTcp,
}

impl Dialect {
    fn read(i: usize) -> (u8, u16) {
        if i.is_multiple_of(2) { (4, 10) } else { (3, 3) }
    }

    /// MEB's reads: the command and its word count.
    fn meb_read(i: usize) -> (MebCmd, u8) {
        if i.is_multiple_of(2) {
            (MebCmd::EA, 6)
        } else {
            (MebCmd::FA, 2)
        }
    }

    /// Writes request `i` into `out`, returns its length.
    pub fn request(self, i: usize, out: &mut [u8; 16]) -> usize {
        let (fc, count) = Self::read(i);
        match self {
            Dialect::ModbusTcp | Dialect::EchoTcp => {
                let tid = (i as u16).to_be_bytes();
                let count = count.to_be_bytes();
                *out = [
                    tid[0], tid[1], 0, 0, 0, 6, 1, fc, 0, 0, count[0], count[1], 0, 0, 0, 0,
                ];
                12
            }
            Dialect::ModbusRtu | Dialect::EchoRtu => {
                let count = count.to_be_bytes();
                out[..6].copy_from_slice(&[1, fc, 0, 0, count[0], count[1]]);
                let crc = crc16_modbus(&out[..6]).to_le_bytes();
                out[6] = crc[0];
                out[7] = crc[1];
                8
            }
            Dialect::MebTcp => {
                let (cmd, cnt) = Self::meb_read(i);
                let request = MebRepr {
                    id: 1,
                    cmd,
                    addr: 0,
                    cnt,
                    data: MebWords::new(),
                };
                // 13 bytes: always fits.
                request.emit(out).unwrap_or(0)
            }
        }
    }

    /// Length of a normal reply to request `i`.
    pub fn reply_len(self, i: usize) -> usize {
        let (_, count) = Self::read(i);
        let data = 2 * usize::from(count);
        match self {
            Dialect::ModbusTcp => 7 + 2 + data,
            Dialect::ModbusRtu => 1 + 2 + data + 2,
            Dialect::EchoTcp => 12,
            Dialect::EchoRtu => 8,
            // Header, FCS and `*\n`: 13 bytes, and four per word.
            Dialect::MebTcp => 13 + 4 * usize::from(Self::meb_read(i).1),
        }
    }

    /// Is `reply` the right answer to request `i` (`req` its bytes)?
    pub fn check(self, i: usize, req: &[u8], reply: &[u8]) -> bool {
        let (fc, count) = Self::read(i);
        match self {
            Dialect::EchoTcp | Dialect::EchoRtu => reply == req,
            Dialect::ModbusTcp => {
                reply[..2] == req[..2]
                    && reply[6] == 1
                    && reply[7] == fc
                    && usize::from(reply[8]) == 2 * usize::from(count)
            }
            Dialect::ModbusRtu => {
                let n = reply.len();
                reply[0] == 1
                    && reply[1] == fc
                    && crc16_modbus(&reply[..n - 2]).to_le_bytes() == [reply[n - 2], reply[n - 1]]
            }
            Dialect::MebTcp => {
                let (cmd, cnt) = Self::meb_read(i);
                MebRepr::parse(reply).is_ok_and(|r| {
                    r.id == 1 && r.cmd == cmd && r.cnt == cnt && r.data.len() == usize::from(cnt)
                })
            }
        }
    }
}

/// Waits until `fd` is readable, for at most [`REPLY_TIMEOUT`].
fn wait_readable(fd: impl AsFd) -> Result<()> {
    let mut fds = [PollFd::new(&fd, PollFlags::IN)];
    let timeout = Timespec {
        tv_sec: REPLY_TIMEOUT.as_secs() as i64,
        tv_nsec: 0,
    };
    if poll(&mut fds, Some(&timeout)).context("poll")? == 0 {
        bail!("no reply within {REPLY_TIMEOUT:?}");
    }
    Ok(())
}

fn read_some<S: Read + AsFd>(link: &mut S, buf: &mut [u8]) -> Result<usize> {
    wait_readable(link.as_fd())?;
    match link.read(buf).context("reading a reply")? {
        0 => bail!("the server closed the link"),
        n => Ok(n),
    }
}

/// Reads the rest of a reply whose first `got` bytes are in `buf`.
fn read_rest<S: Read + AsFd>(
    link: &mut S,
    dialect: Dialect,
    i: usize,
    buf: &mut [u8; 512],
    mut got: usize,
) -> Result<usize> {
    let mut want = dialect.reply_len(i);
    loop {
        if dialect == Dialect::ModbusTcp && got >= 6 {
            // The MBAP length decides, so an exception reply does not stall us.
            want = 6 + usize::from(u16::from_be_bytes([buf[4], buf[5]]));
        }
        if got >= want || got == buf.len() {
            return Ok(got);
        }
        got += read_some(link, &mut buf[got..])?;
    }
}

/// The value below which `q` of a sorted sample falls: its nearest rank,
/// the definition of the server's tick lateness (hdrhistogram's), so the
/// two kinds of p99 this tool prints mean the same.
pub fn quantile<T: Copy>(sorted: &[T], q: f64) -> Option<T> {
    let rank = (q * sorted.len() as f64).ceil() as usize;
    sorted.get(rank.clamp(1, sorted.len().max(1)) - 1).copied()
}

/// The median of the finite `values`: the middle one, or the mean of the
/// two in the middle.
pub fn median(values: impl IntoIterator<Item = f64>) -> Option<f64> {
    let mut v: Vec<f64> = values.into_iter().filter(|x| x.is_finite()).collect();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    match n {
        0 => None,
        _ if n % 2 == 1 => Some(v[n / 2]),
        _ => Some((v[n / 2 - 1] + v[n / 2]) / 2.0),
    }
}

#[derive(Debug, Clone)]
pub struct Latency {
    /// From the request's last byte written: sorted, in nanoseconds.
    pub reply: Samples,
    /// From the first byte of the request's write: the round trip.
    pub round_trip: Samples,
    pub bad_replies: usize,
}

#[derive(Debug, Clone)]
pub struct Samples(Vec<u64>);

impl Samples {
    fn quantile(&self, q: f64) -> Duration {
        Duration::from_nanos(quantile(&self.0, q).unwrap_or(0))
    }
    pub fn median(&self) -> Duration {
        self.quantile(0.5)
    }
    pub fn p99(&self) -> Duration {
        self.quantile(0.99)
    }
    pub fn mean(&self) -> Duration {
        let sum: u64 = self.0.iter().sum();
        Duration::from_nanos(sum / self.0.len().max(1) as u64)
    }
    pub fn max(&self) -> Duration {
        Duration::from_nanos(*self.0.last().expect("samples"))
    }
}

/// `n` requests one at a time (after a warm-up); the time from the request's
/// last byte written to the reply's first byte read.
pub fn latency<S: Read + Write + AsFd>(
    link: &mut S,
    dialect: Dialect,
    n: usize,
) -> Result<Latency> {
    let mut reply_ns = Vec::with_capacity(n);
    let mut round_trip_ns = Vec::with_capacity(n);
    let mut req = [0u8; 16];
    let mut reply = [0u8; 512];
    let mut bad_replies = 0;
    for i in 0..WARMUP + n {
        let len = dialect.request(i, &mut req);
        let writing = Instant::now();
        link.write_all(&req[..len]).context("writing a request")?;
        let sent = Instant::now();
        wait_readable(link.as_fd())?;
        let first = Instant::now();
        let got = read_some(link, &mut reply)?;
        let got = read_rest(link, dialect, i, &mut reply, got)?;
        if got != dialect.reply_len(i) || !dialect.check(i, &req[..len], &reply[..got]) {
            bad_replies += 1;
        }
        if i >= WARMUP {
            reply_ns.push((first - sent).as_nanos() as u64);
            round_trip_ns.push((first - writing).as_nanos() as u64);
        }
    }
    reply_ns.sort_unstable();
    round_trip_ns.sort_unstable();
    Ok(Latency {
        reply: Samples(reply_ns),
        round_trip: Samples(round_trip_ns),
        bad_replies,
    })
}

#[derive(Debug, Clone, Copy)]
pub struct Rate {
    /// Replies checked good.
    pub answered: u64,
    pub per_second: f64,
    pub bad_replies: u64,
    /// The server's CPU time per request answered, if it could be read.
    pub server_cpu: Option<Duration>,
}

/// `links.len()` clients, one thread each, each sending its next request as
/// soon as its reply is in, for `duration`; `server_cpu` reads the server's
/// CPU time used so far.
pub fn rate<S: Read + Write + AsFd + Send + 'static>(
    links: Vec<S>,
    dialect: Dialect,
    duration: Duration,
    server_cpu: impl Fn() -> Option<Duration>,
) -> Result<Rate> {
    let stop = Arc::new(AtomicBool::new(false));
    let done = Arc::new(AtomicU64::new(0));
    let bad = Arc::new(AtomicU64::new(0));
    let start = Arc::new(Barrier::new(links.len() + 1));
    let workers: Vec<_> = links
        .into_iter()
        .map(|mut link| {
            let (stop, done, bad, start) = (stop.clone(), done.clone(), bad.clone(), start.clone());
            std::thread::spawn(move || -> Result<()> {
                let mut req = [0u8; 16];
                let mut reply = [0u8; 512];
                let (mut ok, mut wrong) = (0, 0);
                start.wait();
                let mut i = 0;
                while !stop.load(Ordering::Relaxed) {
                    let len = dialect.request(i, &mut req);
                    link.write_all(&req[..len])?;
                    let got = read_some(&mut link, &mut reply)?;
                    let got = read_rest(&mut link, dialect, i, &mut reply, got)?;
                    if got == dialect.reply_len(i) && dialect.check(i, &req[..len], &reply[..got]) {
                        ok += 1;
                    } else {
                        wrong += 1;
                    }
                    i += 1;
                }
                done.fetch_add(ok, Ordering::Relaxed);
                bad.fetch_add(wrong, Ordering::Relaxed);
                Ok(())
            })
        })
        .collect();
    start.wait();
    let began = Instant::now();
    let cpu_before = server_cpu();
    std::thread::sleep(duration);
    stop.store(true, Ordering::Relaxed);
    for w in workers {
        w.join().expect("client thread")?;
    }
    let elapsed = began.elapsed().as_secs_f64();
    let cpu = server_cpu()
        .zip(cpu_before)
        .map(|(after, before)| after.saturating_sub(before));
    let done = done.load(Ordering::Relaxed);
    Ok(Rate {
        answered: done,
        per_second: done as f64 / elapsed,
        bad_replies: bad.load(Ordering::Relaxed),
        server_cpu: cpu.map(|c| c / u32::try_from(done.max(1)).unwrap_or(u32::MAX)),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_quantile_is_the_nearest_rank_and_a_median_the_middle() {
        let sorted: Vec<u32> = (1..=1000).collect();
        assert_eq!(quantile(&sorted, 0.5), Some(500));
        assert_eq!(quantile(&sorted, 0.99), Some(990));
        assert_eq!(quantile(&sorted, 0.0), Some(1));
        assert_eq!(quantile(&sorted, 1.0), Some(1000));
        assert_eq!(quantile::<u32>(&[], 0.99), None);
        assert_eq!(median([3.0, f64::NAN, 1.0, 2.0]), Some(2.0));
        assert_eq!(median([4.0, 1.0, 3.0, 2.0]), Some(2.5));
        assert_eq!(median([f64::NAN]), None);
    }

    #[test]
    fn meb_reads_are_the_lab_frames_and_their_replies_are_checked() {
        let mut out = [0u8; 16];
        let n = Dialect::MebTcp.request(0, &mut out);
        assert_eq!(&out[..n], b"@01EA000643*\n");
        let n = Dialect::MebTcp.request(1, &mut out);
        assert_eq!(&out[..n], b"@01FA000244*\n");
        let reply = MebRepr {
            id: 1,
            cmd: MebCmd::FA,
            addr: 0,
            cnt: 2,
            data: MebWords::from_slice(&[0x03E8, 0]).unwrap(),
        };
        let mut bytes = [0u8; 64];
        let len = reply.emit(&mut bytes).unwrap();
        assert_eq!(len, Dialect::MebTcp.reply_len(1));
        assert!(Dialect::MebTcp.check(1, &out[..n], &bytes[..len]));
        // The other read's reply, or a spoilt check, is refused.
        assert!(!Dialect::MebTcp.check(0, &out[..n], &bytes[..len]));
        bytes[len - 3] ^= 1;
        assert!(!Dialect::MebTcp.check(1, &out[..n], &bytes[..len]));
    }
}
