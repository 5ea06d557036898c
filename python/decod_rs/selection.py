"""A jointly consistent loop set (beyond the paper, which adds every accepted pair).

Every accepted loop says how far the odometry is off where it was observed: the *implied
correction* ``c = T_db o_db - T_q o_q`` (the database boundary's world position minus the
query boundary's, both placed with the odometry). Odometry drift varies smoothly along the
path, so two true loops imply corrections that differ by at most the drift accumulated
between them; a loop to the wrong one of several similar boundaries implies a correction off
by a boundary spacing, a jump its neighbours do not share.

Pairwise consistency (after PCM, Mangelson et al. 2018): loops ``i`` and ``j`` (other query
submaps, anchors within ``consistency_window_m`` of path of each other, query and database
sides together: ``sep``) conflict when ``|c_i - c_j| > consistency_tolerance_m +
consistency_drift_fraction * sep``. The largest mutually consistent subset is approximated by
removing, while any conflict remains, the loop with the least evidence (``-log10`` of its
chance) per conflict it resolves — a greedy minimum-weight vertex cover of the sparse, local
conflict graph; exact maximum cliques are exponential and the conflict graph here has
only near-neighbour edges. Removed loops get the reason ``inconsistent``. A loop that then
has fewer than ``min_corroborating_loops`` consistent neighbours is ``uncorroborated``
(an isolated loop that nothing confirms: on the simulated aliased hume pipe one wrong loop
with K = 15 passed every per-query test and only its isolation gave it away).

Consistency with the odometry: a loop's implied correction cannot exceed the drift the
odometry can accumulate over the path between its two views, ``consistency_tolerance_m +
consistency_drift_fraction * |path_q - path_db|``; beyond it the loop is ``inconsistent``.
On the simulated aliased hume pipe (identical joints) two wrong loops that agreed with each
other (both 12 m off, 40 m of path apart) passed every per-query test; this gate rejects
them. The tolerance term is the boundary-origin noise (detections move by ~10 cm between
views, DESIGN.md), the drift term the odometry's relative error per metre: set it above
what the odometry can do (a frontend that stalls along the axis needs up to 1).

Sporadic detections only (:func:`drop_if_untracked`): a boundary seen from one submap of its
pass, not from the several that pass by a real joint, is weak evidence of a distinct place;
in a corridor of repeated structure its repeats may simply not have been detected, and then
nothing competes with a wrong match. When no kept loop joins a boundary seen from two or
more submaps (a track, :mod:`decod_rs.tracks`) on either side, the loop set rests on single
detections alone and is dropped (``untracked``). In the simulated pipe with identical joints,
2 m of drift over 30 m and the pipe preset, three wall features 0.7-0.9 m from a joint, each
detected once per pass, matched their copies one joint spacing (2.4 m) away with K = 10-15
against runner-ups of K = 2-4; the three agreed with each other and with the odometry, and
the position prior then placed three more queries the same 2.4 m off: six wrong loops. In the
generalisation matrix, 16 % of the right loops join two single detections, but only two runs
have nothing else (pe, 16 beams, uneven drift: three loops each, and both corrected RMSEs
were above the odometry's).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import QueryResult
from decod_rs.aliasing import aliasing
from decod_rs.stall import path_length

FloatArray = NDArray[np.float64]

__all__ = [
    "WANDER_RATIO",
    "LoopEvidence",
    "Selection",
    "drop_if_aliased",
    "drop_if_untracked",
    "drop_unsafe_sets",
    "effective_db_origin",
    "path_along",
    "select_by_config",
    "select_consistent",
    "select_loops",
    "why_no_loop",
]


@dataclass(frozen=True)
class LoopEvidence:
    """One accepted loop as the selection sees it: the implied correction (metres, odometry
    world frame), the path position (metres along the odometry) of its query and database
    anchors, the query submap stamp (views of one query submap are not independent), and its
    strength (inliers, family-wise chance)."""

    correction: FloatArray
    query_path_m: float
    db_path_m: float
    query_stamp: float
    inliers: int
    chance: float


@dataclass(frozen=True)
class Selection:
    """``kept[k]``: loop ``k`` stays; ``reasons[k]``: ``""``, ``"inconsistent"`` or
    ``"uncorroborated"``; ``conflicts``: the conflicting pairs found (indices)."""

    kept: list[bool]
    reasons: list[str]
    conflicts: list[tuple[int, int]]


#: Loop pairs compared per block in :func:`_relations` (bounds its memory: a block's arrays
#: hold about this many pairs, 2 MB each, the correction differences three times that while
#: their norms are taken). Rows per block were fixed at 512: 512 x 3,184 pairs, 39 MB for
#: the differences alone, in a 400 m pipe's re-inspection against its survey.
RELATION_PAIRS = 1 << 18


def _relations(
    loops: list[LoopEvidence], tolerance_m: float, drift_fraction: float, window_m: float
) -> tuple[list[set[int]], list[NDArray[np.int32]]]:
    """Per loop: the loops it conflicts with, and those that corroborate it. Two loops are
    related when their anchors lie within ``window_m`` of each other (query and database
    path positions summed); related, they conflict when their corrections differ by more
    than ``tolerance_m + drift_fraction * separation``, and otherwise corroborate each other
    unless they share a query submap (which may contradict itself, not corroborate itself:
    its views share the query's pose). The corroborating loops are index arrays: where loops
    are many and dense (a re-inspection's thousands of pairs, each corroborated by hundreds)
    Python sets of them took about 40 bytes an entry."""
    n = len(loops)
    conflicts: list[set[int]] = [set() for _ in range(n)]
    support: list[NDArray[np.int32]] = [np.zeros(0, dtype=np.int32) for _ in range(n)]
    if n < 2:  # (also: an empty correction array cannot be reshaped to (0, 3))
        return conflicts, support
    q = np.array([lp.query_path_m for lp in loops], dtype=np.float64)
    d = np.array([lp.db_path_m for lp in loops], dtype=np.float64)
    c = np.array([lp.correction for lp in loops], dtype=np.float64).reshape(n, -1)
    stamp = np.array([lp.query_stamp for lp in loops], dtype=np.float64)
    block = max(1, RELATION_PAIRS // n)
    for lo in range(0, n, block):
        rows = np.arange(lo, min(lo + block, n))
        sep = np.abs(q[rows, None] - q[None, :]) + np.abs(d[rows, None] - d[None, :])
        gap = np.linalg.norm(c[rows, None, :] - c[None, :, :], axis=2)
        near = (sep <= window_m) & (rows[:, None] != np.arange(n)[None, :])
        clash = near & (gap > tolerance_m + drift_fraction * sep)
        agree = near & ~clash & (stamp[rows, None] != stamp[None, :])
        for r, i in enumerate(rows.tolist()):
            conflicts[i] = set(np.flatnonzero(clash[r]).tolist())
            support[i] = np.flatnonzero(agree[r]).astype(np.int32)
    return conflicts, support


def _weight(loop: LoopEvidence) -> float:
    """Evidence of one loop: -log10 of its chance (inliers when that underflows)."""
    if loop.chance > 0.0:
        return max(-float(np.log10(loop.chance)), 1e-3)
    return 300.0 + loop.inliers


def select_consistent(
    loops: list[LoopEvidence],
    *,
    tolerance_m: float,
    drift_fraction: float,
    window_m: float,
    min_corroborating: int,
) -> Selection:
    """The consistent subset of ``loops`` (module docs)."""
    n = len(loops)
    conflicts, support = _relations(loops, tolerance_m, drift_fraction, window_m)
    pairs = [(i, j) for i in range(n) for j in conflicts[i] if i < j]
    reasons = [""] * n
    for k, loop in enumerate(loops):
        path = abs(loop.query_path_m - loop.db_path_m)
        if float(np.linalg.norm(loop.correction)) > tolerance_m + drift_fraction * path:
            reasons[k] = "inconsistent"  # more drift than the odometry can have travelled
    alive = {k for k in range(n) if not reasons[k]}
    while True:
        # Greedy minimum-weight vertex cover: drop the loop whose evidence is smallest for
        # the conflicts it resolves (weight -log10 chance, K when the chance underflows).
        conflicted = [k for k in alive if conflicts[k] & alive]
        if not conflicted:
            break
        worst = min(
            conflicted,
            key=lambda k: (_weight(loops[k]) / len(conflicts[k] & alive), loops[k].query_stamp),
        )
        alive.discard(worst)
        reasons[worst] = "inconsistent"
    standing = np.zeros(n, dtype=bool)
    standing[sorted(alive)] = True
    for k in sorted(alive):
        if np.count_nonzero(standing[support[k]]) < min_corroborating:
            reasons[k] = "uncorroborated"
    kept = [not r for r in reasons]
    return Selection(kept=kept, reasons=reasons, conflicts=pairs)


def effective_db_origin(result: QueryResult, dz_m: float | None = None) -> FloatArray:
    """The candidate's origin moved by the verified axial offset (``dz_m`` in its place when
    given), so both origins name the same physical plane (``PairResult.dz_m`` is along the
    axis in the query's heading)."""
    sign = 1.0 if abs(result.heading_deg) < 90.0 else -1.0
    dz = result.dz_m if dz_m is None else dz_m
    return np.asarray(result.candidate_origin, dtype=np.float64) + (
        dz * sign * np.asarray(result.candidate_axis, dtype=np.float64)
    )


def path_along(scan_stamps: FloatArray, scan_odom: FloatArray) -> Callable[[float], float]:
    """Path length along the odometry (metres) at a stamp, interpolated between scans."""
    steps = np.linalg.norm(np.diff(scan_odom[:, :3, 3], axis=0), axis=1)
    path = np.concatenate([[0.0], np.cumsum(steps)])
    return lambda stamp: float(np.interp(stamp, scan_stamps, path))


def select_by_config(loops: list[LoopEvidence], matching: Any) -> Selection:
    """:func:`select_consistent` with the tolerances of the ``matching`` config section."""
    return select_consistent(
        loops,
        tolerance_m=float(matching.consistency_tolerance_m),
        drift_fraction=float(matching.consistency_drift_fraction),
        window_m=float(matching.consistency_window_m),
        min_corroborating=int(matching.min_corroborating_loops),
    )


def _drop_all(keep: list[bool], reasons: list[str], why: str) -> tuple[list[bool], list[str]]:
    """No loop stays; those that would have get ``why``."""
    return [False] * len(keep), [why if ok else was for ok, was in zip(keep, reasons, strict=True)]


def drop_if_aliased(
    results: Sequence[QueryResult], keep: list[bool], reasons: list[str]
) -> tuple[list[bool], list[str]]:
    """No loop stays in an aliased corridor (:mod:`decod_rs.aliasing`); the loops that would
    have get ``aliased``."""
    return _drop_all(keep, reasons, "aliased") if aliasing(results).aliased else (keep, reasons)


def drop_if_untracked(
    keep: list[bool], reasons: list[str], tracked: Sequence[bool] | None
) -> tuple[list[bool], list[str]]:
    """No loop stays when none of the kept ones joins a tracked boundary (``tracked[k]``:
    loop ``k``'s query or Top-1 was seen from two or more submaps; module docs); they get
    ``untracked``. ``tracked=None``: nothing is dropped."""
    if tracked is None or any(ok and t for ok, t in zip(keep, tracked, strict=True)):
        return keep, reasons
    return _drop_all(keep, reasons, "untracked")


def drop_unsafe_sets(
    results: Sequence[QueryResult],
    keep: list[bool],
    reasons: list[str],
    tracked: Sequence[bool] | None,
    matching: Any,
) -> tuple[list[bool], list[str]]:
    """The guards on a whole loop set, within a run and against a survey: an aliased
    corridor (:func:`drop_if_aliased`), then single detections alone
    (:func:`drop_if_untracked`, unless ``matching.require_tracked_loop`` is off)."""
    keep, reasons = drop_if_aliased(results, keep, reasons)
    return drop_if_untracked(keep, reasons, tracked if matching.require_tracked_loop else None)


def select_loops(
    results: list[QueryResult],
    anchors: dict[float, FloatArray],
    scan_stamps: FloatArray,
    scan_odom: FloatArray,
    matching: Any,
    also: Sequence[int] = (),
    tracked: Sequence[bool] | None = None,
) -> tuple[list[bool], list[str]]:
    """For every query result: whether it stays a loop, and why not (the matcher's own
    rejection, ``inconsistent`` / ``uncorroborated`` from :func:`select_consistent`, or
    ``aliased`` / ``untracked`` from :func:`drop_unsafe_sets` with ``tracked``). ``also``:
    indices of results the matcher rejected that enter the selection as if accepted
    (:mod:`decod_rs.disambiguation`)."""
    along = path_along(scan_stamps, scan_odom)

    def world(stamp: float, point: FloatArray) -> FloatArray:
        pose = anchors[stamp]
        return np.asarray(pose[:3, :3] @ point + pose[:3, 3], dtype=np.float64)

    extra = set(also)
    accepted = [k for k, r in enumerate(results) if r.accepted or k in extra]
    evidence = [
        LoopEvidence(
            correction=world(r.candidate_stamp, effective_db_origin(r))
            - world(r.query_stamp, np.asarray(r.query_origin, dtype=np.float64)),
            query_path_m=along(r.query_stamp),
            db_path_m=along(r.candidate_stamp),
            query_stamp=r.query_stamp,
            inliers=r.inliers,
            chance=r.chance,
        )
        for r in (results[k] for k in accepted)
    ]
    chosen = select_by_config(evidence, matching)
    keep = [False] * len(results)
    reasons = [r.rejection or "" for r in results]
    for k, ok, why in zip(accepted, chosen.kept, chosen.reasons, strict=True):
        keep[k] = ok
        reasons[k] = why
    return drop_unsafe_sets(results, keep, reasons, tracked, matching)


#: A run without a return whose odometry's path is at least this many times as long as the
#: farthest it gets from its start is said to wander (:func:`why_no_loop`): a one-way run's
#: path is about its extent (1.0-1.5 with back-ups), an odometry that stalls along the axis
#: and jitters back and forth runs up path where the robot did not go (KISS-ICP in the
#: simulated 0.3 m hume pipe: 12.9 m of path within 3.2 m of its start, the robot 60 m).
WANDER_RATIO = 2.0


def why_no_loop(
    landmarks_per_pass: tuple[int, int],
    queries: int,
    extraction_rejections: dict[str, int],
    query_rejections: dict[str, int],
    split_stamp: float | None,
    odometry: FloatArray | None = None,
) -> str:
    """A sentence for ``report.json`` when a run closes no loop: the first stage that came up
    empty, with its commonest reasons. ``odometry`` (N, 3): the positions the run was placed
    on; where they wander (:data:`WANDER_RATIO`) and the run does not come back, the sentence
    says so, since an odometry that does not follow the robot finds no return either."""

    def top(counts: dict[str, int]) -> str:
        ranked = sorted(counts.items(), key=lambda kv: -kv[1])[:3]
        return ", ".join(f"{k} {v}" for k, v in ranked)

    outbound, back = landmarks_per_pass
    if outbound + back == 0:
        why = top(extraction_rejections)
        return "no boundary detected in any submap" + (f" (submaps rejected: {why})" if why else "")
    if split_stamp is None:
        why = "no return pass found (the run does not come back): nothing to close a loop with"
        return why + _wander(odometry)
    if outbound == 0:
        return "the sensor never sampled a boundary on the outbound pass"
    if back == 0:
        return "the sensor never sampled a boundary on the return pass"
    why = top(query_rejections)
    if query_rejections.get("aliased"):
        return (
            "the corridor is aliased: its ambiguous queries' runner-ups match as well as their "
            f"best (report.json aliasing), so no loop is kept (rejections: {why})"
        )
    return f"all {queries} queries rejected" + (f": {why}" if why else "")


def _wander(odometry: FloatArray | None) -> str:
    """The clause :func:`why_no_loop` adds where the odometry wanders, else ``""``."""
    if odometry is None or len(odometry) < 2:
        return ""
    p = np.asarray(odometry, dtype=np.float64)
    path = path_length(p)
    extent = float(np.linalg.norm(p - p[0], axis=1).max())
    if path < WANDER_RATIO * max(extent, 1e-9):
        return ""
    return (
        f"; but the odometry's path of {path:.1f} m stays within {extent:.1f} m of its start: "
        "does it follow the robot along the corridor (a frontend that stalls along the axis)?"
    )
