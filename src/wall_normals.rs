//! The corridor axis from the wall's surface normals (not in the paper).
//!
//! The paper takes the axis as the principal direction of the submap (PCA, §III-A). That
//! holds when the sensor samples the wall evenly around the axis. A spinning sensor pitched
//! on its mount does not: pitched 20 deg nose down, a 16-beam sensor sees the floor ahead of
//! it and the crown behind it, the cloud is a band running diagonally through the tube, and
//! its principal direction leans 11 deg off the axis (median over a simulated horseshoe
//! run; 0.04 deg for the same sensor level). The contour refinement ([`crate::axis::refine_axis`])
//! cannot take that back: each angle of the section is seen at one axial position only, so a
//! free contour absorbs the tilt (ten refinements still left 2.3 deg), and the descriptors of
//! the two passes, unrolled about different wrong axes, did not overlap (no loop in 541
//! queries).
//!
//! A tube's wall is parallel to its axis wherever it is sampled, so every wall normal is
//! perpendicular to the axis, however unevenly the wall is sampled: the axis is the direction
//! least represented among the normals (the eigenvector of the smallest eigenvalue of
//! `sum n n^T`). Normals come from the covariance of the points in cubic cells of
//! [`CELL_VOXELS`] voxels (a planar patch: smallest eigenvalue below [`MAX_CELL_FLATNESS`] of
//! the middle one), on an even stride of at most [`NORMAL_POINTS`] points (the cells then
//! `sqrt(stride)` wider, to hold as many points).

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use crate::axis::{along, eigen_descending};

/// Cell edge in voxels: a voxel-filtered wall puts up to 16 points in a cell across it, and
/// the cell (4 voxels: 0.19 m in a 5 m tunnel, 1.6 cm in a 0.4 m pipe with the automatic
/// configuration's voxel of about radius / 55) stays flat on the curved wall.
pub const CELL_VOXELS: f64 = 4.0;

/// A cell is a wall patch when its points' smallest covariance eigenvalue is below this share
/// of the middle one (thickness below half its width): rough rock (1.5 cm relief in a 0.19 m
/// cell) passes at about 0.07, an edge or a corner where two surfaces meet does not.
pub const MAX_CELL_FLATNESS: f64 = 0.25;

/// ... and wide both ways: the middle eigenvalue at least this share of the largest. A sparse
/// spinning sensor leaves cells whose points lie along one or two scan lines, whose smallest
/// two eigenvalues are both near zero and whose normal is then any direction across the line.
pub const MIN_CELL_WIDTH: f64 = 0.1;

/// Points in a cell needed for its normal.
pub const MIN_CELL_POINTS: usize = 6;

/// Planar cells needed for an axis.
pub const MIN_CELLS: usize = 30;

/// The normals must leave one direction clearly out: the smallest eigenvalue of their
/// (unit-trace) scatter below this share of the middle one. Normals of a closed room spread
/// over three directions alike and give no axis; the pitched 16-beam horseshoe's submaps,
/// whose visible facets lean towards the sensor, measured 0.31.
pub const MAX_AXIS_SPREAD: f64 = 0.5;

/// ... and turn about it: the middle eigenvalue at least this (normals spread over at least
/// ~26 deg of the section). Normals of a single plane (a floor seen alone) point one way and
/// leave the axis anywhere in that plane.
pub const MIN_SECTION_SPREAD: f64 = 0.05;

/// Points the normals are computed from (an even stride over larger clouds): 50,000 points
/// give thousands of cells, and a 64-beam submap (200-400k points) costs no more than a
/// 16-beam one.
pub const NORMAL_POINTS: usize = 50_000;

/// Point moments of one cell: count, sum, sum of outer products (upper triangle).
#[derive(Clone, Copy, Default)]
struct Moments {
    n: usize,
    sum: [f64; 3],
    outer: [f64; 6],
}

impl Moments {
    fn add(&mut self, p: [f64; 3]) {
        self.n += 1;
        for (s, v) in self.sum.iter_mut().zip(p) {
            *s += v;
        }
        let [x, y, z] = p;
        for (o, v) in self
            .outer
            .iter_mut()
            .zip([x * x, x * y, x * z, y * y, y * z, z * z])
        {
            *o += v;
        }
    }

