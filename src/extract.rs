//! The per-submap extraction pipeline (paper §III-A, Fig. 2 left and middle):
//! axis -> basis -> contour -> boundaries -> descriptors. Every submap yields landmarks or
//! rejections with their reasons (nothing is dropped silently), plus diagnostics.

use std::fmt;

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::axis::{
    CorridorAxis, along, angle_deg, centroid, estimate_axis, refine_axis, transverse_basis,
};
use crate::boundary::{BoundaryPeak, ChartPoint, detect_boundaries};
use crate::centre_line::{self, CentreLine};
use crate::config::DecodConfig;
use crate::contour::{ContourFit, fit_contour};
use crate::corridor_end::{EndFace, face_in_view, trim_end_face};
use crate::descriptor::{bottom_mask, build_descriptor, column_samples};
use crate::landmark::Landmark;
use crate::submap::Submap;
use crate::wall_normals::wall_normal_axis;

/// Why a submap (or a boundary in it) yielded no landmark.
#[derive(Clone, Debug, PartialEq)]
pub enum RejectionReason {
    /// Fewer points than `submap.min_points` after filtering.
    TooFewPoints {
        /// Points in the submap.
        count: usize,
        /// Required minimum.
        min: usize,
    },
    /// The ratio of the two largest singular values is below `axis.min_elongation`.
    NotElongated {
        /// Measured ratio.
        ratio: f64,
        /// Required minimum.
        min: f64,
    },
    /// Gravity is along the corridor axis: no circumferential origin (vertical shaft).
    GravityAlongAxis,
    /// Too few projected points lie near the fitted contour.
    ContourMisfit {
        /// Fraction within `contour.inlier_distance_m`.
        inlier_fraction: f64,
        /// Required minimum.
        min: f64,
    },
    /// The DoG profile has no peak above the threshold.
    NoBoundary {
        /// The threshold that applied, metres.
        threshold_m: f64,
    },
    /// A boundary was found but its descriptor has no observed cell.
    EmptyDescriptor {
        /// Axial position of the boundary from the submap centroid, metres.
        z_m: f64,
    },
    /// The geometry could not be computed (degenerate input); the text says why.
    Degenerate(String),
}

/// A submap or boundary that yielded no landmark, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Rejection {
    /// Anchor stamp of the submap, seconds.
    pub submap_stamp: f64,
    /// The reason.
    pub reason: RejectionReason,
}

impl RejectionReason {
    /// Short machine-readable kind (`"too_few_points"`, `"not_elongated"`, ...).
    pub fn kind(&self) -> &'static str {
        match self {
            Self::TooFewPoints { .. } => "too_few_points",
            Self::NotElongated { .. } => "not_elongated",
            Self::GravityAlongAxis => "gravity_along_axis",
            Self::ContourMisfit { .. } => "contour_misfit",
            Self::NoBoundary { .. } => "no_boundary",
            Self::EmptyDescriptor { .. } => "empty_descriptor",
            Self::Degenerate(_) => "degenerate",
        }
    }
}

impl fmt::Display for RejectionReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::TooFewPoints { count, min } => {
                write!(f, "too few points: {count} < submap.min_points = {min}")
            }
            Self::NotElongated { ratio, min } => write!(
                f,
                "not a corridor: singular value ratio {ratio:.2} < axis.min_elongation = {min}"
            ),
            Self::GravityAlongAxis => write!(f, "gravity is along the corridor axis"),
            Self::ContourMisfit {
                inlier_fraction,
                min,
            } => write!(
                f,
                "contour does not fit: {:.1} % of points near it < contour.min_inlier_fraction = {:.1} %",
                100.0 * inlier_fraction,
                100.0 * min
            ),
            Self::NoBoundary { threshold_m } => write!(
                f,
                "no boundary: no DoG peak above {:.2} mm",
                1e3 * threshold_m
            ),
            Self::EmptyDescriptor { z_m } => {
                write!(
                    f,
                    "boundary at z = {z_m:.3} m has no observed descriptor cell"
                )
            }
            Self::Degenerate(why) => write!(f, "degenerate geometry: {why}"),
        }
    }
}

impl fmt::Display for Rejection {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "submap {:.3}: {}", self.submap_stamp, self.reason)
    }
}

/// What extraction saw in one submap (filled as far as the pipeline got).
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SubmapDiagnostics {
    /// Points in the submap.
    pub point_count: usize,
    /// Corridor axis in the submap frame (zeros if not reached).
    pub axis: [f64; 3],
    /// Centroid of the submap, metres.
    pub centroid: [f64; 3],
    /// Ratio of the two largest singular values.
    pub elongation: f64,
    /// `"circle"` or `"polar"` (empty if not reached).
    pub contour_model: String,
    /// Contour centre along `(e1, e2)` from the centroid, metres.
    pub contour_centre_e1e2: [f64; 2],
    /// Mean contour radius, metres.
    pub contour_radius_m: f64,
    /// Fraction of projected points within `contour.inlier_distance_m`.
    pub contour_inlier_fraction: f64,
    /// Median absolute offset from the contour, metres.
    pub contour_median_abs_offset_m: f64,
    /// 90th percentile of the absolute offsets from the contour over the chart (on at most
    /// `RELIEF_SAMPLE` evenly strided points), metres: the wall's relief about the contour
    /// (steel arches before the rock, ribs, couplers), which `auto` measures on its probes.
    pub contour_p90_abs_offset_m: f64,
    /// Radius of the curve of the corridor's centre line within the submap, metres
    /// (`crate::centre_line`; infinite where it is straight or not reached).
    pub curve_radius_m: f64,
    /// Local DoG maxima above threshold before non-maximum suppression.
    pub boundary_candidates: usize,
    /// Robust spread of the DoG profile, metres.
    pub dog_sigma_m: f64,
    /// Peak threshold applied, metres.
    pub dog_threshold_m: f64,
    /// The whole cloud failed the corridor test and the part before an end face in view
    /// passed it (`crate::corridor_end`): the diagnostics above are that part's.
    pub end_face: bool,
    /// An end face in view (`crate::corridor_end::face_in_view`): along the settled axis of a
    /// corridor, or along the heading or the principal direction of a submap rejected as
    /// none (the last metres before a blind end).
    pub face_in_view: Option<EndFace>,
}

/// Landmarks, rejections and diagnostics of one submap.
#[derive(Clone, Debug, Default)]
pub struct ExtractionOutcome {
    /// One landmark per accepted boundary, strongest first.
    pub landmarks: Vec<Landmark>,
    /// Every reason something yielded no landmark.
    pub rejections: Vec<Rejection>,
    /// What the pipeline measured.
    pub diagnostics: SubmapDiagnostics,
}

