//! Motion compensation's inner loop (paper §IV-A.2): every point of a submap's scans moved
//! into the anchor frame, gated by range and keyed by voxel, for [`crate::submap`]'s voxel
//! filter. A 64-beam window is 0.8-1.5 M points, and this loop was an eighth of a whole run's
//! CPU on such logs: written per point with nalgebra, it ran as scalar SSE2 (the wheels are
//! built for baseline x86-64), a division and a branch per coordinate.
//!
//! Here the points go through in chunks: one branch-free pass computes every point's
//! position, gates and key (the compiler vectorises it; [`pulp`] dispatch compiles it for
//! the CPU's AVX2 or AVX-512 at run time), a second pass keeps the rows that pass. The
//! arithmetic is the per-point code's, operation for operation (IEEE: the same bits on every
//! instruction set; Rust never fuses a multiply and an add on its own), so every submap is
//! bit-for-bit the one the per-point code built (tested against it below).

use crate::geometry::Pose;
use crate::scan::Scan;

/// Points per chunk: the chunk's positions, keys and gates stay in L1.
const CHUNK: usize = 256;

/// One scan's move into the anchor frame and the range gates, as plain numbers.
#[derive(Clone, Copy, Debug)]
struct Motion {
    /// `T_anchor_body`'s rotation, row-major.
    rotation: [[f64; 3]; 3],
    /// `T_anchor_body`'s translation.
    translation: [f64; 3],
    /// Squared minimum range from the point's own sensor.
    min_r2: f64,
    /// Squared range from the own sensor beyond which the point is beyond `max_r2` from the
    /// anchor too.
    beyond_r2: f64,
    /// Squared maximum range from the anchor.
    max_r2: f64,
}

impl Motion {
    fn new(anchor_from_world: &Pose, scan: &Scan, (min_r2, max_r2): (f64, f64)) -> Self {
        let anchor_from_body = (anchor_from_world * scan.world_from_body).to_homogeneous();
        let rotation = std::array::from_fn(|i| std::array::from_fn(|j| anchor_from_body[(i, j)]));
        let translation = std::array::from_fn(|i| anchor_from_body[(i, 3)]);
        let shift = anchor_from_body.fixed_view::<3, 1>(0, 3).norm();
        Self {
            rotation,
            translation,
            min_r2,
            // A point farther from its sensor than the range plus the sensor's distance from
            // the anchor (and a micrometre for rounding) lies beyond the range from the anchor.
            beyond_r2: (max_r2.sqrt() + shift + 1e-6).powi(2),
            max_r2,
        }
    }
}

/// Every `stride`-th point of `scans` (from offset `k % stride` in scan `k`) that lies at
/// least `min_r2.sqrt()` from its own sensor and at most `max_r2.sqrt()` from the anchor, in
/// the anchor frame (f32: a micrometre at 10 m; the submap stores f32 centroids anyway), with
/// its `key` (computed on the f64 position).
pub(crate) fn accumulate<K: Copy + Default>(
    scans: &[Scan],
    anchor_from_world: &Pose,
    ranges: (f64, f64),
    stride: usize,
    key: impl Fn(f64, f64, f64) -> K,
) -> Vec<(K, [f32; 3])> {
    let stride = stride.max(1);
    let total: usize = scans
        .iter()
        .map(|s| s.points_in_body.len() / stride + 1)
        .sum();
    let mut rows = Vec::with_capacity(total);
    let mut strided = Vec::new();
    for (k, scan) in scans.iter().enumerate() {
        let motion = Motion::new(anchor_from_world, scan, ranges);
        let points = if stride == 1 {
            &scan.points_in_body[..]
        } else {
            strided.clear();
            strided.extend(scan.points_in_body.iter().skip(k % stride).step_by(stride));
            &strided[..]
        };
        pulp::Arch::new().dispatch(ScanRows {
            points,
            motion: &motion,
            key: &key,
            rows: &mut rows,
        });
    }
    rows
}

/// [`accumulate`]'s work on one scan, compiled for the CPU's instruction set.
struct ScanRows<'a, K, F> {
    points: &'a [[f32; 3]],
    motion: &'a Motion,
    key: &'a F,
    rows: &'a mut Vec<(K, [f32; 3])>,
}

