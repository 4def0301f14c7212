//! A plant sample as the recording's writer serialises it: its protobuf
//! (`twin.PlantSensors`, `twin_recording::topics`) written by hand, field by
//! field, in the order `plant::Sensors` serialises them. A run records one
//! for each module every sample period, the largest part of its recording.

use serde::Serialize;
use twin_recording::proto::{ProtoOut, Protobuf};
use twin_recording::record::Deferred;

/// One module's sensors, handed to the recording's writer as they are.
#[derive(Debug, Clone, Copy, Serialize)]
#[serde(transparent)]
pub struct PlantSample(pub plant::Sensors);

impl Protobuf for PlantSample {
    const SCHEMA: &'static str = "twin.PlantSensors";

    fn write_protobuf(&self, m: &mut ProtoOut<'_>) {
        let s = &self.0;
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
    fn write_protobuf(&self, schema: &str, out: &mut ProtoOut<'_>) -> bool {
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
    fn a_plant_sample_is_the_schema_encoder_s_bytes_field_for_field() {
        let schema = topics::proto_schema("/plant/ev1/sensors").expect("protobuf");
        assert_eq!(schema.name(), PlantSample::SCHEMA);
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
            let mut by_schema = Vec::new();
            twin_recording::proto::encode(&schema, &sample, &mut by_schema).expect("fits");
            let mut by_hand = Vec::new();
            assert!(Deferred::write_protobuf(
                &sample,
                PlantSample::SCHEMA,
                &mut ProtoOut::new(&mut by_hand)
            ));
            assert_eq!(by_hand, by_schema, "{trip:?}");
        }
        let mut nothing = Vec::new();
        assert!(!Deferred::write_protobuf(
            &PlantSample(s),
            "twin.Frame",
            &mut ProtoOut::new(&mut nothing)
        ));
        assert!(nothing.is_empty());
    }
}
