//! How fast the bench simulates, and where the time goes.
//!
//! `cargo bench -p plant` — the `module/one_simulated_second` figure is the
//! wall time of one simulated second: its inverse is the real-time factor.

use criterion::{Criterion, criterion_group, criterion_main};
use plant::converter::Converter;
use plant::light::LightSensor;
use plant::motor::{Drive, Motor};
use plant::wheel::Wheel;
use plant::{Actuators, EvModule, PlantParams};
use std::hint::black_box;

fn module(c: &mut Criterion) {
    let mut g = c.benchmark_group("module");
    for preset in ["vemodule", "controller-network"] {
        let p = PlantParams::preset(preset).expect("preset");
        let act = Actuators {
            enable: true,
            vel_volts: 3.0,
            ..Default::default()
        };
        let mut m = EvModule::new(&p, 1);
        g.bench_function(format!("{preset}/one_simulated_second"), |b| {
            b.iter(|| {
                for _ in 0..1000 {
                    black_box(m.step(1e-3, &act));
                }
            })
        });
    }
    g.finish();
}

fn parts(c: &mut Criterion) {
    let p = PlantParams::vemodule();
    let mut g = c.benchmark_group("part");
    let mut wheel = Wheel::new(&p.wheel, 0.0);
    g.bench_function("wheel_rapier_step", |b| {
        b.iter(|| black_box(wheel.step(5e-3, 0.05, false)))
    });
    let mut motor = Motor::new(&p.motor);
    let drive = Drive {
        enabled: true,
        duty: 0.6,
        reverse: false,
        bus_volts: 37.0,
        shaft_speed: 200.0,
    };
    g.bench_function("motor_substep", |b| {
        b.iter(|| black_box(motor.step(1e-3, &drive)))
    });
    let mut conv = Converter::new(&p.converter, 37.0);
    g.bench_function("converter_substep", |b| {
        b.iter(|| black_box(conv.step(1e-3, Some((37.0, 0.15)), 3.0, false, false)))
    });
    let mut light = LightSensor::new(&p.light, 1);
    let mut angle = 0.0;
    g.bench_function("light_substep", |b| {
        b.iter(|| {
            light.step(0.0, 1e-3, angle, angle + 0.25);
            angle += 0.25;
            black_box(light.adc_counts())
        })
    });
    g.finish();
}

criterion_group!(benches, module, parts);
criterion_main!(benches);