    /// The cell's unit normal if its points lie on a plane ([`MAX_CELL_FLATNESS`]).
    fn normal(&self) -> Option<Vector3<f64>> {
        if self.n < MIN_CELL_POINTS {
            return None;
        }
        let n = self.n as f64;
        let m = Vector3::from(self.sum) / n;
        let [xx, xy, xz, yy, yz, zz] = self.outer.map(|v| v / n);
        let cov = Matrix3::new(xx, xy, xz, xy, yy, yz, xz, yz, zz) - m * m.transpose();
        let (values, normal) = smallest_first(&cov)?;
        let flat = values[0] <= MAX_CELL_FLATNESS * values[1];
        // Points along one scan line lie on a line: their "normal" is any direction across it.
        let wide = values[1] >= MIN_CELL_WIDTH * values[2] && values[1] > 0.0;
        (flat && wide).then_some(normal)
    }
}

/// Eigenvalues smallest first and the eigenvector of the smallest; `None` if not finite.
fn smallest_first(m: &Matrix3<f64>) -> Option<([f64; 3], Vector3<f64>)> {
    let (values, vectors) = eigen_descending(m);
    let least = vectors[2];
    (values.iter().all(|v| v.is_finite()) && least.iter().all(|v| v.is_finite()))
        .then_some(([values[2], values[1], values[0]], least))
}

