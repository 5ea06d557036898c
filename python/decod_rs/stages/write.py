"""Stage 5 of Algorithm 1: the contract's files (DESIGN.md): trajectories, loops,
landmarks, joints, the graph, the run's survey, ``report.json`` and the plots."""

from __future__ import annotations

import platform
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark, QueryResult
from decod_rs.aliasing import aliasing
from decod_rs.allocator import peak_memory_mb
from decod_rs.config import Config
from decod_rs.graph import CorrectionResult, LoopConstraint
from decod_rs.graph_export import write_g2o, write_graph_json
from decod_rs.joints import (
    Joint,
    joint_registry,
    landmark_chainage,
    standing_poses,
    write_joints_csv,
)
from decod_rs.reinspection import Reinspection, write_run_survey
from decod_rs.run_files import (
    LandmarkTable,
    LoopTable,
    write_landmarks_csv,
    write_loops_csv,
)
from decod_rs.selection import why_no_loop
from decod_rs.sequential import (
    SequentialFactors,
)
from decod_rs.stages.extract import SubmapLandmarks
from decod_rs.stages.match import Matched
from decod_rs.tum import interpolate_poses, write_tum
from decod_rs.unmeasured import Stretch

FloatArray = NDArray[np.float64]


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
    #: Submaps cut before an end face in view (``report.json`` ``counts``).
    end_face_submaps: int = 0
    #: Windows ``submap.max_travel_m`` closed (``report.json`` ``counts``).
    travel_submaps: int = 0
    #: Views kept out of the database, taken on ground their pass covered before
    #: (``report.json`` ``counts``, :func:`decod_rs.stages.match.revisit_views`).
    revisited_views: int = 0
    #: Clouds before the odometry's first pose or after its last (``ingest``), not used.
    clouds_outside_odometry: int = 0

    @property
    def realtime_factor(self) -> float:
        total = sum(self.timings_s.values())
        return self.log_duration_s / total if total > 0 else float("inf")


def loop_table(
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


def write_outputs(
    out: Path,
    ex: SubmapLandmarks,
    matched: Matched,
    odometry: tuple[tuple[FloatArray, FloatArray], FloatArray],
    correction: CorrectionResult,
    constraints: list[LoopConstraint],
    cfg: Config,
    stage: Reinspection | None = None,
    plots: bool = True,
) -> tuple[list[Joint], dict[str, Any] | None]:
    """The contract's files: trajectories, loops, landmarks, joints, the graph (on the
    odometry the graph started from: ``odometry[1]``), this run's survey; with ``stage``
    (``--survey``) the cross-session loop rows, survey joint ids and the change report
    (returned: its ``report.json`` section; its figure only with ``plots``)."""
    (scan_stamps, scan_odom), graph_odom = odometry
    anchor_stamps = np.asarray(ex.anchor_stamps, dtype=np.float64)
    write_tum(out / "odometry.tum", scan_stamps, scan_odom)
    write_tum(out / "corrected.tum", scan_stamps, correction.poses)
    table = loop_table(matched.results, matched.keep, matched.reasons, matched.by_prior)
    if stage is not None:
        c = stage.cross
        table = stage.loop_rows(table, loop_table(c.results, c.keep, c.reasons))
    write_loops_csv(out / "loops.csv", table)
    lms = ex.landmarks
    stamps = np.array([lm.submap_stamp for lm in lms], dtype=np.float64)
    origins = np.array([lm.origin for lm in lms], dtype=np.float64).reshape(-1, 3)
    axes = np.array([lm.axis for lm in lms], dtype=np.float64).reshape(-1, 3)
    if stage is not None and stage.placed:
        chainage = stage.chainage(lms, scan_stamps, correction.poses)
    else:
        chainage = landmark_chainage(stamps, origins, axes, scan_stamps, correction.poses)
    kept = [r for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
    same = float(cfg.matching.duplicate_radius_m)
    poses = standing_poses(stamps, scan_stamps, correction.poses)
    joints, joint_of = joint_registry(
        lms, matched.tracks, kept, chainage, matched.split, same, poses
    )
    survey_ids = None if stage is None else stage.survey_ids(joint_of, same)
    write_joints_csv(out / "joints.csv", joints, survey_ids)
    write_run_survey(
        out, lms, joint_of, anchor_stamps, (scan_stamps, correction.poses), joints, cfg
    )
    changes = None
    if stage is not None:
        changes = stage.write_changes(out, lms, joint_of, chainage, cfg, plot=plots)
    write_landmarks_csv(
        out / "landmarks.csv",
        LandmarkTable(
            stamp=stamps,
            origin=origins,
            axis=axes,
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


def run_summary(
    out: Path,
    ex: SubmapLandmarks,
    matched: Matched,
    scans: tuple[FloatArray, FloatArray],
    timings: dict[str, float],
    processor: _core.LogProcessor,
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
        end_face_submaps=ex.end_face_submaps,
        travel_submaps=ex.travel_submaps,
        revisited_views=matched.revisited,
        clouds_outside_odometry=len(processor.skipped_outside_odometry),
    )


def run_report(
    summary: RunSummary,
    log: Path,
    ex: SubmapLandmarks,
    processor: _core.LogProcessor,
    cfg: Config,
    matched: Matched,
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
        correction.poses[:, :3, 3],
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
            "submaps_cut_at_end_face": summary.end_face_submaps,
            "submaps_closed_by_travel": summary.travel_submaps,
            "landmarks": summary.landmarks,
            "tracks": int(np.unique(matched.tracks).size),
            "joints": len(joints),
            "database": matched.database,
            "views_on_revisited_ground": summary.revisited_views,
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
        "peak_memory_mb": peak_memory_mb(),
        "config": cfg.to_dict(),
        "versions": {
            "decod": _core.__version__,
            "python": platform.python_version(),
            "numpy": np.__version__,
        },
    }


def run_plots(
    out: Path,
    stamps: FloatArray,
    odom: FloatArray,
    corrected: FloatArray,
    results: list[QueryResult],
    landmarks: list[Landmark],
    unmeasured: list[Stretch],
    faces: Sequence[float] = (),
) -> None:
    from decod_rs.plots import DescriptorPair, plot_descriptor_pairs, plot_trajectories

    accepted = results  # the loops kept
    plot_trajectories(
        out / "trajectory.png",
        stamps,
        odom,
        corrected,
        [(r.query_stamp, r.candidate_stamp) for r in accepted],
        unmeasured=[(u.from_stamp, u.to_stamp) for u in unmeasured],
        faces=faces,
    )
    by_key = {(lm.submap_stamp, tuple(np.round(lm.origin, 6))): lm for lm in landmarks}
    # The strongest few accepted pairs: enough to inspect, not a file per loop.
    pairs = []
    for k, r in enumerate(sorted(accepted, key=lambda r: -r.score)[:4]):
        q = by_key.get((r.query_stamp, tuple(np.round(r.query_origin, 6))))
        d = by_key.get((r.candidate_stamp, tuple(np.round(r.candidate_origin, 6))))
        if q is None or d is None:
            continue
        title = (
            f"query {r.query_stamp:.1f} s vs db {r.candidate_stamp:.1f} s: "
            f"K={r.inliers}, S={r.score:.2f}, heading {r.heading_deg} deg"
        )
        path = out / f"descriptors_pair{k}.png"
        pairs.append(DescriptorPair(path, q.descriptor, q.mask, d.descriptor, d.mask, title))
    plot_descriptor_pairs(pairs)
