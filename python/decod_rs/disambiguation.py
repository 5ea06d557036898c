"""Ambiguous loops resolved by the corrected trajectory (beyond the paper).

The matcher rejects a query as ``not_unique`` when its Top-1 is beyond chance but so is a
runner-up at another physical boundary (:mod:`decod_rs` Rust ``matching::null_model``):
appearance alone cannot tell the two apart. In segmental-lining and arched tunnels that is
the usual case, not the exception: neighbouring rings share their seams and pockets, so the
runner-up (typically the ring next door, 1-1.5 m away) also beats chance. In the
generalisation matrix this rejected most of the right Top-1s in tunnels (shield tunnel,
64 beams, symmetric drift: 78 right Top-1s rejected ``not_unique`` against 31 accepted).

Where appearance is ambiguous, position is not: after the first optimisation, the loops
that *were* unique and the tracked boundaries (:mod:`decod_rs.sequential`) have corrected
the trajectory, and a second hypothesis one ring away is a metre off. A ``not_unique``
query is kept (``accepted_by = position_prior`` in ``loops.csv``) when, on the corrected
trajectory,

- its Top-1 lies within ``consistency_tolerance_m`` of the query boundary, and
- the runner-up lies more than twice that away from it,

- a loop accepted on its descriptor alone lies within ``consistency_window_m`` of path of
  the query: the corrected trajectory is trusted only where a unique loop anchored it,

so the prior separates the two hypotheses the descriptor could not. A runner-up whose view
lies within the same-boundary radius (``matching.duplicate_radius_m``) of the Top-1's view
on the corrected trajectory is not a second hypothesis but the Top-1's own boundary seen
from another anchor: the matcher keeps a boundary's views from being each other's runner-up
by their track ids, and views the descriptor could not link into one track (pe pipe, 16
beams) are not covered by that. In the matrix's pe-spin16-turn-s1 run under uneven drift
every Top-1 was the right coupler, yet 10 queries stayed ``not_unique`` with the same
coupler 1-2 cm away as runner-up; with the rule 13 loops instead of 6 and 5 of 5 couplers
closed instead of 2. Whole matrix (m94 against m92, same logs): 9,780 -> 11,342 loops, none
wrong, joint coverage below 50 % in 3 rows instead of 5. The Top-1 has already
passed the null model's family-wise chance test; only the choice between beyond-chance
candidates is made by position. ``consistency_tolerance_m`` stays below half the boundary
spacing (its config doc), so a neighbouring boundary never falls within it unless the
corrected trajectory is itself off by more than half a spacing there. The anchoring rule is
what keeps an aliased pipe (identical joints: every query ambiguous, no unique loop) at zero
loops: without it, the odometry rescaled by the boundary tracks placed three of its
ambiguous queries within 0.3 m of a joint in the matrix, one of them the wrong joint. The
resolved loops then go through the same consistency selection as the others
(:func:`decod_rs.selection.select_loops`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import Landmark, QueryResult
from decod_rs.selection import effective_db_origin
from decod_rs.tum import interpolate_poses

FloatArray = NDArray[np.float64]

__all__ = ["AMBIGUOUS", "CorrectedFrame", "near_loops", "resolve_with_prior"]

#: The matcher's rejection this stage may overturn.
AMBIGUOUS = "not_unique"


class CorrectedFrame:
    """World positions of boundary origins (given in their submap anchor's frame) on a
    corrected trajectory: ``scan_stamps`` and ``poses`` (N x 4 x 4)."""

    def __init__(self, scan_stamps: FloatArray, poses: FloatArray) -> None:
        self._stamps = np.asarray(scan_stamps, dtype=np.float64)
        self._poses = np.asarray(poses, dtype=np.float64)
        self._cache: dict[float, FloatArray] = {}

    def world(self, stamp: float, point: FloatArray) -> FloatArray:
        """``point`` (anchor frame at ``stamp``) in the corrected world frame."""
        pose = self._cache.get(stamp)
        if pose is None:
            pose = interpolate_poses(self._stamps, self._poses, np.array([stamp]))[0]
            self._cache[stamp] = pose
        return np.asarray(pose[:3, :3] @ np.asarray(point) + pose[:3, 3], dtype=np.float64)

    def loop_ends(self, r: QueryResult) -> tuple[FloatArray, FloatArray]:
        """The query boundary and its Top-1 (moved by the verified offset) in this frame."""
        query = self.world(r.query_stamp, np.asarray(r.query_origin, dtype=np.float64))
        return query, self.world(r.candidate_stamp, effective_db_origin(r))


def _resolvable(
    r: QueryResult,
    db_landmarks: Sequence[Landmark],
    frame: CorrectedFrame,
    tolerance_m: float,
    same_radius_m: float,
) -> bool:
    query, top = frame.loop_ends(r)
    if float(np.linalg.norm(query - top)) > tolerance_m:
        return False
    if r.runner_up_index is None or not 0 <= r.runner_up_index < len(db_landmarks):
        return True
    runner = db_landmarks[r.runner_up_index]
    other = frame.world(runner.submap_stamp, np.asarray(runner.origin, dtype=np.float64))
    seen_at = frame.world(r.candidate_stamp, np.asarray(r.candidate_origin, dtype=np.float64))
    if float(np.linalg.norm(seen_at - other)) <= same_radius_m:
        return True  # the runner-up is another view of the Top-1's boundary (module docs)
    return float(np.linalg.norm(query - other)) > 2.0 * tolerance_m


def resolve_with_prior(
    results: Sequence[QueryResult],
    reasons: Sequence[str],
    db_landmarks: Sequence[Landmark],
    frame: CorrectedFrame,
    tolerance_m: float,
    anchored: Callable[[float], bool],
    same_radius_m: float = 0.0,
) -> list[int]:
    """Indices of the ``not_unique`` results the corrected trajectory resolves (module
    docs). ``db_landmarks[i]`` is the landmark behind database index ``i`` (the indices
    ``QueryResult.candidate_index`` and ``runner_up_index`` refer to); ``anchored(stamp)``:
    whether a loop accepted on its descriptor lies near the query submap at ``stamp``;
    ``same_radius_m``: a runner-up whose view lies this close to the Top-1's view (the
    same-boundary radius, ``matching.duplicate_radius_m``) is the Top-1's own boundary."""
    if not tolerance_m > 0.0:
        raise ValueError(f"consistency_tolerance_m: {tolerance_m} must be > 0")
    if not same_radius_m >= 0.0:
        raise ValueError(f"duplicate_radius_m: {same_radius_m} must be >= 0")
    return [
        k
        for k, (r, why) in enumerate(zip(results, reasons, strict=True))
        if why == AMBIGUOUS
        and r.candidate_index is not None
        and anchored(r.query_stamp)
        and _resolvable(r, db_landmarks, frame, tolerance_m, same_radius_m)
    ]


def near_loops(
    loop_stamps: Sequence[float], along: Callable[[float], float], window_m: float
) -> Callable[[float], bool]:
    """``anchored`` for :func:`resolve_with_prior`: a stamp whose path position lies within
    ``window_m`` of one of the loops' (query stamps ``loop_stamps``)."""
    paths = np.array([along(t) for t in loop_stamps], dtype=np.float64)
    return lambda stamp: bool(paths.size) and bool(np.min(np.abs(paths - along(stamp))) <= window_m)
