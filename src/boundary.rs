//! Boundary detection on the axial offset profile (paper §III-A, §IV-A.2): a Difference of
//! Gaussians (sigma 2.5 cm and 10 cm in tunnels) over the axial profile of the surface offset,
//! then non-maximum suppression (0.8 m).
//!
//! The paper does not say how the profile is formed. A forward-looking sensor sees a joint at
//! grazing incidence: a few-mm groove gives ~1 mm of response against 0.2–0.5 mm of wall
//! clutter (DESIGN.md, "What makes corridors hard"), and near the sensor only part of the
//! cross-section is observed. So the profile is robust by construction:
//! 1. the circumference is split into `profile_sectors` sectors of equal arclength, and each
//!    sector's median offset over the whole submap is subtracted from its points (a partially
//!    observed cross-section then has no step where a sector enters or leaves view);
//! 2. the profile value of an axial bin is the mean of those normalised offsets; empty bins
//!    carry zero weight;
//! 3. both Gaussians are *normalised* convolutions (`G*(w v) / G*w`), so gaps and the ends of
//!    the data do not create responses;
//! 4. a peak must exceed both `min_strength_m` and `min_snr` times the robust spread
//!    (1.4826 MAD) of the DoG over the submap, which adapts to the wall's clutter;
//! 5. a peak must lie where the surface itself is displaced the way the response says, by at
//!    least the response (small-Gaussian profile `v`: `v * dog > 0` and `|v| >= |dog|`). A
//!    groove's or rib's side lobes lie on the wall at its own level (`v` near 0), and so fail.
//!    So does the far side of an occlusion shadow: a rib seen from afar hides the wall behind
//!    it, and the normalised convolution carries the rib's inward offset into the gap, where
//!    the DoG is positive.
//!
//!    This was measured on the simulator's horseshoe arches (a 0.2 m deep, 0.15 m wide flange
//!    in a 2.5 m radius section), with exact poses. Seen from 3-10 m, the strongest response
//!    was that lobe, 0.14 m beyond the arch on the side away from the sensor, against about 0
//!    from under 3 m. Along a pass that is a stretch (1.5 % of the view distance), and the
//!    sequential factors read it as odometry scale: after correction, 0.9 % of axial error
//!    remained in every horseshoe cell of the matrix. With the rule, the error is +-1 cm at
//!    every distance (slope 0.1 %). Grooves (pipe joints, ring seams) keep every detection
//!    they had.
//!
//! The bottom sector masked in the descriptor (`descriptor.bottom_mask_deg`, ground returns
//! and debris) is left out of the profile too.

use crate::config::BoundaryConfig;
use crate::contour::{ReferenceContour, median_abs};
use crate::error::{DecodError, Result};

/// Largest profile length in bins (a 100 m submap at 1 mm): guards memory against a config
/// with a tiny bin or a cloud with a far outlier.
const MAX_PROFILE_BINS: usize = 2_000_000;

/// Peaks closer than this many large sigmas to either end of the data are ignored: the
/// large Gaussian is one-sided there and the normalised convolution extrapolates.
const EDGE_MARGIN_SIGMAS: f64 = 3.0;

/// A point unrolled for extraction: axial coordinate, arclength, signed offset.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ChartPoint {
    /// Axial coordinate along `a` from the projection centroid, metres.
    pub z: f64,
    /// Normalised arclength `p` in `[0, 1)` from `e1`.
    pub p: f64,
    /// Signed normal offset from the reference contour, metres (positive outwards).
    pub s: f64,
}

/// A detected boundary.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BoundaryPeak {
    /// Axial position of the peak along `a` (same origin as [`ChartPoint::z`]), metres,
    /// refined to sub-bin precision by a parabola through the peak and its neighbours.
    pub z_m: f64,
    /// `|DoG|` at the peak, metres of offset.
    pub strength_m: f64,
    /// Signed DoG at the peak: > 0 for a groove (surface outwards), < 0 for a rib or arch.
    pub response_m: f64,
}

/// The profile and its detections (kept for diagnostics and plots).
#[derive(Clone, Debug, Default)]
pub struct BoundaryDetection {
    /// Axial coordinate of the first profile bin's centre, metres.
    pub z0_m: f64,
    /// Bin size, metres.
    pub bin_m: f64,
    /// DoG response per bin, metres (0 where undefined).
    pub dog_m: Vec<f64>,
    /// Robust spread (1.4826 MAD) of the DoG, metres.
    pub dog_sigma_m: f64,
    /// The threshold a peak had to exceed, metres.
    pub threshold_m: f64,
    /// Local maxima above the threshold before non-maximum suppression.
    pub candidates: usize,
    /// Peaks kept, strongest first.
    pub peaks: Vec<BoundaryPeak>,
}