/// Runs the extraction pipeline on one submap (paper §III-A):
/// 1. point count check;
/// 2. axis by PCA, oriented with forward; elongation check (`axis.min_elongation`); a cloud
///    that fails steps 2-5 is tried once more on its part before an end face in view
///    ([`crate::corridor_end`], not in the paper), and one too short along its corridor for
///    PCA with other axes (`short_corridor`, not in the paper);
/// 3. basis `e1, e2` from gravity (Eq. 1);
/// 4. projection on the transverse plane and contour fit, with `axis.refine_iterations`
///    Gauss–Newton refinements of the axis from the contour residuals (`axis::refine_axis`);
///    where they do not settle, the wall's normals and the contour decide the axis
///    ([`crate::wall_normals`], not in the paper); contour validation on every point
///    (§IV-A.2);
/// 5. unrolling of every point to `(z, p, s)` once;
/// 6. boundaries by DoG + NMS on the axial profile;
/// 7. one descriptor per boundary, origin `o` = contour centre at the peak.
///
/// Every submap is also searched for an end face in view (`SubmapDiagnostics::face_in_view`,
/// [`crate::corridor_end::face_in_view`]; not in the paper): along the settled axis once
/// step 4 has one, along the heading or the principal direction when the submap is rejected.
pub fn extract_landmarks(submap: &Submap, cfg: &DecodConfig) -> ExtractionOutcome {
    let mut out = ExtractionOutcome::default();
    if let Err(reason) = extract_into(submap, cfg, &mut out) {
        let enough = submap.points_in_anchor.len() >= cfg.submap.min_points.max(3);
        if out.diagnostics.face_in_view.is_none() && enough {
            out.diagnostics.face_in_view = end_face_of_rejected(submap, cfg, out.diagnostics.axis);
        }
        out.rejections.push(Rejection {
            submap_stamp: submap.anchor_stamp,
            reason,
        });
    }
    out
}

/// The steps of [`extract_landmarks`], filling `out` as far as they get; the reason the
/// submap stopped short of its descriptors, if it did.
fn extract_into(
    submap: &Submap,
    cfg: &DecodConfig,
    out: &mut ExtractionOutcome,
) -> Result<(), RejectionReason> {
    let points = &submap.points_in_anchor;
    out.diagnostics.point_count = points.len();
    let min = cfg.submap.min_points.max(3);
    if points.len() < min {
        return Err(RejectionReason::TooFewPoints {
            count: points.len(),
            min,
        });
    }
    // 2. Axis.
    let axis = estimate_axis(points, submap.forward_in_anchor)
        .map_err(|e| RejectionReason::Degenerate(e.to_string()))?;
    out.diagnostics.axis = axis.axis;
    out.diagnostics.centroid = axis.centroid;
    out.diagnostics.elongation = axis.elongation;
    // 3-5, or the same on the part of the cloud before an end face in view.
    let (frame, chart) = match corridor(submap, cfg, &axis, &mut out.diagnostics) {
        Ok(found) => found,
        Err(reason) => {
            let short = matches!(reason, RejectionReason::NotElongated { .. });
            before_end_face(submap, cfg, &axis, &mut out.diagnostics)
                .or_else(|| {
                    short.then(|| short_corridor(submap, cfg, &axis, &mut out.diagnostics))?
                })
                .ok_or(reason)?
        }
    };
    out.diagnostics.face_in_view = end_face_in_view(submap, cfg, &frame);
    // 6. Boundaries.
    let detection = detect_boundaries(
        &chart.points,
        &frame.fit.contour,
        cfg.descriptor.bottom_mask_deg,
        &cfg.boundary,
    )
    .map_err(|e| RejectionReason::Degenerate(e.to_string()))?;
    out.diagnostics.boundary_candidates = detection.candidates;
    out.diagnostics.dog_sigma_m = detection.dog_sigma_m;
    out.diagnostics.dog_threshold_m = detection.threshold_m;
    if detection.peaks.is_empty() {
        return Err(RejectionReason::NoBoundary {
            threshold_m: detection.threshold_m,
        });
    }
    // 7.
    describe_boundaries(submap, cfg, &frame, &chart, &detection.peaks, out);
    Ok(())
}

/// Steps 2 (elongation check) to 5 on the whole cloud.
fn corridor(
    submap: &Submap,
    cfg: &DecodConfig,
    axis: &CorridorAxis,
    diag: &mut SubmapDiagnostics,
) -> Result<(CorridorFrame, Chart), RejectionReason> {
    if axis.elongation.is_nan() || axis.elongation < cfg.axis.min_elongation {
        return Err(RejectionReason::NotElongated {
            ratio: axis.elongation,
            min: cfg.axis.min_elongation,
        });
    }
    // 3-4.
    let points = &submap.points_in_anchor;
    let frame = best_frame(points, submap, cfg, axis)?;
    diag.axis = frame.a;
    // 5.
    let chart = unrolled_chart(points, &frame, cfg, diag)?;
    Ok((frame, chart))
}

/// Steps 3-5 on a cloud too short along its corridor for PCA to name the axis (not in the
/// paper): the sensor's heading, then the principal directions (the least one first: the
/// axis of a ring), are tried as the axis until one passes the corridor test (the contour
/// fit; the refinement settles the axis from each) with a section that closes around it
/// ([`SHORT_SECTION_ARC`] of the contour seen; the narrow sensor's pipe submaps: all of it). A forward sensor with a 38 deg field
/// of view sees a 0.6 m pipe's wall from 0.7 m to 1.5 m ahead, densest at the near end: held
/// out (seed 197), 214 of its 233 submaps had singular-value ratios below 1.1 and the run
/// closed no loop. `None`: no direction makes the cloud a corridor (a room, a stub of
/// clutter), and the submap stays `not_elongated`.
fn short_corridor(
    submap: &Submap,
    cfg: &DecodConfig,
    axis: &CorridorAxis,
    diag: &mut SubmapDiagnostics,
) -> Option<(CorridorFrame, Chart)> {
    let points = &submap.points_in_anchor;
    let guesses = [
        submap.forward_in_anchor,
        axis.directions[2],
        axis.directions[0],
        axis.directions[1],
    ];
    let (frame, chart, trial) = guesses.into_iter().find_map(|guess| {
        let mut trial = diag.clone();
        let frame = best_frame(
            points,
            submap,
            cfg,
            &CorridorAxis {
                axis: guess,
                ..*axis
            },
        )
        .ok()?;
        trial.axis = frame.a;
        let chart = unrolled_chart(points, &frame, cfg, &mut trial).ok()?;
        let arc = arc_observed(&chart.points, cfg.contour.inlier_distance_m);
        (arc >= SHORT_SECTION_ARC).then_some((frame, chart, trial))
    })?;
    *diag = trial;
    Some((frame, chart))
}

/// Share of its contour's arc a short corridor (`short_corridor`) must be seen on: its
/// section closes around the axis. An open box room (a floor and four walls) fits a contour
/// along its length with every point on it once its end walls are cut, but nothing is seen
/// over its open top.
const SHORT_SECTION_ARC: f64 = 0.8;

/// Share of [`ARC_SECTORS`] equal sectors of the contour holding a point within `inlier_m`
/// of it.
fn arc_observed(chart: &[ChartPoint], inlier_m: f64) -> f64 {
    let mut seen = [false; ARC_SECTORS];
    for q in chart.iter().filter(|q| q.s.abs() <= inlier_m) {
        let k = (q.p.rem_euclid(1.0) * ARC_SECTORS as f64) as usize;
        seen[k.min(ARC_SECTORS - 1)] = true;
    }
    seen.iter().filter(|&&v| v).count() as f64 / ARC_SECTORS as f64
}

/// Sectors of [`arc_observed`] (10 deg of a round section each).
const ARC_SECTORS: usize = 36;

