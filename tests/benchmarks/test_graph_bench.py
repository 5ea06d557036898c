"""Pose-graph optimisation time (pytest-benchmark; ``make bench``). Without
``--benchmark-enable`` each case runs once as a test.

The issue's figure: a 10,000-pose graph with 500 landmark factors (a straight out-and-back
corridor with 5 % scale drift, loops every ~4 m), solved with the default chain reduction.
"""

from __future__ import annotations

import numpy as np
import pytest

import decod_rs
from decod_rs.config import Config
from decod_rs.graph import LoopConstraint, optimize

TUNNEL = decod_rs.load_config(preset="tunnel").graph


def corridor(n: int, n_loops: int, length: float):
    half = n // 2
    xs = np.concatenate([np.linspace(0, length, half), np.linspace(length, 0, n - half)])
    gt = np.stack([np.eye(4)] * n)
    gt[half:, :2, :2] = [[-1.0, 0.0], [0.0, -1.0]]  # heading reversed on the return
    gt[:, 0, 3] = xs
    rel = np.linalg.inv(gt[:-1]) @ gt[1:]
    rel[:half, :3, 3] *= 1.05
    rel[half:, :3, 3] *= 0.95
    odom = [gt[0]]
    for r in rel:
        odom.append(odom[-1] @ r)
    loops = []
    for x in np.linspace(0.01 * length, 0.99 * length, n_loops):
        i = int(np.argmin(np.abs(xs[half:] - x))) + half
        j = int(np.argmin(np.abs(xs[:half] - x)))
        inv_i, inv_j = np.linalg.inv(gt[i]), np.linalg.inv(gt[j])
        p = np.array([x, 0.0, 0.0, 1.0])
        loops.append(
            LoopConstraint(
                i, j, (inv_i @ p)[:3], inv_i[:3, 0], (inv_j @ p)[:3], inv_j[:3, 0], 20, 0.5
            )
        )
    return gt, np.stack(odom), loops


@pytest.mark.parametrize("loop_factor", ["five_dof", "pose3"])
@pytest.mark.parametrize(("n", "n_loops"), [(300, 10), (10_000, 500)])
def test_optimize(benchmark, n, n_loops, loop_factor):
    gt, odom, loops = corridor(n, n_loops, length=n * 0.2)
    cfg = Config({**TUNNEL.to_dict(), "loop_factor": loop_factor})
    result = benchmark.pedantic(optimize, args=(odom, loops, cfg), rounds=3 if n < 1000 else 1)
    before = np.linalg.norm(odom[-1, :3, 3] - gt[-1, :3, 3])
    after = np.linalg.norm(result.poses[-1, :3, 3] - gt[-1, :3, 3])
    assert after <= 0.2 * before
