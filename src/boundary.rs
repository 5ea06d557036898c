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
//! 6. a groove peak with exactly one *twin* (another groove candidate, at least `TWIN_RATIO` as
//!    strong, within `TWIN_WINDOW_SIGMAS` large sigmas and the suppression radius, with the
//!    surface between them back at least halfway to the wall: two bands, not the two edges
//!    of one wide groove) is one boundary between two bands, placed midway. A ring joint of
//!    a segmental lining is a 1.5 cm seam between two bands of bolt pockets 8 cm deep, 0.2 m
//!    either side (the simulator's shield, after common pocket layouts): the pockets, not
//!    the seam, give the response, and suppression kept whichever band was stronger in that
//!    view, 0.2 m from the joint on either side. Several candidates (a corrugation) or a
//!    weaker neighbour leave the peak where it is. Ribs are left alone: pairing them too
//!    (the horseshoe's arches, each alone in its window, met overbreak and shadow edges)
//!    gave 23 fewer loops and 3 fewer runs with every registry joint within 1 % on the
//!    matrix's tuned rows (m41 against m42), nothing better.
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

/// Step 6: a second candidate this strong (fraction of the peak's |DoG|), of the same sign,
/// within [`TWIN_WINDOW_SIGMAS`] makes the pair twin bands (module doc).
const TWIN_RATIO: f64 = 0.5;
/// Step 6: how far a twin may lie, in large DoG sigmas (auto scaling: r / 30). In a 3 m
/// tunnel 0.8 m (the suppression radius caps it): pocket bands 0.2 m either side of the seam
/// respond at their edges, 0.33-0.47 m apart. In a 0.3 m pipe 8 cm: chips and lateral
/// connections tens of centimetres from a joint are other features, not the joint's other
/// half (with the suppression radius as the window, the worst registry joint of hume runs
/// went from 0.1-1.6 % to 1.6-5 % of its chainage in a partial matrix run).
const TWIN_WINDOW_SIGMAS: f64 = 8.0;
/// Step 6: between twin bands the surface comes back to this fraction of the shallower
/// band's depth (at its response peak) or less: the wall between two bands. Across one wide
/// groove it stays at the groove's depth. Half: a response peak sits on a band's edge, where
/// the smoothed surface is about half as deep as the band, so the wall between must come
/// back further than any point of the band itself.
const TWIN_RETURN: f64 = 0.5;

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
    let (zmin, nbins) = profile_extent(points, bin)?;
    let (sum, weight) = axial_profile(points, contour, bottom_mask_deg, cfg, zmin, nbins);
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
    let w = (cfg.dog_sigma_large_m / bin).ceil().max(1.0) as usize;
    let mut candidates = local_maxima(&dog, &valid, &small, threshold, w);
    let candidate_count = candidates.len();
    candidates.sort_by(|&i, &j| dog[j].abs().total_cmp(&dog[i].abs()));
    let radius_bins = cfg.nms_radius_m / bin;
    let mut kept: Vec<usize> = Vec::new();
    for &b in &candidates {
        if kept
            .iter()
            .all(|&k| (k as f64 - b as f64).abs() > radius_bins)
        {
            kept.push(b);
        }
    }
    let twin_bins = radius_bins.min(TWIN_WINDOW_SIGMAS * cfg.dog_sigma_large_m / bin);
    let profile = Profile {
        z0_m: zmin,
        bin_m: bin,
        dog: &dog,
        surface: &small,
    };
    let peaks = kept
        .iter()
        .map(|&b| profile.peak(b, &candidates, twin_bins))
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

/// The first profile bin's lower edge (the lowest point's `z`) and the number of bins of
/// `bin` metres that cover `points` (not empty), at most [`MAX_PROFILE_BINS`].
fn profile_extent(points: &[ChartPoint], bin: f64) -> Result<(f64, usize)> {
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
    Ok((zmin, nbins))
}

