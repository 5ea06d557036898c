//! Extraction on a 100k-point pipe submap (target <= 20 ms, DESIGN.md "Targets"), per stage
//! and end to end, with element throughput. `cargo bench --bench extraction`.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use decod::DecodConfig;
use decod::axis::estimate_axis;
use decod::extract::extract_landmarks;
use decod::submap::Submap;

/// A 3 m pipe of radius 0.3 m along a tilted axis, with two grooves, deterministic.
fn pipe_submap(n: usize) -> Submap {
    let (yaw, pitch) = (0.3_f64, 0.15_f64);
    let axis = [
        yaw.cos() * pitch.cos(),
        yaw.sin() * pitch.cos(),
        pitch.sin(),
    ];
    let u = [-yaw.sin(), yaw.cos(), 0.0];
    let v = [
        axis[1] * u[2] - axis[2] * u[1],
        axis[2] * u[0] - axis[0] * u[2],
        axis[0] * u[1] - axis[1] * u[0],
    ];
    let points = (0..n)
        .map(|i| {
            let x = -1.5 + 3.0 * (i as f64 + 0.5) / n as f64;
            let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
            let noise = 3e-4 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
            let groove = if (x - 0.37).abs() < 0.006 || (x + 0.8).abs() < 0.006 {
                0.003
            } else {
                0.0
            };
            let r = 0.3 + noise + groove;
            std::array::from_fn(|k| {
                (axis[k] * x + r * (t.cos() * u[k] + t.sin() * v[k]) + [0.5, -0.3, 0.2][k]) as f32
            })
        })
        .collect();
    Submap::from_points(0.0, points, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
        .unwrap_or_else(|e| unreachable!("{e}"))
}

/// A 20 m horseshoe tunnel (3 m vault, flat floor 2 m below the centre) with 10 cm steel
/// arches every 1.2 m: the polar-contour path of the tunnel preset.
fn horseshoe_submap(n: usize) -> Submap {
    let points = (0..n)
        .map(|i| {
            let x = -10.0 + 20.0 * (i as f64 + 0.5) / n as f64;
            let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
            let c = t.cos();
            let noise = 0.01 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
            let on_floor = c > 2.0 / 3.0;
            let arch = !on_floor && ((x + 10.0).rem_euclid(1.2) - 0.6).abs() < 0.075;
            let r = if on_floor {
                2.0 / c
            } else {
                3.0 - if arch { 0.1 } else { 0.0 }
            };
            [
                x as f32,
                ((r + noise) * t.sin()) as f32,
                (-(r + noise) * c) as f32,
            ]
        })
        .collect();
    Submap::from_points(0.0, points, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
        .unwrap_or_else(|e| unreachable!("{e}"))
}

fn bench(c: &mut Criterion) {
    let cfg = DecodConfig::pipe();
    let mut group = c.benchmark_group("extraction");
    for n in [10_000usize, 100_000] {
        let submap = pipe_submap(n);
        group.throughput(Throughput::Elements(n as u64));
        group.bench_function(format!("extract_landmarks/{n}"), |b| {
            b.iter(|| extract_landmarks(std::hint::black_box(&submap), &cfg))
        });
        group.bench_function(format!("pca_axis/{n}"), |b| {
            b.iter(|| estimate_axis(&submap.points_in_anchor, [1.0, 0.0, 0.0]))
        });
    }
    let submap = horseshoe_submap(100_000);
    let tunnel = DecodConfig::tunnel();
    group.throughput(Throughput::Elements(100_000));
    group.bench_function("extract_landmarks_horseshoe/100000", |b| {
        b.iter(|| extract_landmarks(std::hint::black_box(&submap), &tunnel))
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