/// The corridor axis of `points` from their wall normals (module docs), unit, oriented so
/// that `axis . forward >= 0`; `None` when the cloud has too few wall patches
/// ([`MIN_CELLS`]), its normals leave no direction out ([`MAX_AXIS_SPREAD`]) or do not turn
/// about one ([`MIN_SECTION_SPREAD`]), and for a
/// `voxel_m` that is not a positive finite length.
pub fn wall_normal_axis(points: &[[f32; 3]], voxel_m: f64, forward: [f64; 3]) -> Option<[f64; 3]> {
    let stride = points.len().div_ceil(NORMAL_POINTS).max(1);
    // A stride of k leaves 1/k of a wall's points: cells sqrt(k) wider hold as many.
    let cell = CELL_VOXELS * voxel_m * (stride as f64).sqrt();
    if !(cell.is_finite() && cell > 0.0) || points.is_empty() {
        return None;
    }
    let mut cells: HashMap<[i64; 3], Moments> = HashMap::new();
    for p in points.iter().step_by(stride) {
        let q = p.map(f64::from);
        if !q.iter().all(|v| v.is_finite()) {
            continue;
        }
        let key = q.map(|v| (v / cell).floor() as i64);
        // Moments about the cell's corner: sums of small numbers, no cancellation.
        let local = [0, 1, 2].map(|k| q[k] - key[k] as f64 * cell);
        cells.entry(key).or_default().add(local);
    }
    // Summed in key order: a hash map's order changes from one map to the next, and with it
    // the last bits of the sum, so the same cloud gave axes (and, through the contour, radii
    // and landmarks) that differed between runs.
    let mut cells: Vec<([i64; 3], Moments)> = cells.into_iter().collect();
    cells.sort_unstable_by_key(|(key, _)| *key);
    let mut scatter = Matrix3::zeros();
    let mut patches = 0usize;
    for normal in cells.iter().filter_map(|(_, m)| m.normal()) {
        scatter += normal * normal.transpose();
        patches += 1;
    }
    if patches < MIN_CELLS {
        return None;
    }
    let (values, least) = smallest_first(&(scatter / patches as f64))?;
    if values[0] > MAX_AXIS_SPREAD * values[1] || values[1] < MIN_SECTION_SPREAD {
        return None;
    }
    Some(along(least.try_normalize(1e-12)?, forward))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::axis::estimate_axis;

    /// A 5 m tube along `axis` sampled the way a pitched spinning sensor samples it: the lower
    /// half of the section ahead of the sensor, the upper half behind it (`lopsided`), or
    /// evenly; 2 cm of deterministic relief.
    fn tube(axis: Vector3<f64>, lopsided: bool) -> Vec<[f32; 3]> {
        let up = Vector3::z();
        let e1 = (up - axis * axis.dot(&up)).normalize();
        let e2 = axis.cross(&e1);
        let (r, mut out) = (2.5, Vec::new());
        for i in 0..400 {
            let z = -6.0 + 12.0 * i as f64 / 400.0;
            for j in 0..180 {
                let th = std::f64::consts::TAU * j as f64 / 180.0;
                let upper = th.sin() > 0.0;
                if lopsided && (upper == (z > 0.0)) {
                    continue;
                }
                let rr = r + 0.02 * ((7.0 * th).sin() * (3.1 * z).cos());
                let p = axis * z + (e1 * th.sin() + e2 * th.cos()) * rr;
                out.push([p.x as f32, p.y as f32, p.z as f32]);
            }
        }
        out
    }

    fn angle_deg(a: [f64; 3], b: Vector3<f64>) -> f64 {
        Vector3::from(a)
            .normalize()
            .dot(&b)
            .abs()
            .min(1.0)
            .acos()
            .to_degrees()
    }

    #[test]
    fn a_lopsided_tube_leans_pca_but_not_the_normals() {
        let axis = Vector3::new(1.0, 0.2, 0.05).normalize();
        let points = tube(axis, true);
        let pca = estimate_axis(&points, [1.0, 0.0, 0.0]).unwrap();
        assert!(
            angle_deg(pca.axis, axis) > 5.0,
            "PCA is the estimator that leans"
        );
        let normals = wall_normal_axis(&points, 0.05, [1.0, 0.0, 0.0]).unwrap();
        assert!(
            angle_deg(normals, axis) < 0.3,
            "{}",
            angle_deg(normals, axis)
        );
        assert!(Vector3::from(normals).x > 0.0, "oriented with forward");
    }

    #[test]
    fn the_same_cloud_gives_the_same_bits_every_time() {
        // Each call builds its own hash map, whose order is drawn afresh: summed in that
        // order, 2 of 6 calls on one probe submap differed in the last bits.
        let points = tube(Vector3::new(1.0, 0.2, 0.05).normalize(), true);
        let first = wall_normal_axis(&points, 0.05, [1.0, 0.0, 0.0]).unwrap();
        for _ in 0..8 {
            let again = wall_normal_axis(&points, 0.05, [1.0, 0.0, 0.0]).unwrap();
            assert_eq!(again.map(f64::to_bits), first.map(f64::to_bits));
        }
    }

    #[test]
    fn an_evenly_sampled_tube_gives_the_same_axis_either_way() {
        let axis = Vector3::new(1.0, -0.1, 0.02).normalize();
        let points = tube(axis, false);
        let normals = wall_normal_axis(&points, 0.05, [-1.0, 0.0, 0.0]).unwrap();
        assert!(angle_deg(normals, axis) < 0.3);
        assert!(Vector3::from(normals).x < 0.0, "oriented with forward");
    }

    #[test]
    fn a_plane_or_a_room_gives_no_axis() {
        let floor: Vec<[f32; 3]> = (0..200)
            .flat_map(|i| (0..100).map(move |j| [i as f32 * 0.05, j as f32 * 0.05, 0.0]))
            .collect();
        assert!(wall_normal_axis(&floor, 0.05, [1.0, 0.0, 0.0]).is_none());
        // A 4 m cube's six faces: normals along all three directions alike.
        let mut room = Vec::new();
        for i in 0..80 {
            for j in 0..80 {
                let (u, v) = (i as f32 * 0.05 - 2.0, j as f32 * 0.05 - 2.0);
                for s in [-2.0f32, 2.0] {
                    room.extend([[s, u, v], [u, s, v], [u, v, s]]);
                }
            }
        }
        assert!(wall_normal_axis(&room, 0.05, [1.0, 0.0, 0.0]).is_none());
    }

    #[test]
    fn degenerate_input_gives_none_not_a_panic() {
        assert!(wall_normal_axis(&[], 0.05, [1.0, 0.0, 0.0]).is_none());
        let nan = vec![[f32::NAN, 0.0, 0.0]; 100];
        assert!(wall_normal_axis(&nan, 0.05, [1.0, 0.0, 0.0]).is_none());
        let points = tube(Vector3::x(), false);
        for voxel in [0.0, -1.0, f64::NAN, f64::INFINITY] {
            assert!(wall_normal_axis(&points, voxel, [1.0, 0.0, 0.0]).is_none());
        }
    }
}