/// Step 4's candidates: bins whose `|DoG|` reaches `threshold`, not a side lobe (step 5),
/// and is the maximum over +-`w` bins (one large sigma), all of them valid: a slope cut by
/// the edge margin (the true maximum may lie beyond it) is not a peak. Side lobes are never
/// peaks and do not hide the response they flank. In bin order.
fn local_maxima(
    dog: &[f64],
    valid: &[bool],
    surface: &[Option<f64>],
    threshold: f64,
    w: usize,
) -> Vec<usize> {
    let lobe: Vec<bool> = dog
        .iter()
        .zip(surface)
        .map(|(&d, &v)| !displaced_as_response(v, d))
        .collect();
    (w..dog.len().saturating_sub(w))
        .filter(|&b| {
            let m = dog[b].abs();
            m >= threshold
                && !lobe[b]
                && (b - w..=b + w).all(|j| {
                    valid[j] && (lobe[j] || dog[j].abs() < m || (j <= b && dog[j].abs() <= m))
                })
        })
        .collect()
}

/// Steps 1-2 of the module doc: per-sector median offsets, then the sum and count of the
/// normalised offsets per axial bin (`nbins` bins of `cfg.profile_bin_m` from `zmin`), the
/// bottom sector masked.
fn axial_profile(
    points: &[ChartPoint],
    contour: &ReferenceContour,
    bottom_mask_deg: f64,
    cfg: &BoundaryConfig,
    zmin: f64,
    nbins: usize,
) -> (Vec<f64>, Vec<f64>) {
    let bin = cfg.profile_bin_m;
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
    (sum, weight)
}

/// The profile a peak is placed on: its first bin's lower edge, bin size, DoG and surface
/// (small-Gaussian profile).
struct Profile<'a> {
    z0_m: f64,
    bin_m: f64,
    dog: &'a [f64],
    surface: &'a [Option<f64>],
}

