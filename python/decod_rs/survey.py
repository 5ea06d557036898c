"""Re-inspection against an earlier survey (issue 12): ``decod run NEW_LOG --survey OLD_RUN``.

A run writes ``survey.decod`` (:func:`write_survey`): every landmark with its physical
boundary (``joints.csv`` joint id), the corrected poses of the submap anchors the landmarks
are expressed in, the run's outbound path (for chainage), its joints' chainage, the config
and the decod version, in the versioned binary format of ``src/survey.rs`` (another format
version is refused with both versions named; counts are checked before allocating).

A later run on the same corridor (Algorithm 1 with one more database):

1. **match** - every new landmark queries the survey's database under both headings with no
   time-separation rule (the sessions' stamps are unrelated), with the null-model acceptance
   of a run (the family: every survey boundary x 2 headings);
2. **select** - each accepted pair implies a rigid map from the new odometry frame to the
   survey frame: the rotation from the two landmark frames (axis, gravity ``e1``), the
   translation from the origins. Pairs to the wrong one of identical joints imply a shift
   by a joint spacing; the consistent set is chosen like within a run
   (:func:`decod_rs.selection.select_consistent` on the implied translations, with the
   drift allowance along the new path) and needs corroboration;
3. **optimise** - the new anchors start at the aligned poses of the run's own (loop-corrected)
   trajectory, keep its relative motion as odometry factors, and get one 5-DoF factor per
   kept pair to the survey anchor, whose pose is fixed: the new trajectory comes out in the
   survey's frame. No kept pair: the run stays in its own frame (reported).

Chainage is then measured along the survey's path (:func:`chainage_along`), and a new joint
whose views matched a survey joint carries its id (``joints.csv`` ``survey_joint_id``).
"""

from __future__ import annotations

import json
import sys
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import gtsam
import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark, QueryResult
from decod_rs.chainage import forward_course
from decod_rs.config import Config
from decod_rs.graph import (
    PRIOR_SIGMA,
    add_landmark_factors,
    loop_noise_sigmas,
    odometry_sigmas,
    propagate_to_scans,
)
from decod_rs.joints import DIRECTION_SPAN_M, ties_one_boundary
from decod_rs.landmark_factor import LandmarkTerm
from decod_rs.matching import LandmarkDatabase
from decod_rs.selection import (
    LoopEvidence,
    drop_unsafe_sets,
    effective_db_origin,
    select_by_config,
)
from decod_rs.tracks import tracked_loops, views_per_landmark
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]

#: The survey file in a run directory.
SURVEY_FILE = "survey.decod"
#: The survey format version this build reads and writes (``src/survey.rs``).
SURVEY_FORMAT_VERSION: int = _core.SURVEY_FORMAT_VERSION
#: Sigmas of the weak prior on the first new anchor (rad x3, m x3): it only fixes what the
#: 5-DoF factors leave free (rotation about a straight corridor's axis) at the aligned start.
GAUGE_PRIOR_SIGMAS = np.array([0.1, 0.1, 0.1, 10.0, 10.0, 10.0])
#: Two pairs' rotations agree when they differ by less than this (radians): a wrong heading
#: differs by 180 degrees, gravity and axis errors by a degree or two.
ROTATION_AGREEMENT_RAD = np.deg2rad(10.0)

__all__ = [
    "SURVEY_FILE",
    "SURVEY_FORMAT_VERSION",
    "CrossSession",
    "Survey",
    "chainage_along",
    "check_compatible",
    "cross_session",
    "load_survey",
    "write_survey",
]


@dataclass(frozen=True)
class Survey:
    """A loaded survey: ``landmarks`` (L) with ``joint_ids`` (L,); ``anchor_stamps`` (A,)
    and ``anchor_poses`` (A, 4, 4) corrected ``world_from_anchor`` in the survey frame;
    ``path`` (P, 3) its outbound path; ``joint_chainage`` survey joint id -> chainage (m);
    ``config`` the survey run's config; ``header`` the whole header; ``spill`` where the
    landmarks' cells wait (None: in memory), and the patches of the database made of them
    (:func:`survey_database`)."""

    source: Path
    landmarks: list[Landmark]
    joint_ids: NDArray[np.int64]
    anchor_stamps: FloatArray
    anchor_poses: FloatArray
    path: FloatArray
    joint_chainage: dict[int, float]
    config: dict[str, Any]
    header: dict[str, Any]
    spill: _core.Spill | None = None

    def anchor_pose(self, stamp: float) -> FloatArray:
        """The corrected pose of the anchor at ``stamp`` (the nearest anchor)."""
        k = int(np.argmin(np.abs(self.anchor_stamps - stamp)))
        return np.asarray(self.anchor_poses[k], dtype=np.float64)


