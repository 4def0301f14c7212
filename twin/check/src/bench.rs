//! Bench checks: what a slave's registers *mean* on the bench it is wired
//! to. The suite's frames write VEL, EN, BRK and FR and read the inputs as
//! ever; a bench step ([`BenchStep`]) then looks at the plant through the
//! panel of the twin session the slave drives (`twin serve --web`, its
//! JSON API, `docs/panel-api.md`): the drive as the plant sees it, the
//! motor's speed against what the plant's model gives ([`model`]), and the
//! inputs the slave read back against the plant's values within the
//! ADC's resolution.
//!
//! Bench checks are steps in the protocol suites, not a suite of their
//! own: a bench check writes and reads through the very frames, map and
//! id the rest of the suite holds the slave to, and one run (one report,
//! one score, one class line) says both whether the slave speaks its
//! protocol and whether what it says is so. Without a bench (no
//! `--bench`), a check with a bench step is "not applicable": listed, not
//! scored, not failed.
//!
//! The check runs no plant: the plant runs in the session, and the model's
//! closed forms come from the parameters that session serves.
//!
//! A slave's converters may be coarser than the map's 12 bits (an Arduino's
//! ADC has 10; its VEL is a PWM through the bench's RC filter): given as
//! [`Converters`], the tolerances widen to their resolution, and no further.

mod http;
pub mod model;

use http::Panel;
use model::Analog;
use plant::PlantParams;
use serde_json::Value;
use std::time::{Duration, Instant};

/// What a bench step holds the plant to.
#[derive(Debug, Clone, PartialEq)]
pub enum BenchStep {
    /// The drive on with `vel` and the direction written, and the motor
    /// settling at the model's speed for them (counter-clockwise: negative).
    Turns { vel: u16, reverse: bool },
    /// The drive off (EN off), the wheel slowing at least as it coasts.
    Coasts,
    /// The brake on, the wheel slowing faster than it would coast.
    Brakes,
    /// The wheel at rest.
    Stopped,
    /// The last reply's data words are these inputs as the plant has them.
    Inputs {
        words: Vec<Input>,
        rpm_window_ms: u16,
    },
}

/// An input word a reply carries.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Input {
    V1,
    V2,
    I,
    RpmM,
    RpmL,
    Ldr,
    /// A word the step does not compare (`-`).
    Any,
}

impl Input {
    /// The tags of the I/O map (the MEB page's names).
    pub fn from_name(name: &str) -> Option<Self> {
        Some(match name {
            "V1" => Input::V1,
            "V2" => Input::V2,
            "I" => Input::I,
            "RPM_M" => Input::RpmM,
            "RPM_L" => Input::RpmL,
            "LDR" => Input::Ldr,
            "-" => Input::Any,
            _ => return None,
        })
    }

    fn name(self) -> &'static str {
        match self {
            Input::V1 => "V1",
            Input::V2 => "V2",
            Input::I => "I",
            Input::RpmM => "RPM_M",
            Input::RpmL => "RPM_L",
            Input::Ldr => "LDR",
            Input::Any => "-",
        }
    }
}

/// What a step's `bench` may say.
pub const BENCH_STEPS: &str =
    "\"forward\", \"reverse\", \"coasts\", \"brakes\", \"stopped\" or \"inputs\"";

/// The plant as the panel showed it at session time `t` (s).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlantState {
    pub t: f64,
    pub battery_volts: f64,
    pub bus_volts: f64,
    pub inverter_current: f64,
    /// Signed: counter-clockwise is negative.
    pub motor_rpm: f64,
    pub wheel_rpm: f64,
    pub ldr_counts: f64,
    pub enable: bool,
    pub brake: bool,
    pub reverse: bool,
    pub vel_volts: f64,
}

impl PlantState {
    /// The first module of a `GET /api/state` answer, if it has one.
    fn from_json(v: &Value) -> Option<Self> {
        let m = &v["state"]["modules"][0];
        let num = |field: &str| m[field].as_f64();
        let a = &m["actuators"];
        Some(PlantState {
            // The plant's own time where the panel gives it: under load the
            // engine's ticks run late, and the session's clock is ahead of
            // the plant (a wheel watched coasting for a second of clock
            // time coasted less by the plant's).
            t: m["plant_t"].as_f64().or_else(|| v["t"].as_f64())?,
            battery_volts: num("battery_volts")?,
            bus_volts: num("bus_volts")?,
            inverter_current: num("inverter_current")?,
            motor_rpm: num("motor_rpm")?,
            wheel_rpm: num("wheel_rpm")?,
            ldr_counts: num("ldr_counts")?,
            enable: a["enable"].as_bool()?,
            brake: a["brake"].as_bool()?,
            reverse: a["reverse"].as_bool()?,
            vel_volts: a["vel_volts"].as_f64()?,
        })
    }
}

