//! Reference contour `c(p)` of the cross-section (paper §III-A) and its validation
//! (§IV-A.2: at least 90 % of the projected points within 0.18 m of `c`).
//!
//! Points are projected on the transverse plane as `(u, v)` coordinates along `(e1, e2)`.
//! Two models:
//! - `circle` (pipes): Kåsa's algebraic fit, then Gauss–Newton on the geometric residual
//!   `|x - c| - R` with Huber weights (k = 1.345 robust sigmas) so that joints, lateral
//!   connections and debris do not pull the circle.
//! - `polar` (horseshoe / shield sections with a flat floor): a star-shaped closed contour
//!   `r(theta)` about the robust circle centre: per-angle-bin median radius, empty bins
//!   interpolated around the circle, then a circular Gaussian smoothing of a few bins. The
//!   median follows a flat floor and sharp wall/floor corners within the bin width.
//!
//! Both are stored as one lookup table over the polar angle `theta` about the contour centre
//! (measured from `e1` towards `e2`), so descriptor and boundary code share one path. The
//! arclength parameter `p` in `[0, 1)` starts at `theta = 0`, i.e. at `e1` (gravity, the
//! bottom of the section), and runs towards `e2`.

use std::f64::consts::TAU;

use crate::config::ContourConfig;
use crate::error::{DecodError, Result};

/// Samples of the contour lookup table over `theta` (0.5 deg): far finer than the 256
/// descriptor columns, so linear interpolation adds < 0.1 mm on a 3 m tunnel radius.
const TABLE_SIZE: usize = 720;

/// Gauss–Newton iterations of the robust circle fit; converged to < 1e-9 m on the test
/// cylinders after 4, so 8 leaves margin for noisy starts.
const CIRCLE_ITERATIONS: usize = 8;

/// Which contour model was fitted.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ContourModel {
    /// A circle (pipes).
    Circle,
    /// A smoothed polar profile `r(theta)` (horseshoe, shield with a flat floor).
    Polar,
}

impl ContourModel {
    /// Lower-case name as in the config (`"circle"`, `"polar"`).
    pub fn name(&self) -> &'static str {
        match self {
            Self::Circle => "circle",
            Self::Polar => "polar",
        }
    }
}

/// A closed reference contour in the transverse plane.
#[derive(Clone, Debug)]
pub struct ReferenceContour {
    /// Model fitted.
    pub model: ContourModel,
    /// Contour centre in `(e1, e2)` coordinates of the projection, metres.
    pub centre_uv: [f64; 2],
    /// Perimeter, metres.
    pub perimeter_m: f64,
    /// Mean radius (mean distance of the contour from its centre), metres.
    pub mean_radius_m: f64,
    /// Radius at `theta_k = k * TAU / TABLE_SIZE`, plus the first repeated at the end.
    radius: Vec<f64>,
    /// Outward unit normal at `theta_k` (same layout).
    normal: Vec<[f64; 2]>,
    /// Normalised arclength `p` at `theta_k`; `p[TABLE_SIZE] = 1`.
    arclength: Vec<f64>,
}

/// A point unrolled on the contour: normalised arclength and signed normal offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Unrolled {
    /// Normalised arclength `p` in `[0, 1)` from `e1` towards `e2`.
    pub p: f64,
    /// Signed offset `s = n(p)^T (x - c(p))`, metres, positive outwards.
    pub s: f64,
}

/// A contour sample at a given `p`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ContourSample {
    /// Point `c(p)` relative to the contour centre along `(e1, e2)`, metres.
    pub point: [f64; 2],
    /// Outward unit normal along `(e1, e2)`.
    pub normal: [f64; 2],
    /// Polar angle about the centre from `e1` towards `e2`, radians in `[0, TAU)`.
    pub theta: f64,
}

/// Result of fitting and validating a contour.
#[derive(Clone, Debug)]
pub struct ContourFit {
    /// The contour.
    pub contour: ReferenceContour,
    /// Fraction of projected points within `inlier_distance_m` of the contour.
    pub inlier_fraction: f64,
    /// Median absolute offset of the projected points, metres.
    pub median_abs_offset_m: f64,
}

