//! A plant sample as the recording's writer serialises it: its protobuf
//! (`twin.PlantSensors`, `twin/recording/proto/twin/plant_sensors.proto`)
//! as prost writes the type made from that file, every field of
//! `plant::Sensors`, written field by field (`protobuf::wire`).
//! A run records one for each module every sample period, the largest part
//! of its recording.

use serde::Serialize;
use twin_recording::protobuf::Protobuf;
#[cfg(test)]
use twin_recording::protobuf::twin::{PlantSensors, plant_sensors};
use twin_recording::protobuf::wire::Fields;
use twin_recording::record::Deferred;

/// One module's sensors, handed to the recording's writer as they are.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(transparent)]
pub struct PlantSample(pub plant::Sensors);

impl Protobuf for PlantSample {
    const SCHEMA: &'static str = twin_recording::topics::PLANT_SENSORS_SCHEMA;

    /// The bytes prost writes for [`PlantSample::as_message`] (a test holds
    /// it to them), written field by field: see [`Fields`] for why.
    fn write_protobuf(&self, out: &mut Vec<u8>) {
        let s = &self.0;
        let m = &mut Fields::new(out);
        m.double(1, s.time_s);
        m.double(2, s.battery_volts);
        m.double(3, s.bus_volts);
        m.double(4, s.inverter_current);
        m.double(5, s.battery_current);
        m.double(6, s.soc);
        m.bool(7, s.charging);
        if let Some(trip) = s.bms_trip {
            m.str(8, bms_trip_name(trip));
        }
        m.uint(9, s.battery_counts.into());
        m.uint(10, s.bus_counts.into());
        m.uint(11, s.current_counts.into());
        m.double(12, s.motor_current);
        m.bool(13, s.motor_tripped);
        m.double(14, s.motor_rpm);
        m.nested(15, |m| {
            let shaft = &s.shaft;
            m.uint(1, shaft.hall.into());
            m.uint(2, shaft.hall_edges);
            m.double(3, shaft.last_hall_edge_at);
            m.bool(4, shaft.encoder_a);
            m.bool(5, shaft.encoder_b);
            m.sint(6, shaft.encoder_count);
            m.double(7, shaft.last_encoder_edge_at);
        });
        m.double(16, s.wheel_rpm);
        m.double(17, s.wheel_angle);
        m.bool(18, s.brake_applied);
        m.double(19, s.ldr_volts);
        m.uint(20, s.ldr_counts.into());
        m.bool(21, s.flag_in_beam);
        m.nested(22, |m| {
            let e = &s.energy;
            let energies = [
                e.battery_out,
                e.converter_loss,
                e.bleeder_loss,
                e.copper_loss,
                e.friction_loss,
                e.brake_loss,
                e.kinetic,
                e.capacitor,
                e.magnetic,
            ];
            for (number, joules) in (1..).zip(energies) {
                m.double(number, joules);
            }
        });
    }
}

#[cfg(test)]
impl PlantSample {
    /// The sample as the type made from `plant_sensors.proto`: what prost
    /// writes for it is what [`PlantSample::write_protobuf`] must write.
    fn as_message(&self) -> PlantSensors {
        let s = &self.0;
        let shaft = &s.shaft;
        let e = &s.energy;
        PlantSensors {
            time_s: Some(s.time_s),
            battery_volts: Some(s.battery_volts),
            bus_volts: Some(s.bus_volts),
            inverter_current: Some(s.inverter_current),
            battery_current: Some(s.battery_current),
            soc: Some(s.soc),
            charging: Some(s.charging),
            bms_trip: s.bms_trip.map(|t| bms_trip_name(t).to_string()),
            battery_counts: Some(s.battery_counts.into()),
            bus_counts: Some(s.bus_counts.into()),
            current_counts: Some(s.current_counts.into()),
            motor_current: Some(s.motor_current),
            motor_tripped: Some(s.motor_tripped),
            motor_rpm: Some(s.motor_rpm),
            shaft: Some(plant_sensors::Shaft {
                hall: Some(shaft.hall.into()),
                hall_edges: Some(shaft.hall_edges),
                last_hall_edge_at: Some(shaft.last_hall_edge_at),
                encoder_a: Some(shaft.encoder_a),
                encoder_b: Some(shaft.encoder_b),
                encoder_count: Some(shaft.encoder_count),
                last_encoder_edge_at: Some(shaft.last_encoder_edge_at),
            }),
            wheel_rpm: Some(s.wheel_rpm),
            wheel_angle: Some(s.wheel_angle),
            brake_applied: Some(s.brake_applied),
            ldr_volts: Some(s.ldr_volts),
            ldr_counts: Some(s.ldr_counts.into()),
            flag_in_beam: Some(s.flag_in_beam),
            energy: Some(plant_sensors::Energy {
                battery_out: Some(e.battery_out),
                converter_loss: Some(e.converter_loss),
                bleeder_loss: Some(e.bleeder_loss),
                copper_loss: Some(e.copper_loss),
                friction_loss: Some(e.friction_loss),
                brake_loss: Some(e.brake_loss),
                kinetic: Some(e.kinetic),
                capacitor: Some(e.capacitor),
                magnetic: Some(e.magnetic),
            }),
        }
    }
}