/// The trial with the largest share of points on its contour (the first of equals).
fn most_on_contour(
    trials: impl Iterator<Item = (CorridorFrame, Chart, SubmapDiagnostics)>,
) -> Option<(CorridorFrame, Chart, SubmapDiagnostics)> {
    trials.reduce(|best, t| {
        if t.2.contour_inlier_fraction > best.2.contour_inlier_fraction {
            t
        } else {
            best
        }
    })
}

/// The end face the whole cloud shows along the settled axis, looked for in slabs of a
/// descriptor row like [`before_end_face`]'s (`crate::corridor_end::face_in_view`).
fn end_face_in_view(submap: &Submap, cfg: &DecodConfig, frame: &CorridorFrame) -> Option<EndFace> {
    face_in_view(&submap.points_in_anchor, frame.a, true, face_slab_m(cfg))
}

/// The end face a submap that is not a corridor shows along the sensor's heading or its
/// principal direction (the last metres before a blind end, where the face fills the view).
fn end_face_of_rejected(submap: &Submap, cfg: &DecodConfig, pca_axis: [f64; 3]) -> Option<EndFace> {
    [submap.forward_in_anchor, pca_axis]
        .into_iter()
        .filter(|g| g.iter().all(|v| v.is_finite()) && g.iter().any(|&v| v != 0.0))
        .find_map(|g| face_in_view(&submap.points_in_anchor, g, false, face_slab_m(cfg)))
}

/// Slabs of a descriptor row for the end-face search.
fn face_slab_m(cfg: &DecodConfig) -> f64 {
    cfg.descriptor.half_length_m * 2.0 / cfg.descriptor.rows.max(1) as f64
}

/// Steps 3-5 on the points before an end face in view ([`crate::corridor_end`]; not in
/// the paper), for a submap whose whole cloud failed them: the face is looked for along the
/// sensor's heading and along each principal direction, the face's normal is the axis, and
/// of the guesses whose trimmed cloud passes the corridor test the one with the most points
/// on its contour is taken (its diagnostics replace the failed ones). `None`: no face, a
/// room closed at both ends, or no trimmed cloud that is a corridor (the submap then keeps
/// the whole cloud's rejection).
fn before_end_face(
    submap: &Submap,
    cfg: &DecodConfig,
    axis: &CorridorAxis,
    diag: &mut SubmapDiagnostics,
) -> Option<(CorridorFrame, Chart)> {
    let slab = face_slab_m(cfg);
    let guesses = [
        submap.forward_in_anchor,
        axis.directions[0],
        axis.directions[1],
        axis.directions[2],
    ];
    let trials = guesses.into_iter().filter_map(|guess| {
        let (kept, a) = trim_end_face(&submap.points_in_anchor, guess, slab)?;
        // The face gave the axis; the trimmed cloud (3 points or more) its centroid.
        let c = centroid(&kept);
        let mut trial = diag.clone();
        trial.centroid = c;
        let frame = fit_frame(&kept, submap, cfg, c, a, cfg.axis.refine_iterations).ok()?;
        trial.axis = frame.a;
        let chart = unrolled_chart(&kept, &frame, cfg, &mut trial).ok()?;
        Some((frame, chart, trial))
    });
    let (frame, chart, mut trial) = most_on_contour(trials)?;
    trial.end_face = true;
    *diag = trial;
    Some((frame, chart))
}

/// A last refinement step longer than this (deg) means the refinement did not settle the
/// axis (`best_frame`). Where the wall is sampled evenly it settles within hundredths of a
/// degree in two steps; from the 11 deg lean of a pitched sensor's PCA it moved 2 deg per
/// step, the wrong way.
const UNSETTLED_STEP_DEG: f64 = 0.5;

/// The wall normals' axis is tried where it is further than this (deg) from the refined PCA
/// axis (`best_frame`).
const AXIS_DISAGREEMENT_DEG: f64 = 1.0;

/// Another axis replaces the refined PCA axis only where its contour's median absolute
/// offset is at most this share of the PCA axis's (`best_frame`): a pitched spinning sensor's
/// true axis fits 2.8-4.5 times tighter (median 0.25, 90th percentile 0.36 over a simulated
/// horseshoe run), while the forward rosette's submaps, whose refinement also moves 0.8-2 deg
/// a step, gain 5-20 % from axes 0.2-0.5 deg away: that is within what the contour's own
/// fit decides, and taking it moved landmarks enough to pass two loops 0.32-0.38 m off in
/// the matrix's 10 m horseshoe (m114).
const DECISIVE_TIGHTENING: f64 = 0.5;

/// Golden-section steps of the search between two disagreeing axes: the bracket, 1.5 times
/// their angle, shrinks to 0.3 % of it (0.06 deg for axes 20 deg apart).
const AXIS_SEARCH_STEPS: usize = 12;

/// Steps 3-4 from the PCA axis; where its refinement does not settle
/// ([`UNSETTLED_STEP_DEG`]) and the wall's normals give an axis further from it than
/// [`AXIS_DISAGREEMENT_DEG`] ([`crate::wall_normals`]), also from the axis on the arc
/// through the two (and a quarter of it beyond each) whose contour fits tightest (smallest
/// median absolute offset, golden-section search), which replaces the PCA frame if it fits
/// decisively tighter ([`DECISIVE_TIGHTENING`]). Not in
/// the paper: a spinning sensor pitched 20 deg on its mount samples the floor ahead and the
/// crown behind, PCA leans 11 deg one way, the normals (their visible facets lean towards
/// the sensor) 5 deg the other, and the contour's median offset is smallest at the true axis
/// (0.035-0.044 m there against 0.06-0.10 m 5 deg off, in a simulated 5 m horseshoe). Where
/// the refinement settles (the matrix's spinning sensors, all level) nothing else is tried.
fn best_frame(
    points: &[[f32; 3]],
    submap: &Submap,
    cfg: &DecodConfig,
    axis: &CorridorAxis,
) -> Result<CorridorFrame, RejectionReason> {
    let refine = cfg.axis.refine_iterations;
    let c = axis.centroid;
    let pca = fit_frame(points, submap, cfg, c, axis.axis, refine)?;
    if pca.last_step_deg <= UNSETTLED_STEP_DEG {
        return Ok(pca);
    }
    let Some(normals) = wall_normal_axis(points, cfg.submap.voxel_m, submap.forward_in_anchor)
        .filter(|n| angle_deg(*n, pca.a) > AXIS_DISAGREEMENT_DEG)
    else {
        return Ok(pca);
    };
    // The axis on the arc from the PCA axis to the normals' (a quarter beyond each end) whose
    // contour fits tightest, refined.
    let on_arc = |t: f64| {
        let v = [0, 1, 2].map(|k| (1.0 - t) * axis.axis[k] + t * normals[k]);
        let norm = v.iter().map(|x| x * x).sum::<f64>().sqrt();
        v.map(|x| x / norm)
    };
    let spread = |t: f64| {
        fit_frame(points, submap, cfg, c, on_arc(t), 0)
            .map_or(f64::INFINITY, |f| f.fit.median_abs_offset_m)
    };
    let t = golden_minimum(spread, -0.25, 1.25, AXIS_SEARCH_STEPS);
    Ok(match fit_frame(points, submap, cfg, c, on_arc(t), refine) {
        Ok(f) if f.fit.median_abs_offset_m <= DECISIVE_TIGHTENING * pca.fit.median_abs_offset_m => {
            f
        }
        _ => pca,
    })
}

