//! Submaps that look at the end of the corridor (not in the paper).
//!
//! A forward-looking sensor approaching a tunnel's end face (a blind end, a shaft wall, a
//! pipe's end cap) sees a stretch of wall and, beyond it, the face: a plane across the axis
//! that holds a third to two thirds of the submap's points. The cloud is then no longer
//! elongated (its principal directions are a mix of the axis and the face) and the contour
//! fit fails on the face's points, so the last metres of a run gave no landmark: in the
//! simulated 6 m and 9 m shield tunnels and the 10 m horseshoe with the forward sensor, the
//! last 2-4 submaps of the return (`not_elongated` at singular-value ratios 1.03-1.08,
//! `contour_misfit` at 22-72 % inliers), 6-16 m with no loop and no boundary track, which
//! is where the endpoint error was left.
//!
//! The face shows itself along any rough guess of the axis as a slab of the axial histogram
//! holding many times the points of a slab of wall ([`SPIKE_RATIO`]). Its points fit a plane
//! whose normal is the axis (to the degree the face is square to the corridor); along that
//! axis the points beyond the face's near side are dropped, and what is left is an ordinary
//! stretch of corridor that the usual steps (contour fit, corridor test) accept or reject.
//! `crate::extract` tries this only on a submap the usual steps rejected, so no submap
//! that was accepted before changes.
//!
//! The face is also a reference along the axis ([`face_in_view`]): every submap is searched
//! for one (along its settled axis, or, when it is no corridor, along its heading and
//! principal direction), and its distance from the anchor, seen from consecutive anchors of
//! a pass, measures their displacement the way a tracked boundary does
//! (`decod_rs.end_faces`). Near the face the wall ahead is too short a stub for a boundary
//! seen twice, so before this the last 9-26 m of a forward sensor's return were measured by
//! nothing.

use crate::axis::{angle_deg, estimate_axis};

/// A slab of the axial histogram is an end face when it holds at least this many times the
/// median slab's points: a wall slab of the simulated shield seen by the forward sensor holds
/// 1,200-2,500 points of a submap, the end face 12,600-28,000.
pub const SPIKE_RATIO: f64 = 4.0;

/// ... and at least this share of the submap's points (a dense arch face or a cable tray
/// across the section is not the end of the corridor).
pub const SPIKE_SHARE: f64 = 0.1;

/// The face's points must be planar: the smallest standard deviation of the slab's points at
/// most this fraction of the middle one (the face is metres wide and centimetres thick).
pub const MAX_FACE_THICKNESS: f64 = 0.15;

/// The face is looked for on an even stride of at most this many points (the cut is then
/// applied to all of them): a submap holds 0.05-1.5 M, and a rejected 1 M-point room took
/// 128 ms to look through on every point, 10 ms for its PCA alone.
pub const DETECTION_POINTS: usize = 50_000;

/// Rounds of (face slab, face normal): in the unit test a guess 3 degrees off ends 1.09
/// degrees off after one round, 0.36 after two and 0.02 after three.
const NORMAL_ROUNDS: usize = 3;

/// The corridor part of `points` (anchor frame, the sensor at the origin) when an end face
/// is in view along the guess `axis` (unit), and the axis measured as the face's normal
/// (oriented like the guess); `None` when no slab of width `slab_m` is a face, or when what
/// is left has a face too (a closed room). Points within one slab of the face, and beyond
/// it, are dropped.
pub fn trim_end_face(
    points: &[[f32; 3]],
    axis: [f64; 3],
    slab_m: f64,
) -> Option<(Vec<[f32; 3]>, [f64; 3])> {
    if points.len() < 3 || slab_m.is_nan() || slab_m <= 0.0 {
        return None;
    }
    let sample = strided(points);
    let (face, normal) = settled_face(&sample, axis, slab_m)?;
    let along = |p: &[f32; 3]| dot3(p, &normal);
    // Where the face is along the measured axis: the median of its slab's points (ahead of
    // the sensor when positive, behind it when negative).
    let face_z: Vec<f64> = sample
        .iter()
        .map(along)
        .filter(|&z| in_slab(z, face, slab_m))
        .collect();
    let median = median(face_z)?;
    let kept: Vec<[f32; 3]> = if median > 0.0 {
        points
            .iter()
            .filter(|p| along(p) < median - slab_m)
            .copied()
            .collect()
    } else {
        points
            .iter()
            .filter(|p| along(p) > median + slab_m)
            .copied()
            .collect()
    };
    // A second face on the other side closes the space at both ends: a room or a chamber,
    // not a corridor seen up to its end.
    if kept.len() < 3 || face_slab(&strided(&kept), normal, slab_m).is_some() {
        return None;
    }
    Some((kept, normal))
}

