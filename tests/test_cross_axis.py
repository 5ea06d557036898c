"""Whether the landmark factors leave the height to the odometry (:mod:`decod_rs.cross_axis`):
the spread measured on the tracks, the rule, and what it does to the graph."""

from __future__ import annotations

import numpy as np
import pytest
from corridor_chains import boundary_chain

from decod_rs._core import Landmark
from decod_rs.commands.run import print_cross_axis
from decod_rs.config import Config, load_config
from decod_rs.cross_axis import (
    FREE_SIGMA_M,
    MIN_SPREAD_DOF,
    cross_axis,
    cross_axis_spread,
    odometry_across_sigma_m,
)
from decod_rs.graph import LoopConstraint, optimize
from decod_rs.landmark_factor import axis_frame

GRAPH = load_config(preset="tunnel").graph


def _view(stamp: float, origin: np.ndarray, axis: np.ndarray) -> Landmark:
    return Landmark(
        stamp,
        origin,
        axis,
        np.array([0.0, 0.0, -1.0]),
        np.zeros((16, 256)),
        np.ones((16, 256), dtype=bool),
        cell_z_m=0.25,
        perimeter_m=15.0,
    )


def _yaw(deg: float, x: float) -> np.ndarray:
    t = np.eye(4)
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    t[:2, :2] = [[c, -s], [s, c]]
    t[0, 3] = x
    return t


def _tracks(
    lateral_m: float, vertical_m: float, seed: int, boundaries: int = 12, views: int = 5
) -> tuple[list[Landmark], np.ndarray, dict[float, np.ndarray]]:
    """``boundaries`` rings 1.5 m apart, each seen from ``views`` anchors 1 m apart, the
    origins scattered by the given sigmas; half the anchors face the other way (a return
    pass), so the axes in their body frames point backwards."""
    rng = np.random.default_rng(seed)
    landmarks: list[Landmark] = []
    tracks: list[int] = []
    anchors: dict[float, np.ndarray] = {}
    for b in range(boundaries):
        ring = 1.5 * b
        for v in range(views):
            x = ring - 1.0 - v
            back = (b + v) % 2 == 1
            stamp = float(len(anchors))
            pose = _yaw(180.0 if back else 0.0, x)
            anchors[stamp] = pose
            world = np.array([ring, rng.normal(0.0, lateral_m), 1.2 + rng.normal(0.0, vertical_m)])
            body = pose[:3, :3].T @ (world - pose[:3, 3])
            landmarks.append(_view(stamp, body, pose[:3, :3].T @ np.array([1.0, 0.0, 0.0])))
            tracks.append(b)
    return landmarks, np.array(tracks, dtype=np.int64), anchors


def test_the_spread_is_measured_apart_laterally_and_vertically() -> None:
    # A tunnel's views: 3 cm vertically (the floor cut off), 0.2 cm sideways; 48 degrees
    # of freedom, so the measured RMS is within about 20 % of the truth (chi, 1.96 / sqrt(96)).
    lm, tracks, anchors = _tracks(0.002, 0.03, seed=1)
    spread = cross_axis_spread(lm, tracks, anchors)
    assert spread is not None
    lateral, vertical, dof = spread
    assert dof == 12 * 4
    # Each track's mean takes one degree of freedom; the pooled sum is divided by the rest.
    assert lateral == pytest.approx(0.002, rel=0.25)
    assert vertical == pytest.approx(0.03, rel=0.25)


def test_too_few_views_measure_nothing() -> None:
    lm, tracks, anchors = _tracks(0.002, 0.03, seed=2, boundaries=2, views=3)
    assert 2 * 2 < MIN_SPREAD_DOF
    assert cross_axis_spread(lm, tracks, anchors) is None
    assert cross_axis_spread([], np.zeros(0, dtype=np.int64), {}) is None


def test_the_odometry_sigma_is_the_graphs_over_one_anchor_interval() -> None:
    stamps = np.arange(10.0)
    path = {float(s): 2.5 * float(s) for s in stamps}
    sigma = odometry_across_sigma_m(stamps, lambda s: path[s], GRAPH)
    expected = GRAPH.odom_translation_sigma_per_m * GRAPH.odom_across_sigma_ratio * np.sqrt(2.5)
    assert sigma == pytest.approx(expected)
    # No motion, or a single anchor: nothing to compare with.
    assert odometry_across_sigma_m(stamps, lambda s: 0.0, GRAPH) is None
    assert odometry_across_sigma_m(stamps[:1], lambda s: 0.0, GRAPH) is None
    # A stop (anchors 10-29 standing at 25 m) is no interval of travel: the same sigma, where
    # the median over every interval would have been 0 and the heights rule had nothing.
    stopped = np.arange(40.0)
    where = {float(s): 2.5 * float(min(s, 10.0) + max(s - 29.0, 0.0)) for s in stopped}
    assert odometry_across_sigma_m(stopped, lambda s: where[s], GRAPH) == pytest.approx(expected)


