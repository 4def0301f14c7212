//! The light-sensor node (id 02): one paper marker per wheel turn darkens a
//! photoresistor; the node times light→dark edges on its 20 ms sampling grid.

use crate::node::{Firmware, Node};
use protocols::modbus::Exception;
use protocols::time::{SimDuration, SimTime};

use super::{Access, LIGHT_ID, PortConfig, REG_LIGHT_VALUE, RegisterMap, SlavePort, millis};

/// Slots of the smoothing ring.
const RING_LEN: usize = 5;

/// Settings of the light-sensor node; the defaults are the project's firmware.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LightConfig {
    /// Serial port settings and faults.
    pub port: PortConfig,
    /// Sampling period.
    pub sample_period: SimDuration,
    /// Below this the cell is dark (V).
    pub dark_below_volts: f64,
    /// ADC full scale (counts): `volts = counts × reference / full scale`
    /// (the firmware divides by 1023).
    pub adc_full_scale: u16,
    /// ADC reference (V).
    pub adc_reference_volts: f64,
    /// No edge for this long: rpm is 0 and timing restarts.
    pub edge_timeout: SimDuration,
    /// Marks on the wheel: a turn is this many edges, so rpm = 60000 / (marks × Δt).
    pub marks_per_turn: u32,
}

impl Default for LightConfig {
    fn default() -> Self {
        LightConfig {
            port: PortConfig::default(),
            sample_period: SimDuration::from_millis(20),
            dark_below_volts: 3.0,
            adc_full_scale: 1023,
            adc_reference_volts: 5.0,
            edge_timeout: SimDuration::from_secs(5),
            marks_per_turn: 1,
        }
    }
}

impl LightConfig {
    /// The project's firmware, written for the marks the wheel of `light` carries.
    pub fn for_sensor(light: &plant::light::LightParams) -> Self {
        LightConfig {
            marks_per_turn: light.flags.max(1),
            ..LightConfig::default()
        }
    }
}

/// The register: the current (smoothed) wheel rpm.
#[derive(Debug, Clone)]
struct LightRegisters {
    rpm: f64,
}

impl RegisterMap for LightRegisters {
    fn access(&self, addr: u16) -> Option<Access> {
        (addr == REG_LIGHT_VALUE).then_some(Access::Read)
    }

    fn read(&self, _addr: u16) -> u16 {
        // `(uint16_t)(rpm * 100)`: truncated (saturating for nonsense values).
        (self.rpm * 100.0) as u16
    }

    fn write(&mut self, _addr: u16, _value: u16) -> Result<(), Exception> {
        Err(Exception::IllegalFunction)
    }
}

/// The light-sensor node (id 02) of the Controller_network project. It drives
/// nothing: its [`Firmware::loop_tick`] returns idle actuators, which an engine
/// must not apply over the motor node's.
#[derive(Debug, Clone)]
pub struct LightNode {
    config: LightConfig,
    port: SlavePort,
    registers: LightRegisters,
    dark: bool,
    /// `millis()` of the last light→dark edge; `None` after a timeout: the
    /// next edge only restarts timing. At boot it is 0, as the firmware's
    /// `lastRoundTime` starts: a first edge within 5 s is timed from reset.
    last_edge_ms: Option<u64>,
    /// When timing (re)started or the last edge came: the 5 s timeout runs from here.
    timeout_from_ms: u64,
    raw_rpm: f64,
    last_interval_ms: Option<u64>,
    edges: u64,
    ring: [f64; RING_LEN],
    ring_filled: usize,
    ring_next: usize,
}

impl LightNode {
    /// A light-sensor node at power-up: rpm 0, waiting for a first edge.
    pub fn new(config: LightConfig) -> Self {
        LightNode {
            config,
            port: SlavePort::new(LIGHT_ID, config.port),
            registers: LightRegisters { rpm: 0.0 },
            dark: false,
            last_edge_ms: Some(0),
            timeout_from_ms: 0,
            raw_rpm: 0.0,
            last_interval_ms: None,
            edges: 0,
            ring: [0.0; RING_LEN],
            ring_filled: 0,
            ring_next: 0,
        }
    }

    /// The current rpm, smoothed once the ring is full (register `0006` / 100).
    pub fn rpm(&self) -> f64 {
        self.registers.rpm
    }

