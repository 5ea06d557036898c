"""Stage 4 of Algorithm 1 (paper Sec. III-E): loop and sequential factors, the pose graph
started from the odometry rescaled by the tracked boundaries, then loops the optimised graph
cannot satisfy dropped one at a time (:mod:`decod_rs.residuals`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import QueryResult
from decod_rs.config import Config
from decod_rs.cross_axis import CrossAxis, cross_axis
from decod_rs.disambiguation import CorrectedFrame
from decod_rs.end_faces import face_constraints
from decod_rs.graph import CorrectionResult, LoopConstraint, correct_trajectory
from decod_rs.loop_scale import stitch_with_loop_scales
from decod_rs.odometry_scale import ScaleEstimate, odometry_sigma_factors, rescale_odometry
from decod_rs.progress import Progress
from decod_rs.residuals import MAX_DROPS, loop_residuals, worst_unsatisfied
from decod_rs.selection import effective_db_origin, path_along
from decod_rs.sequential import (
    SequentialFactors,
    at_ribs,
    axial_offset_m,
    boundary_polarity,
    sequential_constraints,
    transverse_noise_m,
)
from decod_rs.stages.extract import SubmapLandmarks
from decod_rs.stages.match import Matched, resolve
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]


def loop_constraints(
    results: list[QueryResult],
    keep: list[bool],
    anchor_stamps: FloatArray,
    cell_z_m: float,
    ribs: bool,
) -> list[LoopConstraint]:
    """Loop factors of the kept loops, the axial offsets as :func:`axial_offset_m` takes them
    (descriptor rows of ``cell_z_m``)."""

    def index(stamp: float) -> int:
        return int(np.argmin(np.abs(anchor_stamps - stamp)))

    return [
        LoopConstraint(
            query_index=index(r.query_stamp),
            db_index=index(r.candidate_stamp),
            query_origin=np.asarray(r.query_origin, dtype=np.float64),
            query_axis=np.asarray(r.query_axis, dtype=np.float64),
            db_origin=effective_db_origin(r, axial_offset_m(r.dz_m, cell_z_m, ribs)),
            db_axis=np.asarray(r.candidate_axis, dtype=np.float64),
            inliers=r.inliers,
            score=r.score,
        )
        for r, ok in zip(results, keep, strict=True)
        if ok
    ]


@dataclass(frozen=True)
class TrackTerms:
    """What the factors take from the tracks alone, the same for every loop set of a round
    (stage 3b and the drops change the loops, never the tracks): the spread across the axis
    every factor takes, whether they leave the height to the odometry
    (:mod:`decod_rs.cross_axis`), the boundaries' polarity, and the sequential factors
    (computed once per round: they were 0.1 s of each of the two or more solves of a
    64-beam run)."""

    across: float | None
    cross: CrossAxis | None
    polarity: float | None
    seq: SequentialFactors | None

    def across_axis(self, c: LoopConstraint) -> LoopConstraint:
        """``c`` with the sigmas across the axis of these terms."""
        return replace(c, sigma_transverse_m=self.across, sigma_vertical_m=_vertical(self.cross))


def _vertical(cross: CrossAxis | None) -> float | None:
    """The factors' vertical sigma (None: the spread across the axis)."""
    return None if cross is None else cross.vertical_sigma_m


def track_terms(
    ex: SubmapLandmarks,
    matched: Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
) -> TrackTerms:
    """The sequential factors of the tracks and what the loop factors share with them
    (:mod:`decod_rs.sequential`)."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    across = transverse_noise_m(
        ex.landmarks, matched.tracks, anchors, float(cfg.graph.landmark_position_sigma_m)
    )
    polarity = boundary_polarity(ex.landmarks)
    path_at = path_along(*scans)
    cross = cross_axis(ex.landmarks, matched.tracks, anchors, anchor_stamps, path_at, cfg.graph)
    seq = None
    if cfg.graph.sequential:
        seq = sequential_constraints(
            ex.landmarks,
            matched.tracks,
            anchors,
            anchor_stamps,
            path_at,
            cfg,
            across,
            matched.pairs,
            polarity=polarity,
            sigma_vertical_m=_vertical(cross),
        )
        views = ex.faces if cfg.graph.end_faces else []
        faces = face_constraints(
            views, anchors, anchor_stamps, path_at, matched.split, cfg, seq.sigma_m
        )
        seq.constraints += faces.constraints  # the passes' scales take them too
        seq.end_faces = faces
    return TrackTerms(across, cross, polarity, seq)


def graph_factors(
    ex: SubmapLandmarks, matched: Matched, terms: TrackTerms
) -> tuple[list[LoopConstraint], SequentialFactors | None]:
    """Loop factors of the kept loops, then the sequential factors of the tracks; across the
    axis, every factor takes what the tracks measured (``terms``)."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    cell_z_m = ex.landmarks[0].cell_z_m if ex.landmarks else 0.0
    constraints = [
        terms.across_axis(c)
        for c in loop_constraints(
            matched.results, matched.keep, anchor_stamps, cell_z_m, at_ribs(terms.polarity)
        )
    ]
    if terms.seq is None:
        return constraints, None
    return constraints + terms.seq.constraints, terms.seq