/// A face seen in an accepted submap is used only when square to the corridor: at most this
/// angle (deg) between its normal and the submap's axis (the simulated ends are square; the
/// normal of one measured from 3 deg off ends within 0.02 deg, the unit test below).
pub const MAX_FACE_TILT_DEG: f64 = 3.0;

/// ... and only when it closes the corridor: at most this share of the points lies more than
/// a slab beyond it (an arch or a bulkhead with the corridor behind it is not an end). The
/// simulated ends have none behind them, but a submap stitched on odometry that is 15 % short
/// smears the face over the metres it travelled: 0.9-2.6 % of the points of the held-out 9 m
/// shield's last submaps lay beyond it before the rebuild.
pub const MAX_BEYOND_SHARE: f64 = 0.05;

/// An end face in view of a submap (`face_in_view`).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EndFace {
    /// The foot of the anchor's origin (the sensor) on the face, anchor frame, metres: the
    /// face's normal times its signed distance along it.
    pub point: [f64; 3],
    /// The face's unit normal, oriented like the axis it was found along.
    pub normal: [f64; 3],
    /// The face's share of the points it was looked for on.
    pub share: f64,
}

/// The end face a submap sees along `axis` (unit), if any: a slab holding many times the
/// points of a slab of wall ([`SPIKE_RATIO`], [`SPIKE_SHARE`]), planar, and with the corridor
/// on one side of it only ([`MAX_BEYOND_SHARE`]). `settled`: `axis` is the submap's corridor
/// axis, and the face must be square to it ([`MAX_FACE_TILT_DEG`]); otherwise it is a guess
/// (the sensor's heading, a principal direction of a submap that is not a corridor). Either
/// way [`NORMAL_ROUNDS`] rounds of slab and plane fit take it to the face's normal, as in
/// [`trim_end_face`]. The face's position is the median of its points along its normal. A face
/// seen from consecutive anchors of one pass measures their displacement along the axis the
/// way a tracked boundary does (`decod_rs.end_faces`; not in the paper).
pub fn face_in_view(
    points: &[[f32; 3]],
    axis: [f64; 3],
    settled: bool,
    slab_m: f64,
) -> Option<EndFace> {
    if points.len() < 3 || slab_m.is_nan() || slab_m <= 0.0 {
        return None;
    }
    let sample = strided(points);
    let (face, normal) = settled_face(&sample, axis, slab_m)?;
    if settled && angle_deg(normal, axis) > MAX_FACE_TILT_DEG {
        return None;
    }
    let depth = |p: &[f32; 3]| dot3(p, &normal);
    let rough = median(
        sample
            .iter()
            .map(depth)
            .filter(|&z| in_slab(z, face, slab_m))
            .collect(),
    )?;
    // The face alone: its points within half a slab of the first estimate.
    let on_face: Vec<f64> = sample
        .iter()
        .map(depth)
        .filter(|z| (z - rough).abs() < 0.5 * slab_m)
        .collect();
    let share = on_face.len() as f64 / sample.len() as f64;
    let plane = median(on_face)?;
    let below = sample.iter().filter(|p| depth(p) < plane - slab_m).count();
    let above = sample.iter().filter(|p| depth(p) > plane + slab_m).count();
    if (below.min(above) as f64) > MAX_BEYOND_SHARE * sample.len() as f64 {
        return None;
    }
    let point = normal.map(|v| v * plane);
    point.iter().all(|v| v.is_finite()).then_some(EndFace {
        point,
        normal,
        share,
    })
}

/// The face's slab (lower edge) and normal (oriented like `axis`, [`face_normal`]) from the
/// guess `axis`: the slab is chosen along the current axis, so a guess a few degrees off
/// selects a tilted strip of the wall beside the face, and [`NORMAL_ROUNDS`] rounds of slab
/// and plane fit converge on the face's normal.
fn settled_face(sample: &[[f32; 3]], axis: [f64; 3], slab_m: f64) -> Option<(f64, [f64; 3])> {
    let (mut face, mut normal) = (face_slab(sample, axis, slab_m)?, axis);
    for _ in 0..NORMAL_ROUNDS {
        normal = face_normal(sample, normal, face, slab_m)?;
        face = face_slab(sample, normal, slab_m)?;
    }
    Some((face, normal))
}

