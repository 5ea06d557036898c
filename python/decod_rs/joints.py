"""The joint registry (``joints.csv``): one row per physical boundary, what an inspection
report cites.

A physical boundary is a set of tracks (:mod:`decod_rs.tracks`: the views of one boundary
within one pass) joined by the accepted loops between them (the outbound and the return
track of one joint; not a loop whose verified axial offset ties its query beside the
candidate's boundary, :data:`LOOP_SHIFT_RADII`), and then by place: groups whose
chainages lie within the config's same-boundary radius (``matching.duplicate_radius_m``,
0.1-0.4 m by corridor size, the radius within which the tracks call views one boundary)
are one row. The track links need
the descriptor to confirm a pair, which sparse views often cannot, so without the merge a
joint was listed once per unlinked track: over the 100 runs of the generalisation matrix
(m76) 13,452 rows for about 2,100 joints, 7,448 of them within 0.1 m of another (14 rows
per arch in the horseshoe with 16 beams); with it 5,625 rows, 43 such pairs, and about one
row at each joint (the rest are wall features that are not joints, most of them seen once
and not confirmed: ``views`` and ``loop_confirmed`` say so). Groups are taken strongest
first (loop-confirmed, then most views) and each absorbs the groups within the radius of
it, so rows never chain along a run of nearby features into one. Per boundary: its
chainage (median over its views of the distance from the start along the corrected
trajectory, the views of a robot standing still weighted so that its pose counts once:
:func:`standing_poses`; views that saw a sliver of the wall around the boundary on one
side of the section left out where others saw more: :data:`MIN_WALL_COVERAGE`), the
number of views, tracks and passes that saw it, and whether a loop confirmed it. A run with
``--survey`` measures the chainage along the survey's path (in its frame) and adds the
survey's joint id (``survey_joint_id``).
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, QueryResult
from decod_rs.chainage import outbound_course
from decod_rs.path_curve import path_length

FloatArray = NDArray[np.float64]

JOINTS_COLUMNS = (
    "joint_id",
    "chainage_m",
    "views",
    "tracks",
    "passes",
    "loop_confirmed",
    "first_stamp",
    "last_stamp",
)

__all__ = [
    "JOINTS_COLUMNS",
    "LOOP_SHIFT_RADII",
    "STANDING_STEP_M",
    "Joint",
    "joint_registry",
    "landmark_chainage",
    "standing_poses",
    "ties_one_boundary",
    "wall_coverage",
    "weighted_median",
    "write_joints_csv",
]

#: Path length (m) either side of a landmark's nearest path point over which the direction
#: of travel is read, only to orient the landmark's axis: the path between consecutive scans
#: is 0-15 cm long (none while the robot stands or turns) and its direction is then the
#: odometry's noise, while over 2 x 0.5 m the lateral wobble of the simulated and real
#: paths (1-2 cm) tilts it by about 1 deg.
DIRECTION_SPAN_M = 0.5

#: Consecutive anchors less than this far apart (m, corrected positions) are one pose: the
#: robot standing (or turning on the spot), whose submaps see the wall from one place with
#: one detection error (:func:`standing_poses`). Anchors of a moving robot are 0.1-3 m apart
#: (0.2-2 m/s, an anchor every 0.5-1.5 s); a standing one moves by the odometry's noise.
STANDING_STEP_M = 0.01


#: A loop joins its query's track to its candidate's when the verifier's axial offset
#: between them (``dz_m``) is at most this many same-boundary radii: each view lies within
#: the radius of its boundary, so two views of one boundary lie within twice it (the loops
#: of the matrix that tie one boundary, m11: offsets up to 0.12 m in the pipes, 0.39 m in the
#: horseshoes, 0.56 m in the shields, radii 0.1, 0.22-0.4 and 0.27-0.4 m). A loop with a
#: larger offset ties the query's boundary to one beside the candidate's: in the matrix
#: (m11), 27 loops with offsets of 0.84-1.64 m, each joining views 0.71-1.60 m apart (placed
#: with the ground truth: the next arch or ring, 1.2-1.5 m on, or a wall feature between);
#: joined, one shield's rings at 9.5 and 11.0 m became one registry row at 10.85 m.
LOOP_SHIFT_RADII = 2.0


def ties_one_boundary(dz_m: float, radius_m: float) -> bool:
    """Whether a verified pair whose axial offset is ``dz_m`` ties two views of one
    boundary (within :data:`LOOP_SHIFT_RADII` same-boundary radii ``radius_m``), rather
    than a boundary to the place beside another one."""
    return abs(float(dz_m)) <= LOOP_SHIFT_RADII * radius_m


@dataclass(frozen=True)
class Joint:
    """One physical boundary of the registry (module docs)."""

    joint_id: int
    chainage_m: float
    views: int
    tracks: int
    passes: int
    loop_confirmed: bool
    first_stamp: float
    last_stamp: float


def landmark_chainage(
    stamps: FloatArray,
    origins: FloatArray,
    axes: FloatArray,
    scan_stamps: FloatArray,
    corrected: FloatArray,
) -> FloatArray:
    """Distance (m) from the start along the corrected outbound path (its forward course,
    :mod:`decod_rs.chainage`: a back-up does not count) to each landmark
    (``stamps`` (N,), ``origins`` and ``axes`` (N, 3) in their anchor frames; ``corrected``
    (M, 4, 4) the poses at ``scan_stamps``): the path length to the path point nearest the
    landmark's world position, plus the landmark's offset from that point along its own
    corridor axis, oriented with the direction of travel there (``DIRECTION_SPAN_M``). Not
    snapped to a scan (scans are 4-15 cm apart at 0.4-1.5 m/s, 1-4 % of a joint's chainage
    in the first metres). Beyond the far end or behind the start the offset runs on along
    the axis, so a joint seen past the turnaround gets a chainage past the path's length.
    The direction of the path's last step stood in for the axis before: where the robot
    slows to a stop that step is millimetres of odometry noise, and joints 0.5-2.5 m past
    the turnaround of the simulated tunnels came out 0.7-1.7 m short."""
    path = outbound_course(corrected[:, :3, 3])
    far = path.shape[0] - 1
    arclength = path_length(path)
    out = np.empty(len(stamps))
    for k, stamp in enumerate(stamps):
        pose = corrected[int(np.argmin(np.abs(scan_stamps - stamp)))]
        world = pose[:3, :3] @ origins[k] + pose[:3, 3]
        axis = pose[:3, :3] @ axes[k]
        i = int(np.argmin(np.linalg.norm(path - world, axis=1)))
        lo, hi = np.searchsorted(
            arclength, [arclength[i] - DIRECTION_SPAN_M, arclength[i] + DIRECTION_SPAN_M]
        )
        travel = path[min(int(hi), far)] - path[max(int(lo) - 1, 0)]
        norm = float(np.linalg.norm(axis))
        along = 0.0
        if norm > 1e-9 and float(np.linalg.norm(travel)) > 1e-9:
            axis = axis / norm if float(axis @ travel) >= 0.0 else -axis / norm
            along = float((world - path[i]) @ axis)
        out[k] = arclength[i] + along
    return out


#: A view counts in its boundary's chainage unless it saw a sliver of the wall around the
#: boundary, all of it on one side of the section: less than this fraction of the
#: circumference (:func:`wall_coverage`; the bottom sector the descriptor masks counts as
#: unseen, so whole views read 0.85-0.9) with the seen part's mean direction at least
#: :data:`ONE_SIDED_RESULTANT` from the centre (one arc of under half the circle). Where no
#: view of a boundary saw more, all count. A forward sensor closer to a ring than the
#: corridor's radius sees only the floor's side of it (the avia's 35 deg half-angle takes in
#: the whole section from 1.4 radii on), and there the detection finds a bolt pocket or the
#: slab's edge rather than the seam: over the forward sensor's 6-7 m shield rows of four
#: tiers (m22, f22, r22 and seed 277, 19 runs, 2,905 views) the 395 views that saw under
#: 30 %, 394 of them on one side (resultant 0.6-1), lay 34.5 cm from their ring (median;
#: 84 % beyond 10 cm), the views that saw more than half 5.9 cm. A spinning sensor's view of
#: a ring beside it is a sliver too (its +-22.5 deg band), but on both walls (resultant
#: under 0.4), and those are its best views (8 shield and horseshoe rows with 64 beams,
#: 4,958 views: 2.4 cm for those under 30 %, 4.9 cm for whole views, which land on pocket
#: bands from afar); coverage alone (any view under 30 % left out) cost the 64-beam shields
#: up to 0.4 % of registry error (f22, r22), and half of each joint's best view's coverage
#: took the full tier's registry from 81 to 75 of 98 runs within 1 %.
MIN_WALL_COVERAGE = 0.3
#: The length of the mean unit vector of a view's seen columns (angles around the section)
#: from which its sliver is one-sided: 0 for a whole ring or two opposite arcs, ``sin(pi f)
#: / (pi f)`` for one arc of a fraction ``f`` of the circle (0.64 for a half, 0.86 for 30 %).
ONE_SIDED_RESULTANT = 0.6


def wall_coverage(landmarks: Sequence[Landmark]) -> tuple[FloatArray, FloatArray]:
    """Per landmark, the fraction of the circumference its descriptor observed at the
    boundary (columns of the mask observed in either of the two central rows, the rows either
    side of the boundary's axial position) and the length of the mean unit vector of those
    columns' angles around the section (0: seen all round or on opposite sides; near 1: one
    short arc). Columns are equal arclengths of the contour, taken as equal angles."""
    fraction = np.zeros(len(landmarks))
    resultant = np.ones(len(landmarks))
    for k, lm in enumerate(landmarks):
        mask = np.asarray(lm.mask, dtype=bool)
        if mask.ndim != 2 or mask.shape[0] < 2 or mask.shape[1] == 0:
            continue
        mid = mask.shape[0] // 2
        seen = mask[mid - 1 : mid + 1].any(axis=0)
        if not seen.any():
            continue
        angle = 2.0 * np.pi * (np.flatnonzero(seen) + 0.5) / seen.size
        fraction[k] = float(seen.mean())
        resultant[k] = float(np.hypot(np.cos(angle).mean(), np.sin(angle).mean()))
    return fraction, resultant


def _well_seen(fraction: FloatArray, resultant: FloatArray) -> NDArray[np.bool_]:
    """The views of one boundary that did not see a one-sided sliver of the wall around it
    (:data:`MIN_WALL_COVERAGE`); all of them when none did."""
    sliver = (fraction < MIN_WALL_COVERAGE) & (resultant >= ONE_SIDED_RESULTANT)
    return ~sliver if not sliver.all() else np.ones(fraction.size, dtype=bool)


def standing_poses(
    stamps: FloatArray, scan_stamps: FloatArray, corrected: FloatArray
) -> NDArray[np.int64]:
    """Per landmark (submap ``stamps`` (N,)), the id of the pose its submap saw it from:
    consecutive anchors (in time) less than :data:`STANDING_STEP_M` apart on the corrected
    trajectory (``corrected`` (M, 4, 4) at ``scan_stamps``) share one. A robot standing a
    minute at the start of a log (its operator getting ready) makes 60 submaps of one pose,
    and their views, which share one detection error, outvoted the views from everywhere
    else in a joint's median: the 6 m shield with 64 beams (held out, seed 241, 60 s at
    rest) put its joint 3.5 m in 15 cm short, where its rest views landed on a band of bolt
    pockets (4 % of its chainage)."""
    stamps = np.asarray(stamps, dtype=np.float64)
    if stamps.size == 0:
        return np.zeros(0, dtype=np.int64)
    anchors = np.unique(stamps)
    at = np.clip(np.searchsorted(scan_stamps, anchors), 0, scan_stamps.size - 1)
    positions = corrected[at, :3, 3]
    moved = np.linalg.norm(np.diff(positions, axis=0), axis=1) >= STANDING_STEP_M
    pose_of_anchor = np.concatenate([[0], np.cumsum(moved)]).astype(np.int64)
    return np.asarray(pose_of_anchor[np.searchsorted(anchors, stamps)], dtype=np.int64)


def _pose_median(chainage_m: FloatArray, poses: NDArray[np.int64] | None) -> float:
    """The median of the views' chainage, each view weighted by one over the number of
    anchors of its pose (:func:`standing_poses`): a pose counts once however long the robot
    stood there, and a moving robot's views count one each, as in the plain median (which
    this is where no anchor shares a pose). A view's own weight, not its pose's median: a
    registry row may hold the views of two nearby features from the same submaps, and a
    median per pose would put the row between them."""
    if poses is None:
        return float(np.median(chainage_m))
    _, inverse, counts = np.unique(poses, return_inverse=True, return_counts=True)
    if np.all(counts == 1):
        return float(np.median(chainage_m))
    return weighted_median(chainage_m, 1.0 / counts[inverse])


def weighted_median(values: FloatArray, weights: FloatArray) -> float:
    """The weighted median of ``values`` (the mean of the two middle values where the
    cumulative weight reaches exactly half, as ``np.median`` with equal weights)."""
    order = np.argsort(values, kind="stable")
    v, c = np.asarray(values)[order], np.cumsum(np.asarray(weights)[order])
    half = 0.5 * c[-1]
    i = int(np.searchsorted(c, half - 1e-12 * c[-1]))
    if i + 1 < v.size and abs(c[i] - half) <= 1e-12 * c[-1]:
        return float(0.5 * (v[i] + v[i + 1]))
    return float(v[i])


def _key(stamp: float, origin: FloatArray) -> tuple[float, tuple[float, ...]]:
    return stamp, tuple(np.round(np.asarray(origin, dtype=np.float64), 6))


def _root(parent: dict[int, int], t: int) -> int:
    while parent.setdefault(t, t) != t:
        parent[t] = parent[parent[t]]
        t = parent[t]
    return t


def _loop_groups(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    loops: Sequence[QueryResult],
    radius_m: float,
) -> tuple[NDArray[np.int64], set[int]]:
    """Per landmark, the root track of its group (tracks joined by ``loops``), and the
    tracks a loop touched. A loop whose verified axial offset (``dz_m``) is beyond
    :data:`LOOP_SHIFT_RADII` times ``radius_m`` joins nothing: it ties the query's boundary
    to a place that far from its candidate's, a neighbouring boundary (module docs)."""
    index = {_key(lm.submap_stamp, lm.origin): k for k, lm in enumerate(landmarks)}
    parent: dict[int, int] = {}
    confirmed: set[int] = set()
    for r in loops:
        if not ties_one_boundary(r.dz_m, radius_m):
            continue
        q = index.get(_key(r.query_stamp, r.query_origin))
        d = index.get(_key(r.candidate_stamp, r.candidate_origin))
        if q is None or d is None:
            continue
        a, b = _root(parent, int(tracks[q])), _root(parent, int(tracks[d]))
        parent[max(a, b)] = min(a, b)
        confirmed.update((int(tracks[q]), int(tracks[d])))
    return np.array([_root(parent, int(t)) for t in tracks], dtype=np.int64), confirmed