    /// The value register `0006` reads now.
    pub fn register_value(&self) -> u16 {
        self.registers.read(REG_LIGHT_VALUE)
    }

    /// The last unsmoothed rpm, `60000 / Δt` of the last timed edge.
    pub fn raw_rpm(&self) -> f64 {
        self.raw_rpm
    }

    /// Δt (ms) between the last two timed edges.
    pub fn last_interval_ms(&self) -> Option<u64> {
        self.last_interval_ms
    }

    /// Light→dark edges seen since power-up (timed or not).
    pub fn edges(&self) -> u64 {
        self.edges
    }

    /// Injected fault: corrupt the CRC of every reply from now on (or stop).
    pub fn set_corrupt_reply_crc(&mut self, corrupt: bool) {
        self.config.port.corrupt_reply_crc = corrupt;
        self.port.config.corrupt_reply_crc = corrupt;
    }

    /// One 20 ms sample of the analog pin at `now`.
    fn sample(&mut self, now: SimTime, ldr_counts: u16) {
        let now_ms = millis(now);
        let volts = f64::from(ldr_counts) * self.config.adc_reference_volts
            / f64::from(self.config.adc_full_scale);
        let dark = volts < self.config.dark_below_volts;
        if dark && !self.dark {
            self.edges += 1;
            if let Some(last) = self.last_edge_ms {
                let interval = now_ms.saturating_sub(last);
                if interval > 0 {
                    let marks = f64::from(self.config.marks_per_turn.max(1));
                    self.raw_rpm = 60_000.0 / (marks * interval as f64);
                    self.registers.rpm = self.raw_rpm;
                    self.last_interval_ms = Some(interval);
                }
            }
            self.last_edge_ms = Some(now_ms);
            self.timeout_from_ms = now_ms;
        }
        self.dark = dark;
        let timeout_ms = self.config.edge_timeout.0 / (protocols::time::TICKS_PER_SECOND / 1_000);
        if now_ms.saturating_sub(self.timeout_from_ms) >= timeout_ms {
            // The firmware keeps forcing 0 every sample until an edge comes.
            self.registers.rpm = 0.0;
            self.raw_rpm = 0.0;
            self.last_edge_ms = None;
        }
        self.smooth();
    }

    /// The current rpm enters the ring; once it is full, the rpm becomes
    /// 0.3 × rpm + 0.7 × mean(ring), and that is what the next sample stores.
    fn smooth(&mut self) {
        if let Some(slot) = self.ring.get_mut(self.ring_next) {
            *slot = self.registers.rpm;
        }
        self.ring_next = (self.ring_next + 1) % RING_LEN;
        self.ring_filled = (self.ring_filled + 1).min(RING_LEN);
        if self.ring_filled == RING_LEN {
            let mean = self.ring.iter().sum::<f64>() / RING_LEN as f64;
            self.registers.rpm = 0.3 * self.registers.rpm + 0.7 * mean;
        }
    }
}

impl Default for LightNode {
    fn default() -> Self {
        Self::new(LightConfig::default())
    }
}

impl Node for LightNode {
    fn handle_bytes(&mut self, now: SimTime, bytes: &[u8]) {
        self.port.receive(&mut self.registers, now, bytes);
    }

    fn handle_timeout(&mut self, now: SimTime) {
        self.port.handle_timeout(now);
    }

    fn poll_transmit(&mut self, _now: SimTime, buf: &mut [u8]) -> Option<usize> {
        self.port.poll_transmit(buf)
    }

    fn poll_timeout(&self) -> Option<SimTime> {
        self.port.poll_timeout()
    }

    fn force_refusal(&mut self, refusal: Option<crate::firmware::Refusal>) -> bool {
        self.port.forced = refusal.map(crate::firmware::Refusal::modbus);
        true
    }
}

impl Firmware for LightNode {
    fn loop_period(&self) -> SimDuration {
        self.config.sample_period
    }

    fn loop_tick(&mut self, now: SimTime, sensors: &plant::Sensors) -> plant::Actuators {
        self.sample(now, sensors.ldr_counts);
        // The sensor node drives nothing on the bench.
        plant::Actuators::default()
    }
}