impl ReferenceContour {
    fn from_radii(model: ContourModel, centre_uv: [f64; 2], radii: &[f64]) -> Self {
        let m = radii.len();
        let pts: Vec<[f64; 2]> = (0..m)
            .map(|k| {
                let t = TAU * k as f64 / m as f64;
                [radii[k] * t.cos(), radii[k] * t.sin()]
            })
            .collect();
        let mut normal = Vec::with_capacity(m + 1);
        for k in 0..m {
            let next = pts[(k + 1) % m];
            let prev = pts[(k + m - 1) % m];
            // Counter-clockwise (e1 -> e2) tangent rotated by -90 deg points outwards.
            let (tx, ty) = (next[0] - prev[0], next[1] - prev[1]);
            let len = (tx * tx + ty * ty).sqrt().max(1e-12);
            normal.push([ty / len, -tx / len]);
        }
        normal.push(normal[0]);
        let mut arclength = Vec::with_capacity(m + 1);
        let mut total = 0.0;
        arclength.push(0.0);
        for k in 0..m {
            let (a, b) = (pts[k], pts[(k + 1) % m]);
            total += ((b[0] - a[0]).powi(2) + (b[1] - a[1]).powi(2)).sqrt();
            arclength.push(total);
        }
        for p in &mut arclength {
            *p /= total.max(1e-12);
        }
        let mut radius = radii.to_vec();
        radius.push(radii[0]);
        Self {
            model,
            centre_uv,
            perimeter_m: total,
            mean_radius_m: radii.iter().sum::<f64>() / m as f64,
            radius,
            normal,
            arclength,
        }
    }

    /// A circle of `radius_m` about `centre_uv`.
    pub fn circle(centre_uv: [f64; 2], radius_m: f64) -> Self {
        let mut c = Self::from_radii(ContourModel::Circle, centre_uv, &[radius_m; TABLE_SIZE]);
        c.perimeter_m = TAU * radius_m;
        c
    }

    /// Unrolls the projected point `uv` (along `(e1, e2)`): its `p` is that of the contour
    /// point on the same ray from the centre, its offset `n^T (x - c)` there. On straight
    /// pieces (a flat floor) this is exactly the normal distance; on curved pieces the error
    /// is second order in offset / radius of curvature.
    #[inline]
    pub fn unroll(&self, uv: [f64; 2]) -> Unrolled {
        let (x, y) = (uv[0] - self.centre_uv[0], uv[1] - self.centre_uv[1]);
        let theta = y.atan2(x).rem_euclid(TAU);
        if self.model == ContourModel::Circle {
            return Unrolled {
                p: (theta / TAU).min(1.0 - 1e-12),
                s: (x * x + y * y).sqrt() - self.radius[0],
            };
        }
        let f = theta / TAU * TABLE_SIZE as f64;
        let k = (f as usize).min(TABLE_SIZE - 1);
        let w = f - k as f64;
        let r = self.radius[k] * (1.0 - w) + self.radius[k + 1] * w;
        let (n0, n1) = (self.normal[k], self.normal[k + 1]);
        let (nx, ny) = (n0[0] * (1.0 - w) + n1[0] * w, n0[1] * (1.0 - w) + n1[1] * w);
        let nn = (nx * nx + ny * ny).sqrt().max(1e-12);
        // c(theta) = r(theta) times the point's own unit direction (no sin/cos needed).
        let rho = (x * x + y * y).sqrt().max(1e-12);
        let (cx, cy) = (r * x / rho, r * y / rho);
        let p = self.arclength[k] * (1.0 - w) + self.arclength[k + 1] * w;
        Unrolled {
            p: p.min(1.0 - 1e-12),
            s: ((x - cx) * nx + (y - cy) * ny) / nn,
        }
    }

    /// The contour point, outward normal and polar angle at normalised arclength `p`.
    pub fn sample(&self, p: f64) -> ContourSample {
        let p = p.rem_euclid(1.0);
        if self.model == ContourModel::Circle {
            let theta = p * TAU;
            let (sin, cos) = theta.sin_cos();
            let r = self.radius[0];
            return ContourSample {
                point: [r * cos, r * sin],
                normal: [cos, sin],
                theta,
            };
        }
        // First table index whose arclength exceeds p.
        let hi = self
            .arclength
            .partition_point(|&a| a <= p)
            .clamp(1, TABLE_SIZE);
        let lo = hi - 1;
        let span = (self.arclength[hi] - self.arclength[lo]).max(1e-15);
        let w = ((p - self.arclength[lo]) / span).clamp(0.0, 1.0);
        let theta = TAU * (lo as f64 + w) / TABLE_SIZE as f64;
        let r = self.radius[lo] * (1.0 - w) + self.radius[hi] * w;
        let (n0, n1) = (self.normal[lo], self.normal[hi]);
        let (nx, ny) = (n0[0] * (1.0 - w) + n1[0] * w, n0[1] * (1.0 - w) + n1[1] * w);
        let nn = (nx * nx + ny * ny).sqrt().max(1e-12);
        ContourSample {
            point: [r * theta.cos(), r * theta.sin()],
            normal: [nx / nn, ny / nn],
            theta,
        }
    }
}

