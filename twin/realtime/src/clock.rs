//! The wall clock as nodes see it: a monotonic [`Instant`] origin mapped onto
//! [`SimTime`], so the same node code runs on the virtual and the real clock.
//!
//! The clock can slip: when the machine stops the twin for longer than the
//! engine catches up (a stopped process, a busy machine), the session's time
//! is held back by what could not be caught up, so every tick still runs in
//! order and no node sees a jump in its inputs. Every copy of the clock (the
//! carriers', the panel's) sees the slip at once.

use protocols::time::{SimDuration, SimTime, TICKS_PER_SECOND};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

/// How far behind the wall the engine catches up, tick by tick, in a
/// burst; time lost beyond it slips the clock. A burst of 50 ms is 50 plant
/// ticks and, for a sketch, 800 000 AVR cycles: a few tens of milliseconds
/// of work at most.
pub(crate) const CATCH_UP: SimDuration = SimDuration::from_millis(50);

/// Ticks per nanosecond: 72 GHz / 1 GHz.
const TICKS_PER_NANO: u64 = TICKS_PER_SECOND / 1_000_000_000;

/// A monotonic clock whose zero is the start of the session, less the time
/// it slipped.
#[derive(Debug, Clone)]
pub struct RtClock {
    origin: Instant,
    /// Nanoseconds the session's time has slipped behind the wall.
    slipped_ns: Arc<AtomicU64>,
}

impl RtClock {
    /// A clock whose zero is now.
    pub fn start() -> Self {
        Self {
            origin: Instant::now(),
            slipped_ns: Arc::new(AtomicU64::new(0)),
        }
    }

    /// A clock whose zero was `ago` before now: a session under way, for
    /// tests that need the wall clock ahead of the engine's ticks without
    /// sleeping.
    #[cfg(test)]
    pub(crate) fn started_ago(ago: Duration) -> Self {
        let now = Instant::now();
        Self {
            origin: now.checked_sub(ago).unwrap_or(now),
            slipped_ns: Arc::new(AtomicU64::new(0)),
        }
    }

    /// The session time of `instant` (zero before the origin).
    pub fn at(&self, instant: Instant) -> SimTime {
        let ns = instant.saturating_duration_since(self.origin).as_nanos();
        let ns = u64::try_from(ns)
            .unwrap_or(u64::MAX)
            .saturating_sub(self.slipped_ns.load(Ordering::Acquire));
        SimTime(ns.saturating_mul(TICKS_PER_NANO))
    }

    /// The session time now.
    pub fn now(&self) -> SimTime {
        self.at(Instant::now())
    }

    /// The instant of session time `t`.
    pub fn instant(&self, t: SimTime) -> Instant {
        self.origin
            + Duration::from_nanos(self.slipped_ns.load(Ordering::Acquire))
            + Duration::from_nanos(t.0 / TICKS_PER_NANO)
    }

    /// Holds the session's time back by `by` (whole nanoseconds of it).
    pub fn slip(&self, by: SimDuration) {
        self.slipped_ns
            .fetch_add(by.0 / TICKS_PER_NANO, Ordering::AcqRel);
    }

    /// How far the session's time has slipped behind the wall, in all.
    pub fn slipped(&self) -> SimDuration {
        SimDuration(
            self.slipped_ns
                .load(Ordering::Acquire)
                .saturating_mul(TICKS_PER_NANO),
        )
    }
}

/// How a session is given real-time priority, for the notices that say it
/// has none: the flag, what the host must allow, and the shipped units.
pub const HOW_TO_GRANT: &str = "--rt-priority N (1-99) as root, with CAP_SYS_NICE, or within an \
rtprio limit (`ulimit -r`, limits.conf); the systemd units in deploy/systemd grant it";

/// What a session started without `--rt-priority` says once: `risk` is what
/// a busy machine does to this role, in its own words.
pub fn without_priority(risk: &str) -> String {
    format!(
        "no real-time priority: when this machine is busy, {risk}; ask for it with {HOW_TO_GRANT}"
    )
}

/// Puts the calling thread under the real-time FIFO scheduler at
/// `priority` (1-99), so a busy machine cannot delay its ticks: Linux only,
/// and only where permitted (root, CAP_SYS_NICE, or an RLIMIT_RTPRIO of at
/// least `priority`). Uses `chrt` on the thread's id, which keeps the twin
/// free of unsafe code.
pub fn raise_this_thread(priority: u8) -> Result<(), String> {
    let link = std::fs::read_link("/proc/thread-self")
        .map_err(|e| format!("cannot find this thread's id (/proc/thread-self): {e}"))?;
    let tid = link
        .file_name()
        .and_then(|t| t.to_str())
        .ok_or("cannot read this thread's id")?
        .to_string();
    let out = std::process::Command::new("chrt")
        .args(["-f", "-p", &priority.to_string(), &tid])
        .output()
        .map_err(|e| format!("cannot run chrt (util-linux): {e}"))?;
    if out.status.success() {
        Ok(())
    } else {
        Err(format!(
            "chrt -f -p {priority} {tid} failed: {}",
            String::from_utf8_lossy(&out.stderr).trim()
        ))
    }
}

/// A session duration as a std [`Duration`].
pub fn to_std(d: SimDuration) -> Duration {
    Duration::from_nanos(d.0 / TICKS_PER_NANO)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn instants_and_session_times_map_both_ways() {
        let clock = RtClock::start();
        let t = SimTime::ZERO + SimDuration::from_millis(1500);
        assert_eq!(clock.at(clock.instant(t)), t);
        assert!(clock.now() < SimTime::ZERO + SimDuration::from_secs(5));
        // A copy sees the slip: the same instant is a quarter of a second
        // earlier in the session, and the session's time comes that much later.
        let before = clock.instant(t);
        let copy = clock.clone();
        clock.slip(SimDuration::from_millis(250));
        assert_eq!(copy.slipped(), SimDuration::from_millis(250));
        assert_eq!(copy.at(before + Duration::from_millis(250)), t);
        assert_eq!(copy.instant(t), before + Duration::from_millis(250));
        assert_eq!(clock.at(clock.instant(t)), t);
        assert_eq!(
            to_std(SimDuration::from_micros(250)),
            Duration::from_micros(250)
        );
    }
}