def write_survey(
    out: Path,
    landmarks: list[Landmark],
    joint_ids: NDArray[np.int64],
    anchors: tuple[FloatArray, FloatArray],
    path: FloatArray,
    joint_chainage: dict[int, float],
    cfg: Config,
) -> Path:
    """Write ``out/survey.decod``: ``anchors`` = (stamps (A,), corrected poses (A, 4, 4)),
    ``path`` (P, 3) the outbound corrected positions; returns the file's path."""
    stamps, poses = anchors
    header = {
        "decod_version": _core.__version__,
        "config": cfg.to_dict(),
        "anchors": [
            {"stamp": float(s), "pose": np.asarray(p, dtype=np.float64).ravel().tolist()}
            for s, p in zip(stamps, poses, strict=True)
        ],
        "joint_ids": [int(j) for j in joint_ids],
        "joints": [{"joint_id": int(j), "chainage_m": float(c)} for j, c in joint_chainage.items()],
        "path": np.asarray(path, dtype=np.float64).round(6).tolist(),
    }
    target = out / SURVEY_FILE
    _core.write_survey(str(target), json.dumps(header), list(landmarks))
    return target


def load_survey(run_dir: str | Path, spill: _core.Spill | None = None) -> Survey:
    """The survey written by ``decod run`` into ``run_dir`` (or the file itself).
    ``FileNotFoundError`` names what is missing; ``DatabaseError`` another format version or
    a corrupt file. ``spill``: the landmarks' cells go there as they are read, and the
    survey database's patches when it is made (a survey holds a whole earlier run's
    landmarks, 29 KB each; the same results either way)."""
    path = Path(run_dir)
    if path.is_dir():
        path = path / SURVEY_FILE
    if not path.is_file():
        raise FileNotFoundError(
            f"{path}: no survey: --survey takes the output directory of an earlier `decod run` "
            f"(it writes {SURVEY_FILE})"
        )
    try:
        text, landmarks = _core.read_survey(str(path), spill)
    except OSError as exc:  # a full disk: the survey stays in memory, as the run's would
        if spill is None:
            raise
        print(f"warning: {exc}; the survey's landmarks stay in memory", file=sys.stderr)
        spill = None
        text, landmarks = _core.read_survey(str(path))
    header = json.loads(text)
    anchors = header.get("anchors", [])
    poses = np.array([a["pose"] for a in anchors], dtype=np.float64).reshape(-1, 4, 4)
    return Survey(
        source=path,
        landmarks=landmarks,
        joint_ids=np.asarray(header["joint_ids"], dtype=np.int64),
        anchor_stamps=np.array([a["stamp"] for a in anchors], dtype=np.float64),
        anchor_poses=poses,
        path=np.asarray(header.get("path", []), dtype=np.float64).reshape(-1, 3),
        joint_chainage={int(j["joint_id"]): float(j["chainage_m"]) for j in header["joints"]},
        config=header.get("config", {}),
        header=header,
        spill=spill,
    )


