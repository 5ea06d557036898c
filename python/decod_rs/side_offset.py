"""The side offset: a boundary is placed a few centimetres beyond where it is, on the side
away from the sensor (beyond the paper; measured on the tracks, removed from the sequential
factors).

A ring, arch or joint seen from one side along the axis shows the sensor its near face and
hides its far one, so the detection puts the boundary a little *away from the sensor*: ahead
of an anchor it lands ahead of the boundary, behind it behind. Placed with the ground truth
(``decod_rs.bench.detection_bias``'s views, in 1-3 m bands), the views of the matrix's 6 m
horseshoe with 64 beams (a turn, symmetric drift) are off by -2.3 to -2.8 cm at every range
from 2 to 12 m behind the anchor and by +1.9 to +3.0 cm from 1 to 12 m ahead; those of a
held-out 8 m horseshoe with arches 2 m apart by -3.9 to -5.4 and +2.9 to +5.4 cm. It is a
step, not a slope (the matrix's earlier reading, "+0.26 to +0.29 % of range", fitted a line
through it). Two views from the same side then differ by the true displacement, but two
that *straddle* the boundary (the robot passed it between them) differ by it plus twice the
offset. A spinning sensor gives every boundary such a pair in its track, so the sequential
factors (:mod:`decod_rs.sequential`) read the pass longer than it is: in that 8 m horseshoe
the corrected trajectory ran 0.3-0.5 % long (+21 cm at 38 m).

The offset is measured where the odometry cannot enter it: two submaps that hold both a
straddling pair and same-side pairs saw all of them from the same two anchor poses, so the
straddling pair's residual along the axis (odometry frame) less the same-side pairs' median
is the offset alone, twice, whatever the odometry's error between the two anchors. The
median over all such differences is the run's offset. It is removed from the sequential
factors (each view's origin moved towards its anchor by it, along its axis: the same-side
pairs are unchanged, the straddling ones lose the 2c) when it is measured on at least
:data:`MIN_PAIRS` differences and lies :data:`SIGNIFICANCE` standard errors or more from 0.
``report.json`` ``sequential.side_offset`` gives it, its standard error, the differences and
whether it was removed.

Only an offset away from the sensor is removed. The near face seen and the far one hidden
cannot place a boundary towards the sensor, so a negative reading is something else: in a
round whose submaps were stitched on a trajectory still a few per cent off, or rebuilt on
one, the views' error grows with range instead of stepping. Removing it both ways, the fresh
tier's 4 m horseshoe with 64 beams under uneven drift read -1.1 +- 0.2 cm and its RMSE went
0.077 -> 0.105 m (fresh12); one-sided, it keeps its factors, and no matrix row changes.

Only the sequential factors take it. The step holds near the anchor, where straddling pairs
are; farther out it need not (the 4 m shield's views: +-4.4 cm within 4 m, none at 6-9 m,
where its bands of bolt pockets lie), so moving the loops' and the registry's views by it too
was tried and is not in: on the matrix (m131 against m129, the same logs) it made the 4 m
shield's RMSE 1.7 times as large (0.059 -> 0.101 m) for the same gains elsewhere.

On the matrix (m135 against m129, the same logs): only the 64-beam rows measure it (the
16-beam and forward-sensor tracks hold 0-9 differences, below :data:`MIN_PAIRS`, the pipes'
none). It was removed in 12 of their 20 rows (+1.1 to +2.5 cm, standard errors 0.2-0.4 cm):
the far end's error smaller in 11 of them (median 0.25 -> 0.17 % of the outbound distance),
the axial RMS after correction lower in 10 (the shields under uneven drift 5.6-8.8 -> 1.4-4.7
cm, the horseshoe under symmetric drift 7.8-8.9 -> 4.8-6.3 cm) and higher in two (the 4 m
shield under symmetric drift 5.3 -> 6.6 cm, one shield 1.9 -> 2.0 cm). The horseshoe under
uneven drift, whose submaps are rebuilt, measures -0.5 to +0.7 cm and keeps its factors (its
rebuilt views' error grows with range instead: -0.5 to +0.7 cm within 4 m, +-2.4 cm at 9-12
m, which no pair of views can tell from the odometry's scale). 11,410 -> 11,400 loops, none
wrong; the registry within 1 % in 79 of 98 runs instead of 78; position RMSE over the 20
64-beam rows a geometric mean 0.89 times as large (the 4 m shield, symmetric, 1.2 times),
the other 80 rows unchanged. Held out (seed 149, simulated for this check): the 8 m
horseshoe above, 0.142 -> 0.141 m under symmetric drift (axial RMS 11.0 -> 4.1 cm) and
0.139 -> 0.130 m under uneven drift (7.2 -> 5.3 cm). What is left there is vertical (8.5
and 11.8 cm RMS, the odometry's 0.6-0.9 cm): the graph's, not this offset's.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.graph import LoopConstraint

FloatArray = NDArray[np.float64]

__all__ = [
    "MIN_PAIRS",
    "SideOffset",
    "away_from_sensor",
    "measure_side_offset",
    "without_offset",
]

#: Differences (straddling against same-side pairs of one pair of submaps) below which the
#: offset is not considered measured.
MIN_PAIRS = 10
#: The offset is removed when it lies at least this many standard errors from 0, away from
#: the sensor.
SIGNIFICANCE = 3.0


@dataclass(frozen=True)
class SideOffset:
    """The measured offset (m, positive: away from the sensor), its standard error, the
    differences it is the median of, and whether the factors had it removed."""

    offset_m: float
    sigma_m: float
    pairs: int
    applied: bool

    def report(self) -> dict[str, Any]:
        return {
            "offset_m": self.offset_m,
            "sigma_m": None if not np.isfinite(self.sigma_m) else self.sigma_m,
            "differences": self.pairs,
            "applied": self.applied,
        }


def away_from_sensor(origin: FloatArray, axis: FloatArray) -> FloatArray:
    """The unit axis direction from a view's anchor towards its boundary (anchor frame): the
    axis signed by which side of the anchor the boundary lies on."""
    axis = np.asarray(axis, dtype=np.float64)
    return np.sign(float(np.dot(origin, axis))) * axis


def _residual(c: LoopConstraint, poses: Sequence[FloatArray]) -> tuple[float, float]:
    """Along the db view's axis (odometry frame): the db view's boundary minus the query
    view's, and the difference of their away-from-sensor directions (about -2, 0 or 2)."""
    pd, pq = poses[c.db_index], poses[c.query_index]
    u = pd[:3, :3] @ c.db_axis
    u = u / max(float(np.linalg.norm(u)), 1e-12)
    where_d = pd[:3, :3] @ c.db_origin + pd[:3, 3]
    where_q = pq[:3, :3] @ c.query_origin + pq[:3, 3]
    away_d = pd[:3, :3] @ away_from_sensor(c.db_origin, c.db_axis)
    away_q = pq[:3, :3] @ away_from_sensor(c.query_origin, c.query_axis)
    return float((where_d - where_q) @ u), float((away_d - away_q) @ u)


