"""``decod run``: a log in, a corrected trajectory and an honest report out (paper Alg. 1).

Stages, each timed in ``report.json``:

1. **extract** - the Rust ``LogProcessor`` streams scans from the log, builds submaps and
   extracts landmarks a few submaps at a time (memory bounded by the submaps in flight);
2. **match** - outbound landmarks form the database, return landmarks query it (batch, the
   paper's protocol), or every landmark queries all older ones (online);
3. **optimise** - accepted pairs become 5-DoF factors in the GTSAM graph over the submap
   anchors; every scan gets a corrected pose;
4. **write** - the files of the contract (DESIGN.md) and the plots.
"""

from __future__ import annotations

import json
import platform
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark, QueryResult
from decod_rs.aliasing import aliasing
from decod_rs.autoscale import auto_config, probe_corridor
from decod_rs.config import MODES, Config, load_config
from decod_rs.disambiguation import CorrectedFrame, near_loops, resolve_with_prior
from decod_rs.graph import CorrectionResult, LoopConstraint, correct_trajectory
from decod_rs.graph_export import write_g2o, write_graph_json
from decod_rs.ingest import StreamHealth, ingest_section, warn_once
from decod_rs.io import find_imu_topic
from decod_rs.joints import Joint, joint_registry, landmark_chainage, write_joints_csv
from decod_rs.matching import LandmarkDatabase, PairMemo
from decod_rs.odometry_scale import ScaleEstimate, odometry_sigma_factors, rescale_odometry
from decod_rs.progress import Progress
from decod_rs.refinement import RebuildDecision, rebuild_decision
from decod_rs.reinspection import Reinspection, reinspect, write_run_survey
from decod_rs.residuals import MAX_DROPS, loop_residuals, worst_unsatisfied
from decod_rs.run_files import (
    LandmarkTable,
    LoopTable,
    check_run_dir,
    staged_run_dir,
    write_landmarks_csv,
    write_loops_csv,
)
from decod_rs.selection import effective_db_origin, path_along, select_loops, why_no_loop
from decod_rs.sequential import (
    SequentialFactors,
    at_ribs,
    axial_offset_m,
    boundary_polarity,
    same_boundary,
    sequential_constraints,
    transverse_noise_m,
)
from decod_rs.survey import Survey, check_compatible, load_survey, survey_config
from decod_rs.tracks import (
    group_views,
    tracked_loops,
    views_per_landmark,
    world_axes,
    world_origins,
)
from decod_rs.tum import interpolate_poses, write_tum
from decod_rs.unmeasured import Stretch, unmeasured, unmeasured_report
from decod_rs.visuals import Visuals, finish_visuals, start_visuals

FloatArray = NDArray[np.float64]

PRESET_CHOICES = ("auto", "tunnel", "pipe")

#: In ``auto`` mode the log is split at the turnaround (the scan farthest from the start) when
#: the return leg covers at least this fraction of the outbound distance; otherwise every
#: landmark queries all older ones (online).
MIN_RETURN_FRACTION = 0.25

__all__ = ["MODES", "Extracted", "RunSummary", "Visuals", "finish_run", "run_log"]


@dataclass
class RunSummary:
    """What ``run_log`` did: counts, per-stage seconds, and the output directory."""

    out_dir: Path
    scans: int
    submaps: int
    landmarks: int
    queries: int
    accepted: int
    mode: str
    split_stamp: float | None
    log_duration_s: float
    timings_s: dict[str, float] = field(default_factory=dict)
    rejections: dict[str, int] = field(default_factory=dict)

    @property
    def realtime_factor(self) -> float:
        total = sum(self.timings_s.values())
        return self.log_duration_s / total if total > 0 else float("inf")


@dataclass
class _Extracted:
    anchor_stamps: list[float] = field(default_factory=list)
    anchor_poses: list[FloatArray] = field(default_factory=list)
    landmarks: list[Landmark] = field(default_factory=list)
    rejections: dict[str, int] = field(default_factory=dict)
    rejection_messages: list[str] = field(default_factory=list)


def _extract(
    log: Path,
    cfg: Config,
    points_topic: str | None,
    odom_topic: str | None,
    odom_tum: Path | None,
    imu_topic: str | None,
    progress: bool,
    keep_map: bool = False,
    imu_samples: FloatArray | None = None,
) -> tuple[_core.LogProcessor, _Extracted]:
    processor = _core.LogProcessor(
        str(log),
        json.dumps(cfg.to_dict()),
        points_topic=points_topic,
        odom_topic=odom_topic,
        odom_tum=None if odom_tum is None else str(odom_tum),
        imu_topic=imu_topic,
        map=keep_map,
        imu_samples=imu_samples,
    )
    bar = Progress("extract", processor.total_scans_hint or None, enabled=progress)
    out = _Extracted()
    read = 0
    while (batch := processor.step()) is not None:
        for submap in batch:
            out.anchor_stamps.append(submap.anchor_stamp)
            out.anchor_poses.append(submap.world_from_anchor)
            out.landmarks.extend(submap.result.landmarks)
            for rejection in submap.result.rejections:
                out.rejections[rejection.kind] = out.rejections.get(rejection.kind, 0) + 1
                out.rejection_messages.append(str(rejection))
        bar.advance(processor.scans_read - read)
        read = processor.scans_read
    bar.close()
    return processor, out