def chainage_along(path: FloatArray, points: FloatArray) -> FloatArray:
    """Arclength (m) along the polyline ``path`` (P, 3) at the projection of each of
    ``points`` (N, 3) onto its nearest segment. Beyond either end the path runs on along its
    direction over the last (first) ``2 * DIRECTION_SPAN_M`` of it, as the run's own
    registry does (``joints.landmark_chainage``): a joint seen past the far end gets a
    chainage past the path's length, not the length itself (a re-inspection's view of the
    survey's last joint, 2.3 m beyond the turnaround, was put at the turnaround), and not
    along the last scan step, which is odometry noise where the robot slows to a stop. The
    path is taken along its forward course (:func:`decod_rs.chainage.forward_course`), so a
    survey written before that, whose path doubles back where its robot backed up, measures
    chainage as a new one does."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    path = forward_course(path)
    if path.shape[0] < 2:
        return np.zeros(pts.shape[0])
    a, b = path[:-1], path[1:]
    seg = b - a
    length = np.linalg.norm(seg, axis=1)
    start = np.concatenate([[0.0], np.cumsum(length)])[:-1]
    total = float(start[-1] + length[-1])
    ends = _end_directions(path, np.concatenate([start, [total]]))
    last = seg.shape[0] - 1
    out = np.empty(pts.shape[0])
    for k, x in enumerate(pts):
        raw = np.einsum("ij,ij->i", x - a, seg) / np.maximum(length**2, 1e-12)
        t = np.clip(raw, 0.0, 1.0)
        dist = np.linalg.norm(a + t[:, None] * seg - x, axis=1)
        s = int(np.argmin(dist))
        if s == 0 and raw[s] < 0.0:
            out[k] = float((x - path[0]) @ ends[0])
        elif s == last and raw[s] > 1.0:
            out[k] = total + float((x - path[-1]) @ ends[1])
        else:
            out[k] = start[s] + t[s] * length[s]
    return out


def _end_directions(path: FloatArray, arclength: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Unit directions of travel over the first and the last ``2 * DIRECTION_SPAN_M`` of
    ``path`` (zero vectors where the path has no length)."""
    span = 2.0 * DIRECTION_SPAN_M
    first = path[min(int(np.searchsorted(arclength, span)), path.shape[0] - 1)] - path[0]
    back = max(int(np.searchsorted(arclength, arclength[-1] - span)) - 1, 0)
    last = path[-1] - path[back]
    unit = [d / n if (n := float(np.linalg.norm(d))) > 1e-9 else np.zeros(3) for d in (first, last)]
    return unit[0], unit[1]


@dataclass
class CrossSession:
    """Stage 2-3 against a survey: one Top-1 per new landmark (``results``, in the order of
    the run's landmarks), which pairs stay (``keep``) and why not (``reasons``), the rigid
    map ``survey_from_odometry`` (4, 4) that started the graph (identity if none stayed)."""

    survey: Survey
    results: list[QueryResult]
    keep: list[bool]
    reasons: list[str]
    survey_from_odometry: FloatArray = field(default_factory=lambda: np.eye(4))

    @property
    def kept(self) -> list[int]:
        """Indices (into the run's landmarks) of the kept pairs."""
        return [k for k, ok in enumerate(self.keep) if ok]

    def survey_joint(self, k: int) -> int | None:
        """The survey joint id landmark ``k`` matched (kept pairs only)."""
        r = self.results[k]
        if not self.keep[k] or r.candidate_index is None:
            return None
        return int(self.survey.joint_ids[r.candidate_index])


def _frame(pose: FloatArray, lm_axis: FloatArray, lm_e1: FloatArray) -> FloatArray:
    """The landmark frame ``[a, e1, a x e1]`` (columns) in the world of ``pose``."""
    a = pose[:3, :3] @ np.asarray(lm_axis, dtype=np.float64)
    e1 = pose[:3, :3] @ np.asarray(lm_e1, dtype=np.float64)
    return np.column_stack([a, e1, np.cross(a, e1)])


def _project_so3(m: FloatArray) -> FloatArray:
    u, _, vt = np.linalg.svd(m)
    d = np.sign(np.linalg.det(u @ vt))
    return np.asarray(u @ np.diag([1.0, 1.0, d]) @ vt, dtype=np.float64)


@dataclass(frozen=True)
class _Pair:
    """One accepted cross-session pair in world terms: its rotation survey-from-odometry,
    the new origin (odometry world) and the survey origin (survey world)."""

    index: int
    rotation: FloatArray
    new_world: FloatArray
    survey_world: FloatArray


