//! Masters: the supervisor that closes the speed loop over the bus.
//!
//! [`Supervisor`] polls one or more EV-module slaves over MEB or Modbus RTU and
//! runs a PI speed loop per slave: every poll cycle it reads the six analog
//! inputs (MEB `EA 00 06`, RTU FC 04 from 0, quantity 6), takes the hall rpm
//! (`RPM_M`) or the light-sensor rpm (`RPM_L`) as the measurement, and writes
//! the controller's output to `VEL` (MEB `SA 00`, RTU holding register 0) when
//! it changed; on MEB, at the addresses of the slave's I/O map
//! ([`MebLayout`], the default being the protocol page's). Like every node it is a sans-IO state machine: it sees only `now`
//! and bytes, so the virtual-time engine and a real-time one drive it alike.

pub mod image_server;
mod layout;
mod pi;
mod supervisor;
pub(crate) mod wire;

pub use layout::{LayoutError, MebLayout, SWITCHES, TranslateError};
pub use pi::{SpeedPi, VEL_MAX, VEL_MIN};
pub use supervisor::{
    ForwardError, LoopState, PollCounters, StatusWords, Supervisor, WriteOutcome, WriteTicket,
};

use protocols::time::{SimDuration, SimTime};

/// The wire protocol the supervisor speaks to its slaves.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Protocol {
    /// MEB, the lab's ASCII protocol (`docs/protocols/meb.md`).
    Meb,
    /// Standard Modbus RTU with the map of `docs/protocols/modbus-map.md`.
    ModbusRtu,
}

/// Which of the module's two speed readings closes the loop.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub enum SpeedSource {
    /// `RPM_M` (EA 3 / input register 3): the motor's hall sensors.
    #[default]
    Hall,
    /// `RPM_L` (EA 4 / input register 4): the photoresistor, with its limits.
    Light,
}

impl SpeedSource {
    /// Index of this reading among the six analog inputs read each cycle.
    pub const fn input_index(self) -> usize {
        match self {
            SpeedSource::Hall => 3,
            SpeedSource::Light => 4,
        }
    }

    /// The reading's name in the I/O map.
    pub const fn name(self) -> &'static str {
        match self {
            SpeedSource::Hall => "RPM_M",
            SpeedSource::Light => "RPM_L",
        }
    }
}

/// Whether the supervisor computes `VEL` or holds a value the user set.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum LoopMode {
    /// The PI computes `VEL` from the set point and the measurement.
    Closed,
    /// `VEL` is held at this many counts (clamped to 4095); the PI is idle.
    Open {
        /// The manual `VEL`, DAC counts.
        vel: u16,
    },
}

/// One step of a set-point schedule: from `at` on, the set point is `rpm`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SetPointStep {
    /// When the step takes effect.
    pub at: SimTime,
    /// Wheel speed asked for, rpm.
    pub rpm: f64,
}

/// The digital outputs written once at start-up, before the first read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct StartupOutputs {
    /// `SD0`, active low: bit 0 EN, 1 BRK, 2 PRO, 3 DES, 4 FR.
    pub sd0: u16,
    /// `SD1`, active low: bit 0 CHG.
    pub sd1: u16,
}

impl StartupOutputs {
    /// Module enabled (EN = 0), brake released (BRK = 1), boost off (PRO = 1),
    /// not discharging (DES = 1), clockwise (FR = 0); charger disconnected.
    pub const ENABLED_BRAKE_RELEASED: StartupOutputs = StartupOutputs {
        sd0: 0x000E,
        sd1: 0x0001,
    };
}

/// One slave and its speed loop.
#[derive(Debug, Clone, PartialEq)]
pub struct SlaveLoopConfig {
    /// MEB id (1–99) or Modbus unit id (1–247).
    pub id: u8,
    /// Which rpm reading is the measurement.
    pub speed_source: SpeedSource,
    /// Proportional gain, `VEL` counts per rpm.
    pub kp: f64,
    /// Integral gain, `VEL` counts per rpm per second.
    pub ki: f64,
    /// Closed loop, or a manual `VEL`.
    pub mode: LoopMode,
    /// Set-point steps; before the first one the set point is 0 rpm.
    pub set_points: Vec<SetPointStep>,
}

