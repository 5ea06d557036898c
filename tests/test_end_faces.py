"""Factors between views of an end face within one pass (:mod:`decod_rs.end_faces`): which
pairs become factors, and that a factor holds the true poses and pulls wrong ones."""

from __future__ import annotations

import numpy as np

from decod_rs.config import load_config
from decod_rs.end_faces import ACROSS_SIGMA_M, FaceView, face_constraints
from decod_rs.landmark_factor import axis_frame, landmark_residual

FACE_X = -1.0  # the face, world frame: the plane x = -1, seen from x > -1


def _pose(x: float, yaw_deg: float = 180.0) -> np.ndarray:
    """A pose at (x, 0.05, 0) heading along -x (towards the face) by default."""
    t = np.deg2rad(yaw_deg)
    pose = np.eye(4)
    pose[:3, :3] = [[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]]
    pose[:3, 3] = [x, 0.05, 0.0]
    return pose


def _view(stamp: float, pose: np.ndarray) -> FaceView:
    """The face as the anchor at ``pose`` measures it: the foot of the sensor on the plane
    and the plane's normal (pointing away from the sensor), anchor frame."""
    rot, t = pose[:3, :3], pose[:3, 3]
    normal_world = np.array([-1.0, 0.0, 0.0])
    foot_world = np.array([FACE_X, t[1], t[2]])
    return FaceView(stamp, rot.T @ (foot_world - t), rot.T @ normal_world)


def _scene(xs: list[float], stamps: list[float]) -> tuple[dict[float, np.ndarray], np.ndarray]:
    anchors = {s: _pose(x) for s, x in zip(stamps, xs, strict=True)}
    return anchors, np.asarray(stamps, dtype=np.float64)


def test_consecutive_views_of_one_pass_become_factors_that_hold_the_true_poses() -> None:
    cfg = load_config(None, "tunnel")
    stamps = [50.0, 53.0, 56.0, 59.0]
    xs = [16.0, 11.5, 7.0, 2.5]
    anchors, anchor_stamps = _scene(xs, stamps)
    views = [_view(s, anchors[s]) for s in stamps]

    def path_at(stamp: float) -> float:
        return 30.0 + (stamp - 50.0) * 1.5

    out = face_constraints(views, anchors, anchor_stamps, path_at, 40.0, cfg, 0.02)
    assert (out.pairs, out.jumps, len(out.constraints)) == (3, 0, 3)
    for c in out.constraints:
        assert c.kind == "sequential" and c.query_index == c.db_index + 1
        assert c.sigma_m == 0.02 and c.sigma_transverse_m == ACROSS_SIGMA_M
        ti, tj = anchors[stamps[c.query_index]], anchors[stamps[c.db_index]]
        res, _, _ = landmark_residual(ti, tj, c.query_origin, c.query_axis, c.db_origin, c.db_axis)
        assert np.allclose(res, 0.0, atol=1e-12), res
        # The later anchor placed 0.3 m short along the axis: the residual is the 0.3 m,
        # along the axis, which the factor's frame reads as its first component.
        short = ti.copy()
        short[0, 3] += 0.3
        res, _, _ = landmark_residual(
            short, tj, c.query_origin, c.query_axis, c.db_origin, c.db_axis
        )
        along = axis_frame(c.query_axis) @ res[:3]
        assert abs(abs(along[0]) - 0.3) < 1e-9 and np.allclose(along[1:], 0.0, atol=1e-9)


def test_pairs_across_passes_at_a_standstill_or_that_jump_are_not_factors() -> None:
    cfg = load_config(None, "tunnel")
    stamps = [10.0, 12.0, 12.5, 50.0, 53.0]
    xs = [2.0, 5.0, 5.0, 9.0, 4.5]
    anchors, anchor_stamps = _scene(xs, stamps)
    views = [_view(s, anchors[s]) for s in stamps]
    # The anchor at 53 s sees a face 2 m nearer than the one there: another face, or a
    # wrong one; the odometry over 4.5 m allows far less.
    views[4] = FaceView(53.0, views[4].point - 2.0 * views[4].normal, views[4].normal)
    path = {10.0: 0.0, 12.0: 3.0, 12.5: 3.0, 50.0: 40.0, 53.0: 44.5}
    out = face_constraints(views, anchors, anchor_stamps, path.__getitem__, 30.0, cfg, 0.02)
    # 10 -> 12 is a factor; 12 -> 12.5 is a standstill; 12.5 -> 50 spans the split; 50 -> 53
    # jumps.
    assert (out.pairs, out.jumps, len(out.constraints)) == (2, 1, 1)
    assert (out.constraints[0].db_index, out.constraints[0].query_index) == (0, 1)
    # Without a split (one pass) the pair across the turn is a factor like any other.
    one_pass = face_constraints(views, anchors, anchor_stamps, path.__getitem__, None, cfg, 0.02)
    assert one_pass.pairs == 3 and len(one_pass.constraints) == 2


def test_a_robot_moving_across_the_corridor_is_not_a_jump() -> None:
    # The feet of the sensor on the face move with the robot across the corridor (2.45 m
    # here, a wide tunnel), more than the odometry's allowance over 3 m of path: only the
    # distance along the face's normal is compared.
    cfg = load_config(None, "tunnel")
    anchors = {10.0: _pose(10.0), 13.0: _pose(7.0)}
    anchors[13.0][1, 3] = 2.5
    stamps = np.array([10.0, 13.0])
    views = [_view(s, anchors[s]) for s in (10.0, 13.0)]
    path = {10.0: 0.0, 13.0: 3.0}
    allowance = cfg.matching.consistency_tolerance_m + cfg.matching.consistency_drift_fraction * 3
    assert allowance < 2.45
    out = face_constraints(views, anchors, stamps, path.__getitem__, None, cfg, 0.02)
    assert (out.pairs, out.jumps, len(out.constraints)) == (1, 0, 1)