/// The trip's name as serde writes the variant.
fn bms_trip_name(trip: plant::battery::BmsTrip) -> &'static str {
    use plant::battery::BmsTrip;
    match trip {
        BmsTrip::UnderVoltage => "UnderVoltage",
        BmsTrip::OverVoltage => "OverVoltage",
        BmsTrip::OverCurrent => "OverCurrent",
        BmsTrip::ShortCircuit => "ShortCircuit",
    }
}

impl Deferred for PlantSample {
    fn write_protobuf(&self, schema: &str, out: &mut Vec<u8>) -> bool {
        if schema != Self::SCHEMA {
            return false;
        }
        Protobuf::write_protobuf(self, out);
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use plant::battery::BmsTrip;
    use twin_recording::topics;

    #[test]
    fn a_plant_sample_reads_back_as_its_json_field_for_field() {
        let schema = topics::proto_schema("/plant/ev1/sensors").expect("protobuf");
        assert_eq!(schema.full_name(), PlantSample::SCHEMA);
        let mut s = plant::Sensors {
            time_s: 1.25,
            battery_volts: 12.345678901234567,
            bus_volts: 23.9,
            inverter_current: -0.5,
            battery_current: 1.5,
            soc: 0.87,
            charging: true,
            bms_trip: None,
            battery_counts: 4095,
            bus_counts: 127,
            current_counts: 128,
            motor_current: -3.25,
            motor_tripped: true,
            motor_rpm: -1500.0,
            wheel_rpm: 1499.0,
            wheel_angle: 1e9,
            brake_applied: true,
            ldr_volts: 0.0,
            ldr_counts: 3280,
            flag_in_beam: true,
            ..plant::Sensors::default()
        };
        s.shaft.hall = 5;
        s.shaft.hall_edges = u64::from(u32::MAX) + 7;
        s.shaft.last_hall_edge_at = f64::NAN;
        s.shaft.encoder_a = true;
        s.shaft.encoder_count = -41;
        s.shaft.last_encoder_edge_at = 0.125;
        s.energy.battery_out = 10.0;
        s.energy.kinetic = 0.5;
        s.energy.magnetic = 1e-9;
        let trips = [
            None,
            Some(BmsTrip::UnderVoltage),
            Some(BmsTrip::OverVoltage),
            Some(BmsTrip::OverCurrent),
            Some(BmsTrip::ShortCircuit),
        ];
        for (trip, sample) in trips
            .into_iter()
            .zip([s, plant::Sensors::default()].iter().cycle())
        {
            let sample = PlantSample(plant::Sensors {
                bms_trip: trip,
                ..*sample
            });
            let mut bytes = Vec::new();
            assert!(Deferred::write_protobuf(
                &sample,
                PlantSample::SCHEMA,
                &mut bytes
            ));
            // Byte for byte what prost writes for the `.proto` file's type.
            let mut by_prost = Vec::new();
            twin_recording::protobuf::append(&sample.as_message(), &mut by_prost);
            assert_eq!(bytes, by_prost, "{trip:?}");
            // Every field, the trip absent as `null` and NaN as `null`, as
            // a JSON recording held them.
            let json = serde_json::to_value(sample).unwrap();
            assert_eq!(
                twin_recording::protobuf::to_value(&schema, &bytes).unwrap(),
                json,
                "{trip:?}"
            );
            // The fields in number order, one byte of tag each below 16: the
            // first is `time_s` (1, a double), the last `energy` (22, a
            // message), as the hand-written encoder of earlier twins wrote them.
            assert_eq!(bytes[0], 0x09);
            assert_eq!(&bytes[bytes.len() - 9 * 9 - 3..][..3], &[0xb2, 0x01, 81]);
        }
        let mut nothing = Vec::new();
        assert!(!Deferred::write_protobuf(
            &PlantSample(s),
            "twin.Frame",
            &mut nothing
        ));
        assert!(nothing.is_empty());
    }
}
