"""The side offset (:mod:`decod_rs.side_offset`): boundaries placed a few centimetres away
from the sensor are measured on the tracks whatever the odometry's error, and removed, so the
sequential factors no longer read the offset as odometry scale."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from decod_rs.config import load_config
from decod_rs.graph import LoopConstraint, correct_trajectory
from decod_rs.side_offset import (
    MIN_PAIRS,
    away_from_sensor,
    measure_side_offset,
    without_offset,
)

AXIS = np.array([1.0, 0.0, 0.0])


def _pose(x: float) -> np.ndarray:
    pose = np.eye(4)
    pose[0, 3] = x
    return pose


def _corridor(
    offset_m: float, noise_m: float, scale: float, seed: int, length_m: float = 40.0
) -> tuple[np.ndarray, list[np.ndarray], list[LoopConstraint]]:
    """A straight corridor driven along x: anchors every 1 m (true), rings every 1.5 m seen
    from up to 8 m either side, each view placed ``offset_m`` away from its anchor along the
    axis plus ``noise_m`` of detection noise; the odometry's anchors ``scale`` times as far
    apart as the true ones. Sequential factors between consecutive views of each ring."""
    rng = np.random.default_rng(seed)
    anchors = np.arange(0.0, length_m + 1e-9, 1.0)
    rings = np.arange(0.75, length_m, 1.5)
    odom = [_pose(scale * a) for a in anchors]
    views: dict[int, list[tuple[int, np.ndarray]]] = {j: [] for j in range(rings.size)}
    for i, a in enumerate(anchors):
        for j, ring in enumerate(rings):
            r = ring - a
            if 0.2 < abs(r) <= 8.0:
                x = r + offset_m * np.sign(r) + rng.normal(0.0, noise_m)
                # The contour's centre sits above the sensor in a tunnel: the side is read
                # along the axis only.
                views[j].append((i, np.array([x, 0.02, 1.4])))
    constraints = [
        LoopConstraint(
            query_index=ib,
            db_index=ia,
            query_origin=ob,
            query_axis=AXIS,
            db_origin=oa,
            db_axis=AXIS,
            kind="sequential",
            sigma_m=0.01,
        )
        for seen in views.values()
        for (ia, oa), (ib, ob) in itertools.pairwise(seen)
    ]
    return anchors, odom, constraints


@pytest.mark.parametrize("scale", [0.85, 1.0, 1.1])
def test_the_offset_is_measured_whatever_the_odometry_scale(scale: float) -> None:
    # A 3 cm step (the 8 m horseshoe measured 3-5 cm with the ground truth) and 1 cm of
    # detection noise: 26 straddling pairs, each measuring the offset to about 1 cm, so the
    # median to about 0.3 cm; the odometry's 15 % error between anchors (15 cm) cancels.
    _, odom, constraints = _corridor(0.03, 0.01, scale, seed=3)
    side = measure_side_offset(constraints, odom)
    assert side.pairs >= MIN_PAIRS
    assert side.applied
    assert side.offset_m == pytest.approx(0.03, abs=3 * side.sigma_m + 1e-3)
    assert side.sigma_m < 0.005


def test_no_offset_is_not_applied_and_leaves_the_factors_alone() -> None:
    # A pipe's grooves: seen alike from both sides.
    _, odom, constraints = _corridor(0.0, 0.01, 0.95, seed=5)
    side = measure_side_offset(constraints, odom)
    assert abs(side.offset_m) < 3 * side.sigma_m
    assert not side.applied
    assert without_offset(constraints, side) == constraints


def test_an_offset_towards_the_sensor_is_measured_but_not_removed() -> None:
    # Occlusion only places a boundary away from the sensor; a reading the other way (a
    # rebuilt round's range-dependent error) keeps the factors as they are.
    _, odom, constraints = _corridor(-0.03, 0.01, 1.0, seed=3)
    side = measure_side_offset(constraints, odom)
    assert side.offset_m == pytest.approx(-0.03, abs=3 * side.sigma_m + 1e-3)
    assert not side.applied
    assert without_offset(constraints, side) == constraints


def test_too_few_straddling_pairs_measure_nothing() -> None:
    _, odom, constraints = _corridor(0.05, 0.0, 1.0, seed=1, length_m=6.0)
    side = measure_side_offset(constraints, odom)
    assert side.pairs < MIN_PAIRS and not side.applied
    assert side.report()["sigma_m"] is None  # JSON-safe: no infinity


def test_away_from_sensor_follows_the_axis_not_the_centre_height() -> None:
    up = np.array([0.0, 0.0, 1.0])
    assert np.allclose(away_from_sensor(np.array([2.0, 0.0, 1.5]), AXIS), AXIS)
    assert np.allclose(away_from_sensor(np.array([-2.0, 0.0, 1.5]), AXIS), -AXIS)
    # An axis given the other way round points the same way.
    assert np.allclose(away_from_sensor(np.array([2.0, 0.0, 1.5]), -AXIS), AXIS)
    assert np.allclose(away_from_sensor(np.array([0.0, 3.0, 0.0]), up), np.zeros(3))


def test_the_graph_no_longer_stretches_the_pass() -> None:
    # Odometry exact, every view 3 cm away from its anchor: the sequential factors say the
    # corridor is longer than it is by 2 x 3 cm per straddle, and the graph, weighing them
    # against the odometry, puts the far end 4-5 cm long (0.1 %). With the offset removed it
    # stays where the odometry (here the truth) has it, within a few millimetres.
    cfg = load_config(preset="tunnel").graph
    anchors, odom, constraints = _corridor(0.03, 0.002, 1.0, seed=7)
    stamps = anchors.copy()  # one scan per anchor, 1 s apart
    poses = np.stack(odom)
    side = measure_side_offset(constraints, odom)
    assert side.applied

    def far_end(cs: list[LoopConstraint]) -> float:
        out = correct_trajectory(stamps, poses, stamps, cs, cfg)
        return float(out.poses[-1][0, 3] - poses[-1][0, 3])

    stretched = far_end(constraints)
    fixed = far_end(without_offset(constraints, side))
    assert stretched > 0.03  # the step read as scale: centimetres over 40 m
    assert abs(fixed) < 0.25 * stretched, (stretched, fixed)