/// The lower edge of the densest slab along `axis` when it is a face ([`SPIKE_RATIO`],
/// [`SPIKE_SHARE`]).
fn face_slab(points: &[[f32; 3]], axis: [f64; 3], slab_m: f64) -> Option<f64> {
    let z: Vec<f64> = points.iter().map(|p| dot3(p, &axis)).collect();
    let lo = z.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = z.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !(lo.is_finite() && hi.is_finite()) || (hi - lo) / slab_m > 1e5 {
        return None;
    }
    let n = ((hi - lo) / slab_m) as usize + 1;
    let mut counts = vec![0usize; n];
    for &v in &z {
        counts[(((v - lo) / slab_m) as usize).min(n - 1)] += 1;
    }
    let (peak, &most) = counts.iter().enumerate().max_by_key(|&(_, c)| *c)?;
    let typical = median(
        counts
            .iter()
            .filter(|&&c| c > 0)
            .map(|&c| c as f64)
            .collect(),
    )?;
    let face =
        most as f64 >= SPIKE_RATIO * typical && most as f64 >= SPIKE_SHARE * points.len() as f64;
    face.then_some(lo + peak as f64 * slab_m)
}

/// The unit normal of the points in the slab `[face - slab, face + 2 slab)` along `axis`
/// (the face and its neighbours, for a guess a few degrees off): their least principal
/// direction ([`estimate_axis`]), oriented like `axis`; `None` when they are not planar
/// ([`MAX_FACE_THICKNESS`]).
fn face_normal(points: &[[f32; 3]], axis: [f64; 3], face: f64, slab_m: f64) -> Option<[f64; 3]> {
    let slab: Vec<[f32; 3]> = points
        .iter()
        .filter(|p| in_slab(dot3(p, &axis), face, slab_m))
        .copied()
        .collect();
    let pca = estimate_axis(&slab, axis).ok()?;
    let [_, middle, thin] = pca.singular_values;
    if thin.is_nan() || thin > MAX_FACE_THICKNESS * middle {
        return None;
    }
    Some(pca.directions[2])
}

/// An even stride of `points`, at most [`DETECTION_POINTS`] of them.
fn strided(points: &[[f32; 3]]) -> Vec<[f32; 3]> {
    let stride = points.len().div_ceil(DETECTION_POINTS).max(1);
    points.iter().step_by(stride).copied().collect()
}

fn in_slab(z: f64, face: f64, slab_m: f64) -> bool {
    z >= face - slab_m && z < face + 2.0 * slab_m
}

fn dot3(p: &[f32; 3], v: &[f64; 3]) -> f64 {
    p[0] as f64 * v[0] + p[1] as f64 * v[1] + p[2] as f64 * v[2]
}