def _pairs(
    survey: Survey,
    landmarks: list[Landmark],
    results: list[QueryResult],
    anchors: dict[float, FloatArray],
) -> list[_Pair]:
    out = []
    for k, r in enumerate(results):
        if not r.accepted or r.candidate_index is None:
            continue
        lm, slm = landmarks[k], survey.landmarks[r.candidate_index]
        pose_n, pose_s = anchors[lm.submap_stamp], survey.anchor_pose(r.candidate_stamp)
        f_new = _frame(pose_n, lm.axis, lm.e1)
        f_srv = _frame(pose_s, slm.axis, slm.e1)
        if abs(r.heading_deg) > 90.0:
            f_srv = f_srv @ np.diag([-1.0, 1.0, -1.0])  # reversal: a -> -a, e2 -> -e2
        origin = pose_s[:3, :3] @ effective_db_origin(r) + pose_s[:3, 3]
        out.append(_Pair(k, f_srv @ f_new.T, pose_n[:3, :3] @ lm.origin + pose_n[:3, 3], origin))
    return out


#: Rows of the pairs' agreement matrix computed at a time (:func:`_consensus_rotation`):
#: memory stays at this many times the pair count, whatever the survey's length.
AGREEMENT_ROWS = 512


def _agreement(rotations: FloatArray, rows: slice) -> NDArray[np.bool_]:
    """Whether the rotations of ``rows`` agree with each of ``rotations`` (N, 3, 3): their
    relative angle ``arccos((tr(A^T B) - 1) / 2)`` below ``ROTATION_AGREEMENT_RAD``, with
    ``tr(A^T B)`` the sum of the elementwise product."""
    flat = rotations.reshape(len(rotations), 9)
    cos = np.clip((flat[rows] @ flat.T - 1.0) / 2.0, -1.0, 1.0)
    return np.asarray(np.arccos(cos) < ROTATION_AGREEMENT_RAD)


def _consensus_rotation(pairs: list[_Pair]) -> tuple[FloatArray, list[bool]]:
    """The rotation most pairs agree with (chordal mean of the largest agreeing group) and
    which pairs agree with it. Every pair against every other, a block of rows at a time
    (one angle per pair of pairs in Python took 4.1 s of a 10 s re-inspection with 640
    pairs; the first best on a tie, as before)."""
    rotations = np.stack([p.rotation for p in pairs])
    support = np.concatenate(
        [
            _agreement(rotations, slice(i, i + AGREEMENT_ROWS)).sum(axis=1)
            for i in range(0, len(pairs), AGREEMENT_ROWS)
        ]
    )
    best = int(np.argmax(support))
    agree = _agreement(rotations, slice(best, best + 1))[0]
    mean = _project_so3(np.sum(rotations[agree], axis=0))
    return mean, [bool(a) for a in agree]


def _select(
    survey: Survey,
    results: list[QueryResult],
    pairs: list[_Pair],
    along: Any,
    matching: Any,
    tracked: list[bool] | None = None,
) -> tuple[list[bool], list[str], FloatArray]:
    """Which accepted pairs stay (module docs, step 2) and the initial alignment;
    ``tracked``: :func:`decod_rs.selection.drop_unsafe_sets`."""
    keep = [False] * len(results)
    reasons = [r.rejection or "" for r in results]
    align = np.eye(4)
    if not pairs:
        return keep, reasons, align
    rotation, agree = _consensus_rotation(pairs)
    survey_along = chainage_along(survey.path, np.array([p.survey_world for p in pairs]))
    evidence = [
        LoopEvidence(
            correction=p.survey_world - rotation @ p.new_world,
            query_path_m=along(results[p.index].query_stamp),
            db_path_m=float(s),
            query_stamp=results[p.index].query_stamp,
            inliers=results[p.index].inliers,
            chance=results[p.index].chance,
        )
        for p, s in zip(pairs, survey_along, strict=True)
    ]
    chosen = select_by_config(evidence, matching)
    for p, ok, why, rot_ok in zip(pairs, chosen.kept, chosen.reasons, agree, strict=True):
        keep[p.index] = ok and rot_ok
        reasons[p.index] = why if rot_ok else "inconsistent"
    keep, reasons = drop_unsafe_sets(results, keep, reasons, tracked, matching)
    kept = [e.correction for e, p in zip(evidence, pairs, strict=True) if keep[p.index]]
    if kept:
        align[:3, :3] = rotation
        align[:3, 3] = np.mean(kept, axis=0)
    return keep, reasons, align


