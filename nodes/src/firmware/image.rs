//! The controller's register image (`docs/protocols/meb.md`, default map of the EV
//! module) and the protective-trip latch that guards its outputs.
//!
//! Both slave front ends (MEB and Modbus RTU) read and write this one image,
//! so the range checks, the order of the checks and the trip rule live here
//! once: a front end turns its request into a [`WriteSet`] and the image
//! either stores all of it or refuses it with a [`Refusal`].

pub use crate::refusal::Refusal;

/// `EA` words: V2, I, V1, RPM_M, RPM_L, LDR.
pub const EA_WORDS: usize = 6;
/// `ED` words: HALL.
pub const ED_WORDS: usize = 1;
/// `SA` words: VEL.
pub const SA_WORDS: usize = 1;
/// `SD` words: SD0 (EN, BRK, PRO, DES, FR), SD1 (CHG).
pub const SD_WORDS: usize = 2;
/// `VA` words: LDR_TH, RPM_WIN.
pub const VA_WORDS: usize = 2;
/// `VD` words: LDR_ADAPT.
pub const VD_WORDS: usize = 1;
/// `FA` words: SOC, ERRS.
pub const FA_WORDS: usize = 2;
/// `FD` words: STATUS.
pub const FD_WORDS: usize = 1;

/// `EA` addresses.
pub mod ea {
    /// DC-bus voltage, ADC counts.
    pub const V2: usize = 0;
    /// Inverter input current, ADC counts.
    pub const I: usize = 1;
    /// Battery voltage, ADC counts.
    pub const V1: usize = 2;
    /// Wheel rpm from the hall sensors.
    pub const RPM_M: usize = 3;
    /// Wheel rpm from the photoresistor.
    pub const RPM_L: usize = 4;
    /// Photoresistor divider, ADC counts.
    pub const LDR: usize = 5;
}

/// Bits of `SD0` (active low except FR) and `SD1`.
pub mod sd {
    /// SD0 bit 0: module enable, 0 = enabled.
    pub const EN: u16 = 1 << 0;
    /// SD0 bit 1: brake, 0 = applied.
    pub const BRK: u16 = 1 << 1;
    /// SD0 bit 2: boost, 0 = on.
    pub const PRO: u16 = 1 << 2;
    /// SD0 bit 3: discharge, 0 = discharging.
    pub const DES: u16 = 1 << 3;
    /// SD0 bit 4: direction, 1 = counter-clockwise.
    pub const FR: u16 = 1 << 4;
    /// The bits SD0 maps.
    pub const SD0_MASK: u16 = 0x001F;
    /// SD1 bit 0: charger, 0 = connected.
    pub const CHG: u16 = 1 << 0;
    /// The bits SD1 maps.
    pub const SD1_MASK: u16 = 0x0001;
    /// SD0 at power-up and after a trip: every function off.
    pub const SD0_OFF: u16 = 0x001F;
    /// SD1 at power-up and after a trip: charger disconnected.
    pub const SD1_OFF: u16 = 0x0001;
}

/// Bits of `FD0` STATUS.
pub mod status {
    /// The BMS cut the battery off (latched).
    pub const BATTERY_CUT_OFF: u16 = 1 << 0;
    /// The inverter's over-current protection tripped (latched).
    pub const OVER_CURRENT: u16 = 1 << 1;
    /// The brake is applied.
    pub const BRAKE: u16 = 1 << 2;
    /// Enabled with a speed set, but the wheel has not turned for 0.5 s.
    pub const STALLED: u16 = 1 << 3;
    /// The charger is pushing current into the pack.
    pub const CHARGING: u16 = 1 << 4;
    /// Turning counter-clockwise.
    pub const CCW: u16 = 1 << 5;
}

/// `VD0` bit 0: adaptive dip detector.
pub const LDR_ADAPT: u16 = 1 << 0;
/// `RPM_WIN` range (ms).
pub const RPM_WIN_RANGE: core::ops::RangeInclusive<u16> = 1..=1000;

