//! A corridor that curves within one submap (not in the paper, which takes the corridor
//! straight over a submap): the centre line as a parabola in the transverse plane of the
//! fitted axis.
//!
//! A submap's axis is fitted to all its points (`crate::axis`, `crate::contour`); where the
//! corridor curves, that axis is the chord of the stretch in range, and the true centre line
//! leaves it by the sagitta `z^2 / (2 R)` at `z` metres along it: 0.37 m at 15 m on a 300 m
//! curve (a metro tunnel's), 0.1 m at 2 m in a pipe bent on 20 m. A boundary seen far from
//! the middle of its submap then gets an origin off the centre line and the chord for its
//! axis; on a simulated 6 m shield tunnel on a 300 m curve, views 8-15 m from their anchor
//! were placed 16 cm to the outside and their axes turned 40 mrad from the local tangent,
//! and the boundary factors between such views bent the corrected trajectory straighter
//! (52 mrad of heading and 0.85 m sideways at the far end of 42 m; position RMSE 1.08 ->
//! 0.41 m, where the straight tunnel gets 0.02-0.05 m).
//!
//! [`fit`] measures the centre line on the unrolled chart: a centre displaced by `d(z)` (in
//! the transverse basis `(e1, e2)`) moves every wall point's offset by `n(p)^T d(z)`, `n` the
//! contour's outward normal, so the offsets of the points on the contour give
//! `d(z) = d0 + d1 z + d2 z^2` by linear least squares (six unknowns). It is used only where
//! the curve is measured (the quadratic term [`MIN_T`] standard errors from zero) and matters
//! (its sagitta over the chart at least [`MIN_SAGITTA_RADII`] of the corridor's radius); a
//! straight corridor keeps the straight axis. Then the chart's offsets are taken from the
//! curved centre line (the descriptor and the boundary profile see the wall, not the curve),
//! and each landmark's origin is the centre line's point at its boundary and its axis the
//! centre line's tangent there.

use nalgebra::{DMatrix, DVector, SMatrix, SVector};

use crate::boundary::ChartPoint;
use crate::contour::ReferenceContour;

/// The curve is used when its quadratic term is at least this many standard errors from
/// zero (Mahalanobis over its two components).
pub const MIN_T: f64 = 8.0;

/// ... and its sagitta over the chart (`|d2| z_max^2`) at least this share of the contour's
/// mean radius (3 cm in a 6 m tunnel, 2 mm in a 0.4 m pipe).
pub const MIN_SAGITTA_RADII: f64 = 0.01;

/// Fits after the first, each on the points within the inlier distance of the curve found
/// before (a curve of 0.37 m leaves the far points outside the straight contour's band).
const REFITS: usize = 2;

/// The centre line `d(z) = d0 + d1 z + d2 z^2` in `(e1, e2)`, metres, `z` along the axis from
/// the chart's origin.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CentreLine {
    /// `[d0, d1, d2]`, each `(e1, e2)`.
    pub coef: [[f64; 2]; 3],
}

impl CentreLine {
    /// The centre's displacement at `z`, `(e1, e2)` metres.
    pub fn offset(&self, z: f64) -> [f64; 2] {
        let [d0, d1, d2] = self.coef;
        std::array::from_fn(|k| d0[k] + z * (d1[k] + z * d2[k]))
    }

    /// The slope of the centre line at `z`, `(e1, e2)` metres per metre along the axis.
    pub fn slope(&self, z: f64) -> [f64; 2] {
        let [_, d1, d2] = self.coef;
        std::array::from_fn(|k| d1[k] + 2.0 * z * d2[k])
    }

    /// The radius of the curve, metres (infinite when straight).
    pub fn radius_m(&self) -> f64 {
        let [_, _, d2] = self.coef;
        let k = 2.0 * d2[0].hypot(d2[1]);
        if k > 0.0 { 1.0 / k } else { f64::INFINITY }
    }
}

/// Points the fit wants, an evenly strided subset of the submap's (a 64-beam window holds a
/// million): the caller unrolls these from the straight axis ([`unroll`] without a line).
/// With 12,000 the 0.4 m pe pipe on a 40 m curve, under uneven drift, closed no loop (99
/// views for 28, most off any coupler) where 40,000 close 12.
pub const FIT_POINTS: usize = 40_000;

/// The centre line of the corridor where it curves enough to matter (module docs), from
/// `chart`, points unrolled from the straight axis; None where it is straight, or too few
/// points measure it.
pub fn fit(chart: &[ChartPoint], contour: &ReferenceContour, inlier_m: f64) -> Option<CentreLine> {
    let sample: Vec<(f64, f64, [f64; 2], f64)> = chart
        .iter()
        .map(|q| (q.z, q.p, contour.sample(q.p).normal, q.s))
        .collect();
    let z_max = sample.iter().map(|q| q.0.abs()).fold(0.0, f64::max);
    let mut line = CentreLine {
        coef: [[0.0; 2]; 3],
    };
    let mut t2 = 0.0;
    for _ in 0..=REFITS {
        let (found, t) = solve(&sample, &line, inlier_m)?;
        line = found;
        t2 = t;
    }
    let [_, _, d2] = line.coef;
    let sagitta = d2[0].hypot(d2[1]) * z_max * z_max;
    (t2 >= MIN_T * MIN_T && sagitta >= MIN_SAGITTA_RADII * contour.mean_radius_m).then_some(line)
}