/// Robust circle fit (algebraic start, Huber-weighted Gauss–Newton). Returns centre, radius.
pub fn fit_circle(uv: &[[f64; 2]]) -> Result<([f64; 2], f64)> {
    if uv.len() < 3 {
        return Err(DecodError::invalid(
            "points",
            "circle fit needs >= 3 points",
        ));
    }
    // Kåsa: u^2 + v^2 + D u + E v + F = 0, normal equations in a 3x3 system.
    let mut ata = nalgebra::Matrix3::<f64>::zeros();
    let mut atb = nalgebra::Vector3::<f64>::zeros();
    for &[u, v] in uv {
        let row = nalgebra::Vector3::new(u, v, 1.0);
        ata += row * row.transpose();
        atb -= row * (u * u + v * v);
    }
    let sol = ata
        .lu()
        .solve(&atb)
        .ok_or_else(|| DecodError::invalid("points", "degenerate transverse projection"))?;
    let mut cx = -sol[0] / 2.0;
    let mut cy = -sol[1] / 2.0;
    let mut r = (cx * cx + cy * cy - sol[2]).max(0.0).sqrt();
    let mut residuals = vec![0.0; uv.len()];
    for _ in 0..CIRCLE_ITERATIONS {
        for (res, &[u, v]) in residuals.iter_mut().zip(uv) {
            *res = ((u - cx).powi(2) + (v - cy).powi(2)).sqrt() - r;
        }
        // Robust scale from at most ~2000 residuals (an even stride): plenty for a MAD.
        let mut sample: Vec<f64> = residuals
            .iter()
            .step_by(residuals.len().div_ceil(2000).max(1))
            .copied()
            .collect();
        let scale = (1.4826 * median_abs(&mut sample)).max(1e-6);
        let k = 1.345 * scale;
        let mut h = nalgebra::Matrix3::<f64>::zeros();
        let mut g = nalgebra::Vector3::<f64>::zeros();
        for (&res, &[u, v]) in residuals.iter().zip(uv) {
            let d = ((u - cx).powi(2) + (v - cy).powi(2)).sqrt().max(1e-12);
            let j = nalgebra::Vector3::new(-(u - cx) / d, -(v - cy) / d, -1.0);
            let w = if res.abs() <= k { 1.0 } else { k / res.abs() };
            h += w * j * j.transpose();
            g += w * j * res;
        }
        let Some(step) = h.lu().solve(&(-g)) else {
            break;
        };
        cx += step[0];
        cy += step[1];
        r += step[2];
        if step.norm() < 1e-10 {
            break;
        }
    }
    if !(r.is_finite() && r > 0.0 && cx.is_finite() && cy.is_finite()) {
        return Err(DecodError::invalid("points", "circle fit diverged"));
    }
    Ok(([cx, cy], r.abs()))
}

/// Polar profile about `centre`: per-bin median radius, gaps filled, circular Gaussian
/// smoothing of `smoothing_bins` (sigma), resampled on the lookup table.
pub fn fit_polar(
    uv: &[[f64; 2]],
    centre: [f64; 2],
    bins: usize,
    smoothing_bins: f64,
) -> Result<ReferenceContour> {
    let bins = bins.max(8);
    let mut per_bin: Vec<Vec<f64>> = vec![Vec::new(); bins];
    for &[u, v] in uv {
        let (x, y) = (u - centre[0], v - centre[1]);
        let t = y.atan2(x).rem_euclid(TAU);
        let b = ((t / TAU * bins as f64) as usize).min(bins - 1);
        per_bin[b].push((x * x + y * y).sqrt());
    }
    let mut radius: Vec<Option<f64>> = per_bin
        .iter_mut()
        .map(|r| (!r.is_empty()).then(|| median_abs(r)))
        .collect();
    let observed: Vec<usize> = (0..bins).filter(|&b| radius[b].is_some()).collect();
    if observed.len() < 3 {
        return Err(DecodError::invalid(
            "points",
            "too few angular bins observed for a polar contour",
        ));
    }
    // Fill gaps by linear interpolation between the observed neighbours, around the circle.
    for (i, &b0) in observed.iter().enumerate() {
        let b1 = observed[(i + 1) % observed.len()];
        let gap = (b1 + bins - b0) % bins;
        let (r0, r1) = (radius[b0].unwrap_or(0.0), radius[b1].unwrap_or(0.0));
        for step in 1..gap {
            let w = step as f64 / gap as f64;
            radius[(b0 + step) % bins] = Some(r0 * (1.0 - w) + r1 * w);
        }
    }
    let raw: Vec<f64> = radius.iter().map(|r| r.unwrap_or(0.0)).collect();
    let smooth = circular_gaussian(&raw, smoothing_bins);
    // Resample the bin centres onto the lookup table.
    let table: Vec<f64> = (0..TABLE_SIZE)
        .map(|k| {
            // Table entry k sits at theta_k = k TAU / TABLE_SIZE; bin b is centred at
            // (b + 0.5) TAU / bins. Mirror-symmetric, so a heading reversal maps p to 1 - p.
            let f = k as f64 / TABLE_SIZE as f64 * bins as f64 - 0.5;
            let b0 = f.floor().rem_euclid(bins as f64) as usize;
            let w = f - f.floor();
            smooth[b0] * (1.0 - w) + smooth[(b0 + 1) % bins] * w
        })
        .collect();
    Ok(ReferenceContour::from_radii(
        ContourModel::Polar,
        centre,
        &table,
    ))
}

