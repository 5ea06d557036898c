"""The pose graph: the 5-DoF factor's residual and Jacobians, drift correction on a synthetic
corridor, Huber against a wrong loop, scan propagation, exports and TUM files."""

from __future__ import annotations

import json
from dataclasses import replace

import gtsam
import numpy as np
import pytest
from corridor_chains import boundary_chain

import decod_rs
from decod_rs.config import Config
from decod_rs.graph import (
    LoopConstraint,
    correct_trajectory,
    optimize,
    propagate_to_scans,
)
from decod_rs.graph_export import G2O_LANDMARK_TAG, write_g2o, write_graph_json
from decod_rs.landmark_factor import axis_frame, landmark_factor, landmark_residual
from decod_rs.tum import read_tum, so3_exp, write_tum

TUNNEL = decod_rs.load_config(preset="tunnel").graph


def with_(cfg: Config, **changes: object) -> Config:
    return Config({**cfg.to_dict(), **changes})


def yaw(theta: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = so3_exp(np.array([0.0, 0.0, theta]))
    return m


def random_pose(rng: np.random.Generator) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = so3_exp(rng.normal(size=3))
    m[:3, 3] = rng.normal(size=3) * 3.0
    return m


def observe(pose: np.ndarray, point_w: np.ndarray, axis_w: np.ndarray):
    """A world plane (point, axis) in the body frame of ``pose``."""
    inv = np.linalg.inv(pose)
    return inv[:3, :3] @ point_w + inv[:3, 3], pose[:3, :3].T @ axis_w


def corridor(n=300, length=60.0, scale=0.05, n_loops=12, last=0.02):
    """Out along +x and back (heading reversed), odometry stretching the outbound and
    shrinking the return by ``scale`` (so the endpoint drifts 2 * scale * length along x),
    and loops between outbound and return poses that see the same world planes x = const."""
    half = n // 2
    xs = np.concatenate([np.linspace(0, length, half), np.linspace(length, 0, n - half)])
    gt = np.stack([yaw(0.0 if k < half else np.pi) for k in range(n)])
    gt[:, 0, 3] = xs
    odom = [gt[0].copy()]
    for k in range(n - 1):
        rel = np.linalg.inv(gt[k]) @ gt[k + 1]
        rel[:3, 3] *= (1 + scale) if k < half else (1 - scale)
        odom.append(odom[-1] @ rel)
    loops = []
    for x in np.linspace(last * length, (1 - last) * length, n_loops):
        i = int(np.argmin(np.abs(xs[half:] - x))) + half  # query: return traversal
        j = int(np.argmin(np.abs(xs[:half] - x)))
        plane = np.array([x, 0.3, -0.2])  # contour centre off the sensor path
        ci, ai = observe(gt[i], plane, np.array([-1.0, 0, 0]))  # forward-oriented axes:
        cj, aj = observe(gt[j], plane, np.array([1.0, 0, 0]))  # opposite signs
        loops.append(LoopConstraint(i, j, ci, ai, cj, aj, inliers=20, score=0.5))
    return gt, np.stack(odom), loops


def endpoint_error(poses, gt):
    return float(np.linalg.norm(poses[-1, :3, 3] - gt[-1, :3, 3]))


# --- the factor --------------------------------------------------------------------------


def test_jacobians_match_finite_differences():
    rng = np.random.default_rng(1)
    eps = 1e-6
    for _ in range(10):
        ti, tj = random_pose(rng), random_pose(rng)
        ci, cj = rng.normal(size=3), rng.normal(size=3)
        ai, aj = (v / np.linalg.norm(v) for v in rng.normal(size=(2, 3)))
        _, hi, hj = landmark_residual(ti, tj, ci, ai, cj, aj, jacobians=True)
        for which, analytic in ((0, hi), (1, hj)):
            numeric = np.zeros((4, 6))
            for k in range(6):
                d = np.zeros(6)
                d[k] = eps
                poses = [gtsam.Pose3(ti), gtsam.Pose3(tj)]
                plus = [p.matrix() for p in poses]
                minus = [p.matrix() for p in poses]
                plus[which] = poses[which].retract(d).matrix()  # GTSAM's own chart
                minus[which] = poses[which].retract(-d).matrix()
                rp = landmark_residual(*plus, ci, ai, cj, aj)[0]
                rm = landmark_residual(*minus, ci, ai, cj, aj)[0]
                numeric[:, k] = (rp - rm) / (2 * eps)
            # Central differences: truncation ~eps^2, rounding ~1e-16/eps = 1e-10.
            np.testing.assert_allclose(analytic, numeric, atol=1e-7)


def test_factor_in_gtsam_uses_the_same_residual():
    rng = np.random.default_rng(2)
    ti, tj = random_pose(rng), random_pose(rng)
    ci, ai, cj, aj = rng.normal(size=(4, 3))
    lc = LoopConstraint(0, 1, ci, ai, cj, aj)
    graph, values = decod_rs.graph.build_graph(np.stack([ti, tj]), [lc], TUNNEL)
    factor = graph.at(graph.size() - 1)
    expected = landmark_residual(ti, tj, lc.query_origin, lc.query_axis, cj, lc.db_axis)[0]
    # The graph applies the position sigmas along the query's axis and across it, and its
    # factor carries the residual whitened, its norm the Huber loss's (far beyond k here).
    expected[:3] = axis_frame(lc.query_axis) @ expected[:3]
    whitened = expected / lc.sigmas(TUNNEL)
    norm, k = np.linalg.norm(whitened), TUNNEL.huber_k
    assert norm > k
    huber = whitened * np.sqrt(2 * k * norm - k * k) / norm
    np.testing.assert_allclose(factor.unwhitenedError(values), huber, rtol=1e-12)
    np.testing.assert_allclose(
        np.linalg.norm(expected[:3]),
        np.linalg.norm(
            landmark_residual(ti, tj, lc.query_origin, lc.query_axis, cj, lc.db_axis)[0][:3]
        ),
    )


def _separate_factors(loops, cfg):
    """The graph's loops one robust GTSAM factor each, as GTSAM's noise model weighs them:
    the reference the grouped factors are held to."""
    graph = gtsam.NonlinearFactorGraph()
    for lc in loops:
        noise = gtsam.noiseModel.Robust.Create(
            gtsam.noiseModel.mEstimator.Huber.Create(cfg.huber_k),
            gtsam.noiseModel.Diagonal.Sigmas(lc.sigmas(cfg)),
        )
        graph.add(
            landmark_factor(
                lc.query_index,
                lc.db_index,
                lc.query_origin,
                lc.query_axis,
                lc.db_origin,
                lc.db_axis,
                noise,
                frame=axis_frame(lc.query_axis),
            )
        )
    return graph


def test_loops_between_nearby_poses_act_as_one_robust_factor_each():
    """Loops between nearby poses go into one factor (fewer Python calls in the optimiser):
    its error and its linearisation (the normal equations LM steps on) are those of one
    Huber-robust factor per loop, for loops inside and beyond the Huber threshold, whose
    query is either pose, on three poses of which each loop ties two."""
    rng = np.random.default_rng(7)
    poses = np.stack([random_pose(rng) for _ in range(3)])
    loops = []
    pairs = ((0, 1), (1, 0), (0, 1), (2, 1), (1, 2), (0, 2))
    for (qi, di), off in zip(pairs, (0.0, 0.3, 0.01, 0.5, 0.02, 0.0), strict=True):
        point, axis = rng.normal(size=3), rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        ci, ai = observe(poses[qi], point, axis)
        cj, aj = observe(poses[di], point + rng.normal(size=3) * off, axis)
        loops.append(LoopConstraint(qi, di, ci, ai, cj, aj, inliers=20))
    values = gtsam.Values()
    for k, pose in enumerate(poses):
        values.insert(k, gtsam.Pose3(pose))
    grouped = gtsam.NonlinearFactorGraph()
    decod_rs.graph._add_loops(grouped, poses, loops, TUNNEL)
    separate = _separate_factors(loops, TUNNEL)
    assert grouped.size() == 1 and separate.size() == len(loops)  # poses 0-2: one block
    whitened = [
        np.linalg.norm(
            decod_rs.graph._factor_residual(poses, poses, lc, TUNNEL) / lc.sigmas(TUNNEL)
        )
        for lc in loops
    ]
    assert min(whitened) < TUNNEL.huber_k < max(whitened)  # both sides of the kernel
    np.testing.assert_allclose(grouped.error(values), separate.error(values), rtol=1e-12)
    for graph in (grouped, separate):
        assert graph.error(values) > 0
    h_grouped, g_grouped = grouped.linearize(values).hessian()
    h_separate, g_separate = separate.linearize(values).hessian()
    np.testing.assert_allclose(h_grouped, h_separate, rtol=1e-10, atol=1e-9)
    np.testing.assert_allclose(g_grouped, g_separate, rtol=1e-10, atol=1e-9)


def test_grouped_loops_optimise_like_separate_factors():
    """The corridor with each loop seen again from the same poses (a boundary's views from
    one submap pair) and one wrong loop: LM over the grouped factors (several loops between
    two blocks of poses) ends where it ends over one factor per loop."""
    _, odom, loops = corridor()
    i = 200
    wrong = LoopConstraint(
        i,
        60,
        loops[0].query_origin,
        loops[0].query_axis,
        loops[0].db_origin,
        loops[0].db_axis,
        inliers=9,
    )
    shifted = [replace(lc, query_origin=lc.query_origin + 0.01) for lc in loops]
    # And from the next pose (0.2 m on, where the boundary is not: beyond Huber's k).
    nearby = [replace(lc, query_index=lc.query_index + 1) for lc in loops]
    all_loops = [*loops, *shifted, *nearby, wrong]
    grouped, initial = decod_rs.graph.build_graph(odom, all_loops, TUNNEL)
    separate, _ = decod_rs.graph.build_graph(odom, [], TUNNEL)
    separate.push_back(_separate_factors(all_loops, TUNNEL))
    assert grouped.size() < separate.size()
    assert max(len(grouped.at(k).keys()) for k in range(grouped.size())) >= 3
    params = gtsam.LevenbergMarquardtParams()
    ends = [
        gtsam.LevenbergMarquardtOptimizer(graph, initial, params).optimize()
        for graph in (grouped, separate)
    ]
    a, b = (np.stack([v.atPose3(k).matrix() for k in range(odom.shape[0])]) for v in ends)
    assert np.abs(a[:, :3, 3] - odom[:, :3, 3]).max() > 1.0  # the loops moved the poses
    np.testing.assert_allclose(a, b, atol=1e-9)


def consistent_pair(rng):
    ti, tj = random_pose(rng), random_pose(rng)
    point, axis = rng.normal(size=3), rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    ci, ai = observe(ti, point, axis)
    cj, aj = observe(tj, point, axis)
    return ti, tj, ci, ai, cj, aj


def about_line(point_b: np.ndarray, axis_b: np.ndarray, angle: float) -> np.ndarray:
    """A body-frame rotation by ``angle`` about the line through ``point_b`` along ``axis_b``."""
    m = np.eye(4)
    m[:3, :3] = so3_exp(axis_b * angle)
    m[:3, 3] = point_b - m[:3, :3] @ point_b
    return m


def test_residual_zero_roll_free_and_sign_invariant():
    rng = np.random.default_rng(3)
    for _ in range(5):
        ti, tj, ci, ai, cj, aj = consistent_pair(rng)
        res = landmark_residual(ti, tj, ci, ai, cj, aj)[0]
        np.testing.assert_allclose(res, 0.0, atol=1e-12)
        # A wrong pair is not zero (the check above can fail).
        assert np.linalg.norm(landmark_residual(ti, tj, ci + 0.1, ai, cj, aj)[0]) > 0.09
        angle = rng.uniform(0.3, 3.0)
        # Roll of the database pose about the shared axis: residual unchanged.
        tj_rolled = tj @ about_line(cj, aj, angle)
        other = landmark_residual(ti, tj_rolled, ci, ai, cj, aj)[0]
        np.testing.assert_allclose(other, 0.0, atol=1e-12)
        # Roll of the query pose with an offset landmark: the residual vector turns in frame
        # k_i, its norm (the isotropic cost) and delta do not change.
        off = landmark_residual(ti, tj, ci, ai, cj + np.array([0.2, -0.1, 0.05]), aj)[0]
        rolled = landmark_residual(
            ti @ about_line(ci, ai, angle), tj, ci, ai, cj + np.array([0.2, -0.1, 0.05]), aj
        )[0]
        assert np.linalg.norm(off[:3]) > 0.1
        assert np.linalg.norm(rolled[:3]) == pytest.approx(np.linalg.norm(off[:3]), abs=1e-12)
        assert rolled[3] == pytest.approx(off[3], abs=1e-12)
        # Reversed heading: flipping either axis sign changes nothing.
        tilted = so3_exp(np.array([0.05, -0.02, 0.0])) @ aj
        base = landmark_residual(ti, tj, ci, ai, cj, tilted)[0]
        assert base[3] > 1e-4
        np.testing.assert_array_equal(landmark_residual(ti, tj, ci, ai, cj, -tilted)[0], base)
        np.testing.assert_array_equal(landmark_residual(ti, tj, ci, -ai, cj, tilted)[0], base)


# --- the graph ---------------------------------------------------------------------------


def test_residual_refuses_wrong_shapes_by_name():
    with pytest.raises(ValueError, match="world_from_j"):
        landmark_residual(np.eye(4), np.eye(3), np.zeros(3), np.ones(3), np.zeros(3), np.ones(3))
    with pytest.raises(ValueError, match="c_j"):
        landmark_residual(np.eye(4), np.eye(4), np.zeros(3), np.ones(3), np.zeros(2), np.ones(3))


def test_corridor_drift_is_corrected():
    gt, odom, loops = corridor()
    before = endpoint_error(odom, gt)
    assert before == pytest.approx(6.0, rel=1e-6)  # 2 * 5 % * 60 m
    for factor in ("five_dof", "pose3"):
        result = optimize(odom, loops, with_(TUNNEL, loop_factor=factor))
        after = endpoint_error(result.poses, gt)
        assert after <= 0.2 * before, (factor, after)  # the issue's >= 80 % reduction
        assert result.iterations > 0
        assert result.final_error < result.initial_error
        assert np.all(result.loop_weights == 1.0)  # consistent loops end as Huber inliers


def test_reduced_graph_matches_full_graph():
    _, odom, loops = corridor(n=120, n_loops=6)
    full = optimize(odom, loops, TUNNEL, reduce=False)
    reduced = optimize(odom, loops, TUNNEL, reduce=True)
    # Same optimum up to LM's convergence tolerance (both relative error 1e-5).
    np.testing.assert_allclose(reduced.poses, full.poses, atol=1e-3)
    assert reduced.final_error == pytest.approx(full.final_error, rel=1e-3)


def test_no_loop_returns_odometry_bit_for_bit():
    _, odom, _ = corridor(n=50)
    result = optimize(odom, [], TUNNEL)
    assert np.array_equal(result.poses, odom) and result.poses is not odom
    stamps = np.arange(50.0)
    out = correct_trajectory(stamps, odom, stamps[::10], [], TUNNEL)
    assert np.array_equal(out.poses, odom)


def test_wrong_loop_is_down_weighted_by_huber():
    gt, odom, loops = corridor()
    i = 200  # a return pose; its database partner sees the joint 2.4 m further on
    j = int(np.argmin(np.abs(gt[:150, 0, 3] - (gt[i, 0, 3] + 2.4))))
    ci, ai = observe(gt[i], gt[i, :3, 3], np.array([-1.0, 0, 0]))
    cj, aj = observe(gt[j], gt[j, :3, 3], np.array([1.0, 0, 0]))
    wrong = LoopConstraint(i, j, ci, ai, cj, aj, inliers=9)
    clean = optimize(odom, loops, TUNNEL).poses
    robust = optimize(odom, [*loops, wrong], TUNNEL)
    plain = optimize(odom, [*loops, wrong], with_(TUNNEL, huber_k=1e9)).poses
    shift_robust = np.abs(robust.poses[:, :3, 3] - clean[:, :3, 3]).max()
    shift_plain = np.abs(plain[:, :3, 3] - clean[:, :3, 3]).max()
    # Huber caps the wrong loop's pull at that of an inlier with residual k * sigma (6.7 cm).
    # Correct loops ~5 m apart pin the chain (0.05 m/sqrt(m)): each side of the wrong loop
    # gives ~k/sigma * sigma_t^2 * 1.3 m = 0.09 m; measured 0.135 m. Bound 0.2 m; a quadratic
    # loss moves the poses by 1.23 m, so the test fails without the robust kernel.
    assert shift_robust <= 0.2
    assert shift_plain >= 5 * shift_robust
    assert robust.loop_weights[-1] < 0.1
    assert np.all(robust.loop_weights[:-1] > 0.5)


def test_propagation_keeps_nodes_and_is_continuous():
    rng = np.random.default_rng(4)
    scan_st = np.linspace(0.0, 10.0, 101)
    scan = np.stack([random_pose(rng) @ np.eye(4) for _ in range(101)])
    scan[:, :3, 3] = np.column_stack([scan_st, np.zeros(101), np.zeros(101)])
    for k in range(101):
        scan[k, :3, :3] = so3_exp(np.array([0.0, 0.0, 0.01 * k]))
    nodes = np.arange(0, 101, 20)
    correction = np.stack([np.eye(4)] * nodes.size)
    for n in range(nodes.size):
        correction[n, :3, :3] = so3_exp(np.array([0.0, 0.0, 0.02 * n]))
        correction[n, :3, 3] = [0.5 * n, 0.1, 0.0]
    optimised = correction @ scan[nodes]
    out = propagate_to_scans(scan_st, scan, scan_st[nodes], scan[nodes], optimised)
    np.testing.assert_allclose(out[nodes], optimised, atol=1e-12)
    steps = np.linalg.norm(np.diff(out[:, :3, 3], axis=0), axis=1)
    # Continuous: no jump beyond odometry step (0.1 m) + correction step per scan
    # (0.5 m / 20 scans) + the rotation's lever arm (0.02 rad * 10 m / 20 scans).
    assert steps.max() <= 0.1 + 0.025 + 0.01 + 1e-9


def _straight(x: np.ndarray) -> np.ndarray:
    poses = np.stack([np.eye(4)] * x.size)
    poses[:, 0, 3] = x
    return poses


def test_propagation_leaves_a_robot_at_rest_where_it_stood():
    # 2 s at rest, then 1 m/s; the odometry 5 % short, the nodes (at rest, 1 m and 2 m)
    # corrected to the true positions. Blended by stamp, the correction between the node at
    # rest and the first moving one would creep into the rest.
    stamps = np.arange(0.0, 4.01, 0.1)
    truth = np.clip(stamps - 2.0, 0.0, None)
    odom = _straight(0.95 * truth)
    nodes = np.array([10, 30, 40])
    out = propagate_to_scans(stamps, odom, stamps[nodes], odom[nodes], _straight(truth[nodes]))
    np.testing.assert_allclose(out[:21, 0, 3], 0.0, atol=1e-12)
    # Between the moving nodes the odometry's travel and the stamps agree: the true positions.
    np.testing.assert_allclose(out[20:, 0, 3], truth[20:], atol=1e-9)


def test_propagation_does_not_depend_on_the_order_the_scans_come_in():
    stamps = np.arange(0.0, 4.01, 0.1)
    truth = np.clip(stamps - 2.0, 0.0, None)
    odom = _straight(0.95 * truth)
    nodes = np.array([10, 30, 40])
    corrected = _straight(truth[nodes])
    ordered = propagate_to_scans(stamps, odom, stamps[nodes], odom[nodes], corrected)
    perm = np.random.default_rng(3).permutation(stamps.size)
    shuffled = propagate_to_scans(stamps[perm], odom[perm], stamps[nodes], odom[nodes], corrected)
    np.testing.assert_allclose(shuffled, ordered[perm], atol=1e-12)


def test_propagation_follows_the_stamps_where_the_odometry_stalled():
    # The odometry saw 2 % of a 2 m advance between two nodes, all of it in the first scan:
    # its travel says nothing of where the robot moved, so the stamps decide.
    stamps = np.arange(0.0, 2.01, 0.1)
    odom_x = np.full(stamps.size, 0.04)
    odom_x[0] = 0.0
    nodes = np.array([0, 20])
    corrected = _straight(np.array([0.0, 2.0]))
    out = propagate_to_scans(
        stamps, _straight(odom_x), stamps[nodes], _straight(odom_x[nodes]), corrected
    )
    # Each scan keeps its odometry relative to the nodes' corrections, blended by stamp.
    expected = (1.0 - stamps / 2.0) * odom_x + stamps / 2.0 * (odom_x + 2.0 - 0.04)
    np.testing.assert_allclose(out[:, 0, 3], expected, atol=1e-9)
    assert out[10, 0, 3] == pytest.approx(1.02)  # halfway in time, not at the stall's end


def test_correct_trajectory_at_both_granularities():
    gt, odom, node_loops = corridor()
    stamps = np.arange(odom.shape[0]) * 0.5
    anchor_idx = sorted({lc.query_index for lc in node_loops} | {lc.db_index for lc in node_loops})
    index = {k: n for n, k in enumerate(anchor_idx)}
    loops = [
        LoopConstraint(
            index[lc.query_index],
            index[lc.db_index],
            lc.query_origin,
            lc.query_axis,
            lc.db_origin,
            lc.db_axis,
        )
        for lc in node_loops
    ]
    for granularity in ("submap", "scan"):
        out = correct_trajectory(
            stamps, odom, stamps[anchor_idx], loops, with_(TUNNEL, granularity=granularity)
        )
        assert out.poses.shape == odom.shape
        assert endpoint_error(out.poses, gt) <= 0.2 * endpoint_error(odom, gt)


# --- exports and files -------------------------------------------------------------------


def test_g2o_and_json_exports(tmp_path):
    _, odom, loops = corridor(n=40, n_loops=3)
    write_g2o(tmp_path / "g.g2o", odom, loops, TUNNEL)
    lines = (tmp_path / "g.g2o").read_text().splitlines()
    kinds = [line.split()[0] for line in lines]
    assert kinds.count("VERTEX_SE3:QUAT") == 40
    assert kinds.count("EDGE_SE3:QUAT") == 39
    assert kinds.count(G2O_LANDMARK_TAG) == 3
    vertex = [float(v) for v in lines[5].split()[2:]]
    np.testing.assert_allclose(vertex[:3], odom[5, :3, 3], atol=1e-9)
    assert len(lines[41].split()) == 3 + 7 + 21  # tag, ids, measurement, information
    write_g2o(tmp_path / "p.g2o", odom, loops, with_(TUNNEL, loop_factor="pose3"))
    kinds = [line.split()[0] for line in (tmp_path / "p.g2o").read_text().splitlines()]
    assert kinds.count("EDGE_SE3:QUAT") == 39 + 3
    write_graph_json(tmp_path / "g.json", odom, loops, TUNNEL)
    doc = json.loads((tmp_path / "g.json").read_text())
    assert len(doc["poses"]) == 40 and len(doc["odometry"]) == 39 and len(doc["loops"]) == 3
    assert doc["loops"][1]["db_index"] == loops[1].db_index


def test_tum_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(5)
    poses = np.stack([random_pose(rng) for _ in range(20)])
    stamps = 1.7e9 + np.cumsum(rng.uniform(0.05, 0.15, size=20))
    write_tum(tmp_path / "t.tum", stamps, poses)
    st, back = read_tum(tmp_path / "t.tum")
    np.testing.assert_allclose(st, stamps, atol=1e-9, rtol=0)
    np.testing.assert_allclose(back, poses, atol=1e-9)
    bad = tmp_path / "bad.tum"
    bad.write_text("# header\n0.0 0 0 0 0 0 0 1\n0.1 0 0 0 0 0 0.5 1\n")
    with pytest.raises(ValueError, match=r"bad\.tum:3: quaternion norm"):
        read_tum(bad)
    bad.write_text("0.0 0 0 0 0 0 0 1\n0.1 0 0 x 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.tum:2: not a number"):
        read_tum(bad)
    bad.write_text("0.0 0 0 0 0 0 0 1\n0.0 0 0 0 0 0 0 1\n")
    with pytest.raises(ValueError, match=r"bad\.tum:2: stamp"):
        read_tum(bad)
    with pytest.raises(FileNotFoundError):
        read_tum(tmp_path / "missing.tum")


def _tilting_views(scale: float, bias_per_m: float) -> tuple[np.ndarray, list[LoopConstraint]]:
    """A straight 40 m corridor along x (poses every 2 m, the odometry ``scale`` short) and
    every boundary (every 1.5 m) seen from the anchors 2-10 m behind it, its origin placed
    ``bias_per_m`` high per metre of distance (an axis estimate pitched that much)."""
    return boundary_chain(np.arange(0.0, 40.0, 2.0), scale, lambda r: bias_per_m * r)


def test_landmark_factors_do_not_tilt_the_trajectory_away_from_gravity() -> None:
    # Views of a boundary from farther away placed it higher (1 cm per metre): chained
    # along the pass, the factors say the corridor climbs. The odometry's gravity says it
    # does not; with its roll and pitch held (graph.odom_attitude_sigma_rad) the corrected
    # trajectory climbs a sixth as much, and the 3 % scale error is corrected either way.
    odom, loops = _tilting_views(scale=0.03, bias_per_m=0.01)
    free = optimize(odom, loops, with_(TUNNEL, odom_attitude_sigma_rad=1e3)).poses
    held = optimize(odom, loops, TUNNEL).poses
    climb_free, climb_held = np.max(np.abs(free[:, 2, 3])), np.max(np.abs(held[:, 2, 3]))
    assert climb_free > 0.25, climb_free  # 0.33 m over 38 m
    assert climb_held < 0.25 * climb_free, (climb_held, climb_free)  # 0.05 m
    # The odometry says 36.9 m of the 38 m; the boundaries put the end within 0.25 m.
    for poses in (free, held):
        assert abs(poses[-1, 0, 3] - 38.0) < 0.25, poses[-1, 0, 3]