def _graph(
    anchor_start: FloatArray,
    anchor_stamps: FloatArray,
    survey: Survey,
    results: list[QueryResult],
    landmarks: list[Landmark],
    kept: list[int],
    cfg: Config,
) -> FloatArray:
    """The anchors (A, 4, 4) in the survey frame: odometry factors from ``anchor_start``
    (the run's own corrected anchors, aligned), 5-DoF factors to fixed survey anchors."""
    n = anchor_start.shape[0]
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(n):
        values.insert(k, gtsam.Pose3(anchor_start[k]))
    graph.add(
        gtsam.PriorFactorPose3(
            0, gtsam.Pose3(anchor_start[0]), gtsam.noiseModel.Diagonal.Sigmas(GAUGE_PRIOR_SIGMAS)
        )
    )
    sig = odometry_sigmas(anchor_start, cfg.graph)
    for k in range(n - 1):
        rel = np.linalg.inv(anchor_start[k]) @ anchor_start[k + 1]
        graph.add(
            gtsam.BetweenFactorPose3(
                k, k + 1, gtsam.Pose3(rel), gtsam.noiseModel.Diagonal.Sigmas(sig[k])
            )
        )
    survey_key: dict[int, int] = {}
    sigmas = loop_noise_sigmas(cfg.graph)
    terms = []
    pin = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    for k in kept:
        r = results[k]
        a = int(np.argmin(np.abs(survey.anchor_stamps - r.candidate_stamp)))
        if a not in survey_key:
            survey_key[a] = n + len(survey_key)
            pose = gtsam.Pose3(survey.anchor_poses[a])
            values.insert(survey_key[a], pose)
            graph.add(gtsam.PriorFactorPose3(survey_key[a], pose, pin))
        lm = landmarks[k]
        terms.append(
            LandmarkTerm(
                int(np.argmin(np.abs(anchor_stamps - lm.submap_stamp))),
                survey_key[a],
                np.asarray(lm.origin, dtype=np.float64),
                np.asarray(lm.axis, dtype=np.float64),
                effective_db_origin(r),
                np.asarray(r.candidate_axis, dtype=np.float64),
                np.eye(3),
                sigmas,
            )
        )
    add_landmark_factors(graph, terms, float(cfg.graph.huber_k))
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(cfg.graph.max_iterations))
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    return np.stack([result.atPose3(k).matrix() for k in range(n)])


def survey_placement(survey: Survey) -> tuple[FloatArray, FloatArray]:
    """(L, 3) each the survey's boundary origins and axes (oriented with their sensor's
    forward) in its corrected frame, from one lookup of their anchors' poses."""
    poses = [survey.anchor_pose(lm.submap_stamp) for lm in survey.landmarks]
    pose = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    origins = np.array([lm.origin for lm in survey.landmarks], dtype=np.float64).reshape(-1, 3)
    axes = np.array([lm.axis for lm in survey.landmarks], dtype=np.float64).reshape(-1, 3)
    rotation = pose[:, :3, :3]
    return (
        np.einsum("nij,nj->ni", rotation, origins) + pose[:, :3, 3],
        np.einsum("nij,nj->ni", rotation, axes),
    )


def survey_origins(survey: Survey) -> FloatArray:
    """(L, 3) the survey's boundary origins in its corrected frame."""
    return survey_placement(survey)[0]


def survey_axes(survey: Survey) -> FloatArray:
    """(L, 3) the survey's boundary axes (oriented with their sensor's forward) in its
    corrected frame."""
    return survey_placement(survey)[1]


def survey_database(survey: Survey, cfg: Config) -> LandmarkDatabase:
    """The survey's views as a database: one candidate per survey joint, placed and oriented
    in the survey's corrected frame. The orientation serves the matcher's same-place rule
    (``matching.runner_up_same_place_rows``: views compared with each other, in the
    survey's frame); the queries bring no axes, so the heading prior, which would compare a
    query's odometry frame with the survey's, stays off. Measured on two re-inspections
    (a second run of the same simulated world, against the first's survey): the 9 m shield
    with the forward sensor and a turn kept 8 -> 24 cross-session pairs, the horseshoe with
    64 beams and a turn 635 -> 640, every one within 0.15 m of the truth."""
    db = LandmarkDatabase(cfg)
    origins, axes = survey_placement(survey)
    ids = [int(j) for j in survey.joint_ids]
    try:
        stored = db.extend(survey.landmarks, ids, origins, spill=survey.spill)
    except OSError as exc:  # a full disk: the database's patches stay in memory
        if survey.spill is None:
            raise
        print(f"warning: {exc}; the survey database stays in memory", file=sys.stderr)
        db = LandmarkDatabase(cfg)
        stored = db.extend(survey.landmarks, ids, origins)
    if stored:
        db.set_directions(stored, axes)
    return db