def optimise(
    scans: tuple[FloatArray, FloatArray],
    ex: SubmapLandmarks,
    split: float | None,
    constraints: list[LoopConstraint],
    seq: SequentialFactors | None,
    cfg: Config,
    gap_factors: FloatArray | None = None,
) -> tuple[CorrectionResult, ScaleEstimate | None, FloatArray, FloatArray | None]:
    """The pose graph, started from the odometry rescaled by the tracked boundaries
    (:mod:`decod_rs.odometry_scale`) when there are sequential factors; also returns the
    scan odometry the graph started from, and the trajectory to stitch rebuilt submaps on
    when it differs from the corrected one (None otherwise): without a loop, a pass whose
    scale was measured but that is not rescaled alone in the output (it would move the other
    pass) is still rescaled for stitching, where only its own geometry counts; with loops, a
    pass whose tracks did not measure its scale is stitched beyond its loops at the scale
    they measure (:mod:`decod_rs.loop_scale`)."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)

    def graph(tied: bool) -> tuple[CorrectionResult, ScaleEstimate | None, FloatArray]:
        """The graph with the passes rescaled as when loops tie them (``tied``) or not."""
        start, scale = scans[1], None
        if seq is not None and seq.constraints:
            anchor_odom = interpolate_poses(*scans, anchor_stamps)
            start, scale = rescale_odometry(
                scans[0],
                scans[1],
                anchor_stamps,
                anchor_odom,
                seq.constraints,
                seq.sigma_m,
                split,
                tied,
                curved=bool(cfg.axis.curved),
            )
        # Nothing measured the degenerate axis: the odometry stands (paper Alg. 1, "keep
        # X* = X_odom if L is empty"); a few sequential factors alone only add noise.
        factors_in = constraints if _rescaled(scale) or tied else []
        factors = None if scale is None else odometry_sigma_factors(scans[0], scale, split)
        if gap_factors is not None:  # odometry gaps bridged by a weak factor (decod_rs.ingest)
            factors = gap_factors if factors is None else factors * gap_factors
        correction = correct_trajectory(
            scans[0], start, anchor_stamps, factors_in, cfg.graph, sigma_factors=factors
        )
        return correction, scale, start

    tied = any(c.kind == "loop" for c in constraints)
    correction, scale, start = graph(tied)
    stitch = None
    if not tied and scale is not None and not _rescaled(scale):
        alone, alone_scale, _ = graph(True)
        stitch = alone.poses if _rescaled(alone_scale) else None
    elif tied and scale is not None:
        measured = [bool(p["rescaled"]) for p in scale.passes]
        stitch = stitch_with_loop_scales(
            scans[0], start, correction.poses, anchor_stamps, constraints, split, measured
        )
    return correction, scale, start, stitch


def _rescaled(scale: ScaleEstimate | None) -> bool:
    """Whether some pass had its odometry scale measured and applied."""
    return scale is not None and any(p["rescaled"] for p in scale.passes)


@dataclass(frozen=True)
class Solved:
    """Stage 4: the factors, the optimised trajectory and the odometry it started from."""

    constraints: list[LoopConstraint]
    seq: SequentialFactors | None
    correction: CorrectionResult
    scale: ScaleEstimate | None
    start: FloatArray
    #: The trajectory to stitch rebuilt submaps on, where it is not ``correction``'s
    #: (:func:`optimise`).
    stitch: FloatArray | None = None
    #: The views' spread across the axis and whether the factors left the height to the
    #: odometry.
    cross: CrossAxis | None = None

    @property
    def stitching(self) -> FloatArray:
        """The scan poses rebuilt submaps are stitched on (:mod:`decod_rs.stages.refine`)."""
        return self.correction.poses if self.stitch is None else self.stitch


def solve(
    ex: SubmapLandmarks,
    matched: Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
    loops: bool,
    gap_factors: FloatArray | None = None,
    progress: bool = False,
) -> tuple[Matched, Solved]:
    """Factors and optimisation; then ambiguous queries placed by the corrected trajectory
    and, if any became loops, factors and optimisation again (stage 3b); then, one at a
    time, loops the optimised graph cannot satisfy dropped (:mod:`decod_rs.residuals`).
    ``progress``: the graphs solved so far, on stderr."""

    terms = track_terms(ex, matched, cfg, scans) if loops else None
    bar = Progress("optimise", None, enabled=progress, unit="graphs")

    def solve_once(matched: Matched) -> Solved:
        constraints, seq = ([], None) if terms is None else graph_factors(ex, matched, terms)
        optimised = optimise(scans, ex, matched.split, constraints, seq, cfg, gap_factors)
        bar.advance()
        return Solved(constraints, seq, *optimised, cross=None if terms is None else terms.cross)

    solved = solve_once(matched)
    if loops and cfg.matching.resolve_with_prior:
        resolved = resolve(ex, matched, cfg, scans, solved.correction.poses)
        if resolved is not matched:
            matched, solved = resolved, solve_once(resolved)
    tolerance = float(cfg.matching.consistency_tolerance_m)
    for _ in range(MAX_DROPS if loops else 0):
        frame = CorrectedFrame(scans[0], solved.correction.poses)
        worst = worst_unsatisfied(loop_residuals(matched.results, matched.keep, frame), tolerance)
        if worst is None:
            break
        keep, reasons = list(matched.keep), list(matched.reasons)
        keep[worst], reasons[worst] = False, "inconsistent"
        matched = replace(matched, keep=keep, reasons=reasons, by_prior=matched.by_prior - {worst})
        solved = solve_once(matched)
    bar.close()
    return matched, solved