/// Golden-section search for the minimum of `f` on `[lo, hi]` in `steps` steps (the
/// bracket's middle at the end).
fn golden_minimum(f: impl Fn(f64) -> f64, lo: f64, hi: f64, steps: usize) -> f64 {
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let (mut a, mut b) = (lo, hi);
    let (mut x1, mut x2) = (b - g * (b - a), a + g * (b - a));
    let (mut f1, mut f2) = (f(x1), f(x2));
    for _ in 0..steps {
        if f1 <= f2 {
            b = x2;
            (x2, f2) = (x1, f1);
            x1 = b - g * (b - a);
            f1 = f(x1);
        } else {
            a = x1;
            (x1, f1) = (x2, f2);
            x2 = a + g * (b - a);
            f2 = f(x2);
        }
    }
    0.5 * (a + b)
}

/// The submap's corridor frame: centroid `c`, axis `a`, basis `e1, e2` (Eq. 1) and the
/// contour fitted in it.
struct CorridorFrame {
    c: [f64; 3],
    a: [f64; 3],
    e1: [f64; 3],
    e2: [f64; 3],
    fit: ContourFit,
    /// How far the last refinement moved the axis, deg (0 without refinement).
    last_step_deg: f64,
}

/// Steps 3-4: basis (Eq. 1), projection on the transverse plane and contour fit on an evenly
/// strided subset (`contour.max_fit_points`), then `axis.refine_iterations` Gauss-Newton
/// steps on the axis from the contour residuals; all on the subset, so that the full cloud
/// is projected and unrolled only once (step 5).
fn fit_frame(
    points: &[[f32; 3]],
    submap: &Submap,
    cfg: &DecodConfig,
    c: [f64; 3],
    axis: [f64; 3],
    refinements: usize,
) -> Result<CorridorFrame, RejectionReason> {
    let mut a = axis;
    let stride = points
        .len()
        .div_ceil(cfg.contour.max_fit_points.max(3))
        .max(1);
    let subset: Vec<[f32; 3]> = points.iter().step_by(stride).copied().collect();
    let mut refine_left = refinements;
    let mut last_step_deg = 0.0;
    // `auto` chooses the model on the first fit; refinements keep that model.
    let mut contour_cfg = cfg.contour.clone();
    loop {
        let (e1, e2) = transverse_basis(a, submap.gravity_in_anchor)
            .map_err(|_| RejectionReason::GravityAlongAxis)?;
        let (uv, z) = project(&subset, c, a, e1, e2);
        let fit = fit_contour(&uv, &contour_cfg)
            .map_err(|e| RejectionReason::Degenerate(e.to_string()))?;
        contour_cfg.model = fit.contour.model.name().to_string();
        if refine_left == 0 {
            return Ok(CorridorFrame {
                c,
                a,
                e1,
                e2,
                fit,
                last_step_deg,
            });
        }
        refine_left -= 1;
        let contour = &fit.contour;
        let samples = uv.iter().zip(&z).map(|(&x, &z)| {
            let u = contour.unroll(x);
            let n = contour.sample(u.p).normal;
            (z, n[0], n[1], u.s)
        });
        // Inliers: within 3 robust sigmas (1.4826 MAD) of the contour.
        let gate = 3.0 * 1.4826 * fit.median_abs_offset_m;
        match refine_axis(a, e1, e2, samples, gate.max(1e-6)) {
            Some(refined) => {
                let f = submap.forward_in_anchor;
                let next = along(nalgebra::Vector3::from(refined), f);
                last_step_deg = angle_deg(a, next);
                a = next;
            }
            None => {
                return Ok(CorridorFrame {
                    c,
                    a,
                    e1,
                    e2,
                    fit,
                    last_step_deg,
                });
            }
        }
    }
}

/// The unrolled points bucketed by axial descriptor cell (counting sort, O(N)), so that
/// each descriptor reads only the points within its +-half_length window.
struct Chart {
    points: Vec<ChartPoint>,
    bucket_start: Vec<usize>,
    z_lo: f64,
    bucket_m: f64,
    /// The centre line where the corridor curves within the submap (`crate::centre_line`):
    /// the offsets above are taken from it.
    centre_line: Option<CentreLine>,
}

/// Step 5: every point unrolled once to `(z, p, s)`, cut to the corridor's axial span, and
/// the contour validated on all of them (paper §IV-A.2: >= 90 % within 0.18 m); fills the
/// contour diagnostics.
fn unrolled_chart(
    points: &[[f32; 3]],
    frame: &CorridorFrame,
    cfg: &DecodConfig,
    diag: &mut SubmapDiagnostics,
) -> Result<Chart, RejectionReason> {
    let (c, a, e1, e2) = (frame.c, frame.a, frame.e1, frame.e2);
    let contour = &frame.fit.contour;
    let unroll = |p: &[f32; 3], line: Option<&CentreLine>| {
        let d = [p[0] as f64 - c[0], p[1] as f64 - c[1], p[2] as f64 - c[2]];
        let dot = |v: &[f64; 3]| d[0] * v[0] + d[1] * v[1] + d[2] * v[2];
        centre_line::unroll(contour, line, dot(&a), [dot(&e1), dot(&e2)])
    };
    // A corridor that curves within the submap: its centre line, fitted on a subset unrolled
    // from the straight axis; every point is then unrolled from it.
    let centre_line = if cfg.axis.curved {
        let stride = points.len().div_ceil(centre_line::FIT_POINTS).max(1);
        let sample: Vec<ChartPoint> = points
            .iter()
            .step_by(stride)
            .map(|p| unroll(p, None))
            .collect();
        centre_line::fit(&sample, contour, cfg.contour.inlier_distance_m)
    } else {
        None
    };
    let chart: Vec<ChartPoint> = points
        .iter()
        .map(|p| unroll(p, centre_line.as_ref()))
        .collect();
    diag.curve_radius_m = centre_line.map_or(f64::INFINITY, |l| l.radius_m());
    // A corridor end (portal, cap, junction) in range: keep the axial span that is corridor.
    let chart = corridor_span(chart, cfg);
    let (chart, bucket_start, z_lo, bucket_m) = bucket_by_z(
        chart,
        cfg.descriptor.half_length_m * 2.0 / cfg.descriptor.rows.max(1) as f64,
    );
    let inliers = chart
        .iter()
        .filter(|q| q.s.abs() <= cfg.contour.inlier_distance_m)
        .count();
    let inlier_fraction = inliers as f64 / chart.len() as f64;
    diag.contour_model = contour.model.name().to_string();
    diag.contour_centre_e1e2 = contour.centre_uv;
    diag.contour_radius_m = contour.mean_radius_m;
    diag.contour_inlier_fraction = inlier_fraction;
    diag.contour_median_abs_offset_m = frame.fit.median_abs_offset_m;
    diag.contour_p90_abs_offset_m = p90_abs_offset(&chart);
    if inlier_fraction < cfg.contour.min_inlier_fraction {
        return Err(RejectionReason::ContourMisfit {
            inlier_fraction,
            min: cfg.contour.min_inlier_fraction,
        });
    }
    Ok(Chart {
        points: chart,
        bucket_start,
        z_lo,
        bucket_m,
        centre_line,
    })
}