/// Angular sectors of the contour, each with its own constant offset in the fit: where the
/// reference contour misfits a stretch of the section (a floor, a crown of arches) that the
/// sensor samples over other axial distances than the rest, that misfit would otherwise
/// read as a centre moving with `z`. On the simulated 3 m horseshoe (straight) without them,
/// 64 of 67 submaps of a 16-beam run fitted a curve of 150-1,400 m; with them (and the
/// section's offset growing with `z`, below) 21 still do, and 9 of 37 in the 5 m horseshoe,
/// which is why the fit runs only where the robot's path curves (`axis.curved`).
const SECTORS: usize = 36;

/// Terms after the sectors' constants: `d1` and `d2` (the constant `d0` is the pattern
/// `n(p)^T d0`, which the sectors absorb), then an offset of the whole section growing with
/// `z` (linearly and quadratically): what the sensor sees of the wall changes with the
/// distance (the rock between a horseshoe's arches is hidden behind them further out), and
/// on a section with a floor that change would otherwise read as a centre moving with `z`.
const TERMS: usize = 6;

/// Unknowns of the fit.
const UNKNOWNS: usize = SECTORS + TERMS;

/// One least-squares fit on the points within `inlier_m` of `line`: the new line and the
/// squared Mahalanobis distance of its quadratic term from zero.
fn solve(
    sample: &[(f64, f64, [f64; 2], f64)],
    line: &CentreLine,
    inlier_m: f64,
) -> Option<(CentreLine, f64)> {
    let mut ata = DMatrix::<f64>::zeros(UNKNOWNS, UNKNOWNS);
    let mut atb = DVector::<f64>::zeros(UNKNOWNS);
    let mut used: Vec<(usize, [f64; TERMS], f64)> = Vec::new();
    for &(z, p, n, s) in sample {
        let d = line.offset(z);
        if (s - n[0] * d[0] - n[1] * d[1]).abs() > inlier_m {
            continue;
        }
        let sector = ((p * SECTORS as f64) as usize).min(SECTORS - 1);
        let curve = [z * n[0], z * n[1], z * z * n[0], z * z * n[1], z, z * z];
        // The row is 1 at its sector and `curve` after the sectors: accumulated sparsely.
        ata[(sector, sector)] += 1.0;
        atb[sector] += s;
        for k in 0..TERMS {
            ata[(sector, SECTORS + k)] += curve[k];
            ata[(SECTORS + k, sector)] += curve[k];
            atb[SECTORS + k] += curve[k] * s;
            for l in 0..TERMS {
                ata[(SECTORS + k, SECTORS + l)] += curve[k] * curve[l];
            }
        }
        used.push((sector, curve, s));
    }
    if used.len() < 10 * UNKNOWNS {
        return None;
    }
    // A sector with no point: its constant pinned at 0 (it enters no residual).
    for k in 0..SECTORS {
        if ata[(k, k)] == 0.0 {
            ata[(k, k)] = 1.0;
        }
    }
    let inv = ata.try_inverse()?;
    let x = &inv * &atb;
    let rss: f64 = used
        .iter()
        .map(|(sector, curve, s)| {
            let fit = x[*sector] + (0..TERMS).map(|k| curve[k] * x[SECTORS + k]).sum::<f64>();
            (s - fit).powi(2)
        })
        .sum();
    let var = rss / (used.len() - UNKNOWNS) as f64;
    let q = SECTORS + 2;
    let cov = SMatrix::<f64, 2, 2>::new(
        inv[(q, q)],
        inv[(q, q + 1)],
        inv[(q + 1, q)],
        inv[(q + 1, q + 1)],
    ) * var;
    let d2 = SVector::<f64, 2>::new(x[q], x[q + 1]);
    let t2 = cov
        .try_inverse()
        .map(|c| (d2.transpose() * c * d2)[(0, 0)])
        .unwrap_or(0.0);
    // `d0`: the centre line's mean over the points is the contour's centre (fitted to them).
    let (d1, d2v) = ([x[SECTORS], x[SECTORS + 1]], [x[q], x[q + 1]]);
    let (mut m1, mut m2) = (0.0, 0.0);
    for &(z, _, _, _) in sample {
        m1 += z;
        m2 += z * z;
    }
    let count = sample.len() as f64;
    let (m1, m2) = (m1 / count, m2 / count);
    let d0 = std::array::from_fn(|k| -(d1[k] * m1 + d2v[k] * m2));
    let line = CentreLine {
        coef: [d0, d1, d2v],
    };
    Some((line, t2))
}

