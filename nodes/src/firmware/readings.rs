//! What the controller reads now, as a master would get it by reading every
//! input block (`EA`, `ED`, `FA`, `FD`), with the analog words converted to
//! volts and amperes by the controller's own scaling (`docs/protocols/meb.md`:
//! "the scaling to volts, amperes and rpm lives in the node's configuration").

use plant::params::SensingParams;

use super::image::{EA_WORDS, RegisterImage, ea};

/// The controller's readings: its register words and what they mean.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Readings {
    /// `EA0..EA5` as a master reads them: V2, I, V1, RPM_M, RPM_L, LDR.
    pub ea: [u16; EA_WORDS],
    /// `ED0` HALL: hall code in bits 0–2, the light detector's dark bit 3.
    pub hall: u16,
    /// `FA0` SOC (0.1 % per count) and `FA1` ERRS.
    pub soc: u16,
    pub errs: u16,
    /// `FD0` STATUS.
    pub status: u16,
    /// V1 in volts at the battery (through its divider).
    pub battery_volts: f64,
    /// V2 in volts on the DC bus (through its divider).
    pub bus_volts: f64,
    /// I in amperes into the inverter (the current sensor's offset removed).
    pub inverter_amps: f64,
}

impl Readings {
    /// The image's input words, converted with `sensing`.
    pub fn of(image: &RegisterImage, sensing: &SensingParams) -> Self {
        let bits = sensing.adc_bits.clamp(1, 16);
        let full = f64::from((1u32 << bits) - 1);
        // The plant's converter rounds `pin / reference * full`: its inverse.
        let pin = |word: u16| f64::from(word) / full * sensing.adc_reference_volts;
        let inputs = &image.inputs;
        let amps_per_volt = if sensing.current_volts_per_amp != 0.0 {
            1.0 / sensing.current_volts_per_amp
        } else {
            0.0
        };
        Self {
            ea: *inputs,
            hall: image.hall,
            soc: image.soc,
            errs: image.errs,
            status: image.status,
            battery_volts: pin(inputs[ea::V1]) * sensing.battery_divider,
            bus_volts: pin(inputs[ea::V2]) * sensing.bus_divider,
            inverter_amps: (pin(inputs[ea::I]) - sensing.current_zero_volts) * amps_per_volt,
        }
    }

    /// `RPM_M`: wheel rpm from the hall sensors.
    pub fn hall_rpm(&self) -> u16 {
        self.ea[ea::RPM_M]
    }

    /// `RPM_L`: wheel rpm from the photoresistor.
    pub fn light_rpm(&self) -> u16 {
        self.ea[ea::RPM_L]
    }

    /// `ED0` bit 3: the light detector sees the flag.
    pub fn flag_dark(&self) -> bool {
        self.hall & (1 << 3) != 0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_convert_back_to_what_the_plant_measured() {
        let sensing = SensingParams::default();
        let mut image = RegisterImage::new(12, 12, 1933, 100);
        image.inputs[ea::V1] = sensing.counts(40.0 / sensing.battery_divider);
        image.inputs[ea::V2] = sensing.counts(44.0 / sensing.bus_divider);
        image.inputs[ea::I] =
            sensing.counts(sensing.current_zero_volts + 1.5 * sensing.current_volts_per_amp);
        image.inputs[ea::RPM_L] = 1499;
        image.hall = 0b1101;
        let r = Readings::of(&image, &sensing);
        // Within half a count of each converter.
        assert!(
            (r.battery_volts - 40.0).abs() < 0.007,
            "{}",
            r.battery_volts
        );
        assert!((r.bus_volts - 44.0).abs() < 0.007, "{}", r.bus_volts);
        assert!((r.inverter_amps - 1.5).abs() < 0.007, "{}", r.inverter_amps);
        assert_eq!(r.light_rpm(), 1499);
        assert!(r.flag_dark());
    }
}