/// Fits the configured model (`circle`, `polar`, or `auto`: polar if its median absolute
/// offset is below `auto_polar_ratio` times the circle's, or if the circle fails the corridor
/// test, `min_inlier_fraction` within `inlier_distance_m`, and the polar contour holds more
/// points) and validates it. The second clause: a forward-looking sensor in the simulated
/// shield tunnel (flat invert) sees mostly the curved wall, so the circle's median offset is
/// small while the floor, a quarter to half of the points, lies off it: 47-55 % inliers and
/// 27 of 31 submaps rejected; polar: 10 loops, all right.
pub fn fit_contour(uv: &[[f64; 2]], cfg: &ContourConfig) -> Result<ContourFit> {
    // Fit on an evenly strided subset of at most `max_fit_points`; the inlier fraction and
    // median offset below are over every point of `uv`.
    let stride = uv.len().div_ceil(cfg.max_fit_points.max(3)).max(1);
    let subset: Vec<[f64; 2]> = uv.iter().step_by(stride).copied().collect();
    let (centre, r) = fit_circle(&subset)?;
    let circle = ReferenceContour::circle(centre, r);
    let contour = match cfg.model.as_str() {
        "circle" => circle,
        "polar" => fit_polar(&subset, centre, cfg.polar_bins, cfg.polar_smoothing_bins)?,
        _ => {
            let polar = fit_polar(&subset, centre, cfg.polar_bins, cfg.polar_smoothing_bins)?;
            let mc = median_abs(
                &mut subset
                    .iter()
                    .map(|&x| circle.unroll(x).s)
                    .collect::<Vec<_>>(),
            );
            let mp = median_abs(
                &mut subset
                    .iter()
                    .map(|&x| polar.unroll(x).s)
                    .collect::<Vec<_>>(),
            );
            let within = |c: &ReferenceContour| {
                subset
                    .iter()
                    .filter(|&&x| c.unroll(x).s.abs() <= cfg.inlier_distance_m)
                    .count()
            };
            let (ic, ip) = (within(&circle), within(&polar));
            let circle_fails = (ic as f64) < cfg.min_inlier_fraction * subset.len() as f64;
            if mp < cfg.auto_polar_ratio * mc || (circle_fails && ip > ic) {
                polar
            } else {
                circle
            }
        }
    };
    let mut offsets: Vec<f64> = uv.iter().map(|&x| contour.unroll(x).s).collect();
    let inliers = offsets
        .iter()
        .filter(|s| s.abs() <= cfg.inlier_distance_m)
        .count();
    let inlier_fraction = inliers as f64 / uv.len().max(1) as f64;
    Ok(ContourFit {
        contour,
        inlier_fraction,
        median_abs_offset_m: median_abs(&mut offsets),
    })
}