/// Step 7: one descriptor per boundary, origin `o` = contour centre at the peak; a boundary
/// whose descriptor observes no cell is a rejection.
fn describe_boundaries(
    submap: &Submap,
    cfg: &DecodConfig,
    frame: &CorridorFrame,
    chart: &Chart,
    peaks: &[BoundaryPeak],
    out: &mut ExtractionOutcome,
) {
    let contour = &frame.fit.contour;
    let columns = column_samples(contour, cfg.descriptor.cols);
    let masked = bottom_mask(&columns, cfg.descriptor.bottom_mask_deg);
    let starts = &chart.bucket_start;
    let bucket = |z: f64| ((z - chart.z_lo) / chart.bucket_m).floor().max(0.0) as usize;
    for peak in peaks {
        let first = bucket(peak.z_m - cfg.descriptor.half_length_m).min(starts.len() - 1);
        let last = (bucket(peak.z_m + cfg.descriptor.half_length_m) + 1).min(starts.len() - 1);
        let window = &chart.points[starts[first]..starts[last]];
        let descriptor = build_descriptor(
            window,
            peak.z_m,
            contour,
            &columns,
            &masked,
            &cfg.descriptor,
        );
        if descriptor.observed_count() == 0 {
            out.rejections.push(Rejection {
                submap_stamp: submap.anchor_stamp,
                reason: RejectionReason::EmptyDescriptor { z_m: peak.z_m },
            });
            continue;
        }
        let (origin, axis, b1, b2) = local_frame(frame, chart.centre_line.as_ref(), peak.z_m);
        out.landmarks.push(Landmark {
            submap_stamp: submap.anchor_stamp,
            scan_stamps: submap.scan_stamps.clone(),
            origin_in_submap: origin,
            axis_in_submap: axis,
            e1_in_submap: b1,
            e2_in_submap: b2,
            contour_e1e2_m: columns.iter().map(|s| s.point).collect(),
            radius_m: contour.mean_radius_m,
            strength: peak.strength_m,
            descriptor,
        });
    }
}

/// A boundary's origin (the contour centre at the peak), axis and transverse basis in the
/// submap frame: on the fitted axis, or, where the corridor curves within the submap, on the
/// centre line's point there with its tangent for the axis (`crate::centre_line`; the basis
/// turned with it, `e1` kept as close as it goes).
fn local_frame(
    frame: &CorridorFrame,
    line: Option<&CentreLine>,
    z: f64,
) -> ([f64; 3], [f64; 3], [f64; 3], [f64; 3]) {
    let (c, a, e1, e2) = (frame.c, frame.a, frame.e1, frame.e2);
    let [cu, cv] = frame.fit.contour.centre_uv;
    let Some(line) = line else {
        let origin = std::array::from_fn(|i| c[i] + cu * e1[i] + cv * e2[i] + z * a[i]);
        return (origin, a, e1, e2);
    };
    let [du, dv] = line.offset(z);
    let [su, sv] = line.slope(z);
    let origin = std::array::from_fn(|i| c[i] + (cu + du) * e1[i] + (cv + dv) * e2[i] + z * a[i]);
    let (a, e1, e2) = (Vector3::from(a), Vector3::from(e1), Vector3::from(e2));
    let axis = (a + su * e1 + sv * e2).normalize();
    let b1 = (e1 - e1.dot(&axis) * axis).normalize();
    let b2 = axis.cross(&b1);
    let b2 = if b2.dot(&e2) < 0.0 { -b2 } else { b2 };
    (origin, axis.into(), b1.into(), b2.into())
}

/// Points sampled for `contour_p90_abs_offset_m`; enough for a percentile to 0.3 %.
const RELIEF_SAMPLE: usize = 50_000;

/// 90th percentile of `|s|` over an evenly strided subset of `chart` (0 if empty).
fn p90_abs_offset(chart: &[ChartPoint]) -> f64 {
    let stride = chart.len().div_ceil(RELIEF_SAMPLE).max(1);
    let mut s: Vec<f64> = chart.iter().step_by(stride).map(|q| q.s.abs()).collect();
    if s.is_empty() {
        return 0.0;
    }
    let k = (s.len() * 9 / 10).min(s.len() - 1);
    let (_, v, _) = s.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    *v
}

/// The chart cut to its corridor (`contour.corridor_span`) when the whole cloud fails the
/// corridor test (`contour.min_inlier_fraction` within `contour.inlier_distance_m`) and
/// what is kept is at least one descriptor long; else the chart as it is (the contour test
/// then decides). Slices are descriptor rows along the axis; `"longest"` keeps the longest
/// run of slices that each pass the test, `"ends"` drops the failing slices at either end
/// only (`auto`'s relief probe: a wall with arches keeps them), `"off"` keeps everything.
/// Not in the paper. A submap that sees the end of the corridor (a tunnel portal, a cap, a
/// junction) fails as a whole: on the simulated shield tunnel with a 64-beam sensor the
/// first and last four submaps of a 40 m run (80-89 % of points on the contour, the end cap
/// behind the sensor) gave no landmark, so the last metres of the return had no loop.
fn corridor_span(chart: Vec<ChartPoint>, cfg: &DecodConfig) -> Vec<ChartPoint> {
    let tol = cfg.contour.inlier_distance_m;
    let total = chart.iter().filter(|q| q.s.abs() <= tol).count();
    let mode = cfg.contour.corridor_span.as_str();
    if mode == "off"
        || chart.is_empty()
        || total as f64 >= cfg.contour.min_inlier_fraction * chart.len() as f64
    {
        return chart;
    }
    let slice = cfg.descriptor.half_length_m * 2.0 / cfg.descriptor.rows.max(1) as f64;
    let z_min = chart.iter().map(|q| q.z).fold(f64::INFINITY, f64::min);
    let z_max = chart.iter().map(|q| q.z).fold(f64::NEG_INFINITY, f64::max);
    if !(slice > 0.0 && z_max > z_min) || (z_max - z_min) / slice > 1e5 {
        return chart;
    }
    let n = ((z_max - z_min) / slice) as usize + 1;
    let key = |z: f64| (((z - z_min) / slice) as usize).min(n - 1);
    let (mut all, mut good) = (vec![0usize; n], vec![0usize; n]);
    for q in &chart {
        all[key(q.z)] += 1;
        good[key(q.z)] += usize::from(q.s.abs() <= tol);
    }
    let ok =
        |k: usize| all[k] == 0 || good[k] as f64 >= cfg.contour.min_inlier_fraction * all[k] as f64;
    let (lo, hi) = if mode == "ends" {
        let lo = (0..n).find(|&k| ok(k)).unwrap_or(n);
        let hi = (0..n).rev().find(|&k| ok(k)).map_or(lo, |k| k + 1);
        (lo, hi)
    } else {
        longest_passing_run(n, ok)
    };
    if ((hi - lo) as f64) * slice < 2.0 * cfg.descriptor.half_length_m {
        return chart;
    }
    chart
        .into_iter()
        .filter(|q| (lo..hi).contains(&key(q.z)))
        .collect()
}

/// The longest run `lo..hi` of slices `0..n` that each pass `ok` (the first if tied).
fn longest_passing_run(n: usize, ok: impl Fn(usize) -> bool) -> (usize, usize) {
    let (mut best, mut run_start) = ((0, 0), 0);
    for k in 0..=n {
        if k == n || !ok(k) {
            if k - run_start > best.1 - best.0 {
                best = (run_start, k);
            }
            run_start = k + 1;
        }
    }
    best
}