/// Detects boundaries in `points` (see the module doc for the steps).
///
/// `contour` gives the sector geometry for the bottom mask; `bottom_mask_deg` is the
/// half-width of the masked sector about `e1`.
pub fn detect_boundaries(
    points: &[ChartPoint],
    contour: &ReferenceContour,
    bottom_mask_deg: f64,
    cfg: &BoundaryConfig,
) -> Result<BoundaryDetection> {
    let bin = cfg.profile_bin_m;
    if points.is_empty() {
        return Ok(BoundaryDetection {
            bin_m: bin,
            ..Default::default()
        });
    }
    let (mut zmin, mut zmax) = (f64::INFINITY, f64::NEG_INFINITY);
    for q in points {
        zmin = zmin.min(q.z);
        zmax = zmax.max(q.z);
    }
    let nbins = ((zmax - zmin) / bin).floor() as usize + 1;
    if nbins > MAX_PROFILE_BINS {
        return Err(DecodError::invalid(
            "points",
            format!(
                "axial extent {:.2} m needs {nbins} profile bins of {bin} m (max {MAX_PROFILE_BINS})",
                zmax - zmin
            ),
        ));
    }
    // Sectors and their bottom mask.
    let sectors = cfg.profile_sectors.max(1);
    let mask_rad = bottom_mask_deg.to_radians();
    let masked: Vec<bool> = (0..sectors)
        .map(|k| {
            let theta = contour.sample((k as f64 + 0.5) / sectors as f64).theta;
            let wrapped = (theta + std::f64::consts::PI).rem_euclid(std::f64::consts::TAU)
                - std::f64::consts::PI;
            wrapped.abs() <= mask_rad
        })
        .collect();
    let sector_of = |p: f64| ((p * sectors as f64) as usize).min(sectors - 1);
    // 1. Per-sector median offsets.
    let mut per_sector: Vec<Vec<f64>> = vec![Vec::new(); sectors];
    for q in points {
        let k = sector_of(q.p);
        if !masked[k] {
            per_sector[k].push(q.s);
        }
    }
    let baseline: Vec<f64> = per_sector.iter_mut().map(|v| signed_median(v)).collect();
    drop(per_sector);
    // 2. Profile: sum and count per bin.
    let mut sum = vec![0.0; nbins];
    let mut weight = vec![0.0; nbins];
    for q in points {
        let k = sector_of(q.p);
        if masked[k] {
            continue;
        }
        let b = (((q.z - zmin) / bin) as usize).min(nbins - 1);
        sum[b] += q.s - baseline[k];
        weight[b] += 1.0;
    }
    // 3. Normalised convolutions and their difference.
    let small = normalised_gaussian(&sum, &weight, cfg.dog_sigma_small_m / bin);
    let large = normalised_gaussian(&sum, &weight, cfg.dog_sigma_large_m / bin);
    let margin = (EDGE_MARGIN_SIGMAS * cfg.dog_sigma_large_m / bin).ceil() as usize;
    let mut dog = vec![0.0; nbins];
    let mut valid = vec![false; nbins];
    for b in margin..nbins.saturating_sub(margin) {
        if let (Some(s), Some(l)) = (small[b], large[b]) {
            dog[b] = s - l;
            valid[b] = true;
        }
    }
    // 4. Threshold from the robust spread, local maxima, NMS.
    let mut spread: Vec<f64> = (0..nbins).filter(|&b| valid[b]).map(|b| dog[b]).collect();
    let dog_sigma = 1.4826 * median_abs(&mut spread);
    let threshold = cfg.min_strength_m.max(cfg.min_snr * dog_sigma);
    // A candidate is the maximum of |DoG| over +-1 large sigma, all of it valid: a slope cut
    // by the edge margin (the true maximum may lie beyond it) is not a peak. Side lobes (step 5)
    // are never peaks and do not hide the response they flank.
    let lobe: Vec<bool> = (0..nbins)
        .map(|b| !displaced_as_response(small[b], dog[b]))
        .collect();
    let w = (cfg.dog_sigma_large_m / bin).ceil().max(1.0) as usize;
    let mut candidates: Vec<usize> = (w..nbins.saturating_sub(w))
        .filter(|&b| {
            let m = dog[b].abs();
            m >= threshold
                && !lobe[b]
                && (b - w..=b + w).all(|j| {
                    valid[j] && (lobe[j] || dog[j].abs() < m || (j <= b && dog[j].abs() <= m))
                })
        })
        .collect();
    let candidate_count = candidates.len();
    candidates.sort_by(|&i, &j| dog[j].abs().total_cmp(&dog[i].abs()));
    let radius_bins = cfg.nms_radius_m / bin;
    let mut kept: Vec<usize> = Vec::new();
    for b in candidates {
        if kept
            .iter()
            .all(|&k| (k as f64 - b as f64).abs() > radius_bins)
        {
            kept.push(b);
        }
    }
    let peaks = kept
        .into_iter()
        .map(|b| {
            let (l, c, r) = (dog[b - 1].abs(), dog[b].abs(), dog[b + 1].abs());
            let denom = l - 2.0 * c + r;
            let shift = if denom.abs() > 1e-18 {
                (0.5 * (l - r) / denom).clamp(-0.5, 0.5)
            } else {
                0.0
            };
            BoundaryPeak {
                z_m: zmin + (b as f64 + 0.5 + shift) * bin,
                strength_m: c,
                response_m: dog[b],
            }
        })
        .collect();
    Ok(BoundaryDetection {
        z0_m: zmin + 0.5 * bin,
        bin_m: bin,
        dog_m: dog,
        dog_sigma_m: dog_sigma,
        threshold_m: threshold,
        candidates: candidate_count,
        peaks,
    })
}