/// One point unrolled (`z` along the fitted axis, `uv` across it in `(e1, e2)` from the
/// frame's centre, as [`ReferenceContour::unroll`] takes it); with a `line`, from the curved
/// centre line: its offset is measured from the section's centre there, `uv - d(z)`, and its
/// axial coordinate moved to the section across the tangent it lies in, `z + q^T d'(z)` with
/// `q` its position across the centre line (first order in the slope). A ring lies across
/// the centre line's tangent, not across the chord: on a 100 m curve a ring 10 m from the
/// middle of the submap is turned 0.1 rad, and the 2.5 m of a 5 m horseshoe's wall either
/// side of the axis reach 0.25 m along the chord in front of it and behind it; where the
/// inside wall of the curve hides part of the ring (far along it), the part seen placed it
/// up to that far off.
#[inline]
pub fn unroll(
    contour: &ReferenceContour,
    line: Option<&CentreLine>,
    z: f64,
    uv: [f64; 2],
) -> ChartPoint {
    let Some(line) = line else {
        let u = contour.unroll(uv);
        return ChartPoint { z, p: u.p, s: u.s };
    };
    let d = line.offset(z);
    let slope = line.slope(z);
    let moved = [uv[0] - d[0], uv[1] - d[1]];
    let u = contour.unroll(moved);
    let [cu, cv] = contour.centre_uv;
    let across = [moved[0] - cu, moved[1] - cv];
    ChartPoint {
        z: z + across[0] * slope[0] + across[1] * slope[1],
        p: u.p,
        s: u.s,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Points on a circle of radius `r` whose centre follows `d2 z^2` (less its mean), `z` in
    /// `[-h, h]`, with a texture of `texture` metres: `(z, uv)` across the straight axis.
    fn curved(
        r: f64,
        h: f64,
        d2: [f64; 2],
        texture: f64,
    ) -> (Vec<(f64, [f64; 2])>, ReferenceContour) {
        let contour = ReferenceContour::circle([0.0, 0.0], r);
        let mut pts = Vec::new();
        let mut state = 7u64;
        for i in 0..200 {
            let z = -h + 2.0 * h * i as f64 / 199.0;
            for j in 0..120 {
                let n = contour.sample(j as f64 / 120.0).normal;
                state = state
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                let noise = texture * (((state >> 33) as f64 / (1u64 << 31) as f64) - 0.5);
                // The contour's centre is the mean of the section's centres (fitted to all
                // the points): the centre line about it.
                let bow = z * z - h * h / 3.0;
                let rho = r + noise;
                pts.push((z, [rho * n[0] + d2[0] * bow, rho * n[1] + d2[1] * bow]));
            }
        }
        (pts, contour)
    }

    fn chart(
        pts: &[(f64, [f64; 2])],
        contour: &ReferenceContour,
        line: Option<&CentreLine>,
    ) -> Vec<ChartPoint> {
        pts.iter()
            .map(|&(z, uv)| unroll(contour, line, z, uv))
            .collect()
    }

    #[test]
    fn a_curve_is_found_and_taken_out_of_the_offsets() {
        // A 6 m tunnel on a 300 m curve, 15 m either side: sagitta 0.375 m.
        let d2 = [1.0 / 600.0, 0.0];
        let (pts, contour) = curved(3.0, 15.0, d2, 0.02);
        let straight = chart(&pts, &contour, None);
        let line =
            fit(&straight, &contour, 0.18).unwrap_or_else(|| unreachable!("curve not found"));
        assert!(
            (line.radius_m() - 300.0).abs() < 10.0,
            "{}",
            line.radius_m()
        );
        let slope = line.slope(10.0);
        assert!(
            (slope[0] - 20.0 / 600.0).abs() < 1e-3 && slope[1].abs() < 1e-3,
            "{slope:?}"
        );
        let curved = chart(&pts, &contour, Some(&line));
        let worst = curved.iter().map(|q| q.s.abs()).fold(0.0, f64::max);
        assert!(worst < 0.011 + 0.002, "{worst}");
        // Along the axis, a point moves to the section across the tangent it lies in: on the
        // wall's +e1 side 10 m along, by the radius times the slope (3 m x 1/30).
        for (a, b) in straight.iter().zip(&curved) {
            if a.p < 1e-9 && (a.z - 10.0).abs() < 0.1 {
                let moved = b.z - a.z;
                assert!((moved - 3.0 * a.z / 300.0).abs() < 0.005, "{moved}");
            }
        }
    }

    #[test]
    fn a_straight_corridor_keeps_its_axis() {
        let (pts, contour) = curved(3.0, 15.0, [0.0, 0.0], 0.02);
        assert!(fit(&chart(&pts, &contour, None), &contour, 0.18).is_none());
        // A curve too gentle to matter (3 km: 3.7 cm at 15 m, above 1 % of 3 m) is used; at
        // 30 km (4 mm) it is not.
        let (pts, contour) = curved(3.0, 15.0, [0.0, 1.0 / 6000.0], 0.02);
        assert!(fit(&chart(&pts, &contour, None), &contour, 0.18).is_some());
        let (pts, contour) = curved(3.0, 15.0, [0.0, 1.0 / 60000.0], 0.02);
        assert!(fit(&chart(&pts, &contour, None), &contour, 0.18).is_none());
    }
}
