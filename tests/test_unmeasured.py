"""Where only the odometry places the corrected trajectory (``report.json`` ``unmeasured``):
the stretches no loop or sequential pair reaches, on an out-and-back whose factors are
placed by construction, so the right answer is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from decod_rs.graph import LoopConstraint
from decod_rs.unmeasured import MIN_STRETCH_M, unmeasured, unmeasured_report

ORIGIN = np.zeros(3)
AXIS = np.array([1.0, 0.0, 0.0])


def _out_and_back() -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """20 m out at 1 m/s, 20 m back; a scan every 0.1 s, an anchor every second."""
    t = np.round(np.arange(0.0, 40.01, 0.1), 6)
    x = np.where(t <= 20.0, t, 40.0 - t)
    poses = np.tile(np.eye(4), (t.size, 1, 1))
    poses[:, 0, 3] = x
    return t, poses, np.arange(0.5, 40.0, 1.0), 20.0


def _pair(a: int, b: int, kind: str) -> LoopConstraint:
    return LoopConstraint(b, a, ORIGIN, AXIS, ORIGIN, AXIS, kind=kind)


def test_the_stretches_no_factor_reaches_are_reported_with_their_length() -> None:
    t, poses, anchors, split = _out_and_back()
    # Outbound: sequential pairs span anchors 2-9 (2.5-9.5 s). Loops tie outbound anchors
    # 4 and 8 (4.5, 8.5 s) to return anchors 35 and 31 (35.5, 31.5 s): the return is
    # measured between its first and last loop anchor, the rest of each pass only by the
    # odometry.
    constraints = [_pair(2, 5, "sequential"), _pair(5, 9, "sequential")]
    constraints += [_pair(4, 35, "loop"), _pair(8, 31, "loop")]
    stretches, shares = unmeasured(t, poses, anchors, constraints, split)
    found = {(s.pass_name, s.where): (s.from_stamp, s.to_stamp, s.length_m) for s in stretches}
    assert found == {
        ("outbound", "start"): (0.0, 2.5, pytest.approx(2.5)),
        ("outbound", "end"): (9.5, 20.0, pytest.approx(10.5)),
        ("return", "start"): (20.1, 31.5, pytest.approx(11.4)),  # its first scan
        ("return", "end"): (35.5, 40.0, pytest.approx(4.5)),
    }
    assert shares["outbound"] == pytest.approx((2.5 + 10.5) / 20.0)
    assert shares["return"] == pytest.approx((11.4 + 4.5) / 19.9)
    # A loop at outbound anchor 11 and return anchor 28 extends both passes' measured
    # stretches: between the first and last loop anchors of a pass, loops pin it.
    stretches, _ = unmeasured(t, poses, anchors, [*constraints, _pair(11, 28, "loop")], split)
    found = {(s.pass_name, s.where): (s.from_stamp, s.to_stamp, s.length_m) for s in stretches}
    assert found[("outbound", "end")] == (11.5, 20.0, pytest.approx(8.5))
    assert found[("return", "start")] == (20.1, 28.5, pytest.approx(8.4))


def test_short_gaps_are_not_stretches_and_nothing_measured_is_the_whole_pass() -> None:
    t, poses, anchors, split = _out_and_back()
    # Sequential pairs over every anchor of both passes but three intervals (1 m) and two
    # adjacent ones (2 m: not longer than MIN_STRETCH_M), and the pass ends (0.4-0.5 m):
    # nothing to report.
    pairs = [_pair(k, k + 1, "sequential") for k in range(39) if k not in (5, 19, 30, 33, 34)]
    stretches, shares = unmeasured(t, poses, anchors, pairs, split)
    assert MIN_STRETCH_M == 2.0 and stretches == []
    assert shares == {"outbound": 0.0, "return": 0.0}
    # No factor (--no-loops, or the odometry stood): each pass is one stretch.
    stretches, shares = unmeasured(t, poses, anchors, [], split)
    assert [(s.pass_name, s.where, s.length_m) for s in stretches] == [
        ("outbound", "whole", pytest.approx(20.0)),
        ("return", "whole", pytest.approx(19.9)),  # from its first scan, 0.1 s after the turn
    ]
    report = unmeasured_report(stretches, shares)
    assert report["share_of_pass"] == {"outbound": 1.0, "return": 1.0}
    assert report["stretches"][1]["from_stamp"] == 20.1  # the return's first scan


def test_the_trajectory_plot_shades_the_stretches(tmp_path: Path) -> None:
    from matplotlib.image import imread

    from decod_rs.plots import plot_trajectories

    t, poses, _, _ = _out_and_back()
    plain = plot_trajectories(tmp_path / "plain.png", t, poses, poses)
    shaded = plot_trajectories(tmp_path / "shaded.png", t, poses, poses, unmeasured=[(30.0, 40.0)])
    a, b = imread(plain), imread(shaded)
    assert a.shape == b.shape
    # The band is light grey behind the lines: pixels that were white are now grey.
    grey = np.all(np.abs(b[..., :3] - 0.88) < 0.02, axis=-1) & np.all(a[..., :3] > 0.99, axis=-1)
    assert grey.sum() > 0.01 * grey.size


def test_the_trajectory_plot_marks_the_anchors_an_end_face_ties(tmp_path: Path) -> None:
    from matplotlib.image import imread

    from decod_rs.plots import plot_trajectories

    t, poses, _, _ = _out_and_back()
    plain = plot_trajectories(tmp_path / "plain.png", t, poses, poses)
    marked = plot_trajectories(tmp_path / "faces.png", t, poses, poses, faces=[30.0, 33.0, 36.0])
    a, b = imread(plain), imread(marked)
    assert a.shape == b.shape
    # Black ticks on the along-the-corridor panel (the lines are red and blue), one per
    # anchor, and the legend's.
    black = np.all(b[..., :3] < 0.1, axis=-1) & ~np.all(a[..., :3] < 0.1, axis=-1)
    assert black.sum() > 100, black.sum()