/// Median of `|values|` (reorders `values`); 0 for an empty slice.
pub(crate) fn median_abs(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    for v in values.iter_mut() {
        *v = v.abs();
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Circular convolution with a normalised Gaussian of `sigma` samples.
fn circular_gaussian(values: &[f64], sigma: f64) -> Vec<f64> {
    let n = values.len();
    if sigma <= 0.0 {
        return values.to_vec();
    }
    let half = ((3.0 * sigma).ceil() as usize).min(n / 2);
    let kernel: Vec<f64> = (0..=half)
        .map(|i| (-0.5 * (i as f64 / sigma).powi(2)).exp())
        .collect();
    let total: f64 = kernel[0] + 2.0 * kernel[1..].iter().sum::<f64>();
    (0..n)
        .map(|i| {
            let mut acc = kernel[0] * values[i];
            for (d, &w) in kernel.iter().enumerate().skip(1) {
                acc += w * (values[(i + d) % n] + values[(i + n - d) % n]);
            }
            acc / total
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;

    fn ring(n: usize, centre: [f64; 2], r: f64) -> Vec<[f64; 2]> {
        (0..n)
            .map(|i| {
                let t = TAU * i as f64 / n as f64;
                let noise = 1e-3 * ((i * 7919 % 13) as f64 / 6.0 - 1.0);
                [
                    centre[0] + (r + noise) * t.cos(),
                    centre[1] + (r + noise) * t.sin(),
                ]
            })
            .collect()
    }

    /// A horseshoe: an arch of radius 3 m above a flat floor 2 m below the centre.
    fn horseshoe(n: usize) -> Vec<[f64; 2]> {
        (0..n)
            .map(|i| {
                let t = TAU * i as f64 / n as f64;
                // e1 points down: the floor is u = +2 (towards gravity).
                let (c, s) = (t.cos(), t.sin());
                let r = if c > 2.0 / 3.0 { 2.0 / c } else { 3.0 };
                [r * c + 0.5, r * s - 0.2]
            })
            .collect()
    }

    #[test]
    fn circle_fit_recovers_centre_and_radius_despite_outliers() {
        let mut pts = ring(5000, [0.1, -0.05], 0.3);
        pts.extend((0..300).map(|i| [0.1 + 0.001 * i as f64 / 300.0, -0.05]));
        let (c, r) = fit_circle(&pts).unwrap();
        assert!(
            (c[0] - 0.1).abs() < 5e-4 && (c[1] + 0.05).abs() < 5e-4,
            "{c:?}"
        );
        assert!((r - 0.3).abs() < 5e-4, "{r}");
        let contour = ReferenceContour::circle(c, r);
        let u = contour.unroll([0.1, -0.05 + 0.31]);
        assert!(
            (u.p - 0.25).abs() < 1e-3 && (u.s - 0.01).abs() < 1e-3,
            "{u:?}"
        );
    }

    #[test]
    fn auto_picks_polar_for_a_flat_floor_and_validates() {
        let cfg = DecodConfig::tunnel().contour;
        let fit = fit_contour(&horseshoe(20_000), &cfg).unwrap();
        assert_eq!(fit.contour.model, ContourModel::Polar);
        assert!(fit.inlier_fraction > 0.97, "{}", fit.inlier_fraction);
        // On the floor (theta = 0 direction is down): outward normal is +e1.
        let s = fit.contour.sample(0.0);
        assert!(s.normal[0] > 0.99, "{s:?}");
        let circle = fit_contour(&ring(5000, [0.0, 0.0], 3.0), &cfg).unwrap();
        assert_eq!(circle.contour.model, ContourModel::Circle);
    }

    /// Median |offset| of the polar fit over that of the circle: the figure behind
    /// `contour.auto_polar_ratio = 0.5`.
    fn polar_over_circle(uv: &[[f64; 2]]) -> f64 {
        let (c, r) = fit_circle(uv).unwrap();
        let circle = ReferenceContour::circle(c, r);
        let polar = fit_polar(uv, c, 180, 1.5).unwrap();
        let med = |k: &ReferenceContour| {
            median_abs(&mut uv.iter().map(|&x| k.unroll(x).s).collect::<Vec<_>>())
        };
        med(&polar) / med(&circle)
    }

    #[test]
    fn polar_to_circle_residual_ratio_separates_the_models() {
        let noisy_ring: Vec<[f64; 2]> = ring(20_000, [0.2, 0.1], 3.0)
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let n = 0.01 * (((i * 104_729) % 101) as f64 / 50.0 - 1.0);
                [p[0] * (1.0 + n / 3.0), p[1] * (1.0 + n / 3.0)]
            })
            .collect();
        let ring_ratio = polar_over_circle(&noisy_ring);
        let horseshoe_ratio = polar_over_circle(&horseshoe(20_000));
        assert!(ring_ratio > 0.8, "{ring_ratio}");
        assert!(horseshoe_ratio < 0.1, "{horseshoe_ratio}");
    }

    #[test]
    fn sample_and_unroll_agree_on_p() {
        let cfg = DecodConfig::tunnel().contour;
        let fit = fit_contour(&horseshoe(20_000), &cfg).unwrap();
        let c = &fit.contour;
        for p in [0.01, 0.2, 0.45, 0.7, 0.93] {
            let s = c.sample(p);
            let uv = [s.point[0] + c.centre_uv[0], s.point[1] + c.centre_uv[1]];
            let u = c.unroll(uv);
            assert!((u.p - p).abs() < 2e-3 && u.s.abs() < 2e-3, "{p} {u:?}");
        }
    }
}
