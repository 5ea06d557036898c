"""A pass whose tracks did not measure its scale is stitched beyond its loops at the scale
the loops measure (decod_rs.loop_scale)."""

from __future__ import annotations

import numpy as np

from decod_rs.graph import LoopConstraint
from decod_rs.loop_scale import MIN_TIED_ANCHORS, stitch_with_loop_scales


def _poses(x: np.ndarray) -> np.ndarray:
    out = np.repeat(np.eye(4)[None], x.size, axis=0)
    out[:, 0, 3] = x
    return out


def _loop(q: int, d: int) -> LoopConstraint:
    z = np.zeros(3)
    return LoopConstraint(q, d, z, np.array([1.0, 0, 0]), z, np.array([1.0, 0, 0]))


def _run() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float]:
    """Out 30 m and back at 0.3 m/s (10 Hz); the odometry reads the return 15 % short, the
    graph (loops on the return's first 15 m) has it right there and follows the odometry
    after. Returns stamps, truth, odometry, corrected and the split."""
    t = np.arange(0.0, 200.0, 0.1)
    truth = np.where(t <= 100.0, 0.3 * t, 30.0 - 0.3 * (t - 100.0))
    truth = np.clip(truth, 0.0, None)
    odo = np.where(t <= 100.0, truth, 30.0 - 0.85 * (30.0 - truth))
    tied_end = 150.0  # the last loop: 15 m back
    k = int(np.searchsorted(t, tied_end))
    corrected = np.where(t <= tied_end, truth, truth[k] + (odo - odo[k]))
    return t, _poses(truth), _poses(odo), _poses(corrected), 100.0


def test_the_return_is_stitched_at_its_loops_scale_beyond_them() -> None:
    t, truth, odo, corrected, split = _run()
    anchors = t[::10]  # an anchor a second
    # Loops tie return anchors at 110-150 s to outbound ones.
    loops = [_loop(int(q), int(q) - 100) for q in range(110, 151, 10)]
    stitch = stitch_with_loop_scales(t, odo, corrected, anchors, loops, split, [True, False])
    assert stitch is not None
    late = t > 151.0
    # Beyond the last loop the corrected trajectory follows the 15 % short odometry (the
    # smear the rebuild would keep); the stitching is the truth to the walk's precision.
    assert np.max(np.abs(corrected[late, 0, 3] - truth[late, 0, 3])) > 2.0
    assert np.max(np.abs(stitch[late, 0, 3] - truth[late, 0, 3])) < 0.01
    # Before the first loop too (the return's first 10 s): at the loops' scale, the truth.
    early = (t > split) & (t < 110.0)
    assert np.max(np.abs(stitch[early, 0, 3] - truth[early, 0, 3])) < 0.01
    # Within the loops' stretch and on the outbound, the graph's poses are kept.
    kept = (t <= split) | ((t >= 110.0) & (t <= 150.0))
    assert np.array_equal(stitch[kept], corrected[kept])


def test_no_stitch_where_the_tracks_measured_the_pass_or_few_loops_tie_it() -> None:
    t, _, odo, corrected, split = _run()
    anchors = t[::10]
    loops = [_loop(int(q), int(q) - 100) for q in range(110, 151, 10)]
    measured = stitch_with_loop_scales(t, odo, corrected, anchors, loops, split, [True, True])
    assert measured is None
    few = loops[: MIN_TIED_ANCHORS - 1]
    # Two loops tie two return anchors and two outbound ones: the return has too few.
    assert stitch_with_loop_scales(t, odo, corrected, anchors, few, split, [True, False]) is None
    # Loops over a stretch shorter than MIN_STRETCH_M (1.2 m of the return) measure nothing.
    close = [_loop(q, q - 100) for q in (110, 111, 112, 113, 114)]
    assert stitch_with_loop_scales(t, odo, corrected, anchors, close, split, [True, False]) is None