def cross_session(
    survey: Survey,
    landmarks: list[Landmark],
    anchors: dict[float, FloatArray],
    along: Any,
    cfg: Config,
    views: NDArray[np.int64] | None = None,
) -> CrossSession:
    """Steps 1-2 (module docs): every landmark against the survey, then the consistent set.
    ``anchors``: the run's anchor stamp -> odometry pose (the frame pairs are judged in);
    ``along``: path length along the run's odometry at a stamp; ``views``: the views of each
    landmark's track (a pair between boundaries each detected once does not stand alone:
    :func:`decod_rs.selection.drop_if_untracked`; None: not applied)."""
    db = survey_database(survey, cfg)
    results = db.query_batch(landmarks, cross_session=True) if landmarks else []
    pairs = _pairs(survey, landmarks, results, anchors)
    tracked = None
    if views is not None:
        survey_views = views_per_landmark(np.asarray(survey.joint_ids, dtype=np.int64))
        tracked = tracked_loops(results, landmarks, views, survey_views)
    keep, reasons, align = _select(survey, results, pairs, along, cfg.matching, tracked)
    return CrossSession(survey, results, keep, reasons, align)


def place_in_survey(
    cross: CrossSession,
    landmarks: list[Landmark],
    scans: tuple[FloatArray, FloatArray],
    anchor_stamps: FloatArray,
    cfg: Config,
) -> FloatArray | None:
    """Step 3: the run's scan poses (M, 4, 4) in the survey frame, starting from ``scans``
    (stamps, the run's own corrected poses); None when no pair stayed."""
    if not cross.kept:
        return None
    anchor_own = interpolate_poses(*scans, anchor_stamps)
    start = cross.survey_from_odometry @ anchor_own
    optimised = _graph(
        start, anchor_stamps, cross.survey, cross.results, landmarks, cross.kept, cfg
    )
    return propagate_to_scans(scans[0], scans[1], anchor_stamps, anchor_own, optimised)


def survey_joint_ids(
    cross: CrossSession, joint_of: NDArray[np.int64], radius_m: float
) -> dict[int, int]:
    """New joint id -> the survey joint id most of its kept views matched; a view whose
    verified axial offset ties it beside its survey candidate (``radius_m``, the
    same-boundary radius: :func:`decod_rs.joints.ties_one_boundary`) does not vote."""
    votes: dict[int, Counter[int]] = {}
    for k in cross.kept:
        sj = cross.survey_joint(k)
        if sj is not None and ties_one_boundary(cross.results[k].dz_m, radius_m):
            votes.setdefault(int(joint_of[k]), Counter())[sj] += 1
    return {j: c.most_common(1)[0][0] for j, c in votes.items()}


def _merged(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merged(out[key], value)
        else:
            out[key] = value
    return out


def check_compatible(survey: Survey, cfg: Config) -> None:
    """``ValueError`` when ``cfg``'s descriptor grid is not the survey's: descriptors on
    other grids (or cell sizes) cannot be compared (say so before the run, not after)."""
    theirs = survey.config.get("descriptor", {})
    ours = cfg.descriptor.to_dict()
    for key in ("rows", "cols", "half_length_m"):
        if key in theirs and float(theirs[key]) != float(ours[key]):
            raise ValueError(
                f"--survey {survey.source}: descriptor.{key} is {theirs[key]} in the survey and "
                f"{ours[key]} here; run without --preset/--config to use the survey's config"
            )


def survey_config(survey: Survey) -> Config:
    """The survey run's config, over the defaults of its preset (a survey written by an
    older decod may lack newer parameters): a later run compares like with like (same grid,
    cells and matcher)."""
    preset = str(survey.config.get("preset", "tunnel")).lower()
    base = json.loads(
        _core.resolve_config_json(preset if preset in ("tunnel", "pipe") else "tunnel", "")
    )
    cfg = Config(_merged(base, survey.config))
    LandmarkDatabase(cfg)  # the matching section must validate
    return cfg