/// The outputs and variables as the master wrote them (write-only blocks).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Settings {
    /// `SA0` VEL, DAC counts.
    pub vel: u16,
    /// `SD0` pins.
    pub sd0: u16,
    /// `SD1` pins.
    pub sd1: u16,
    /// `VA0` LDR_TH, ADC counts.
    pub ldr_threshold: u16,
    /// `VA1` RPM_WIN, ms.
    pub rpm_window_ms: u16,
    /// `VD0`.
    pub ldr_adaptive: u16,
}

impl Settings {
    /// Whether SD0 enables the module (EN low).
    pub fn enabled(&self) -> bool {
        self.sd0 & sd::EN == 0
    }
}

/// The words of one write, any of them present; stored all together or not at all.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct WriteSet {
    /// `SA0`.
    pub vel: Option<u16>,
    /// `SD0`.
    pub sd0: Option<u16>,
    /// `SD1`.
    pub sd1: Option<u16>,
    /// `VA0`.
    pub ldr_threshold: Option<u16>,
    /// `VA1`.
    pub rpm_window_ms: Option<u16>,
    /// `VD0`.
    pub ldr_adaptive: Option<u16>,
}

/// The protective-trip latch (`docs/protocols/meb.md`, "A trip latches").
///
/// A trip latches its flag and forces the outputs off. Enabling while its
/// cause persists is refused; once the cause is gone, a write that releases
/// EN followed by one that applies it clears the latch at the next loop tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Protection {
    /// Battery cut-off latched.
    pub battery: bool,
    /// Inverter over-current latched.
    pub over_current: bool,
    /// EN was written released since the trip.
    released: bool,
    /// An accepted enabling write clears the latch at the next tick.
    clear_pending: bool,
    /// The last sample showed a trip's cause (set by the loop).
    pub cause_persists: bool,
}

impl Protection {
    /// Whether a trip holds the outputs off.
    pub fn tripped(&self) -> bool {
        self.battery || self.over_current
    }

    /// Latch the trips the loop saw; `enable_stored` is the stored EN.
    pub fn latch(&mut self, battery: bool, over_current: bool, enable_stored: bool) {
        if (battery || over_current) && !self.tripped() {
            // A module that was already disabled when it tripped counts as released.
            self.released = !enable_stored;
            self.clear_pending = false;
        }
        self.battery |= battery;
        self.over_current |= over_current;
    }

    /// Clears the latch if an enabling write asked for it; returns whether it did.
    pub fn take_clear(&mut self) -> bool {
        if self.clear_pending {
            *self = Protection {
                cause_persists: self.cause_persists,
                ..Protection::default()
            };
            true
        } else {
            false
        }
    }

    /// Records an accepted SD0 write.
    fn note_sd0(&mut self, sd0: u16) {
        if !self.tripped() {
            return;
        }
        if sd0 & sd::EN != 0 {
            self.released = true;
            self.clear_pending = false;
        } else if self.released {
            self.clear_pending = true;
        }
    }
}

/// The register image: inputs and flags the loop refreshes, outputs and
/// variables the master writes.
#[derive(Debug, Clone)]
pub struct RegisterImage {
    /// `EA0`–`EA5`.
    pub inputs: [u16; EA_WORDS],
    /// `ED0`.
    pub hall: u16,
    /// `FA0` SOC, 0.1 %.
    pub soc: u16,
    /// `FA1` ERRS.
    pub errs: u16,
    /// `FD0` STATUS.
    pub status: u16,
    /// What the master wrote (acknowledged), applied at the next loop tick.
    pub stored: Settings,
    /// The trip latch.
    pub protection: Protection,
    /// Highest `VEL` (DAC full scale).
    dac_max: u16,
    /// Highest ADC reading (`LDR_TH` range).
    adc_max: u16,
}

