//! Extraction on a 100k-point pipe submap (target <= 20 ms, DESIGN.md "Targets"), per stage
//! and end to end, with element throughput, and on one that looks at the pipe's end face (the
//! retry of `decod::corridor_end`, and the face search every submap now gets), and on a horseshoe sampled lopsidedly, as a pitched
//! sensor samples it (the axis decision of `decod::wall_normals`); and the accumulation of a 64-beam window into a
//! submap (scans moved into the anchor frame, voxel-filtered). `cargo bench --bench extraction`.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use decod::DecodConfig;
use decod::axis::estimate_axis;
use decod::corridor_end::face_in_view;
use decod::extract::extract_landmarks;
use decod::geometry::Pose;
use decod::scan::Scan;
use decod::submap::Submap;
use decod::wall_normals::wall_normal_axis;
use nalgebra::{Translation3, UnitQuaternion};

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

/// [`horseshoe_submap`] sampled the way a spinning sensor pitched nose down samples it: the
/// lower part of the section ahead of the sensor (x > 0), the upper part behind it; `n`
/// points kept.
fn lopsided_horseshoe_submap(n: usize) -> Submap {
    let all = horseshoe_submap(2 * n);
    let points: Vec<[f32; 3]> = all
        .points_in_anchor
        .into_iter()
        .filter(|p| (p[2] < -0.5) == (p[0] > 0.0))
        .take(n)
        .collect();
    Submap::from_points(0.0, points, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
        .unwrap_or_else(|e| unreachable!("{e}"))
}

/// A 64-beam spinning sensor's window in a 5 m tunnel: `scans` scans of 512 columns x 64
/// beams over 45 degrees (32,768 points), 0.1 m apart along the axis, a little yaw; the
/// walls at 2.5 m with a 2 cm ripple, the floor 1.5 m below the sensor.
fn spinning_window(scans: usize) -> Vec<Scan> {
    let points: Vec<[f32; 3]> = (0..512)
        .flat_map(|c| (0..64).map(move |b| (c, b)))
        .map(|(c, b)| {
            let az = c as f64 * std::f64::consts::TAU / 512.0;
            let el = (b as f64 / 63.0 - 0.5) * 45f64.to_radians();
            let dir = [az.cos() * el.cos(), az.sin() * el.cos(), el.sin()];
            let across = (dir[1].powi(2) + dir[2].powi(2)).sqrt().max(1e-9);
            let wall = 2.5 + 0.02 * (7.0 * az).sin();
            let floor = if dir[2] < 0.0 {
                1.5 / -dir[2]
            } else {
                f64::INFINITY
            };
            let range = (wall / across).min(floor).min(40.0);
            [
                (dir[0] * range) as f32,
                (dir[1] * range) as f32,
                (dir[2] * range) as f32,
            ]
        })
        .collect();
    (0..scans)
        .map(|k| Scan {
            stamp: k as f64 * 0.1,
            points_in_body: points.clone(),
            world_from_body: Pose::from_parts(
                Translation3::new(0.1 * k as f64, 0.0, 0.0),
                UnitQuaternion::from_euler_angles(0.0, 0.0, 0.002 * k as f64),
            ),
            specific_force_in_body: Some([0.0, 0.0, 9.81]),
        })
        .collect()
}

/// What a forward-looking sensor sees of a pipe ending ahead (`decod::corridor_end`): 0.6 m
/// of wall (radius 0.3 m, a groove at 0.37 m; half the points) and an end face at 0.7 m (the
/// other half): the whole cloud fails the corridor test, the part before the face passes.
fn pipe_end_submap(n: usize) -> Submap {
    let half = n / 2;
    let wall = (0..half).map(|i| {
        let x = 0.1 + 0.6 * (i as f64 + 0.5) / half as f64;
        let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
        let noise = 3e-4 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
        let r = 0.3 + noise + if (x - 0.37).abs() < 0.006 { 0.003 } else { 0.0 };
        [x as f32, (r * t.sin()) as f32, (-r * t.cos()) as f32]
    });
    let face = (0..n - half).map(|i| {
        let r = 0.3 * ((i as f64 + 0.5) / (n - half) as f64).sqrt();
        let t = i as f64 * 2.399_963_229_7;
        [0.7f32, (r * t.sin()) as f32, (-r * t.cos()) as f32]
    });
    Submap::from_points(
        0.0,
        wall.chain(face).collect(),
        [0.0, 0.0, -1.0],
        [1.0, 0.0, 0.0],
    )
    .unwrap_or_else(|e| unreachable!("{e}"))
}

fn bench(c: &mut Criterion) {
    // The automatic configuration's window for the simulated horseshoe with 64 beams
    // (4.7 cm voxels, 12.16 m range, 24 scans): 0.79 M points into ~0.1 M voxels.
    let mut window_cfg = DecodConfig::tunnel().submap;
    (window_cfg.voxel_m, window_cfg.max_range_m) = (0.0474, 12.16);
    let window = spinning_window(24);
    let mut group = c.benchmark_group("accumulation");
    group.throughput(Throughput::Elements(24 * 32_768));
    group.bench_function("from_scans/64-beam-24-scans", |b| {
        b.iter(|| Submap::from_scans(std::hint::black_box(&window), 12, &window_cfg))
    });
    group.finish();

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
    // The retry before an end face: the whole-cloud steps, then the face search on the
    // guesses and the steps again on the part before it.
    let end = pipe_end_submap(100_000);
    let found = extract_landmarks(&end, &cfg);
    assert!(
        found.diagnostics.end_face && found.landmarks.len() == 1,
        "the benchmark must take the end-face path: {:?}",
        found.rejections
    );
    group.throughput(Throughput::Elements(100_000));
    group.bench_function("extract_landmarks_end_face/100000", |b| {
        b.iter(|| extract_landmarks(std::hint::black_box(&end), &cfg))
    });
    // The face as a reference (`decod_rs.end_faces`): looked for in every submap along its
    // settled axis, found in this one.
    assert!(
        found.diagnostics.face_in_view.is_some(),
        "the face must be found"
    );
    let slab = cfg.descriptor.half_length_m * 2.0 / cfg.descriptor.rows as f64;
    group.bench_function("face_in_view/100000", |b| {
        b.iter(|| {
            face_in_view(
                std::hint::black_box(&end.points_in_anchor),
                [1.0, 0.0, 0.0],
                true,
                slab,
            )
        })
    });
    let submap = horseshoe_submap(100_000);
    let tunnel = DecodConfig::tunnel();
    group.throughput(Throughput::Elements(100_000));
    group.bench_function("extract_landmarks_horseshoe/100000", |b| {
        b.iter(|| extract_landmarks(std::hint::black_box(&submap), &tunnel))
    });
    // The axis decision where the refinement does not settle (`decod::wall_normals`): PCA
    // leans on the lopsided cloud, the normals and the contour find the axis.
    let lopsided = lopsided_horseshoe_submap(100_000);
    let pca = estimate_axis(&lopsided.points_in_anchor, [1.0, 0.0, 0.0])
        .unwrap_or_else(|e| unreachable!("{e}"));
    let found = extract_landmarks(&lopsided, &tunnel);
    assert!(
        pca.axis[0] < 3f64.to_radians().cos()
            && found.diagnostics.axis[0] > 1f64.to_radians().cos(),
        "the benchmark must take the axis decision: PCA {:?}, found {:?}",
        pca.axis,
        found.diagnostics.axis
    );
    group.bench_function("extract_landmarks_lopsided_horseshoe/100000", |b| {
        b.iter(|| extract_landmarks(std::hint::black_box(&lopsided), &tunnel))
    });
    group.bench_function("wall_normal_axis/100000", |b| {
        b.iter(|| {
            wall_normal_axis(
                std::hint::black_box(&lopsided.points_in_anchor),
                tunnel.submap.voxel_m,
                [1.0, 0.0, 0.0],
            )
        })
    });
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
