"""Where only the odometry places the corrected trajectory (beyond the paper; ``report.json``
``unmeasured``, and a line of ``decod run``'s summary).

A user with a real log has no ground truth, and the corrected trajectory is not equally good
everywhere: between anchors that a loop or a sequential factor reaches, the boundaries
measured the axial position; beyond them, only the odometry (rescaled by the pass's measured
scale where :mod:`decod_rs.odometry_scale` applied one) carries it on. In the simulated
corridors this is where the endpoint error stays: a forward-looking sensor looks out of the
tunnel's portal over the last 10 m of a return pass (its submaps are rejected as not a
corridor), or the last coupler a loop closed in a pipe is 10 m before the end; the corrected
error there grew 0.04 -> 1.05 m (pe pipe, 16 beams, return 15 % short) and 0.09 -> 0.61 m
(shield tunnel, forward sensor, drift changing sign along the return).

Per pass (outbound up to the turnaround, return after it; one pass without a return), the
path between consecutive anchors (and from the pass's first scan to its first anchor, and
from its last anchor to its last scan) is measured where a sequential pair of the pass spans
it, or where it lies between the pass's first and last loop anchors (each pinned to the
other pass). Each run of unmeasured intervals is a stretch, reported when it is longer than
``MIN_STRETCH_M`` along the corrected trajectory: ``"start"``, ``"middle"``, ``"end"`` of its
pass, or ``"whole"``. The outbound's start is the origin of the graph: its stretch drifts
only as far as the odometry does over it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.graph import LoopConstraint
from decod_rs.maps import PASS_NAMES, pass_of

FloatArray = NDArray[np.float64]

__all__ = ["MIN_STRETCH_M", "Stretch", "unmeasured", "unmeasured_report"]

#: A stretch no longer than this is not reported, whatever the length of its pass (a 40 m
#: gap in a kilometre of tunnel matters as much as in 40 m): the odometry of the matrix drifts
#: by 3-15 %, 6-30 cm over 2 m, the scale of a joint's detection noise and of the sequential
#: factors' spacing (anchors are 0.3-3.3 m apart in the simulated corridors).
MIN_STRETCH_M = 2.0


@dataclass(frozen=True)
class Stretch:
    """A stretch of one pass that only the odometry places: ``where`` is ``"start"``,
    ``"middle"``, ``"end"`` or ``"whole"``; stamps in seconds, length along the corrected
    path in metres."""

    pass_name: str
    where: str
    from_stamp: float
    to_stamp: float
    length_m: float


def unmeasured(
    scan_stamps: FloatArray,
    corrected: FloatArray,
    anchor_stamps: FloatArray,
    constraints: Sequence[LoopConstraint],
    split_stamp: float | None,
) -> tuple[list[Stretch], dict[str, float]]:
    """The stretches (module docs) and, per pass, the share of its path they cover
    (``scan_stamps`` (N,), ``corrected`` (N, 4, 4); ``constraints`` index ``anchor_stamps``)."""
    stretches: list[Stretch] = []
    shares: dict[str, float] = {}
    which = pass_of(scan_stamps, split_stamp)
    for k, name in enumerate(PASS_NAMES[: 1 if split_stamp is None else 2]):
        in_pass = which == k
        t = scan_stamps[in_pass]
        if t.size < 2:
            continue
        steps = np.linalg.norm(np.diff(corrected[in_pass, :3, 3], axis=0), axis=1)
        path = np.concatenate([[0.0], np.cumsum(steps)])
        total = float(path[-1])
        if total <= 0.0:
            continue
        own = np.flatnonzero((anchor_stamps >= t[0]) & (anchor_stamps <= t[-1]))
        # Points: the pass's first scan, its anchors, its last scan; interval j joins points
        # j and j + 1, so anchor own[k] is point k + 1.
        points = np.concatenate([[t[0]], anchor_stamps[own], [t[-1]]])
        covered = _covered(own, constraints, points.size - 1)
        found = 0.0
        for lo, hi in _runs(~covered):
            a, b = float(points[lo]), float(points[hi])
            length = float(np.interp(b, t, path) - np.interp(a, t, path))
            if length > MIN_STRETCH_M:
                where = _where(lo, hi, points.size - 1)
                stretches.append(Stretch(name, where, a, b, length))
                found += length
        shares[name] = found / total
    return stretches, shares


def _covered(
    own: NDArray[np.int64], constraints: Sequence[LoopConstraint], intervals: int
) -> NDArray[np.bool_]:
    """Which of a pass's ``intervals`` some factor measures: every interval a sequential
    pair of the pass spans, and every one between the pass's first and last loop anchors
    (each pinned to the other pass); ``own``: the pass's anchor indices (point k + 1)."""
    point = {int(g): k + 1 for k, g in enumerate(own)}
    covered = np.zeros(intervals, dtype=bool)
    looped = []
    for c in constraints:
        q, d = point.get(c.query_index), point.get(c.db_index)
        if c.kind == "loop":
            looped += [p for p in (q, d) if p is not None]
        elif q is not None and d is not None:
            covered[min(q, d) : max(q, d)] = True
    if len(looped) >= 2:
        covered[min(looped) : max(looped)] = True
    return covered


def _runs(mask: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """Maximal runs of True as (first interval, one past the last): point indices."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))


def _where(lo: int, hi: int, intervals: int) -> str:
    if lo == 0 and hi == intervals:
        return "whole"
    return "start" if lo == 0 else "end" if hi == intervals else "middle"


def unmeasured_report(stretches: list[Stretch], shares: dict[str, float]) -> dict[str, Any]:
    """``report.json`` ``unmeasured``: what it means, the thresholds, the stretches, the
    share of each pass."""
    return {
        "what": "stretches of the corrected trajectory that no loop or sequential factor "
        "reaches: only the odometry (rescaled by the pass's measured scale, if any) places "
        "them, so their axial error grows with the odometry's drift over them",
        "min_length_m": MIN_STRETCH_M,
        "stretches": [asdict(s) for s in stretches],
        "share_of_pass": shares,
    }
