"""Loops the optimised graph cannot satisfy (beyond the paper).

The pairwise selection (:mod:`decod_rs.selection`) must allow for the drift the odometry can
accumulate between two loops, so a loop off by two or three joint spacings can slip through
where the allowance is wide (15 % of the path between loops with the auto configuration).
After the optimisation, the trajectory is held by every other loop and by the boundary
tracks, and a true loop's two boundary views coincide on it to within the detection noise:
in the generalisation matrix the largest residual of a right loop was 0.13 m (median 0.5-2
cm), while the two loops off by 2.1 m and 3.3 m (horseshoe arches, K = 7 and 8 with chances
of 1e-6 and 1e-8: correlated repeated structure the null model does not see) kept
residuals of 1.9 m and 3.4 m — the robust kernel had already refused to bend the graph for
them.

:func:`worst_unsatisfied` names the loop whose views lie farthest apart on the corrected
trajectory if that exceeds ``consistency_tolerance_m`` (below half any boundary spacing);
the pipeline drops it as ``inconsistent``, optimises again and repeats, one loop at a time
(a wrong loop can pull its neighbours' residuals up; removing the worst first leaves them).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from decod_rs._core import QueryResult
from decod_rs.disambiguation import CorrectedFrame

FloatArray = NDArray[np.float64]

__all__ = ["MAX_DROPS", "loop_residuals", "worst_unsatisfied"]

#: At most this many loops dropped per run (each drop costs one optimisation).
MAX_DROPS = 20


def loop_residuals(
    results: Sequence[QueryResult], keep: Sequence[bool], frame: CorrectedFrame
) -> FloatArray:
    """For every kept loop, the distance (metres) between its query boundary and its
    database boundary (moved by the verified offset) on the corrected trajectory; NaN for
    the others."""
    out = np.full(len(results), np.nan)
    for k, (r, ok) in enumerate(zip(results, keep, strict=True)):
        if ok and r.candidate_index is not None:
            query, db = frame.loop_ends(r)
            out[k] = float(np.linalg.norm(query - db))
    return out


def worst_unsatisfied(residuals: FloatArray, tolerance_m: float) -> int | None:
    """The index of the largest residual if it exceeds ``tolerance_m``, else None."""
    if not tolerance_m > 0.0:
        raise ValueError(f"consistency_tolerance_m: {tolerance_m} must be > 0")
    finite = np.where(np.isfinite(residuals), residuals, -np.inf)
    if finite.size == 0:
        return None
    k = int(np.argmax(finite))
    return k if finite[k] > tolerance_m else None