impl Profile<'_> {
    /// Bin `b`'s axial position, refined to sub-bin precision by a parabola through it and its
    /// neighbours.
    fn refined(&self, b: usize) -> f64 {
        let dog = self.dog;
        let (l, c, r) = (dog[b - 1].abs(), dog[b].abs(), dog[b + 1].abs());
        let denom = l - 2.0 * c + r;
        let shift = if denom.abs() > 1e-18 {
            (0.5 * (l - r) / denom).clamp(-0.5, 0.5)
        } else {
            0.0
        };
        self.z0_m + (b as f64 + 0.5 + shift) * self.bin_m
    }

    /// The boundary of kept peak `b`: midway between twin bands (step 6), else at the peak.
    fn peak(&self, b: usize, candidates: &[usize], twin_window_bins: f64) -> BoundaryPeak {
        let z_m = match self.twin_of(b, candidates, twin_window_bins) {
            Some(t) => 0.5 * (self.refined(b) + self.refined(t)),
            None => self.refined(b),
        };
        BoundaryPeak {
            z_m,
            strength_m: self.dog[b].abs(),
            response_m: self.dog[b],
        }
    }

    /// Step 6 of the module doc: for a groove peak `b` (positive response), the one other
    /// groove candidate of at least [`TWIN_RATIO`] of its strength within `window_bins`, with
    /// the surface between them back to [`TWIN_RETURN`] of the shallower one's depth or less,
    /// if there is exactly one (`candidates`: every candidate, any order).
    fn twin_of(&self, b: usize, candidates: &[usize], window_bins: f64) -> Option<usize> {
        let (dog, surface) = (self.dog, self.surface);
        if dog[b] <= 0.0 {
            return None; // ribs have no twins (module doc, step 6)
        }
        // Two bands, not the two edges of one wide groove: between them the surface comes
        // back at least halfway to the wall.
        let depth = |j: usize| surface[j].unwrap_or(0.0);
        let apart = |c: usize| {
            let (lo, hi) = (b.min(c), b.max(c));
            let half = TWIN_RETURN * depth(b).min(depth(c));
            (lo..=hi).any(|j| surface[j].is_some_and(|v| v <= half))
        };
        let mut twins = candidates.iter().copied().filter(|&c| {
            c != b
                && (c as f64 - b as f64).abs() <= window_bins
                && dog[c] >= TWIN_RATIO * dog[b]
                && apart(c)
        });
        match (twins.next(), twins.next()) {
            (Some(t), None) => Some(t),
            _ => None,
        }
    }
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

    /// A tunnel wall with recessed bands `(centre m, half-width m, depth m)`.
    fn banded(bands: &[(f64, f64, f64)]) -> Vec<ChartPoint> {
        (0..200_000)
            .map(|i| {
                let z = -3.0 + 6.0 * (i as f64 / 200_000.0);
                let p = (i as f64 * 0.618_033_988_7).fract();
                let clutter = 1e-3 * ((i * 7919 % 17) as f64 / 8.0 - 1.0);
                let recess: f64 = bands
                    .iter()
                    .filter(|(c, h, _)| (z - c).abs() < *h)
                    .map(|(_, _, d)| d)
                    .sum();
                ChartPoint {
                    z,
                    p,
                    s: recess + clutter,
                }
            })
            .collect()
    }

    fn peaks_of(bands: &[(f64, f64, f64)]) -> Vec<BoundaryPeak> {
        let cfg = DecodConfig::tunnel();
        let contour = ReferenceContour::circle([0.0, 0.0], 3.0);
        detect_boundaries(&banded(bands), &contour, 30.0, &cfg.boundary)
            .unwrap()
            .peaks
    }

    #[test]
    fn twin_pocket_bands_put_the_boundary_at_the_seam_between_them() {
        // A ring seam (1.5 cm, 2 cm wide) at z = 0.5 between bolt-pocket bands 8 and 7.6 cm
        // deep, 18 cm wide, 0.2 m either side: the simulator's shield joint.
        let joint = [(0.5, 0.01, 0.015), (0.3, 0.09, 0.08), (0.7, 0.09, 0.076)];
        let peaks = peaks_of(&joint);
        assert_eq!(peaks.len(), 1, "{peaks:?}");
        // A band 18 cm wide responds at its edges (7 cm apart within one large sigma, so
        // one candidate per band): the midpoint is the seam to within half that.
        assert!((peaks[0].z_m - 0.5).abs() < 0.04, "{peaks:?}");
        // One band alone, or beside a much weaker one, stays at that band.
        let peaks = peaks_of(&[(0.3, 0.09, 0.08)]);
        assert!((peaks[0].z_m - 0.3).abs() < 0.09, "{peaks:?}");
        let peaks = peaks_of(&[(0.3, 0.09, 0.08), (0.7, 0.09, 0.02)]);
        assert!((peaks[0].z_m - 0.3).abs() < 0.09, "{peaks:?}");
        // Three bands in the radius (a corrugation): no pair, the strongest band stays.
        let peaks = peaks_of(&[(0.0, 0.09, 0.07), (0.35, 0.09, 0.08), (0.7, 0.09, 0.07)]);
        assert!((peaks[0].z_m - 0.35).abs() < 0.09, "{peaks:?}");
        // The two edges of one groove 25 cm wide (two candidates, no wall between them)
        // are not twins: the peak stays at an edge.
        let peaks = peaks_of(&[(0.5, 0.125, 0.03)]);
        assert!((peaks[0].z_m - 0.5).abs() > 0.05, "{peaks:?}");
        // Two ribs are not twins: the peak stays at one of them.
        let peaks = peaks_of(&[(0.3, 0.09, -0.08), (0.7, 0.09, -0.076)]);
        let z = peaks[0].z_m;
        assert!(
            (z - 0.3).abs() < 0.09 || (z - 0.7).abs() < 0.09,
            "{peaks:?}"
        );
        // A groove and a rib (opposite signs) are not twins.
        let peaks = peaks_of(&[(0.3, 0.09, 0.08), (0.7, 0.09, -0.08)]);
        let z = peaks[0].z_m;
        assert!(
            (z - 0.3).abs() < 0.09 || (z - 0.7).abs() < 0.09,
            "{peaks:?}"
        );
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