/// The longest the plant may take to show an output the slave
/// acknowledged: its next loop tick and the panel's next update.
const OUTPUTS_SHOWN_WITHIN: Duration = Duration::from_secs(2);
/// The longest a motor may take to settle at its speed: a reversal at the
/// drive's current limit takes about 2 s on the EV module.
const SETTLE_WITHIN: Duration = Duration::from_secs(15);
/// How long the wheel is watched slowing down.
const COAST_FOR_S: f64 = 1.0;
const BRAKE_FOR_S: f64 = 0.25;

/// The slave's own converters, where they are coarser than the map's 12
/// bits: its ADC (the inputs it reads back) and the output that gives VEL
/// its voltage.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Converters {
    pub adc_bits: u8,
    pub vel_bits: u8,
}

impl Default for Converters {
    /// The map's: 12-bit counts both ways.
    fn default() -> Self {
        Converters {
            adc_bits: MAP_BITS,
            vel_bits: MAP_BITS,
        }
    }
}

/// The MEB page's default scaling counts 12 bits.
pub const MAP_BITS: u8 = 12;

/// How far a PWM's voltage ripples about its mean through the bench's RC
/// filter, as the plant sees it at any one moment: a 15.6 kHz PWM through
/// 1 ms moves 80 mV peak to peak at half duty.
const PWM_RIPPLE_VOLTS: f64 = 0.1;

impl Converters {
    /// One step of a converter of `bits`, in the map's 12-bit counts.
    fn step(bits: u8) -> f64 {
        f64::from(1u32 << MAP_BITS.saturating_sub(bits.clamp(1, MAP_BITS)))
    }

    /// The counts an input read back may be off by: one step of the ADC
    /// (a coarser one truncates to its step, and its reading scaled to 12
    /// bits is rounded: one count more).
    fn adc_counts(self) -> f64 {
        let step = Self::step(self.adc_bits);
        if step > 1.0 { step + 1.0 } else { step }
    }

    /// The VEL counts the drive may be off by: one step of its output.
    fn vel_counts(self) -> f64 {
        Self::step(self.vel_bits)
    }

    /// What the plant's VEL input may be off by at any one moment (V): one
    /// step, and a PWM's ripple if VEL is one.
    fn vel_volts(self) -> f64 {
        let step = self.vel_counts() * model::vel_volts(1);
        if self.vel_bits < MAP_BITS {
            step + PWM_RIPPLE_VOLTS
        } else {
            step
        }
    }
}

/// The bench a slave is wired to: its session's panel and plant.
#[derive(Debug, Clone)]
pub struct Bench {
    panel: Panel,
    params: PlantParams,
    module: String,
    converters: Converters,
}

/// Whether `url` is a panel's address (`http://HOST:PORT[/?token=…]`),
/// without reaching it: a roster's mistake is said before anything runs.
pub fn check_url(url: &str) -> Result<(), String> {
    Panel::parse(url).map(|_| ())
}

impl Bench {
    /// The panel at `url` (`http://HOST:PORT`, `?token=…` if it needs
    /// one), and the plant's parameters it serves.
    pub fn connect(url: &str) -> Result<Self, String> {
        let panel = Panel::parse(url)?;
        let body = panel.get("/api/plant")?;
        let value: Value = serde_json::from_str(&body)
            .map_err(|e| format!("{}: /api/plant is no JSON: {e}", panel.shown))?;
        let Some(module) = value["modules"].as_array().and_then(|m| m.first()) else {
            return Err(format!(
                "the session at {} has no plant: --bench names the panel of the `twin serve` session the slave is wired to",
                panel.shown
            ));
        };
        let params: PlantParams = serde_json::from_value(module["params"].clone())
            .map_err(|e| format!("{}: the plant's parameters: {e}", panel.shown))?;
        Ok(Bench {
            module: module["name"].as_str().unwrap_or("").to_string(),
            panel,
            params,
            converters: Converters::default(),
        })
    }