fn median(mut v: Vec<f64>) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let k = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    Some(*m)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tunnel of radius `r` along +x from the sensor to an end face at `end` m: wall points
    /// every 5 cm in x and 1 degree round, face points on a 5 cm grid inside the section.
    /// The same 3 m tunnel up to just short of its end face: no face in view.
    fn open_tunnel() -> Vec<[f32; 3]> {
        tunnel_with_end(3.0, 8.0)
            .into_iter()
            .filter(|p| p[0] < 7.9)
            .collect()
    }

    fn tunnel_with_end(r: f64, end: f64) -> Vec<[f32; 3]> {
        let mut pts = Vec::new();
        let mut x = 1.0;
        while x < end {
            for k in 0..360 {
                let t = (k as f64).to_radians();
                pts.push([x as f32, (r * t.cos()) as f32, (r * t.sin()) as f32]);
            }
            x += 0.05;
        }
        let steps = (r / 0.05) as i64;
        for i in -steps..=steps {
            for j in -steps..=steps {
                let (y, z) = (i as f64 * 0.05, j as f64 * 0.05);
                if y * y + z * z < r * r {
                    pts.push([end as f32, y as f32, z as f32]);
                }
            }
        }
        pts
    }

    #[test]
    fn an_end_face_ahead_is_cut_off_and_gives_the_axis() {
        let pts = tunnel_with_end(3.0, 8.0);
        // A guess 3 degrees off the axis (a robot heading along the corridor) still finds the
        // face, and the axis is measured from it.
        let t = 3f64.to_radians();
        let (kept, axis) = trim_end_face(&pts, [t.cos(), t.sin(), 0.0], 0.3).expect("a face");
        assert!(angle_deg(axis, [1.0, 0.0, 0.0]) < 0.1, "axis {axis:?}");
        assert!(kept.iter().all(|p| p[0] < 7.8), "face points kept");
        // Everything up to a slab short of the face stays.
        let wall_before = pts.iter().filter(|p| p[0] < 7.6).count();
        assert!(kept.len() >= wall_before, "{} < {wall_before}", kept.len());
    }

    #[test]
    fn a_corridor_without_an_end_is_left_alone() {
        let pts = open_tunnel();
        assert!(trim_end_face(&pts, [1.0, 0.0, 0.0], 0.3).is_none());
    }

    #[test]
    fn a_dense_slab_that_is_not_planar_is_not_a_face() {
        // A cube of points in the middle of the corridor: dense, but not a plane.
        let mut pts = open_tunnel();
        let n = pts.len();
        for k in 0..n {
            let f = |m: f64| (k as f64 * m).fract() - 0.5;
            pts.push([
                (4.0 + 0.6 * f(0.618)) as f32,
                (0.6 * f(0.414)) as f32,
                (0.6 * f(0.732)) as f32,
            ]);
        }
        assert!(trim_end_face(&pts, [1.0, 0.0, 0.0], 0.3).is_none());
    }

    #[test]
    fn a_room_closed_at_both_ends_is_not_a_corridor_end() {
        // The tunnel closed by a second face behind the sensor, as a spinning sensor sees it.
        let mut pts = tunnel_with_end(3.0, 8.0);
        let back: Vec<[f32; 3]> = pts
            .iter()
            .filter(|p| p[0] >= 7.99)
            .map(|p| [1.0, p[1], p[2]])
            .collect();
        pts.extend(back);
        assert!(trim_end_face(&pts, [1.0, 0.0, 0.0], 0.3).is_none());
    }

    #[test]
    fn degenerate_input_gives_none_not_a_panic() {
        assert!(trim_end_face(&[], [1.0, 0.0, 0.0], 0.3).is_none());
        let pts = vec![[1.0f32, 0.0, 0.0]; 10];
        assert!(trim_end_face(&pts, [1.0, 0.0, 0.0], 0.0).is_none());
        assert!(trim_end_face(&pts, [1.0, 0.0, 0.0], f64::NAN).is_none());
        let nan = vec![[f32::NAN, 0.0, 0.0]; 10];
        assert!(trim_end_face(&nan, [1.0, 0.0, 0.0], 0.3).is_none());
    }

    #[test]
    fn a_face_in_view_is_measured_along_its_normal() {
        let pts = tunnel_with_end(3.0, 8.0);
        let face = face_in_view(&pts, [1.0, 0.0, 0.0], true, 0.3).expect("a face");
        // Face points on a 5 cm grid at x = 8 exactly (f32): the median is the plane.
        assert!((face.point[0] - 8.0).abs() < 1e-4, "{:?}", face.point);
        assert!(face.point[1].abs() < 1e-3 && face.point[2].abs() < 1e-3);
        assert!(
            angle_deg(face.normal, [1.0, 0.0, 0.0]) < 0.1,
            "{:?}",
            face.normal
        );
        assert!(face.share > 0.1 && face.share < 0.5, "share {}", face.share);
        // Looked for along the axis pointing the other way: the same plane, the normal along
        // that axis.
        let back = face_in_view(&pts, [-1.0, 0.0, 0.0], true, 0.3).expect("a face");
        assert!((back.point[0] - 8.0).abs() < 1e-4 && back.normal[0] < -0.999);
        // From a guess 3 degrees off (a heading), the face's normal and the same plane.
        let t = 3f64.to_radians();
        let guess = face_in_view(&pts, [t.cos(), t.sin(), 0.0], false, 0.3).expect("a face");
        assert!(
            angle_deg(guess.normal, [1.0, 0.0, 0.0]) < 0.1,
            "{:?}",
            guess.normal
        );
        assert!((guess.point[0] - 8.0).abs() < 0.01, "{:?}", guess.point);
        // A settled axis 5 degrees off the face's normal: the face is not square to it.
        let t = 5f64.to_radians();
        assert!(face_in_view(&pts, [t.cos(), t.sin(), 0.0], true, 0.3).is_none());
    }

    #[test]
    fn a_face_with_the_corridor_beyond_it_is_not_an_end() {
        // A bulkhead across the section with the tunnel going on behind it.
        let mut pts = tunnel_with_end(3.0, 8.0);
        let beyond: Vec<[f32; 3]> = pts
            .iter()
            .filter(|p| p[0] < 4.0)
            .map(|p| [p[0] + 7.0, p[1], p[2]])
            .collect();
        pts.extend(beyond);
        assert!(face_in_view(&pts, [1.0, 0.0, 0.0], true, 0.3).is_none());
        assert!(face_in_view(&pts, [1.0, 0.0, 0.0], false, 0.3).is_none());
    }

    #[test]
    fn no_face_in_an_open_corridor_or_in_degenerate_input() {
        let open = open_tunnel();
        for settled in [true, false] {
            assert!(face_in_view(&open, [1.0, 0.0, 0.0], settled, 0.3).is_none());
            assert!(face_in_view(&[], [1.0, 0.0, 0.0], settled, 0.3).is_none());
            let nan = vec![[f32::NAN, 0.0, 0.0]; 10];
            assert!(face_in_view(&nan, [1.0, 0.0, 0.0], settled, 0.3).is_none());
            assert!(face_in_view(&open, [1.0, 0.0, 0.0], settled, f64::NAN).is_none());
        }
    }
}
