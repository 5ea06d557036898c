"""Synthetic boundary chains for graph tests: a straight corridor whose boundaries each
anchor sees from behind, tied view to view by sequential factors."""

from __future__ import annotations

import itertools
from collections.abc import Callable
from typing import Any

import numpy as np

from decod_rs.graph import LoopConstraint


def boundary_chain(
    xs: np.ndarray, scale: float, height: Callable[[float], float], **factor: Any
) -> tuple[np.ndarray, list[LoopConstraint]]:
    """Anchors at ``xs`` along world x, the odometry ``scale`` short; a boundary every 1.5 m
    from 3 m to 40 m, seen from the anchors 2-10 m behind it, each view's origin ``height(range)``
    above its anchor; consecutive views of a boundary tied by a sequential factor
    (``factor``: further ``LoopConstraint`` fields)."""
    odom = np.repeat(np.eye(4)[None], xs.size, axis=0)
    odom[:, 0, 3] = xs * (1.0 - scale)
    axis = np.array([1.0, 0.0, 0.0])
    loops = []
    for b in np.arange(3.0, 40.0, 1.5):
        seen = [k for k, x in enumerate(xs) if 2.0 <= b - x <= 10.0]
        views = {k: np.array([b - xs[k], 0.0, height(b - xs[k])]) for k in seen}
        for i, j in itertools.pairwise(seen):
            loops.append(
                LoopConstraint(j, i, views[j], axis, views[i], axis, kind="sequential", **factor)
            )
    return odom, loops
