//! Decode throughput of point-cloud messages (issue 4 target: >= 50 M points/s on one core
//! for the common contiguous x,y,z float32 little-endian layout). Elements = points.

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use decod::io::{Encoding, MessageKind, messages::decode_cloud};

/// A ROS 1 PointCloud2 with `n` points; `fast` = x y z f32 at 0/4/8 + intensity (step 16,
/// e.g. Ouster/Hesai/most drivers), else x y z f64 behind a time field (generic path).
fn cloud(n: usize, fast: bool) -> Vec<u8> {
    let mut b = Vec::new();
    for v in [0u32, 1, 0, 5] {
        b.extend_from_slice(&v.to_le_bytes());
    }
    b.extend_from_slice(b"lidar");
    b.extend_from_slice(&1u32.to_le_bytes());
    b.extend_from_slice(&(n as u32).to_le_bytes());
    let (fields, step): (Vec<(&str, u32, u8)>, u32) = if fast {
        (
            vec![("x", 0, 7), ("y", 4, 7), ("z", 8, 7), ("intensity", 12, 7)],
            16,
        )
    } else {
        (
            vec![("t", 0, 6), ("x", 4, 8), ("y", 12, 8), ("z", 20, 8)],
            28,
        )
    };
    b.extend_from_slice(&(fields.len() as u32).to_le_bytes());
    for (name, offset, datatype) in &fields {
        b.extend_from_slice(&(name.len() as u32).to_le_bytes());
        b.extend_from_slice(name.as_bytes());
        b.extend_from_slice(&offset.to_le_bytes());
        b.push(*datatype);
        b.extend_from_slice(&1u32.to_le_bytes());
    }
    b.push(0);
    b.extend_from_slice(&step.to_le_bytes());
    b.extend_from_slice(&(step * n as u32).to_le_bytes());
    b.extend_from_slice(&(step * n as u32).to_le_bytes());
    for i in 0..n {
        let v = [i as f32 * 0.001, 1.0, -2.0];
        if fast {
            for c in v {
                b.extend_from_slice(&c.to_le_bytes());
            }
            b.extend_from_slice(&3.0f32.to_le_bytes());
        } else {
            b.extend_from_slice(&(i as u32).to_le_bytes());
            for c in v {
                b.extend_from_slice(&f64::from(c).to_le_bytes());
            }
        }
    }
    b.push(1);
    b
}

fn bench_pointcloud2(c: &mut Criterion) {
    let mut group = c.benchmark_group("pointcloud2_decode");
    for &n in &[1_000usize, 100_000, 1_000_000] {
        for fast in [true, false] {
            let msg = cloud(n, fast);
            group.throughput(Throughput::Elements(n as u64));
            let name = format!("{}_{n}", if fast { "xyz_f32_le" } else { "generic_f64" });
            group.bench_function(name, |b| {
                b.iter(|| {
                    decode_cloud(MessageKind::PointCloud2, Encoding::Ros1, &msg)
                        .map(|cloud| cloud.points.len())
                })
            });
        }
    }
    group.finish();
}

criterion_group!(benches, bench_pointcloud2);
criterion_main!(benches);
