"""Chainage: the distance along the corridor from the start of a run, as an inspection report
cites a joint (beyond the paper).

A robot's path is not the corridor: an operator backs up a few metres to look again at a
defect and drives on, so the path's length past that point exceeds the distance along the
corridor by twice the back-up, and the path passes the same joint three times. Measured along
the path, every joint past a back-up of 2-6 m came out long by twice the back-up (held
out, seed 233, two pipes and two tunnels: the registry's median error 14-21 %). Chainage
therefore runs along the path's *forward course*: from the start to the farthest point, only
the positions that take the robot further than it has been, each at least
:data:`MIN_STEP_M` beyond the last one kept and not back the way it came there. On a run
driven straight through, the forward course is the path itself, thinned to
:data:`MIN_STEP_M` (the wobble between samples adds a few millimetres in a hundred metres).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

__all__ = ["AHEAD_COS", "MIN_STEP_M", "forward_course", "outbound_course", "revisits"]

#: The forward course keeps a position at least this far (m) from the last one kept: a step
#: long enough to give the direction of travel against a corrected trajectory's centimetre of
#: noise and a crawler's wobble (1-2 cm sideways over metres), short enough that chainage
#: is not coarser than the scans (4-15 cm apart at 0.4-1.5 m/s).
MIN_STEP_M = 0.05


#: A step counts as ahead while it turns less than 120 deg from the last kept one (the
#: cosine's bound, negated): a back-up turns 180 deg, a corridor's corner 90 deg at most.
AHEAD_COS = 0.5


def _walk(p: FloatArray) -> tuple[list[int], FloatArray]:
    """The forward course's indices into ``p`` (N, 3) and, per position, how far it lies
    behind the course's front (the last position kept so far; 0 where it is kept, or ahead
    of the front but within :data:`MIN_STEP_M` of it)."""
    far = p[int(np.argmax(np.linalg.norm(p - p[0], axis=1)))] - p[0]
    direction = far / max(float(np.linalg.norm(far)), 1e-12)
    kept = [0]
    last = p[0]
    behind = np.zeros(p.shape[0])
    for i in range(1, p.shape[0]):
        step = p[i] - last
        length = float(np.linalg.norm(step))
        along = float(step @ direction)
        if length >= MIN_STEP_M and along > -AHEAD_COS * length:
            kept.append(i)
            direction, last = step / length, p[i]
        elif along < 0.0:
            behind[i] = length
    return kept, behind


def forward_course(positions: FloatArray) -> FloatArray:
    """The positions (P, 3) of ``positions`` (N, 3, in time order) that take the robot
    further along (module doc): the first, then each one at least :data:`MIN_STEP_M` from
    the last kept and ahead of it (within 120 deg, :data:`AHEAD_COS`, of the last kept step;
    at first, of the direction to the farthest position). A back-up and the drive over the
    same stretch again are left out; so is a robot standing still."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 2:
        return p.reshape(-1, 3)
    kept, _ = _walk(p)
    return p[kept]


def revisits(positions: FloatArray, behind_m: float) -> NDArray[np.bool_]:
    """Per position of ``positions`` (N, 3, in time order): whether the robot is there on
    ground it has covered before, at least ``behind_m`` behind the front of its forward
    course (:func:`forward_course`): backing up, or driving over the backed-up stretch
    again until it passes the front. A robot standing still, or creeping, never is."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 2:
        return np.zeros(p.shape[0] if p.ndim == 2 else 0, dtype=bool)
    _, behind = _walk(p)
    return np.asarray(behind >= behind_m, dtype=bool)


def outbound_course(positions: FloatArray) -> FloatArray:
    """The forward course (:func:`forward_course`) of ``positions`` (N, 3) from the start to
    the farthest point from it (the turnaround of an out-and-back run): what chainage runs
    along."""
    p = np.asarray(positions, dtype=np.float64)
    if p.shape[0] == 0:
        return p.reshape(0, 3)
    far = int(np.argmax(np.linalg.norm(p - p[0], axis=1)))
    return forward_course(p[: far + 1])