def _merge_by_place(
    groups: list[NDArray[np.int64]],
    chainage_m: FloatArray,
    strong: list[tuple[bool, int]],
    radius_m: float,
) -> list[NDArray[np.int64]]:
    """The landmark indices of each physical boundary: strongest group first (``strong``:
    loop-confirmed, views), each absorbing the groups not yet taken whose median chainage is
    within ``radius_m`` of its own (module docs)."""
    centre = np.array([float(np.median(chainage_m[g])) for g in groups])
    order = sorted(range(len(groups)), key=lambda g: (not strong[g][0], -strong[g][1], centre[g]))
    taken = np.zeros(len(groups), dtype=bool)
    merged = []
    for g in order:
        if taken[g]:
            continue
        near = np.flatnonzero(~taken & (np.abs(centre - centre[g]) <= radius_m))
        taken[near] = True
        merged.append(np.sort(np.concatenate([groups[h] for h in near])))
    return merged


def joint_registry(
    landmarks: Sequence[Landmark],
    tracks: NDArray[np.int64],
    loops: Sequence[QueryResult],
    chainage_m: FloatArray,
    split_stamp: float | None,
    radius_m: float,
    poses: NDArray[np.int64] | None = None,
) -> tuple[list[Joint], NDArray[np.int64]]:
    """The registry and each landmark's joint id; ``loops``: the accepted loops only;
    ``radius_m``: the same-boundary radius (module docs; 0 merges nothing by place);
    ``poses``: per landmark, the pose it was seen from (:func:`standing_poses`; None: each
    view its own), each counted once in a joint's chainage; views that saw a one-sided
    sliver of the wall do not count in it where others saw more (:data:`MIN_WALL_COVERAGE`)."""
    roots, confirmed = _loop_groups(landmarks, tracks, loops, radius_m)
    groups = [np.flatnonzero(roots == r) for r in np.unique(roots)]
    strong = [(bool(set(tracks[g].tolist()) & confirmed), int(g.size)) for g in groups]
    boundaries = _merge_by_place(groups, chainage_m, strong, radius_m) if groups else []
    stamps = np.array([lm.submap_stamp for lm in landmarks])
    fraction, resultant = wall_coverage(landmarks)
    placed = []
    for idx in boundaries:
        kept = idx[_well_seen(fraction[idx], resultant[idx])]
        placed.append((_pose_median(chainage_m[kept], None if poses is None else poses[kept]), idx))
    placed.sort(key=lambda row: (row[0], int(row[1][0])))
    joint_of = np.empty(len(landmarks), dtype=np.int64)
    joints = []
    for jid, (chain, idx) in enumerate(placed):
        joint_of[idx] = jid
        members = set(tracks[idx].tolist())
        seen = {0 if split_stamp is None or s <= split_stamp else 1 for s in stamps[idx]}
        joints.append(
            Joint(
                joint_id=jid,
                chainage_m=chain,
                views=int(idx.size),
                tracks=len(members),
                passes=len(seen),
                loop_confirmed=bool(members & confirmed),
                first_stamp=float(stamps[idx].min()),
                last_stamp=float(stamps[idx].max()),
            )
        )
    return joints, joint_of


def write_joints_csv(
    path: str | Path, joints: Sequence[Joint], survey_ids: dict[int, int] | None = None
) -> None:
    """``joints.csv`` with ``JOINTS_COLUMNS``; with ``survey_ids`` (a run with ``--survey``:
    joint id -> the survey's joint id where one of its views matched) one more column,
    ``survey_joint_id`` (empty where the joint did not match)."""
    with Path(path).open("w", encoding="utf-8", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(JOINTS_COLUMNS if survey_ids is None else (*JOINTS_COLUMNS, "survey_joint_id"))
        for j in joints:
            tail = [] if survey_ids is None else [str(survey_ids.get(j.joint_id, ""))]
            w.writerow(
                [
                    j.joint_id,
                    f"{j.chainage_m:.4f}",
                    j.views,
                    j.tracks,
                    j.passes,
                    int(j.loop_confirmed),
                    f"{j.first_stamp:.9f}",
                    f"{j.last_stamp:.9f}",
                    *tail,
                ]
            )