    /// The slave's converters, if coarser than the map's.
    pub fn with_converters(mut self, converters: Converters) -> Self {
        self.converters = converters;
        self
    }

    /// What the bench says of the slave's converters in a report's head:
    /// nothing for the map's own.
    pub fn described(&self) -> String {
        let c = self.converters;
        if c == Converters::default() {
            return self.panel.shown.clone();
        }
        format!(
            "{} (the slave's ADC {} bits, VEL {} bits)",
            self.panel.shown, c.adc_bits, c.vel_bits
        )
    }

    /// The panel's address, for reports.
    pub fn url(&self) -> &str {
        &self.panel.shown
    }

    pub fn params(&self) -> &PlantParams {
        &self.params
    }

    /// The plant now (the panel's last update).
    pub fn state(&self) -> Result<PlantState, String> {
        let give_up = Instant::now() + OUTPUTS_SHOWN_WITHIN;
        loop {
            let body = self.panel.get("/api/state")?;
            let value: Value = serde_json::from_str(&body)
                .map_err(|e| format!("{}: /api/state is no JSON: {e}", self.panel.shown))?;
            if let Some(state) = PlantState::from_json(&value) {
                return Ok(state);
            }
            // A session just started has published nothing yet.
            if Instant::now() > give_up || value.get("state").is_some() {
                return Err(format!(
                    "the session at {} shows no plant{}",
                    self.panel.shown,
                    if self.module.is_empty() {
                        String::new()
                    } else {
                        format!(" for {}", self.module)
                    }
                ));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// The first update after session time `t`.
    fn after(&self, t: f64) -> Result<PlantState, String> {
        let give_up = Instant::now() + OUTPUTS_SHOWN_WITHIN;
        loop {
            let state = self.state()?;
            if state.t > t {
                return Ok(state);
            }
            if Instant::now() > give_up {
                return Err(format!(
                    "the panel at {} stopped updating (session time {t:.3} s)",
                    self.panel.shown
                ));
            }
            std::thread::sleep(Duration::from_millis(15));
        }
    }

    /// The first update at least `seconds` of session time after `from`.
    fn later(&self, from: &PlantState, seconds: f64) -> Result<PlantState, String> {
        let give_up = Instant::now() + Duration::from_secs_f64(seconds) + OUTPUTS_SHOWN_WITHIN;
        loop {
            let state = self.state()?;
            if state.t >= from.t + seconds {
                return Ok(state);
            }
            if Instant::now() > give_up {
                return Err(format!(
                    "the panel at {} stopped updating (session time {:.3} s)",
                    self.panel.shown, state.t
                ));
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    /// Waits until the plant shows what `wanted` says of it; the last
    /// update and what was wrong with it if it never did.
    fn until(
        &self,
        within: Duration,
        wanted: impl Fn(&PlantState) -> Result<(), String>,
    ) -> Result<Result<PlantState, (PlantState, String)>, String> {
        let give_up = Instant::now() + within;
        let mut state = self.state()?;
        loop {
            match wanted(&state) {
                Ok(()) => return Ok(Ok(state)),
                Err(why) if Instant::now() > give_up => return Ok(Err((state, why))),
                Err(_) => {}
            }
            state = self.after(state.t)?;
        }
    }

    /// The step's verdict: `Err(why)` when the plant does not do what the
    /// slave's frames said, or the bench could not be read. `reply` is the
    /// data words of the last reply; `before` the plant before its request.
    pub fn judge(
        &self,
        step: &BenchStep,
        reply: Option<&[u16]>,
        before: Option<&PlantState>,
    ) -> Result<(), String> {
        match step {
            BenchStep::Turns { vel, reverse } => self.turns(*vel, *reverse),
            BenchStep::Coasts => self.slows(false),
            BenchStep::Brakes => self.slows(true),
            BenchStep::Stopped => match self.until(SETTLE_WITHIN, |s| {
                if s.motor_rpm.abs() < 1.0 {
                    Ok(())
                } else {
                    Err(format!("the motor still turns at {:.0} rpm", s.motor_rpm))
                }
            })? {
                Ok(_) => Ok(()),
                Err((_, why)) => Err(format!("{why} after {} s", SETTLE_WITHIN.as_secs())),
            },
            BenchStep::Inputs {
                words,
                rpm_window_ms,
            } => {
                let Some(reply) = reply else {
                    return Err("no reply with data words came to compare with the plant".into());
                };
                let Some(before) = before else {
                    return Err("the plant was not read before the request".into());
                };
                // The reply was made between `before` and the first update
                // after it came.
                let now = self.state()?;
                let after = self.after(now.t)?;
                self.inputs(words, *rpm_window_ms, reply, before, &after)
            }
        }
    }

    /// The drive on with `vel` in the direction written, then the motor at
    /// the model's speed.
    fn turns(&self, vel: u16, reverse: bool) -> Result<(), String> {
        let volts = model::vel_volts(vel);
        let vel_slack = self.converters.vel_volts();
        let drive = self.until(OUTPUTS_SHOWN_WITHIN, |s| {
            if !s.enable {
                return Err("the plant's drive is off (EN off as the plant sees it)".into());
            }
            if s.brake {
                return Err("the plant's brake is on (BRK on as the plant sees it)".into());
            }
            if s.reverse != reverse {
                return Err(format!(
                    "the plant turns the motor {} (FR as the plant sees it) where FR was written {}",
                    direction(s.reverse),
                    direction(reverse)
                ));
            }
            if (s.vel_volts - volts).abs() > vel_slack {
                return Err(format!(
                    "the plant's speed input is {:.3} V where VEL {vel} is {volts:.3} V",
                    s.vel_volts
                ));
            }
            Ok(())
        })?;
        if let Err((_, why)) = drive {
            return Err(format!(
                "{why}, {} s after the slave acknowledged the writes",
                OUTPUTS_SHOWN_WITHIN.as_secs()
            ));
        }
        let sign = if reverse { -1.0 } else { 1.0 };
        let p = &self.params;
        let expected = |s: &PlantState| sign * model::steady_rpm(p, vel, s.bus_volts);
        // The speed VEL is written with: one step of the slave's output
        // either side (the map's DAC: one count).
        let counts = self.converters.vel_counts();
        let tolerance =
            |s: &PlantState| (counts * model::rpm_per_count(p, vel, s.bus_volts)).max(1.0);
        let settled = self.until(SETTLE_WITHIN, |s| {
            let off = s.motor_rpm - expected(s);
            if off.abs() <= tolerance(s) {
                Ok(())
            } else {
                Err(String::new())
            }
        })?;
        match settled {
            Ok(_) => Ok(()),
            Err((s, _)) => Err(format!(
                "the motor turns at {:.0} rpm after {} s; the plant's model gives {:.0} ± {:.1} rpm for VEL {vel} ({volts:.3} V) on its {:.1} V bus",
                s.motor_rpm,
                SETTLE_WITHIN.as_secs(),
                expected(&s),
                tolerance(&s),
                s.bus_volts
            )),
        }
    }

    /// The drive off (and with `brake`, the brake on), and the wheel
    /// slowing as fast as it coasts at least (with `brake`: twice as fast
    /// at least).
    fn slows(&self, brake: bool) -> Result<(), String> {
        let shown = self.until(OUTPUTS_SHOWN_WITHIN, |s| {
            if brake && !s.brake {
                return Err("the plant's brake is off (BRK off as the plant sees it)".into());
            }
            if !brake && s.enable {
                return Err("the plant's drive is on (EN on as the plant sees it)".into());
            }
            Ok(())
        })?;
        let from = match shown {
            Ok(s) => s,
            Err((_, why)) => {
                return Err(format!(
                    "{why}, {} s after the slave acknowledged the write",
                    OUTPUTS_SHOWN_WITHIN.as_secs()
                ));
            }
        };
        if from.motor_rpm.abs() < 1.0 {
            return Err("the motor was not turning: there is nothing to slow down".into());
        }
        let seconds = if brake { BRAKE_FOR_S } else { COAST_FOR_S };
        let to = self.later(&from, seconds)?;
        let dt = to.t - from.t;
        let coasted = model::coasted_rpm(&self.params, from.motor_rpm, dt);
        let coast_drop = from.motor_rpm.abs() - coasted.abs();
        let drop = from.motor_rpm.abs() - to.motor_rpm.abs();
        // The wheel's speed is the plant's own (no sensor between), but the
        // plant moves it a mechanical step at a time: what coasting loses
        // over one step either end is allowed.
        let slack = coast_drop / dt.max(1e-3) * 2.0 * self.params.wheel.step_s;
        let (wanted, what) = if brake {
            (2.0 * coast_drop, "twice what it loses coasting")
        } else {
            (coast_drop - slack, "what it loses coasting")
        };
        if drop >= wanted {
            Ok(())
        } else {
            Err(format!(
                "the motor went from {:.0} to {:.0} rpm in {dt:.2} s: it lost {drop:.0} rpm where it must lose {what} ({coast_drop:.0} rpm by the plant's model){}",
                from.motor_rpm,
                to.motor_rpm,
                if !brake && to.enable {
                    "; the plant's drive is on"
                } else {
                    ""
                }
            ))
        }
    }

    /// Each word of `reply` against its input in the plant, between the
    /// updates `before` and `after` the reply, within the ADC's
    /// resolution (an rpm within the estimate's resolution over
    /// `rpm_window_ms`).
    fn inputs(
        &self,
        words: &[Input],
        rpm_window_ms: u16,
        reply: &[u16],
        before: &PlantState,
        after: &PlantState,
    ) -> Result<(), String> {
        if reply.len() < words.len() {
            return Err(format!(
                "the reply carries {} words where {} inputs were read",
                reply.len(),
                words.len()
            ));
        }
        let p = &self.params;
        let window = f64::from(rpm_window_ms.max(1)) / 1e3;
        let adc = self.converters.adc_counts();
        let mut wrong = Vec::new();
        for (&input, &word) in words.iter().zip(reply) {
            let both = |f: &dyn Fn(&PlantState) -> f64| {
                let (a, b) = (f(before), f(after));
                (a.min(b), a.max(b))
            };
            let (low, high, slack, what) = match input {
                Input::Any => continue,
                Input::V1 | Input::V2 | Input::I => {
                    let (analog, value): (Analog, &dyn Fn(&PlantState) -> f64) = match input {
                        Input::V1 => (Analog::V1, &|s| s.battery_volts),
                        Input::V2 => (Analog::V2, &|s| s.bus_volts),
                        _ => (Analog::I, &|s| s.inverter_current),
                    };
                    let (lo, hi) = both(value);
                    let unit = if analog == Analog::I { "A" } else { "V" };
                    let (c1, c2) = (model::counts(p, analog, lo), model::counts(p, analog, hi));
                    let what = match analog {
                        Analog::V1 => "the battery",
                        Analog::V2 => "the bus",
                        Analog::I => "the inverter's current",
                    };
                    (
                        f64::from(c1.min(c2)),
                        f64::from(c1.max(c2)),
                        adc,
                        format!("{what} at {} {unit}", range(lo, hi, 2)),
                    )
                }
                Input::Ldr => {
                    let (lo, hi) = both(&|s| s.ldr_counts);
                    // Its noise is drawn afresh at every sample.
                    let noise = model::ldr_noise_counts(p);
                    (lo, hi, adc + noise, "the photoresistor's divider".into())
                }
                Input::RpmM | Input::RpmL => {
                    let (lo, hi) = both(&|s| s.wheel_rpm.abs());
                    // One hall edge, or one flag, more or less in a window.
                    let per_turn = if input == Input::RpmM {
                        model::hall_edges_per_wheel_turn(p)
                    } else {
                        1.0
                    };
                    (
                        lo,
                        hi,
                        60.0 / (per_turn * window),
                        format!("the wheel at {} rpm", range(lo, hi, 0)),
                    )
                }
            };
            let got = f64::from(word);
            if got < low - slack - 1e-9 || got > high + slack + 1e-9 {
                let unit = if matches!(input, Input::RpmM | Input::RpmL) {
                    "rpm"
                } else {
                    "counts"
                };
                let why = match input {
                    Input::RpmM | Input::RpmL => format!("one sensor edge in {rpm_window_ms} ms"),
                    Input::Ldr => "the ADC's resolution and 5 sigma of the sensor's noise".into(),
                    _ => "the ADC's resolution".into(),
                };
                wrong.push(format!(
                    "{} read {word}; {what} gives {} {unit} (± {slack:.0}, {why})",
                    input.name(),
                    range(low, high, 0),
                ));
            }
        }
        if wrong.is_empty() {
            Ok(())
        } else {
            Err(wrong.join("; "))
        }
    }
}

fn direction(reverse: bool) -> &'static str {
    if reverse {
        "counter-clockwise"
    } else {
        "clockwise"
    }
}

/// `a` or `a-b`, with `digits` decimals.
fn range(a: f64, b: f64, digits: usize) -> String {
    let (a, b) = (format!("{a:.digits$}"), format!("{b:.digits$}"));
    if a == b { a } else { format!("{a}-{b}") }
}