impl<K: Copy + Default, F: Fn(f64, f64, f64) -> K> pulp::WithSimd for ScanRows<'_, K, F> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let mut moved = [(K::default(), [0.0f32; 3]); CHUNK];
        let mut kept = [false; CHUNK];
        let mut out = [(K::default(), [0.0f32; 3]); CHUNK];
        for chunk in self.points.chunks(CHUNK) {
            let n = chunk.len();
            for (p, (row, keep)) in chunk.iter().zip(moved[..n].iter_mut().zip(&mut kept[..n])) {
                let (q, k, inside) = move_point(p, self.motion, self.key);
                (*row, *keep) = ((k, q), inside);
            }
            // Branch-free compaction: every row is written, the count moves on past the kept
            // ones (a branch per point mispredicts wherever the range gate cuts a scan).
            let mut count = 0;
            for (row, keep) in moved[..n].iter().zip(&kept[..n]) {
                out[count] = *row;
                count += usize::from(*keep);
            }
            self.rows.extend_from_slice(&out[..count]);
        }
    }
}

/// One point in the anchor frame, its key and whether it passes the range gates; the
/// operations and their order are those of `rotation * body + translation` and
/// `norm_squared` in nalgebra (row by row: `(r0 x + r1 y) + r2 z`, then `+ t`).
#[inline(always)]
fn move_point<K>(
    p: &[f32; 3],
    m: &Motion,
    key: &impl Fn(f64, f64, f64) -> K,
) -> ([f32; 3], K, bool) {
    let (x, y, z) = (f64::from(p[0]), f64::from(p[1]), f64::from(p[2]));
    let r2 = x * x + y * y + z * z;
    let row = |i: usize| {
        let r = &m.rotation[i];
        r[0] * x + r[1] * y + r[2] * z + m.translation[i]
    };
    let (qx, qy, qz) = (row(0), row(1), row(2));
    let q2 = qx * qx + qy * qy + qz * qz;
    let keep = (r2 >= m.min_r2) & (r2 <= m.beyond_r2) & (q2 <= m.max_r2);
    ([qx as f32, qy as f32, qz as f32], key(qx, qy, qz), keep)
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion, Vector3};

    /// The per-point code this module replaced (nalgebra, one point at a time).
    fn per_point<K>(
        scans: &[Scan],
        anchor_from_world: &Pose,
        (min_r2, max_r2): (f64, f64),
        stride: usize,
        key: impl Fn(f64, f64, f64) -> K,
    ) -> Vec<(K, [f32; 3])> {
        let mut rows = Vec::new();
        for (k, scan) in scans.iter().enumerate() {
            let anchor_from_body = (anchor_from_world * scan.world_from_body).to_homogeneous();
            let rotation = anchor_from_body.fixed_view::<3, 3>(0, 0).into_owned();
            let translation = anchor_from_body.fixed_view::<3, 1>(0, 3).into_owned();
            let beyond = (max_r2.sqrt() + translation.norm() + 1e-6).powi(2);
            for p in scan.points_in_body.iter().skip(k % stride).step_by(stride) {
                let body = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                let r2 = body.norm_squared();
                if r2 < min_r2 || r2 > beyond {
                    continue;
                }
                let q = rotation * body + translation;
                if q.norm_squared() > max_r2 {
                    continue;
                }
                rows.push((key(q.x, q.y, q.z), [q.x as f32, q.y as f32, q.z as f32]));
            }
        }
        rows
    }

    /// Scans of pseudo-random points (some nearer than the minimum range, some beyond the
    /// maximum) from poses that move and turn, so that every gate and every rounding is hit.
    fn scans() -> Vec<Scan> {
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut uniform = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..7)
            .map(|k| {
                let points = (0..1000 + 37 * k)
                    .map(|_| std::array::from_fn(|_| ((uniform() - 0.5) * 30.0) as f32))
                    .collect();
                Scan {
                    stamp: 0.1 * k as f64,
                    points_in_body: points,
                    world_from_body: Pose::from_parts(
                        Translation3::new(0.37 * k as f64, 0.01 * k as f64, -0.02),
                        UnitQuaternion::from_euler_angles(0.01 * k as f64, -0.02, 0.3 * k as f64),
                    ),
                    specific_force_in_body: None,
                }
            })
            .collect()
    }

    #[test]
    fn rows_are_bit_for_bit_the_per_point_codes() {
        let scans = scans();
        let anchor = scans[3].world_from_body.inverse();
        let voxel = 0.047;
        let key = |x: f64, y: f64, z: f64| [x, y, z].map(|v| crate::submap::voxel_index(v, voxel));
        for stride in [1, 3] {
            for ranges in [(0.25, 144.0), (4.0, 49.0)] {
                let fast = accumulate(&scans, &anchor, ranges, stride, key);
                let slow = per_point(&scans, &anchor, ranges, stride, key);
                assert!(!fast.is_empty() && fast.len() < scans.len() * 1000 / stride);
                assert_eq!(fast.len(), slow.len());
                for (a, b) in fast.iter().zip(&slow) {
                    assert_eq!(a.0, b.0);
                    assert_eq!(a.1.map(f32::to_bits), b.1.map(f32::to_bits));
                }
            }
        }
    }
}