def test_tunnel_views_leave_height_to_the_odometry_pipe_views_do_not() -> None:
    stamps = np.arange(60.0)
    path = {float(s): 1.0 * float(s) for s in stamps}  # the anchors 1 m apart: 0.5 cm
    tunnel = cross_axis(*_tracks(0.002, 0.03, seed=3), stamps, lambda s: path[s], GRAPH)
    pipe = cross_axis(*_tracks(0.001, 0.001, seed=4), stamps, lambda s: path[s], GRAPH)
    assert tunnel is not None and pipe is not None
    assert tunnel.odometry_sigma_m == pytest.approx(0.005)
    assert tunnel.vertical_sigma_m == FREE_SIGMA_M
    assert pipe.vertical_sigma_m is None
    assert tunnel.report()["height_left_to_odometry"]
    assert not pipe.report()["height_left_to_odometry"]
    # An odometry modelled as drifting 5 cm per root metre across its travel (a frontend
    # without gravity): the tunnel's 3 cm views are then the better height, and kept.
    loose = Config({**GRAPH.to_dict(), "odom_across_sigma_ratio": 1.0})
    kept = cross_axis(*_tracks(0.002, 0.03, seed=3), stamps, lambda s: path[s], loose)
    assert kept is not None and kept.vertical_sigma_m is None


def test_the_vertical_sigma_applies_in_the_axis_frame() -> None:
    # axis_frame's rows for a level axis: along, horizontal across, vertical.
    frame = axis_frame(np.array([0.8, 0.6, 0.0]))
    assert abs(frame[1, 2]) < 1e-12 and abs(abs(frame[2, 2]) - 1.0) < 1e-12
    lc = LoopConstraint(
        1,
        0,
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        sigma_m=0.02,
        sigma_transverse_m=0.05,
        sigma_vertical_m=FREE_SIGMA_M,
    )
    np.testing.assert_allclose(lc.sigmas(GRAPH)[:3], [0.02, 0.05, FREE_SIGMA_M])
    with pytest.raises(ValueError, match="sigma_vertical_m"):
        LoopConstraint(1, 0, np.zeros(3), np.ones(3), np.zeros(3), np.ones(3), sigma_vertical_m=0.0)


def _scattered_views(scale: float, seed: int) -> tuple[np.ndarray, list[LoopConstraint]]:
    """A 40 m pass, anchors every 1 m, odometry ``scale`` short; rings every 1.5 m seen from
    2-10 m behind; each view's height off by 3 cm RMS plus 1 cm per 10 m of range (a
    partial section: views from farther see less of the floor)."""
    rng = np.random.default_rng(seed)
    return boundary_chain(
        np.arange(0.0, 40.0, 1.0),
        scale,
        lambda r: 1.2 + 0.001 * r + rng.normal(0.0, 0.03),
        sigma_m=0.02,
        sigma_transverse_m=0.03,
    )


def test_heights_left_to_the_odometry_keep_the_trajectory_level() -> None:
    # The odometry is level and 3 % short. With the views' heights in the graph the
    # corrected trajectory wanders vertically (1.2 cm); left to the odometry it stays level
    # (0.14 cm), and the scale is corrected either way.
    odom, loops = _scattered_views(scale=0.03, seed=5)
    used = optimize(odom, loops, GRAPH).poses
    free = [LoopConstraint(**{**lc.__dict__, "sigma_vertical_m": FREE_SIGMA_M}) for lc in loops]
    left = optimize(odom, free, GRAPH).poses
    z_used, z_left = np.max(np.abs(used[:, 2, 3])), np.max(np.abs(left[:, 2, 3]))
    assert z_left < 0.2 * z_used, (z_left, z_used)
    assert z_left < 0.005, z_left
    # The odometry ends 1.17 m short; the last 2 m of anchors see no ring ahead, so the
    # corrected end is 0.11 m short, the same either way.
    assert abs(left[-1, 0, 3] - 39.0) < 0.15, left[-1, 0, 3]
    assert abs(left[-1, 0, 3] - used[-1, 0, 3]) < 0.01


def test_decod_run_says_where_the_heights_came_from(capsys: pytest.CaptureFixture[str]) -> None:
    tunnel = cross_axis(*_tracks(0.002, 0.03, seed=3), np.arange(60.0), float, GRAPH)
    assert tunnel is not None
    print_cross_axis({"cross_axis": tunnel.report()})
    print_cross_axis({"cross_axis": None})
    print_cross_axis({"cross_axis": None, "loops_enabled": False})
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("heights        left to the odometry (the views scatter 3."), lines
    assert lines[0].endswith("the odometry holds 0.5 cm)"), lines
    assert lines[1].startswith("heights        from the boundaries (too few tracked views"), lines
    assert lines[2] == "heights        from the odometry (--no-loops: no landmark factors)", lines
