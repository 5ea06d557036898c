"""Loops the optimised graph cannot satisfy (:mod:`decod_rs.residuals`), on hand-built
results in a straight corridor along x."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from decod_rs.disambiguation import CorrectedFrame
from decod_rs.residuals import loop_residuals, worst_unsatisfied


def _frame() -> CorrectedFrame:
    stamps = np.arange(0.0, 101.0)
    poses = np.repeat(np.eye(4)[None], stamps.size, axis=0)
    poses[:, 0, 3] = stamps
    return CorrectedFrame(stamps, poses)


def _loop(query_x: float, db_x: float, dz: float = 0.0) -> Any:
    """A query at anchor 90 s and its database view at anchor 8 s, boundaries at the given
    world x on the corrected trajectory (database view moved by ``dz`` along +x)."""
    return SimpleNamespace(
        query_stamp=90.0,
        query_origin=(query_x - 90.0, 0.0, 0.0),
        candidate_index=0,
        candidate_stamp=8.0,
        candidate_origin=(db_x - 8.0, 0.0, 0.0),
        candidate_axis=(1.0, 0.0, 0.0),
        heading_deg=0.0,
        dz_m=dz,
    )


def test_residuals_measure_where_the_corrected_trajectory_puts_both_views() -> None:
    loops = [_loop(10.0, 10.05), _loop(10.0, 12.4), _loop(10.0, 9.8, dz=0.2), _loop(5.0, 50.0)]
    res = loop_residuals(loops, [True, True, True, False], _frame())
    assert res[:3] == pytest.approx([0.05, 2.4, 0.0], abs=1e-9)
    assert np.isnan(res[3])  # not a loop: no residual


def test_the_worst_loop_beyond_the_tolerance_goes_first() -> None:
    assert worst_unsatisfied(np.array([0.05, 2.4, np.nan, 3.3]), 0.3) == 3
    assert worst_unsatisfied(np.array([0.05, 0.29, np.nan]), 0.3) is None
    assert worst_unsatisfied(np.array([np.nan]), 0.3) is None
    assert worst_unsatisfied(np.array([]), 0.3) is None
    with pytest.raises(ValueError, match="consistency_tolerance_m"):
        worst_unsatisfied(np.array([1.0]), 0.0)