def _split_stamp(stamps: FloatArray, poses: FloatArray) -> float | None:
    """The turnaround stamp of an out-and-back run, or None if there is no real return."""
    positions = poses[:, :3, 3]
    reach = np.linalg.norm(positions - positions[0], axis=1)
    far = int(np.argmax(reach))
    back = float(np.linalg.norm(positions[-1] - positions[far]))
    if reach[far] <= 0 or back < MIN_RETURN_FRACTION * reach[far]:
        return None
    return float(stamps[far])


def _match(
    landmarks: list[Landmark],
    tracks: NDArray[np.int64],
    where: tuple[FloatArray, FloatArray],
    cfg: Config,
    mode: str,
    split: float | None,
    pairs: PairMemo,
) -> tuple[list[QueryResult], str, list[int]]:
    """Queries and their top-1 results, the mode used, and the landmark behind each
    database index. Every view goes into the database under its track (physical boundary)
    id, placed at ``where`` (origins and axes, (N, 3) each, in the odometry frame: the
    coarse stage's neighbours and the heading prior); batch mode takes the landmarks as the
    track links prepared them (``pairs.views``)."""
    origins, axes = where
    db = LandmarkDatabase(cfg)
    if mode == "auto":
        mode = "batch" if split is not None else "online"
    if mode == "batch":
        if split is None:
            raise ValueError(
                "--mode batch: the trajectory has no return leg to query with (use --mode online)"
            )
        outbound = [k for k, lm in enumerate(landmarks) if lm.submap_stamp <= split]
        views = pairs.views
        ids = [int(tracks[k]) for k in outbound]
        db.extend_prepared(views, outbound, ids, origins[outbound], axes[outbound])
        queries = [k for k, lm in enumerate(landmarks) if lm.submap_stamp > split]
        results = db.query_batch_prepared(
            views, queries, across_passes=True, directions=axes[queries]
        )
        return results, mode, outbound
    results = []
    order = sorted(range(len(landmarks)), key=lambda k: landmarks[k].submap_stamp)
    for k in order:
        results.append(db.query(landmarks[k], direction=axes[k]))
        db.add(landmarks[k], int(tracks[k]), origins[k], axes[k])
    return results, mode, order


def _loop_table(
    results: list[QueryResult],
    keep: list[bool],
    reasons: list[str],
    by_prior: frozenset[int] = frozenset(),
) -> LoopTable:
    n = len(results)
    nan3 = np.full(3, np.nan)

    def vec(r: QueryResult, name: str) -> FloatArray:
        return (
            np.asarray(getattr(r, name), dtype=np.float64)
            if r.candidate_index is not None
            else nan3
        )

    return LoopTable(
        query_stamp=np.array([r.query_stamp for r in results], dtype=np.float64),
        db_stamp=np.array(
            [r.candidate_stamp if r.candidate_index is not None else np.nan for r in results],
            dtype=np.float64,
        ),
        query_origin=np.array([r.query_origin for r in results], dtype=np.float64).reshape(n, 3),
        query_axis=np.array([r.query_axis for r in results], dtype=np.float64).reshape(n, 3),
        db_origin=np.array([vec(r, "candidate_origin") for r in results]).reshape(n, 3),
        db_axis=np.array([vec(r, "candidate_axis") for r in results]).reshape(n, 3),
        inliers=np.array([r.inliers for r in results], dtype=np.int64),
        score=np.array([r.score for r in results], dtype=np.float64),
        accepted=np.array(keep, dtype=bool),
        extra={
            "heading_deg": [f"{r.heading_deg:.0f}" for r in results],
            "dz_m": [f"{r.dz_m:.6f}" for r in results],
            "runner_up_score": [f"{r.runner_up_score:.6f}" for r in results],
            "runner_up_inliers": [str(r.runner_up_inliers) for r in results],
            "eligible_candidates": [str(r.eligible) for r in results],
            "chance": [f"{r.chance:.3g}" for r in results],
            "reason": reasons,
            "accepted_by": [
                ("position_prior" if k in by_prior else "descriptor") if ok else ""
                for k, ok in enumerate(keep)
            ],
        },
    )