impl SlaveLoopConfig {
    /// A closed loop on the hall rpm with modest gains and no set point yet.
    pub fn new(id: u8) -> Self {
        Self {
            id,
            speed_source: SpeedSource::Hall,
            kp: 0.5,
            ki: 2.0,
            mode: LoopMode::Closed,
            set_points: Vec::new(),
        }
    }

    /// The scheduled set point at `now`: the last step at or before `now`
    /// (steps are kept sorted by [`Supervisor::new`]).
    pub fn set_point_at(&self, now: SimTime) -> f64 {
        let after = self.set_points.partition_point(|step| step.at <= now);
        match after.checked_sub(1).and_then(|i| self.set_points.get(i)) {
            Some(step) => step.rpm,
            None => 0.0,
        }
    }
}

/// How the supervisor polls.
#[derive(Debug, Clone, PartialEq)]
pub struct SupervisorConfig {
    /// MEB or Modbus RTU.
    pub protocol: Protocol,
    /// The slaves, polled in this order every cycle.
    pub slaves: Vec<SlaveLoopConfig>,
    /// From one cycle's start to the next one's (default 10 ms); a cycle that
    /// overruns is followed at once (after the gap).
    pub poll_period: SimDuration,
    /// Wait after a reply (or a timeout) before the next request (default 0).
    pub inter_frame_gap: SimDuration,
    /// From the request's last stop bit to giving up on the reply (default 100 ms).
    pub reply_timeout: SimDuration,
    /// Extra attempts after a missing or bad reply before the request is lost (default 2).
    pub retries: u8,
    /// When the first request goes out (default: at once).
    pub first_poll_at: SimTime,
    /// Outputs written to each slave before its first read; `None` writes nothing.
    pub startup_outputs: Option<StartupOutputs>,
    /// The line silence that ends a partial RTU reply (default 1.75 ms, the
    /// Modbus serial line value above 19 200 baud); on every protocol, also how
    /// long the line must be quiet before a request follows stray bytes (the
    /// tail of a reply given up on mid-frame), so a retry never talks over it.
    pub rtu_silence: SimDuration,
    /// Every this many poll cycles, also read each slave's status words
    /// (`ED 00`, `FA 00`–`01`, `FD 00`) for the image a server answers from.
    /// MEB only; 0 (the default) never, which keeps a cycle one read and one write.
    pub status_every: u32,
    /// Where the slaves' signals sit on MEB (their I/O map); the default is
    /// `docs/protocols/meb.md`'s. Modbus RTU takes only the default.
    pub layout: MebLayout,
}

impl SupervisorConfig {
    /// The defaults for `protocol` and `slaves`: a 10 ms poll period, the
    /// 100 ms reply timeout of `docs/protocols/meb.md`, two retries.
    pub fn new(protocol: Protocol, slaves: Vec<SlaveLoopConfig>) -> Self {
        Self {
            protocol,
            slaves,
            poll_period: SimDuration::from_millis(10),
            inter_frame_gap: SimDuration::ZERO,
            reply_timeout: SimDuration::from_millis(100),
            retries: 2,
            first_poll_at: SimTime::ZERO,
            startup_outputs: Some(StartupOutputs::ENABLED_BRAKE_RELEASED),
            rtu_silence: SimDuration::from_micros(1_750),
            status_every: 0,
            layout: MebLayout::default(),
        }
    }
}

/// Why a [`SupervisorConfig`] cannot run.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SupervisorConfigError {
    /// No slave to poll.
    #[error("the supervisor has no slaves to poll")]
    NoSlaves,
    /// An id the protocol cannot address (0 is broadcast, never answered).
    #[error("slave id {id} is outside {min}..={max} for this protocol")]
    IdOutOfRange {
        /// The id.
        id: u8,
        /// Lowest id allowed.
        min: u8,
        /// Highest id allowed.
        max: u8,
    },
    /// Two loops on one slave would fight over its `VEL`.
    #[error("slave id {0} appears twice")]
    DuplicateId(u8),
    /// A gain or set point that is not a finite number.
    #[error("slave {id}: {field} is not a finite number")]
    NotFinite {
        /// The slave.
        id: u8,
        /// `kp`, `ki` or `set_points`.
        field: &'static str,
    },
    /// An I/O map is MEB's: a Modbus RTU bus has its own register map.
    #[error("an I/O map places MEB's signals; a Modbus RTU bus uses docs/protocols/modbus-map.md")]
    MapNeedsMeb,
    /// The map lacks a signal the loop needs.
    #[error("{0}")]
    Map(LayoutError),
}
