"""The scale a pass's loops measure, carried over the stretches of the pass that no factor
reaches, for stitching rebuilt submaps (beyond the paper).

A pass whose tracks measure its odometry scale is rescaled (:mod:`decod_rs.odometry_scale`).
One whose tracks do not (a 0.4 m ribbed pipe seen by 16 beams on a return stitched 15 %
short: the smeared windows give one or two track pairs) keeps the odometry's scale, and the
submaps rebuilt on the corrected trajectory (:mod:`decod_rs.stages.refine`) are sharp only
where loops tie the pass: between its first and last loop the graph has the pass at the
outbound's measured scale; beyond them it follows the odometry, and stays smeared, so the
rebuilt round finds no more loops there (held out, seed 241: loops on the first half of the
return only, the endpoint error 3.09 -> 1.93 m).

Between its first and last tied anchor the corrected trajectory measures the pass's scale:
the ratio of its travel to the odometry's there. Where that stretch is at least
:data:`MIN_STRETCH_M` long and tied by :data:`MIN_TIED_ANCHORS` anchors, the trajectory rebuilt
submaps are stitched on takes that ratio over the rest of the pass: each scan's position
beyond the stretch is the stretch's end plus the odometry's displacement from it, times the
ratio. Only the stitching: the output is the graph's.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from decod_rs.graph import LoopConstraint
from decod_rs.maps import pass_of
from decod_rs.path_curve import path_length

FloatArray = NDArray[np.float64]

__all__ = ["MIN_STRETCH_M", "MIN_TIED_ANCHORS", "stitch_with_loop_scales"]

#: The tied stretch must be this long (m of odometry travel) to measure a scale: the
#: odometry's random walk (1 cm / sqrt(m) in the simulator's leg model) is then 0.6 % of it.
MIN_STRETCH_M = 3.0
#: Anchors of the pass that loops tie, at least.
MIN_TIED_ANCHORS = 3
#: Ratios outside this range are not a scale error but a failure (a stalled frontend).
RATIO_RANGE = (0.5, 2.0)


def stitch_with_loop_scales(
    scan_stamps: FloatArray,
    start: FloatArray,
    corrected: FloatArray,
    anchor_stamps: FloatArray,
    constraints: Sequence[LoopConstraint],
    split_stamp: float | None,
    measured: Sequence[bool],
) -> FloatArray | None:
    """The scan poses to stitch rebuilt submaps on (module docs), or None where no pass
    needs it. ``start``: the odometry the graph started from, ``corrected``: its output,
    both (M, 4, 4) at ``scan_stamps``; ``measured[k]``: pass ``k``'s scale was measured by
    its tracks (then it is left as the graph has it)."""
    tied = sorted(
        {c.query_index for c in constraints if c.kind == "loop"}
        | {c.db_index for c in constraints if c.kind == "loop"}
    )
    if not tied or scan_stamps.size < 2:
        return None
    tied_stamps = anchor_stamps[np.asarray(tied, dtype=np.int64)]
    scan_pass = pass_of(scan_stamps, split_stamp)
    tied_pass = pass_of(tied_stamps, split_stamp)
    out = corrected.copy()
    changed = False
    for k, done in enumerate(measured):
        stamps = tied_stamps[tied_pass == k]
        scans = np.flatnonzero(scan_pass == k)
        if done or stamps.size < MIN_TIED_ANCHORS or scans.size < 2:
            continue
        first, last = np.searchsorted(scan_stamps, [stamps.min(), stamps.max()])
        first, last = int(min(first, scan_stamps.size - 1)), int(min(last, scan_stamps.size - 1))
        odo = path_length(start[first : last + 1, :3, 3])[-1]
        cor = path_length(corrected[first : last + 1, :3, 3])[-1]
        if odo < MIN_STRETCH_M:
            continue
        ratio = cor / odo
        if not RATIO_RANGE[0] <= ratio <= RATIO_RANGE[1]:
            continue
        for ends, anchor in (
            (scans[scans > last], last),
            (scans[scans < first], first),
        ):
            if ends.size:
                shift = start[ends, :3, 3] - start[anchor, :3, 3]
                out[ends, :3, 3] = corrected[anchor, :3, 3] + ratio * shift
                changed = True
    return out if changed else None