/// Counting sort of `chart` by `floor((z - z_min) / bucket_m)`. Returns the sorted points,
/// the start index of each bucket (`len = buckets + 1`, last = `chart.len()`), `z_min` and
/// the bucket size.
fn bucket_by_z(chart: Vec<ChartPoint>, bucket_m: f64) -> (Vec<ChartPoint>, Vec<usize>, f64, f64) {
    let z_min = chart.iter().map(|q| q.z).fold(f64::INFINITY, f64::min);
    let z_max = chart.iter().map(|q| q.z).fold(f64::NEG_INFINITY, f64::max);
    // Bounded bucket count: a far outlier cannot allocate without limit.
    let bucket_m = bucket_m.max((z_max - z_min) / 1e6).max(1e-9);
    let buckets = ((z_max - z_min) / bucket_m) as usize + 1;
    let key = |q: &ChartPoint| (((q.z - z_min) / bucket_m) as usize).min(buckets - 1);
    let mut start = vec![0usize; buckets + 1];
    for q in &chart {
        start[key(q) + 1] += 1;
    }
    for b in 0..buckets {
        start[b + 1] += start[b];
    }
    let mut next = start.clone();
    let mut sorted = vec![
        ChartPoint {
            z: 0.0,
            p: 0.0,
            s: 0.0
        };
        chart.len()
    ];
    for q in chart {
        let k = key(&q);
        sorted[next[k]] = q;
        next[k] += 1;
    }
    (sorted, start, z_min, bucket_m)
}

