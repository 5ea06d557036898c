"""Ambiguous (``not_unique``) queries placed by the corrected trajectory: the rules of
:mod:`decod_rs.disambiguation` on hand-built results in a straight corridor along x."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from decod_rs.disambiguation import CorrectedFrame, near_loops, resolve_with_prior

TOL = 0.3


def _frame() -> CorrectedFrame:
    # Scans every second, the corrected trajectory straight along x at 1 m/s.
    stamps = np.arange(0.0, 101.0)
    poses = np.repeat(np.eye(4)[None], stamps.size, axis=0)
    poses[:, 0, 3] = stamps
    return CorrectedFrame(stamps, poses)


def _landmark(stamp: float, x: float) -> Any:
    return SimpleNamespace(submap_stamp=stamp, origin=(x, 0.0, 0.0))


def _result(query: tuple[float, float], top: tuple[float, float], runner: int | None) -> Any:
    """A query at anchor stamp ``query[0]`` with its boundary ``query[1]`` ahead of the
    anchor; its Top-1 likewise (``dz`` 0, same heading); ``runner`` a database index."""
    return SimpleNamespace(
        query_stamp=query[0],
        query_origin=(query[1], 0.0, 0.0),
        candidate_index=0,
        candidate_stamp=top[0],
        candidate_origin=(top[1], 0.0, 0.0),
        candidate_axis=(1.0, 0.0, 0.0),
        heading_deg=0.0,
        dz_m=0.0,
        runner_up_index=runner,
    )


# Database: index 0 the Top-1's view of the boundary at x = 10; 1 the next ring (x = 11.5);
# 2 a second view of a boundary only 0.4 m from x = 10; 3 another view of the Top-1's own
# boundary, from the anchor a second earlier (x = 10.05: the detection's spread).
DB = [_landmark(8.0, 2.0), _landmark(9.0, 2.5), _landmark(9.0, 1.4), _landmark(7.0, 3.05)]
SAME = 0.1  # the pipes' same-boundary radius (matching.duplicate_radius_m)


def _resolve(results: list[Any], reasons: list[str], anchored: bool = True) -> list[int]:
    return resolve_with_prior(
        results, reasons, DB, _frame(), TOL, lambda _stamp: anchored, same_radius_m=SAME
    )


def test_the_prior_keeps_a_top1_it_separates_from_the_runner_up() -> None:
    # The query at 90 s sees its boundary 1.9 m behind: x = 10.1 -> within 0.3 m of x = 10.
    r = _result((90.0, -79.9), (8.0, 2.0), runner=1)
    assert _resolve([r], ["not_unique"]) == [0]


def test_the_prior_does_not_choose_between_two_candidates_it_cannot_separate() -> None:
    r = _result((90.0, -79.9), (8.0, 2.0), runner=2)  # runner-up 0.3 m from the query
    assert _resolve([r], ["not_unique"]) == []


def test_a_top1_away_from_where_the_trajectory_puts_the_query_stays_rejected() -> None:
    r = _result((90.0, -78.5), (8.0, 2.0), runner=1)  # query at x = 11.5: the next ring
    assert _resolve([r], ["not_unique"]) == []


def test_only_ambiguous_queries_near_a_unique_loop_are_reconsidered() -> None:
    r = _result((90.0, -79.9), (8.0, 2.0), runner=1)
    assert _resolve([r], ["not_unique"], anchored=False) == []
    for reason in ("too_few_inliers", "chance", "inconsistent", ""):
        assert _resolve([r], [reason]) == []


def test_near_loops_measures_path_not_time() -> None:
    along = lambda stamp: 2.0 * stamp  # noqa: E731 - 2 m of path per second
    anchored = near_loops([10.0], along, window_m=5.0)
    assert anchored(12.0) and anchored(7.5)
    assert not anchored(13.0)
    assert not near_loops([], along, 5.0)(10.0)


def test_a_non_positive_tolerance_is_refused() -> None:
    with pytest.raises(ValueError, match="consistency_tolerance_m"):
        resolve_with_prior([], [], DB, _frame(), 0.0, lambda _s: True)


def test_a_runner_up_at_the_top1s_own_boundary_does_not_make_it_ambiguous() -> None:
    # pe pipe, 16 beams, uneven drift (matrix pe-spin16-turn-s1): every Top-1 was the right
    # coupler, but its views had not been linked into one track, so the runner-up was the
    # same coupler seen from the next anchor, 1-2 cm away on the corrected trajectory, and
    # 10 right queries stayed `not_unique` (2 of 5 couplers closed; 5 of 5 with this rule).
    r = _result((90.0, -79.9), (8.0, 2.0), runner=3)
    assert _resolve([r], ["not_unique"]) == [0]
    # Without a same-boundary radius the rule is the old one: too close to tell apart.
    assert resolve_with_prior([r], ["not_unique"], DB, _frame(), TOL, lambda _s: True) == []
    # A boundary 0.4 m away is another boundary, and still too close to the query to choose.
    assert _resolve([_result((90.0, -79.9), (8.0, 2.0), runner=2)], ["not_unique"]) == []


def test_a_negative_same_boundary_radius_is_refused() -> None:
    with pytest.raises(ValueError, match="duplicate_radius_m"):
        resolve_with_prior([], [], DB, _frame(), TOL, lambda _s: True, same_radius_m=-0.1)
