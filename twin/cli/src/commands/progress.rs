//! The progress line of a long run on the virtual clock: a bar on stderr
//! while stderr is a terminal, nothing at all when it is piped or redirected
//! (or when `TERM` is `dumb` or unset), so logs and scripts see only the
//! results on stdout. The engine reports how far it has got through its
//! progress hook (every few thousand events, never per step); the wall clock
//! that paces the redraws is read here, in the binary, never in the
//! simulation.

use indicatif::{ProgressBar, ProgressDrawTarget, ProgressState, ProgressStyle};
use std::io::IsTerminal;

/// Positions are kept in thousandths: simulated milliseconds, or per mille.
const SCALE: f64 = 1000.0;

/// A progress line; cleared when finished or dropped.
pub struct Progress {
    bar: ProgressBar,
}

impl Progress {
    /// A run of `total_s` simulated seconds, shown as simulated time.
    pub fn simulated(what: &str, total_s: f64) -> Self {
        let style = style(
            "{prefix} [{bar:25}] {sim} of {total} s simulated, {speed}x real time, {eta} left",
        )
        .with_key("sim", |s: &ProgressState, w: &mut dyn std::fmt::Write| {
            let _ = write!(w, "{:.1}", s.pos() as f64 / SCALE);
        })
        .with_key("total", |s: &ProgressState, w: &mut dyn std::fmt::Write| {
            let _ = write!(w, "{:.1}", s.len().unwrap_or(0) as f64 / SCALE);
        })
        // Simulated milliseconds per wall-clock second, as `twin bench` counts.
        .with_key("speed", |s: &ProgressState, w: &mut dyn std::fmt::Write| {
            let _ = write!(w, "{:.0}", s.per_sec() / SCALE);
        });
        Self::new(what, total_s * SCALE, style)
    }

    /// Work measured as a fraction done (a sweep's runs, a step response's
    /// stages), shown as a percentage.
    pub fn fraction(what: &str) -> Self {
        Self::new(
            what,
            SCALE,
            style("{prefix} [{bar:25}] {percent:>3} %, {eta} left"),
        )
    }

    fn new(what: &str, len: f64, style: ProgressStyle) -> Self {
        let target = if std::io::stderr().is_terminal() {
            // indicatif hides it still where TERM says the terminal cannot
            // move its cursor.
            ProgressDrawTarget::stderr_with_hz(5)
        } else {
            ProgressDrawTarget::hidden()
        };
        let bar = ProgressBar::with_draw_target(Some(len.max(1.0) as u64), target);
        bar.set_style(style);
        bar.set_prefix(format!("  {what}"));
        Self { bar }
    }

    /// Move to `done`, the fraction of the run done (0 to 1).
    pub fn show(&self, done: f64) {
        let len = self.bar.length().unwrap_or(0);
        let at = (done.clamp(0.0, 1.0) * len as f64) as u64;
        // The first report draws at once, so a run long enough to report
        // progress shows it; later ones at most five times a second.
        self.bar.set_position(at);
    }

    /// Take the line off the terminal.
    pub fn clear(&self) {
        self.bar.finish_and_clear();
    }
}

impl Drop for Progress {
    fn drop(&mut self) {
        // An error leaves through `?`: the line goes before its message.
        if !self.bar.is_finished() {
            self.bar.finish_and_clear();
        }
    }
}

impl std::fmt::Debug for Progress {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Progress").finish_non_exhaustive()
    }
}

fn style(template: &str) -> ProgressStyle {
    ProgressStyle::with_template(template)
        .unwrap_or_else(|_| ProgressStyle::default_bar())
        .progress_chars("=> ")
}