impl RegisterImage {
    /// The image at power-up: outputs off, variables at their defaults.
    pub fn new(dac_bits: u8, adc_bits: u8, ldr_threshold: u16, rpm_window_ms: u16) -> Self {
        let full_scale = |bits: u8| ((1u32 << bits.clamp(1, 16)) - 1) as u16;
        let adc_max = full_scale(adc_bits);
        Self {
            inputs: [0; EA_WORDS],
            hall: 0,
            soc: 0,
            errs: 0,
            status: 0,
            stored: Settings {
                vel: 0,
                sd0: sd::SD0_OFF,
                sd1: sd::SD1_OFF,
                ldr_threshold: ldr_threshold.min(adc_max),
                rpm_window_ms: rpm_window_ms.clamp(*RPM_WIN_RANGE.start(), *RPM_WIN_RANGE.end()),
                ldr_adaptive: 0,
            },
            protection: Protection::default(),
            dac_max: full_scale(dac_bits),
            adc_max,
        }
    }

    /// Highest `VEL` count.
    pub fn dac_max(&self) -> u16 {
        self.dac_max
    }

    /// Checks every value of `set` (03), then whether it may be applied now
    /// (04), then stores all of it.
    pub fn store(&mut self, set: &WriteSet) -> Result<(), Refusal> {
        let within = |value: Option<u16>, ok: &dyn Fn(u16) -> bool| value.is_none_or(ok);
        let valid = within(set.vel, &|v| v <= self.dac_max)
            && within(set.sd0, &|v| v & !sd::SD0_MASK == 0)
            && within(set.sd1, &|v| v & !sd::SD1_MASK == 0)
            && within(set.ldr_threshold, &|v| v <= self.adc_max)
            && within(set.rpm_window_ms, &|v| RPM_WIN_RANGE.contains(&v))
            && within(set.ldr_adaptive, &|v| v & !LDR_ADAPT == 0);
        if !valid {
            return Err(Refusal::IllegalData);
        }
        let enabling = set.sd0.is_some_and(|v| v & sd::EN == 0);
        if enabling && self.protection.cause_persists {
            return Err(Refusal::DeviceFailure);
        }
        let s = &mut self.stored;
        s.vel = set.vel.unwrap_or(s.vel);
        s.sd0 = set.sd0.unwrap_or(s.sd0);
        s.sd1 = set.sd1.unwrap_or(s.sd1);
        s.ldr_threshold = set.ldr_threshold.unwrap_or(s.ldr_threshold);
        s.rpm_window_ms = set.rpm_window_ms.unwrap_or(s.rpm_window_ms);
        s.ldr_adaptive = set.ldr_adaptive.unwrap_or(s.ldr_adaptive);
        if let Some(sd0) = set.sd0 {
            self.protection.note_sd0(sd0);
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_refused_write_stores_nothing() {
        let mut image = RegisterImage::new(12, 12, 1933, 100);
        let before = image.stored;
        let set = WriteSet {
            vel: Some(100),
            rpm_window_ms: Some(0),
            ..WriteSet::default()
        };
        assert_eq!(image.store(&set), Err(Refusal::IllegalData));
        assert_eq!(image.stored, before);
    }

    #[test]
    fn trip_clears_only_after_release_then_enable_without_cause() {
        let mut image = RegisterImage::new(12, 12, 1933, 100);
        let enable = WriteSet {
            sd0: Some(0x001E),
            ..WriteSet::default()
        };
        let release = WriteSet {
            sd0: Some(0x001F),
            ..WriteSet::default()
        };
        image.store(&enable).unwrap();
        image.protection.cause_persists = true;
        image.protection.latch(false, true, image.stored.enabled());
        assert_eq!(image.store(&enable), Err(Refusal::DeviceFailure));
        image.protection.cause_persists = false;
        // Enabling again without releasing first does not clear it.
        image.store(&enable).unwrap();
        assert!(!image.protection.take_clear());
        image.store(&release).unwrap();
        assert!(!image.protection.take_clear());
        image.store(&enable).unwrap();
        assert!(image.protection.take_clear());
        assert!(!image.protection.tripped());
    }
}