/// Transverse `(e1, e2)` coordinates and axial `z` of every point relative to `centroid`.
fn project(
    points: &[[f32; 3]],
    centroid: [f64; 3],
    a: [f64; 3],
    e1: [f64; 3],
    e2: [f64; 3],
) -> (Vec<[f64; 2]>, Vec<f64>) {
    let dot = |u: &[f64; 3], v: &[f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let mut uv = Vec::with_capacity(points.len());
    let mut z = Vec::with_capacity(points.len());
    for p in points {
        let d = [
            p[0] as f64 - centroid[0],
            p[1] as f64 - centroid[1],
            p[2] as f64 - centroid[2],
        ];
        uv.push([dot(&d, &e1), dot(&d, &e2)]);
        z.push(dot(&d, &a));
    }
    (uv, z)
}

/// [`extract_landmarks`] over many submaps in parallel (rayon); results in input order.
pub fn extract_all(submaps: &[Submap], cfg: &DecodConfig) -> Vec<ExtractionOutcome> {
    submaps
        .par_iter()
        .map(|m| extract_landmarks(m, cfg))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Rotation3, Vector3};
    use proptest::prelude::*;

    /// A pipe of radius 0.3 m along `+x` (3 m long), a 3 mm deep, 12 mm wide groove at
    /// x = 0.37, 0.3 mm of deterministic clutter, moved by `rot`, `trans`.
    fn pipe(n: usize, rot: Rotation3<f64>, trans: Vector3<f64>) -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| {
                let x = -1.5 + 3.0 * (i as f64 + 0.5) / n as f64;
                let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
                let noise = 3e-4 * (((i * 7919) % 17) as f64 / 8.0 - 1.0);
                let groove = if (x - 0.37).abs() < 0.006 { 0.003 } else { 0.0 };
                let r = 0.3 + noise + groove;
                let p = rot * Vector3::new(x, r * t.sin(), -r * t.cos()) + trans;
                [p.x as f32, p.y as f32, p.z as f32]
            })
            .collect()
    }

    fn run(
        points: Vec<[f32; 3]>,
        gravity: Vector3<f64>,
        forward: Vector3<f64>,
    ) -> ExtractionOutcome {
        let submap = Submap::from_points(1.0, points, gravity.into(), forward.into())
            .unwrap_or_else(|e| unreachable!("{e}"));
        extract_landmarks(&submap, &DecodConfig::pipe())
    }

    /// Fraction of cells observed in both with |difference| <= tol, and the mask agreement.
    fn compare(a: &Landmark, b: &Landmark, flip: bool, tol: f64) -> (f64, f64) {
        let (da, db) = (&a.descriptor, &b.descriptor);
        let (mut both, mut close, mut agree) = (0usize, 0usize, 0usize);
        for r in 0..da.rows {
            for c in 0..da.cols {
                let (rb, cb) = if flip {
                    (da.rows - 1 - r, da.cols - 1 - c)
                } else {
                    (r, c)
                };
                let (i, j) = (da.index(r, c), db.index(rb, cb));
                agree += usize::from(da.observed[i] == db.observed[j]);
                if da.observed[i] && db.observed[j] {
                    both += 1;
                    close +=
                        usize::from(f64::from((da.offsets_m[i] - db.offsets_m[j]).abs()) <= tol);
                }
            }
        }
        (
            close as f64 / both.max(1) as f64,
            agree as f64 / da.observed.len() as f64,
        )
    }

    #[test]
    fn tilted_pipe_groove_axis_and_descriptor() {
        let rot = Rotation3::from_euler_angles(0.05, 0.17, 0.35);
        let trans = Vector3::new(0.5, -0.3, 0.2);
        let out = run(pipe(100_000, rot, trans), -Vector3::z(), Vector3::x());
        assert!(out.rejections.is_empty(), "{:?}", out.rejections);
        assert_eq!(out.landmarks.len(), 1);
        let lm = &out.landmarks[0];
        let true_axis = rot * Vector3::x();
        let err_deg = Vector3::from(lm.axis_in_submap)
            .angle(&true_axis)
            .to_degrees();
        assert!(err_deg < 0.05, "axis error {err_deg} deg");
        let local = rot.inverse() * (Vector3::from(lm.origin_in_submap) - trans);
        // Within 1 cm along the axis (issue 2), and on the pipe's centre line.
        assert!((local.x - 0.37).abs() < 0.01, "{local:?}");
        assert!(local.y.abs() < 1e-3 && local.z.abs() < 1e-3, "{local:?}");
        // The origin sits on the groove centre, the edge between rows 7 and 8: each of them
        // holds 6 mm of the 3 mm deep groove in its 30 mm, a mean of 0.6 mm; rows away from
        // it ~0 (noise 0.3 mm over ~1.5k points per row: 0.01 mm; tolerance 0.1 mm).
        let d = &lm.descriptor;
        let row_mean = |r: usize| {
            let cells: Vec<f64> = (0..d.cols)
                .filter(|&c| d.observed[d.index(r, c)])
                .map(|c| f64::from(d.offsets_m[d.index(r, c)]))
                .collect();
            cells.iter().sum::<f64>() / cells.len().max(1) as f64
        };
        for r in [7, 8] {
            assert!(
                (row_mean(r) - 0.6e-3).abs() < 0.1e-3,
                "row {r}: {}",
                row_mean(r)
            );
        }
        assert!(row_mean(0).abs() < 0.1e-3 && row_mean(15).abs() < 0.1e-3);
    }

    const GROOVE_X: f64 = 0.6;

    /// The test pipe bent sideways on a curve of `bend` metres (centre line `y = x^2 / 2
    /// bend`), its groove at `GROOVE_X`.
    fn bent_pipe(n: usize, bend: f64) -> Vec<[f32; 3]> {
        (0..n)
            .map(|i| {
                let x = -1.5 + 3.0 * (i as f64 + 0.5) / n as f64;
                let t = (i as f64 * 0.618_033_988_7).fract() * std::f64::consts::TAU;
                let noise = 3e-4 * (((i * 7919) % 17) as f64 / 8.0 - 1.0);
                let groove = if (x - GROOVE_X).abs() < 0.006 {
                    0.003
                } else {
                    0.0
                };
                let r = 0.3 + noise + groove;
                // The section is across the local tangent (1, x / bend): its lateral
                // offset moves the point back along the axis by r sin(t) x / bend.
                let slope = x / bend;
                let (lat, up) = (r * t.sin(), -r * t.cos());
                [
                    (x - lat * slope) as f32,
                    (x * x / (2.0 * bend) + lat) as f32,
                    up as f32,
                ]
            })
            .collect()
    }

    #[test]
    fn a_bent_pipe_gives_its_boundary_the_local_axis_and_centre() {
        let bend = 30.0;
        let points = bent_pipe(150_000, bend);
        let submap = Submap::from_points(1.0, points, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
            .unwrap_or_else(|e| unreachable!("{e}"));
        let mut cfg = DecodConfig::pipe();
        let groove = |cfg: &DecodConfig| {
            let out = extract_landmarks(&submap, cfg);
            let found = out
                .landmarks
                .iter()
                .find(|l| (l.origin_in_submap[0] - GROOVE_X).abs() < 0.05)
                .cloned();
            (found, out.diagnostics.curve_radius_m)
        };
        // The tangent at the groove turns x / bend = 20 mrad from the chord; the centre is
        // 6 mm sideways of the line through x = 0.
        let tangent = Vector3::new(1.0, GROOVE_X / bend, 0.0).normalize();
        let (straight, radius) = groove(&cfg);
        assert!(radius.is_infinite());
        // On the chord, the groove's 3 mm are lost in the curve's +-2.5 cm about it, or it
        // gets the chord for its axis.
        if let Some(lm) = straight {
            let off = Vector3::from(lm.axis_in_submap).angle(&tangent);
            assert!(off > 0.015, "the chord: {off} rad off the tangent");
        }
        cfg.axis.curved = true;
        let (curved, radius) = groove(&cfg);
        let curved = curved.unwrap_or_else(|| {
            unreachable!(
                "the groove is found on the curve ({radius} m): {:?}",
                extract_landmarks(&submap, &cfg).rejections
            )
        });
        assert!((radius - bend).abs() < 0.1 * bend, "{radius}");
        let off = Vector3::from(curved.axis_in_submap).angle(&tangent);
        assert!(off < 0.004, "{off} rad off the tangent");
        let o = curved.origin_in_submap;
        assert!(
            (o[1] - GROOVE_X * GROOVE_X / (2.0 * bend)).abs() < 0.002 && o[2].abs() < 0.002,
            "{o:?}"
        );
        // Still an orthonormal basis about the new axis (Landmark::validate).
        assert!(curved.validate().is_ok());
    }

    #[test]
    fn heading_reversal_flips_the_descriptor() {
        let rot = Rotation3::from_euler_angles(0.0, 0.1, 0.2);
        let trans = Vector3::new(0.1, 0.0, 0.0);
        let pts = pipe(60_000, rot, trans);
        let a = run(pts.clone(), -Vector3::z(), Vector3::x());
        let b = run(pts, -Vector3::z(), -Vector3::x());
        let (la, lb) = (&a.landmarks[0], &b.landmarks[0]);
        let axis_dot = Vector3::from(la.axis_in_submap).dot(&Vector3::from(lb.axis_in_submap));
        assert!((axis_dot + 1.0).abs() < 1e-9);
        assert!((Vector3::from(la.e1_in_submap) - Vector3::from(lb.e1_in_submap)).norm() < 1e-9);
        let shift =
            (Vector3::from(la.origin_in_submap) - Vector3::from(lb.origin_in_submap)).norm();
        assert!(shift < 1e-3, "{shift}");
        let (close, agree) = compare(la, lb, true, 1e-4);
        assert!(close > 0.97 && agree > 0.97, "{close} {agree}");
        // Not flipped, they do not agree (the test can fail).
        let (close_unflipped, _) = compare(la, lb, false, 1e-4);
        assert!(close_unflipped < 0.9, "{close_unflipped}");
    }

    /// The pipe of [`pipe`] from `start` to `end` m, closed there by a face (a disc of
    /// `face_points` points spread evenly over its area), moved by `rot`.
    fn pipe_with_end_face(
        start: f64,
        end: f64,
        face_points: usize,
        rot: Rotation3<f64>,
    ) -> Vec<[f32; 3]> {
        let mut pts: Vec<[f32; 3]> = pipe(100_000, Rotation3::identity(), Vector3::zeros())
            .into_iter()
            .filter(|p| (start..end).contains(&(p[0] as f64)))
            .collect();
        for i in 0..face_points {
            // Sunflower spiral: even over the disc of radius 0.3 m.
            let r = 0.3 * ((i as f64 + 0.5) / face_points as f64).sqrt();
            let t = i as f64 * 2.399_963_229_7;
            pts.push([end as f32, (r * t.sin()) as f32, (-r * t.cos()) as f32]);
        }
        pts.into_iter()
            .map(|p| {
                let q = rot * Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                [q.x as f32, q.y as f32, q.z as f32]
            })
            .collect()
    }

    #[test]
    fn a_submap_looking_at_the_end_of_the_corridor_keeps_its_boundary() {
        // What a forward-looking sensor sees of a corridor ending ahead: 0.6 m of pipe wall
        // (wider than long, so the cloud is not elongated) and an end face with as many
        // points again.
        let rot = Rotation3::from_euler_angles(0.02, 0.1, 0.3);
        let pts = pipe_with_end_face(0.1, 0.7, 12_000, rot);
        let x = [1.0, 0.0, 0.0];
        let elongation = estimate_axis(&pts, x).map_or(f64::NAN, |a| a.elongation);
        assert!(
            elongation < DecodConfig::pipe().axis.min_elongation,
            "the test cloud must fail the elongation check: {elongation}"
        );
        // The sensor heads 3 degrees off the axis.
        let forward = rot * Rotation3::from_euler_angles(0.0, 0.0, 0.05) * Vector3::x();
        let out = run(pts, -Vector3::z(), forward);
        assert!(out.rejections.is_empty(), "{:?}", out.rejections);
        assert_eq!(
            out.landmarks.len(),
            1,
            "the groove, and nothing at the face"
        );
        let lm = &out.landmarks[0];
        let err_deg = Vector3::from(lm.axis_in_submap)
            .angle(&(rot * Vector3::x()))
            .to_degrees();
        assert!(err_deg < 0.1, "axis error {err_deg} deg");
        // The same boundary as the whole pipe gives the usual way.
        let open = run(pipe(100_000, rot, Vector3::zeros()), -Vector3::z(), forward);
        let d =
            Vector3::from(open.landmarks[0].origin_in_submap) - Vector3::from(lm.origin_in_submap);
        assert!(d.norm() < 2e-3, "{d:?}");
        // Without the face the stub is a short corridor (`short_corridor`): the same groove.
        let stub = run(pipe_with_end_face(0.1, 0.7, 0, rot), -Vector3::z(), forward);
        assert!(stub.rejections.is_empty(), "{:?}", stub.rejections);
        let d = Vector3::from(stub.landmarks[0].origin_in_submap)
            - Vector3::from(open.landmarks[0].origin_in_submap);
        assert!(d.norm() < 2e-3, "{d:?}");
    }

    #[test]
    fn the_relief_probe_measures_the_whole_wall_not_the_slices_that_pass() {
        // The test pipe with three 12 cm rings standing 30 mm proud of the wall (beyond the
        // pipe preset's 18 mm gate) at x = -0.9, 0 and 0.9: 12 % of its points, so the wall
        // fails the corridor test (88 % < 90 %) and so does the cloud; and an end face at
        // x = 1.5 with a fifth as many points as the wall.
        let ringed: Vec<[f32; 3]> = pipe(100_000, Rotation3::identity(), Vector3::zeros())
            .into_iter()
            .map(|p| {
                let x = p[0] as f64;
                if [-0.9, 0.0, 0.9].iter().any(|&c| (x - c).abs() < 0.06) {
                    let k = ((0.3 - 0.03) / 0.3) as f32;
                    [p[0], p[1] * k, p[2] * k]
                } else {
                    p
                }
            })
            .collect();
        let face = pipe_with_end_face(1.4, 1.5, 20_000, Rotation3::identity())
            .into_iter()
            .filter(|p| p[0] == 1.5);
        let pts: Vec<[f32; 3]> = ringed.iter().copied().chain(face).collect();
        let extract = |span: &str| {
            let mut cfg = DecodConfig::pipe();
            cfg.contour.corridor_span = span.into();
            let submap = Submap::from_points(1.0, pts.clone(), [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
                .unwrap_or_else(|e| unreachable!("{e}"));
            extract_landmarks(&submap, &cfg)
        };
        // The run's extraction keeps the longest stretch between two rings (0.78 m, more than
        // the 0.48 m descriptor): its relief is the wall's noise alone.
        let longest = extract("longest");
        let d = &longest.diagnostics;
        assert!(d.contour_p90_abs_offset_m < 0.005, "{d:?}");
        // What auto's probe reads: the end face dropped, the rings kept, and the gate fails.
        let ends = extract("ends");
        let d = &ends.diagnostics;
        assert!((0.02..0.04).contains(&d.contour_p90_abs_offset_m), "{d:?}");
        assert!((d.contour_inlier_fraction - 0.88).abs() < 0.02, "{d:?}");
        assert!(
            matches!(
                ends.rejections.first().map(|r| &r.reason),
                Some(RejectionReason::ContourMisfit { .. })
            ),
            "{:?}",
            ends.rejections
        );
        // Everything: the face's points are the tenth furthest from the contour.
        let d = extract("off").diagnostics;
        assert!(d.contour_p90_abs_offset_m > 0.05, "{d:?}");
    }

    #[test]
    fn arc_observed_counts_the_sectors_seen_near_the_contour() {
        // Points every 1 deg over half the section, on the contour; the other half only far
        // off it (an end wall, clutter): half the arc is seen.
        let on = (0..180).map(|k| ChartPoint {
            z: 0.0,
            p: k as f64 / 360.0,
            s: 0.01,
        });
        let off = (180..360).map(|k| ChartPoint {
            z: 0.0,
            p: k as f64 / 360.0,
            s: 0.5,
        });
        let chart: Vec<ChartPoint> = on.chain(off).collect();
        assert!((arc_observed(&chart, 0.1) - 0.5).abs() < 1e-12);
        assert!((arc_observed(&chart, 1.0) - 1.0).abs() < 1e-12);
        assert_eq!(arc_observed(&[], 0.1), 0.0);
    }

    #[test]
    fn rejections_carry_reasons() {
        let out = run(vec![[1.0, 0.0, 0.0]; 10], -Vector3::z(), Vector3::x());
        assert!(matches!(
            out.rejections[0].reason,
            RejectionReason::TooFewPoints { count: 10, .. }
        ));
        // A 1 m x 1 m x 1 m cube of points: not elongated.
        let cube: Vec<[f32; 3]> = (0..20_000)
            .map(|i| {
                let f = |k: f64| ((i as f64) * k).fract() as f32;
                [f(0.618_033_988_7), f(0.414_213_562_3), f(0.732_050_807_6)]
            })
            .collect();
        let out = run(cube, -Vector3::z(), Vector3::x());
        assert_eq!(out.rejections[0].reason.kind(), "not_elongated");
        assert!(
            out.rejections[0]
                .to_string()
                .contains("axis.min_elongation")
        );
        // Gravity along a vertical shaft.
        let shaft = pipe(
            20_000,
            Rotation3::from_euler_angles(0.0, -std::f64::consts::FRAC_PI_2, 0.0),
            Vector3::zeros(),
        );
        let out = run(shaft, -Vector3::z(), Vector3::z());
        assert_eq!(out.rejections[0].reason, RejectionReason::GravityAlongAxis);
    }

    #[test]
    fn parallel_equals_serial() {
        let submaps: Vec<Submap> = (0..4)
            .map(|k| {
                let rot = Rotation3::from_euler_angles(0.1 * k as f64, 0.05, 0.2);
                Submap::from_points(
                    k as f64,
                    pipe(30_000, rot, Vector3::zeros()),
                    [0.0, 0.0, -1.0],
                    [1.0, 0.0, 0.0],
                )
                .unwrap_or_else(|e| unreachable!("{e}"))
            })
            .collect();
        let cfg = DecodConfig::pipe();
        let parallel = extract_all(&submaps, &cfg);
        for (m, p) in submaps.iter().zip(&parallel) {
            let serial = extract_landmarks(m, &cfg);
            assert_eq!(serial.landmarks, p.landmarks);
            assert_eq!(serial.rejections, p.rejections);
        }
    }

    proptest! {
        #![proptest_config(ProptestConfig { cases: 6, ..ProptestConfig::default() })]
        /// Moving the cloud, gravity and forward rigidly moves the landmark with them and
        /// leaves the descriptor unchanged.
        #[test]
        fn rigid_motion_invariance(
            roll in -3.1f64..3.1, pitch in -1.4f64..1.4, yaw in -3.1f64..3.1,
            tx in -5.0f64..5.0, ty in -5.0f64..5.0, tz in -5.0f64..5.0,
        ) {
            let base = Rotation3::from_euler_angles(0.0, 0.1, 0.2);
            let pts = pipe(40_000, base, Vector3::zeros());
            let a = run(pts.clone(), -Vector3::z(), Vector3::x());
            let motion = Rotation3::from_euler_angles(roll, pitch, yaw);
            let t = Vector3::new(tx, ty, tz);
            let moved: Vec<[f32; 3]> = pts
                .iter()
                .map(|p| {
                    let q = motion * Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) + t;
                    [q.x as f32, q.y as f32, q.z as f32]
                })
                .collect();
            let b = run(moved, motion * -Vector3::z(), motion * Vector3::x());
            prop_assert_eq!(a.landmarks.len(), 1);
            prop_assert_eq!(b.landmarks.len(), 1);
            let (la, lb) = (&a.landmarks[0], &b.landmarks[0]);
            let mapped = motion * Vector3::from(la.origin_in_submap) + t;
            prop_assert!((mapped - Vector3::from(lb.origin_in_submap)).norm() < 1e-3);
            let (close, agree) = compare(la, lb, false, 1e-4);
            prop_assert!(close > 0.97 && agree > 0.97, "{} {}", close, agree);
        }
    }
}