/// Step 5 of the module doc: the surface at the peak (small-Gaussian profile) is displaced in
/// the direction of the response, by at least the response.
fn displaced_as_response(surface: Option<f64>, response: f64) -> bool {
    surface.is_some_and(|v| v * response > 0.0 && v.abs() >= response.abs())
}

/// Median with sign (reorders `values`); 0 for an empty slice.
fn signed_median(values: &mut [f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mid = values.len() / 2;
    let (_, m, _) = values.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// `G_sigma * sum / G_sigma * weight` per bin, `None` where the smoothed weight vanishes.
fn normalised_gaussian(sum: &[f64], weight: &[f64], sigma_bins: f64) -> Vec<Option<f64>> {
    let n = sum.len();
    let half = (3.0 * sigma_bins).ceil().max(1.0) as usize;
    let kernel: Vec<f64> = (0..=half)
        .map(|i| (-0.5 * (i as f64 / sigma_bins.max(1e-9)).powi(2)).exp())
        .collect();
    let mut out = Vec::with_capacity(n);
    for b in 0..n {
        let lo = b.saturating_sub(half);
        let hi = (b + half).min(n - 1);
        let (mut acc, mut w) = (0.0, 0.0);
        for j in lo..=hi {
            let k = kernel[b.abs_diff(j)];
            acc += k * sum[j];
            w += k * weight[j];
        }
        out.push((w > 1e-9).then(|| acc / w));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::DecodConfig;

    /// A wall profile with a 5 mm deep, 10 cm wide groove at z = 1.23 m, tunnel scale.
    fn scene() -> Vec<ChartPoint> {
        let mut pts = Vec::new();
        for i in 0..200_000 {
            let z = -3.0 + 6.0 * (i as f64 / 200_000.0);
            let p = (i as f64 * 0.618_033_988_7).fract();
            let clutter = 1e-3 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
            let groove = if (z - 1.23).abs() < 0.05 { 0.005 } else { 0.0 };
            pts.push(ChartPoint {
                z,
                p,
                s: groove + clutter,
            });
        }
        pts
    }

    #[test]
    fn groove_is_found_at_its_position() {
        let cfg = DecodConfig::tunnel();
        let contour = ReferenceContour::circle([0.0, 0.0], 3.0);
        let det = detect_boundaries(&scene(), &contour, 30.0, &cfg.boundary).unwrap();
        assert_eq!(det.peaks.len(), 1, "{:?}", det.peaks);
        assert!((det.peaks[0].z_m - 1.23).abs() < 0.01, "{:?}", det.peaks);
        assert!(det.peaks[0].response_m > 0.0);
    }

    #[test]
    fn a_side_lobe_is_not_a_peak() {
        assert!(displaced_as_response(Some(-0.2), -0.07));
        assert!(displaced_as_response(Some(0.004), 0.003));
        // The far side of a shadow: the rib's offset smoothed into the gap, positive DoG.
        assert!(!displaced_as_response(Some(-0.08), 0.09));
        // A lobe on the wall at its own level.
        assert!(!displaced_as_response(Some(0.001), 0.003));
        assert!(!displaced_as_response(None, 0.003));
    }

    #[test]
    fn half_observed_section_makes_no_step() {
        // Sector offsets differ by 2 cm between halves and one half is seen only for z > 0:
        // without per-sector normalisation this is a 1 cm step at z = 0.
        let cfg = DecodConfig::tunnel();
        let contour = ReferenceContour::circle([0.0, 0.0], 3.0);
        let pts: Vec<ChartPoint> = (0..100_000)
            .filter_map(|i| {
                let z = -3.0 + 6.0 * (i as f64 / 100_000.0);
                let p = (i as f64 * 0.618_033_988_7).fract();
                let s = if p < 0.5 { 0.02 } else { 0.0 };
                (p >= 0.5 || z > 0.0).then_some(ChartPoint { z, p, s })
            })
            .collect();
        let det = detect_boundaries(&pts, &contour, 30.0, &cfg.boundary).unwrap();
        assert!(det.peaks.is_empty(), "{:?}", det.peaks);
    }
}