def _constraints(
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


@dataclass
class _Matched:
    """Stages 2-3: the tracks, every query's Top-1 and which stay loops (and why not);
    ``db_order[i]``: the landmark behind database index ``i``; ``by_prior``: the loops kept
    by :mod:`decod_rs.disambiguation`; ``tracked[k]``: query ``k`` or its Top-1 is a track
    (:func:`decod_rs.selection.drop_if_untracked`)."""

    split: float | None
    tracks: NDArray[np.int64]
    results: list[QueryResult]
    mode: str
    db_order: list[int]
    keep: list[bool]
    reasons: list[str]
    by_prior: frozenset[int] = frozenset()
    pairs: PairMemo | None = None
    tracked: list[bool] | None = None

    @property
    def database(self) -> int:
        return len(self.db_order)


def _configure(
    log: Path,
    preset: str,
    config_path: str | Path | None,
    topics: tuple[str | None, str | None, Path | None, str | None],
    sequential: bool | None,
    survey: Survey | None = None,
) -> tuple[Config, dict[str, Any] | None, FloatArray | None]:
    """The config: measured and derived (``auto``) or a preset, plus the user's TOML; with a
    survey and neither a preset nor a TOML, the survey's own (same grid and matcher). Also
    the IMU samples the ``auto`` probe read, if it read any (for the extraction)."""
    auto: dict[str, Any] | None = None
    imu: FloatArray | None = None
    if survey is not None and preset == "auto" and config_path is None:
        cfg = survey_config(survey)
    elif preset == "auto":
        probe, imu = probe_corridor(log, *topics)
        cfg, auto = auto_config(probe, None if config_path is None else Path(config_path))
    else:
        cfg = load_config(config_path, preset)
    if sequential is not None:
        values = cfg.to_dict()
        values["graph"]["sequential"] = bool(sequential)
        cfg = Config(values)
    return cfg, auto, imu


def _match_and_select(
    ex: _Extracted,
    cfg: Config,
    mode: str,
    scan_stamps: FloatArray,
    scan_odom: FloatArray,
    link_frame: FloatArray | None = None,
) -> _Matched:
    """Stages 2-3: tracks, matching, selection. ``link_frame``: the scan poses in which views
    are linked into tracks (default the odometry; a rebuilt round links in the corrected
    trajectory of the first, :mod:`decod_rs.refinement`)."""
    split = _split_stamp(scan_stamps, scan_odom)
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    m = cfg.matching
    linking = anchors
    if link_frame is not None and ex.anchor_stamps:
        stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
        poses = interpolate_poses(scan_stamps, link_frame, stamps)
        linking = dict(zip(ex.anchor_stamps, poses, strict=True))
    pairs = PairMemo(ex.landmarks, m)
    tracks = group_views(
        ex.landmarks,
        linking,
        float(m.duplicate_radius_m),
        float(m.min_time_separation_s),
        same_boundary(ex.landmarks, m, pairs),
        split_stamp=split,
    )
    where = (world_origins(ex.landmarks, anchors), world_axes(ex.landmarks, anchors))
    results, used_mode, db_order = _match(ex.landmarks, tracks, where, cfg, mode, split, pairs)
    pairs.release_views()
    views = views_per_landmark(tracks)
    tracked = tracked_loops(results, ex.landmarks, views, views[db_order])
    keep, reasons = select_loops(results, anchors, scan_stamps, scan_odom, m, tracked=tracked)
    return _Matched(
        split, tracks, results, used_mode, db_order, keep, reasons, pairs=pairs, tracked=tracked
    )


def _resolve(
    ex: _Extracted,
    matched: _Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
) -> _Matched:
    """Stage 3b: ambiguous queries placed by the corrected trajectory, then the whole
    loop set selected again (:mod:`decod_rs.disambiguation`)."""
    m = cfg.matching
    loops = [r.query_stamp for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
    promoted = resolve_with_prior(
        matched.results,
        matched.reasons,
        [ex.landmarks[i] for i in matched.db_order],
        CorrectedFrame(scans[0], corrected),
        float(m.consistency_tolerance_m),
        near_loops(loops, path_along(*scans), float(m.consistency_window_m)),
    )
    if not promoted:
        return matched
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    keep, reasons = select_loops(
        matched.results, anchors, *scans, m, also=promoted, tracked=matched.tracked
    )
    by_prior = frozenset(k for k in promoted if keep[k])
    return replace(matched, keep=keep, reasons=reasons, by_prior=by_prior)


@dataclass(frozen=True)
class _TrackTerms:
    """What the factors take from the tracks alone, the same for every loop set of a round
    (stage 3b and the drops change the loops, never the tracks): the spread across the axis
    every factor takes, the boundaries' polarity, and the sequential factors (computed once
    per round: they were 0.1 s of each of the two or more solves of a 64-beam run)."""

    across: float | None
    polarity: float | None
    seq: SequentialFactors | None


def _track_terms(
    ex: _Extracted,
    matched: _Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
) -> _TrackTerms:
    """The sequential factors of the tracks and what the loop factors share with them
    (:mod:`decod_rs.sequential`)."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    anchors = dict(zip(ex.anchor_stamps, ex.anchor_poses, strict=True))
    across = transverse_noise_m(
        ex.landmarks, matched.tracks, anchors, float(cfg.graph.landmark_position_sigma_m)
    )
    polarity = boundary_polarity(ex.landmarks)
    seq = None
    if cfg.graph.sequential:
        seq = sequential_constraints(
            ex.landmarks,
            matched.tracks,
            anchors,
            anchor_stamps,
            path_along(*scans),
            cfg,
            across,
            matched.pairs,
            polarity=polarity,
        )
    return _TrackTerms(across, polarity, seq)


def _factors(
    ex: _Extracted, matched: _Matched, terms: _TrackTerms
) -> tuple[list[LoopConstraint], SequentialFactors | None]:
    """Loop factors of the kept loops, then the sequential factors of the tracks; across the
    axis, every factor takes the spread measured on the tracks (``terms``)."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    cell_z_m = ex.landmarks[0].cell_z_m if ex.landmarks else 0.0
    constraints = [
        replace(c, sigma_transverse_m=terms.across)
        for c in _constraints(
            matched.results, matched.keep, anchor_stamps, cell_z_m, at_ribs(terms.polarity)
        )
    ]
    if terms.seq is None:
        return constraints, None
    return constraints + terms.seq.constraints, terms.seq


def _optimise(
    scans: tuple[FloatArray, FloatArray],
    ex: _Extracted,
    split: float | None,
    constraints: list[LoopConstraint],
    seq: SequentialFactors | None,
    cfg: Config,
    gap_factors: FloatArray | None = None,
) -> tuple[CorrectionResult, ScaleEstimate | None, FloatArray]:
    """The pose graph, started from the odometry rescaled by the tracked boundaries
    (:mod:`decod_rs.odometry_scale`) when there are sequential factors; also returns the
    scan odometry the graph started from."""
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    start, scale = scans[1], None
    tied = any(c.kind == "loop" for c in constraints)
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
        )
    rescaled = scale is not None and any(p["rescaled"] for p in scale.passes)
    if not rescaled and not tied:
        # Nothing measured the degenerate axis: the odometry stands (paper Alg. 1, "keep
        # X* = X_odom if L is empty"); a few sequential factors alone only add noise.
        constraints = []
    factors = None if scale is None else odometry_sigma_factors(scans[0], scale, split)
    if gap_factors is not None:  # odometry gaps bridged by a weak factor (decod_rs.ingest)
        factors = gap_factors if factors is None else factors * gap_factors
    correction = correct_trajectory(
        scans[0], start, anchor_stamps, constraints, cfg.graph, sigma_factors=factors
    )
    return correction, scale, start


@dataclass(frozen=True)
class _Solved:
    """Stage 4: the factors, the optimised trajectory and the odometry it started from."""

    constraints: list[LoopConstraint]
    seq: SequentialFactors | None
    correction: CorrectionResult
    scale: ScaleEstimate | None
    start: FloatArray


def _solve(
    ex: _Extracted,
    matched: _Matched,
    cfg: Config,
    scans: tuple[FloatArray, FloatArray],
    loops: bool,
    gap_factors: FloatArray | None = None,
) -> tuple[_Matched, _Solved]:
    """Factors and optimisation; then ambiguous queries placed by the corrected trajectory
    and, if any became loops, factors and optimisation again (stage 3b); then, one at a
    time, loops the optimised graph cannot satisfy dropped (:mod:`decod_rs.residuals`)."""

    terms = _track_terms(ex, matched, cfg, scans) if loops else None

    def solve(matched: _Matched) -> _Solved:
        constraints, seq = ([], None) if terms is None else _factors(ex, matched, terms)
        optimised = _optimise(scans, ex, matched.split, constraints, seq, cfg, gap_factors)
        return _Solved(constraints, seq, *optimised)

    solved = solve(matched)
    if loops and cfg.matching.resolve_with_prior:
        resolved = _resolve(ex, matched, cfg, scans, solved.correction.poses)
        if resolved is not matched:
            matched, solved = resolved, solve(resolved)
    tolerance = float(cfg.matching.consistency_tolerance_m)
    for _ in range(MAX_DROPS if loops else 0):
        frame = CorrectedFrame(scans[0], solved.correction.poses)
        worst = worst_unsatisfied(loop_residuals(matched.results, matched.keep, frame), tolerance)
        if worst is None:
            break
        keep, reasons = list(matched.keep), list(matched.reasons)
        keep[worst], reasons[worst] = False, "inconsistent"
        matched = replace(matched, keep=keep, reasons=reasons, by_prior=matched.by_prior - {worst})
        solved = solve(matched)
    return matched, solved


def _rebuild(
    extraction: Extracted, cfg: Config, corrected: FloatArray, progress: bool
) -> _Extracted:
    """Stage 1 again, the submaps stitched by the corrected trajectory; the anchors placed
    on the odometry like the first ones (:mod:`decod_rs.refinement`)."""
    stamps, odometry = extraction.scans
    with tempfile.TemporaryDirectory(prefix="decod-rebuild-") as tmp:
        tum = Path(tmp) / "corrected.tum"
        write_tum(tum, stamps, corrected)
        points = extraction.processor.points_topic
        # The IMU the first extraction read: with the odometry from the file above, the log is
        # then read once, for its scans (not once more for the IMU).
        imu = extraction.processor.imu_samples()
        topic = extraction.imu_topic if imu is None else None
        _, ex = _extract(extraction.log, cfg, points, None, tum, topic, progress, imu_samples=imu)
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    ex.anchor_poses = list(interpolate_poses(stamps, odometry, anchors)) if anchors.size else []
    return ex


def _rescaled_passes(solved: _Solved) -> int:
    """How many passes of a round had their scale measured and applied."""
    return 0 if solved.scale is None else sum(bool(p["rescaled"]) for p in solved.scale.passes)


def _rebuilt(
    extraction: Extracted,
    ex: _Extracted,
    matched: _Matched,
    solved: _Solved,
    cfg: Config,
    mode: str,
    progress: bool,
) -> tuple[_Extracted, _Matched, _Solved, RebuildDecision]:
    """Stages 1-4 again on submaps rebuilt on the corrected trajectory when it stitches
    them differently enough; the rebuilt round replaces the first only if it closes more
    loops (:mod:`decod_rs.refinement`)."""
    scans = extraction.scans
    decision = rebuild_decision(scans[1], solved.correction.poses, cfg)
    if not decision.needed:
        return ex, matched, solved, decision
    ex2 = _rebuild(extraction, cfg, solved.correction.poses, progress)
    matched2 = _match_and_select(ex2, cfg, mode, *scans, link_frame=solved.correction.poses)
    matched2, solved2 = _solve(ex2, matched2, cfg, scans, True, extraction.gap_factors)
    decision = replace(
        decision,
        loops=(sum(matched.keep), sum(matched2.keep)),
        rescaled=(_rescaled_passes(solved), _rescaled_passes(solved2)),
    )
    if decision.kept:
        return ex2, matched2, solved2, decision
    return ex, matched, solved, decision


def _write(
    out: Path,
    ex: _Extracted,
    matched: _Matched,
    odometry: tuple[tuple[FloatArray, FloatArray], FloatArray],
    correction: CorrectionResult,
    constraints: list[LoopConstraint],
    cfg: Config,
    stage: Reinspection | None = None,
) -> tuple[list[Joint], dict[str, Any] | None]:
    """The contract's files: trajectories, loops, landmarks, joints, the graph (on the
    odometry the graph started from: ``odometry[1]``), this run's survey; with ``stage``
    (``--survey``) the cross-session loop rows, survey joint ids and the change report
    (returned: its ``report.json`` section)."""
    (scan_stamps, scan_odom), graph_odom = odometry
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    write_tum(out / "odometry.tum", scan_stamps, scan_odom)
    write_tum(out / "corrected.tum", scan_stamps, correction.poses)
    table = _loop_table(matched.results, matched.keep, matched.reasons, matched.by_prior)
    if stage is not None:
        c = stage.cross
        table = stage.loop_rows(table, _loop_table(c.results, c.keep, c.reasons))
    write_loops_csv(out / "loops.csv", table)
    lms = ex.landmarks
    if stage is not None and stage.placed:
        chainage = stage.chainage(lms, scan_stamps, correction.poses)
    else:
        chainage = landmark_chainage(
            np.array([lm.submap_stamp for lm in lms]),
            np.array([lm.origin for lm in lms]).reshape(-1, 3),
            np.array([lm.axis for lm in lms]).reshape(-1, 3),
            scan_stamps,
            correction.poses,
        )
    kept = [r for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
    same = float(cfg.matching.duplicate_radius_m)
    joints, joint_of = joint_registry(lms, matched.tracks, kept, chainage, matched.split, same)
    survey_ids = None if stage is None else stage.survey_ids(joint_of)
    write_joints_csv(out / "joints.csv", joints, survey_ids)
    write_run_survey(
        out, lms, joint_of, anchor_stamps, (scan_stamps, correction.poses), joints, cfg
    )
    changes = None
    if stage is not None:
        changes = stage.write_changes(out, lms, joint_of, chainage, cfg)
    write_landmarks_csv(
        out / "landmarks.csv",
        LandmarkTable(
            stamp=np.array([lm.submap_stamp for lm in lms], dtype=np.float64),
            origin=np.array([lm.origin for lm in lms], dtype=np.float64).reshape(-1, 3),
            axis=np.array([lm.axis for lm in lms], dtype=np.float64).reshape(-1, 3),
            radius_m=np.array([lm.radius_m for lm in lms], dtype=np.float64),
            chainage_m=chainage,
            track_id=matched.tracks,
            joint_id=joint_of,
        ),
    )
    # The graph on the submap anchors, for users who optimise elsewhere (g2o and JSON).
    if anchor_stamps.size:
        anchor_odom = interpolate_poses(scan_stamps, graph_odom, anchor_stamps)
        write_g2o(out / "graph.g2o", anchor_odom, constraints, cfg.graph)
        write_graph_json(out / "graph.json", anchor_odom, constraints, cfg.graph)
    return joints, changes


def run_log(
    log: str | Path,
    out_dir: str | Path,
    *,
    preset: str = "auto",
    config_path: str | Path | None = None,
    points_topic: str | None = None,
    odom_topic: str | None = None,
    odom_tum: str | Path | None = None,
    imu_topic: str | None = None,
    use_imu: bool = True,
    mode: str = "auto",
    loops: bool = True,
    sequential: bool | None = None,
    plots: bool = True,
    progress: bool = True,
    map: bool = False,
    rerun: str | Path | None = None,
    survey: str | Path | None = None,
) -> RunSummary:
    """Run DeCOD on ``log`` and write the contract's files into ``out_dir`` (paper Alg. 1:
    extract -> match -> select -> optimise -> write).

    ``preset="auto"`` measures the corridor from the first scans and derives the spatial
    parameters (:mod:`decod_rs.autoscale`); ``"pipe"`` / ``"tunnel"`` take the fixed presets.
    ``imu_topic=None`` takes the log's unique IMU topic if there is one (``use_imu=False``:
    never; gravity is then the sensor's -z). ``loops=False`` disables every factor (the
    output trajectory is then the odometry); the matching still runs and is reported.
    ``sequential`` overrides ``graph.sequential`` (False: the paper's loops-only graph).
    ``map=True`` also writes the corrected and odometry maps (PLY) and the map-consistency
    figure; ``rerun=FILE.rrd`` a 3D recording (rerun-sdk, extra ``rerun``): see
    :mod:`decod_rs.visuals`. ``survey=OLD_RUN_DIR`` re-inspects an earlier run's corridor:
    the trajectory comes out in its frame, with its joint ids and a change report
    (:mod:`decod_rs.reinspection`); without ``preset``/``config_path`` its config is used.
    """
    if mode not in MODES:
        raise ValueError(f"mode: {mode!r} is not one of {MODES}")
    if preset not in PRESET_CHOICES:
        raise ValueError(f"preset: {preset!r} is not one of {PRESET_CHOICES}")
    if rerun is not None:
        from decod_rs.recording import require_rerun

        require_rerun()  # fail before the run, not after it
    srv = None if survey is None else load_survey(survey)  # fail before the run
    log, out = Path(log), check_run_dir(Path(out_dir))
    if imu_topic is None and use_imu:
        # Gravity from the IMU when the log has exactly one; the sensor's -z otherwise.
        imu_topic = find_imu_topic(log)
    tum = None if odom_tum is None else Path(odom_tum)
    topics = (points_topic, odom_topic, tum, imu_topic)
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    cfg, auto, imu = _configure(log, preset, config_path, topics, sequential, srv)
    if srv is not None:
        check_compatible(srv, cfg)
    timings["configure"] = time.perf_counter() - t0
    # The recording is written by a worker process while the figures are drawn, if any.
    visuals = Visuals(map=map, rerun=None if rerun is None else Path(rerun), worker=plots)
    visuals.prepare()

    t0 = time.perf_counter()
    # The voxel map costs 2-12 % of the stream: kept only when a map or recording is asked.
    processor, ex = _extract(
        log, cfg, *topics, progress, keep_map=map or rerun is not None, imu_samples=imu
    )
    timings["extract"] = time.perf_counter() - t0
    scans = (
        np.asarray(processor.scan_stamps(), dtype=np.float64),
        np.asarray(processor.scan_poses(), dtype=np.float64),
    )
    health = StreamHealth.from_core(processor.health())
    warn_once(log, health)  # damage, gaps: the run goes on with what the log holds
    if scans[0].size == 0:
        raise ValueError(f"{log}: no scan could be paired with odometry")
    gap_periods = float(cfg.submap.odometry_gap_periods)
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    ingest, gap_factors = ingest_section(
        health, processor.points_topic, scans, gap_periods, anchors
    )

    head = {"preset": preset, "auto": auto, "imu_topic": imu_topic, "ingest": ingest}
    extraction = Extracted(log, processor, ex, scans, gap_factors, imu_topic)
    # Written into OUT.partial, published into OUT at the end: never a half-written OUT.
    with staged_run_dir(out) as staging:
        summary = finish_run(
            extraction,
            staging,
            cfg,
            mode,
            loops,
            plots,
            timings,
            head,
            visuals,
            progress,
            survey=srv,
        )
    summary.out_dir = out
    return summary


@dataclass(frozen=True)
class Extracted:
    """Stage 1's result, what stages 2-5 need: the log, the processor that streamed it (its
    voxel map, its skip lists), the landmarks and anchors, and the scan odometry."""

    log: Path
    processor: _core.LogProcessor
    extracted: _Extracted
    scans: tuple[FloatArray, FloatArray]
    gap_factors: FloatArray | None = None
    imu_topic: str | None = None


def finish_run(
    extraction: Extracted,
    out: Path,
    cfg: Config,
    mode: str,
    loops: bool,
    plots: bool,
    timings: dict[str, float],
    report_head: dict[str, Any],
    visuals: Visuals,
    progress: bool = False,
    survey: Survey | None = None,
) -> RunSummary:
    """Stages 2-5 of Algorithm 1 on an extraction: match -> select -> optimise -> write
    (report.json last, with ``report_head`` merged in). ``decod run`` and ``decod sweep``
    (which replays one extraction under several matching/graph settings) share it."""
    ex, scans, processor = extraction.extracted, extraction.scans, extraction.processor
    t0 = time.perf_counter()
    matched = _match_and_select(ex, cfg, mode, *scans)
    timings["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matched, solved = _solve(ex, matched, cfg, scans, loops, extraction.gap_factors)
    timings["optimise"] = time.perf_counter() - t0

    rebuild = None
    if loops and cfg.submap.rebuild_on_correction and survey is None:
        t0 = time.perf_counter()
        ex, matched, solved, rebuild = _rebuilt(
            extraction, ex, matched, solved, cfg, mode, progress
        )
        timings["rebuild"] = time.perf_counter() - t0
    constraints, seq, correction = solved.constraints, solved.seq, solved.correction
    scale, start = solved.scale, solved.start

    stage = None
    if survey is not None:
        # Against the earlier survey: match, keep the consistent pairs, move into its frame.
        t0 = time.perf_counter()
        stage, correction = _reinspect(survey, ex, matched.tracks, scans, correction, cfg)
        timings["survey"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    joints, changes = _write(out, ex, matched, (scans, start), correction, constraints, cfg, stage)
    used = constraints if len(correction.graph.loop_weights) else []  # none: odometry stood
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    odometry_only = unmeasured(scans[0], correction.poses, anchors, used, matched.split)
    timings["write"] = time.perf_counter() - t0
    # Maps rendered, the recording's worker started: it writes while the figures are drawn.
    pending = start_visuals(processor, scans, correction.poses, ex.landmarks, matched, visuals)
    if plots:
        t0 = time.perf_counter()
        kept = [r for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
        _plots(out, *scans, correction.poses, kept, ex.landmarks, odometry_only[0])
        timings["plots"] = time.perf_counter() - t0

    summary = _summary(out, ex, matched, scans, timings)
    report = _report(
        summary, extraction.log, ex, processor, cfg, matched, constraints, correction, seq, joints
    )
    report.update(loops_enabled=loops, rebuild=None if rebuild is None else rebuild.report())
    report["unmeasured"] = unmeasured_report(*odometry_only)
    report["survey"] = None if stage is None else {**stage.report(), "changes": changes}
    if scale is not None and report["sequential"] is not None:
        report["sequential"]["odometry_scale"] = scale.passes
    report.update(report_head)
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    if pending is not None:
        summary.timings_s.update(finish_visuals(out, pending))
    return summary


def _reinspect(
    survey: Survey,
    ex: _Extracted,
    tracks: NDArray[np.int64],
    scans: tuple[FloatArray, FloatArray],
    correction: CorrectionResult,
    cfg: Config,
) -> tuple[Reinspection, CorrectionResult]:
    """The run against an earlier survey, and the trajectory moved into its frame when the
    cross-session loops place it (:mod:`decod_rs.reinspection`)."""
    stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    views = views_per_landmark(tracks)
    stage = reinspect(survey, ex.landmarks, views, stamps, scans, correction.poses, cfg)
    if stage.poses is not None:
        correction = replace(correction, poses=stage.poses)
    return stage, correction


def _summary(
    out: Path,
    ex: _Extracted,
    matched: _Matched,
    scans: tuple[FloatArray, FloatArray],
    timings: dict[str, float],
) -> RunSummary:
    return RunSummary(
        out_dir=out,
        scans=int(scans[0].size),
        submaps=len(ex.anchor_stamps),
        landmarks=len(ex.landmarks),
        queries=len(matched.results),
        accepted=int(sum(matched.keep)),
        mode=matched.mode,
        split_stamp=matched.split,
        log_duration_s=float(scans[0][-1] - scans[0][0]),
        timings_s=timings,
        rejections=ex.rejections,
    )


def _report(
    summary: RunSummary,
    log: Path,
    ex: _Extracted,
    processor: _core.LogProcessor,
    cfg: Config,
    matched: _Matched,
    constraints: list[LoopConstraint],
    correction: CorrectionResult,
    seq: SequentialFactors | None,
    joints: list[Joint],
) -> dict[str, Any]:
    """``report.json``: counts, every rejection and its reason, timings, config, versions."""
    rejected: dict[str, int] = {}
    for why, ok in zip(matched.reasons, matched.keep, strict=True):
        if not ok:
            rejected[why or "unknown"] = rejected.get(why or "unknown", 0) + 1
    loop_factors = sum(1 for c in constraints if c.kind == "loop")
    split = summary.split_stamp
    stamps = np.array([lm.submap_stamp for lm in ex.landmarks])
    outbound = int(np.sum(stamps <= split)) if split is not None else int(stamps.size)
    no_loop = why_no_loop(
        (outbound, int(stamps.size) - outbound),
        summary.queries,
        summary.rejections,
        rejected,
        split,
    )
    return {
        "no_loop_reason": None if summary.accepted else no_loop,
        "log": str(log),
        "points_topic": processor.points_topic,
        "mode": summary.mode,
        "split_stamp": summary.split_stamp,
        # Which database entries a query may meet (decod_rs.evaluate counts recall the same way).
        "eligibility": "across_passes" if summary.mode == "batch" else "time_separation",
        "counts": {
            "scans": summary.scans,
            "skipped_outside_odometry": len(processor.skipped_outside_odometry),
            "skipped_in_odometry_gaps": len(processor.health()[2]),
            "submaps": summary.submaps,
            "landmarks": summary.landmarks,
            "tracks": int(np.unique(matched.tracks).size),
            "joints": len(joints),
            "database": matched.database,
            "queries": summary.queries,
            "accepted": summary.accepted,
            "accepted_by_position_prior": len(matched.by_prior),
            "loop_factors": loop_factors,
            "sequential_factors": len(constraints) - loop_factors,
        },
        "extraction_rejections": summary.rejections,
        "extraction_rejection_messages": ex.rejection_messages[:200],
        "query_rejections": rejected,
        "aliasing": aliasing(matched.results).report(),
        "sequential": None if seq is None else seq.report(),
        "optimisation": {
            "nodes": int(correction.node_stamps.size),
            "iterations": correction.graph.iterations,
            "initial_error": correction.graph.initial_error,
            "final_error": correction.graph.final_error,
            "loop_weights": [float(w) for w in correction.graph.loop_weights],
        },
        "timings_s": summary.timings_s,
        "log_duration_s": summary.log_duration_s,
        "realtime_factor": summary.realtime_factor,
        "config": cfg.to_dict(),
        "versions": {
            "decod": _core.__version__,
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
    }


def _plots(
    out: Path,
    stamps: FloatArray,
    odom: FloatArray,
    corrected: FloatArray,
    results: list[QueryResult],
    landmarks: list[Landmark],
    unmeasured: list[Stretch],
) -> None:
    from decod_rs.plots import plot_descriptor_pair, plot_trajectories

    accepted = results  # the loops kept
    plot_trajectories(
        out / "trajectory.png",
        stamps,
        odom,
        corrected,
        [(r.query_stamp, r.candidate_stamp) for r in accepted],
        unmeasured=[(u.from_stamp, u.to_stamp) for u in unmeasured],
    )
    by_key = {(lm.submap_stamp, tuple(np.round(lm.origin, 6))): lm for lm in landmarks}
    # The strongest few accepted pairs: enough to inspect, not a file per loop.
    for k, r in enumerate(sorted(accepted, key=lambda r: -r.score)[:4]):
        q = by_key.get((r.query_stamp, tuple(np.round(r.query_origin, 6))))
        d = by_key.get((r.candidate_stamp, tuple(np.round(r.candidate_origin, 6))))
        if q is None or d is None:
            continue
        plot_descriptor_pair(
            out / f"descriptors_pair{k}.png",
            q.descriptor,
            q.mask,
            d.descriptor,
            d.mask,
            title=f"query {r.query_stamp:.1f} s vs db {r.candidate_stamp:.1f} s: "
            f"K={r.inliers}, S={r.score:.2f}, heading {r.heading_deg} deg",
        )