def measure_side_offset(
    constraints: Sequence[LoopConstraint], poses: Sequence[FloatArray]
) -> SideOffset:
    """The offset from within-pass factors (module docs): for every pair of submaps with a
    straddling pair and same-side pairs, the straddling residual less the same-side pairs'
    median, over the direction difference; the median of those. ``poses``: the anchors'
    odometry poses by index."""
    groups: dict[tuple[int, int], list[tuple[float, float]]] = defaultdict(list)
    for c in constraints:
        if c.kind == "sequential":
            groups[(c.db_index, c.query_index)].append(_residual(c, poses))
    estimates = []
    for members in groups.values():
        same = [e for e, d in members if abs(d) < 1.0]
        if not same:
            continue
        base = float(np.median(same))
        estimates += [(e - base) / d for e, d in members if abs(d) >= 1.0]
    if len(estimates) < MIN_PAIRS:
        return SideOffset(0.0, float("inf"), len(estimates), False)
    values = np.asarray(estimates)
    offset = float(np.median(values))
    # The median's standard error: 1.253 x the robust sigma (1.4826 MAD) / sqrt(n).
    mad = float(np.median(np.abs(values - offset)))
    sigma = 1.253 * 1.4826 * mad / np.sqrt(values.size)
    # Away from the sensor only: the near face seen and the far one hidden cannot place a
    # boundary towards the sensor, so a negative reading is something else (module docs).
    applied = bool(offset > SIGNIFICANCE * sigma)
    return SideOffset(offset, float(sigma), int(values.size), applied)


def without_offset(constraints: Sequence[LoopConstraint], side: SideOffset) -> list[LoopConstraint]:
    """The factors with each view's origin moved towards its anchor by the offset, along the
    axis (unchanged when the offset was not applied)."""
    if not side.applied:
        return list(constraints)
    c0 = side.offset_m
    return [
        replace(
            c,
            query_origin=c.query_origin - c0 * away_from_sensor(c.query_origin, c.query_axis),
            db_origin=c.db_origin - c0 * away_from_sensor(c.db_origin, c.db_axis),
        )
        for c in constraints
    ]
