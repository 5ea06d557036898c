"""How much the robot's path curves: whether ``auto`` fits curved centre lines (beyond the
paper).

Where a tunnel or a pipe curves, a submap's fitted axis is the chord of the stretch in range
and a boundary seen far from the middle of it gets an origin off the centre line and the chord
for its axis (``src/centre_line.rs``); the boundary factors then straighten the corrected
trajectory. The fix, a parabola fitted to the centre line in each submap, must not run on
straight corridors, where it reads the wall's pattern of visibility as a curve. The robot's
own path tells the two apart: it follows the corridor, and the odometry measures its heading
well (the walls constrain the attitude; only the distance along the axis drifts).

:func:`path_curvature` resamples the path every :data:`STEP_M` metres, splits it where the
direction of travel reverses (the turnaround, in either return mode), and measures the turn
of the direction over windows of ``window_m`` metres of each pass (the slopes of straight
lines fitted to the heading and the climb along the window); the figure is their 75th
percentile (a log that curves over a quarter of its length counts as curved). The robot's
steering wobble (the simulated crawlers turn +-1-2 deg every few metres) averages out of a
line over many samples; comparing the mean directions of the window's first and last
quarters instead, a straight 4 m horseshoe read 0.0016 /m over 20 m windows, 0.93 of its
threshold. Windows are the stretch a submap sees (:mod:`decod_rs.autoscale`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

#: Path resampling step, metres.
STEP_M = 0.25
#: The percentile of the windows' curvatures that is the log's.
PERCENTILE = 75.0

__all__ = ["PERCENTILE", "STEP_M", "path_curvature", "path_length", "points_along"]


def path_length(positions: FloatArray) -> FloatArray:
    """``(N,)`` distance travelled along ``positions`` (N, 3) up to each, metres (0 first)."""
    steps = np.linalg.norm(np.diff(np.asarray(positions, dtype=np.float64), axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def points_along(positions: FloatArray, lengths: FloatArray, at: FloatArray) -> FloatArray:
    """``(M, 3)`` points of the path ``positions`` (N, 3), whose travel to each is ``lengths``
    (:func:`path_length`), at the travels ``at`` (M,), linearly between its points and
    clamped at its ends."""
    return np.column_stack([np.interp(at, lengths, positions[:, i]) for i in range(3)])


def path_curvature(positions: FloatArray, window_m: float) -> float:
    """The path's curvature (1/m) by the module's rule; 0 for a path shorter than one
    window in every pass. ``positions``: (N, 3) in time order."""
    p = np.asarray(positions, dtype=np.float64)
    if p.ndim != 2 or p.shape[0] < 3 or not window_m > 0:
        return 0.0
    s = path_length(p)
    grid = np.arange(0.0, s[-1], STEP_M)
    if grid.size < 3:
        return 0.0
    q = points_along(p, s, grid)
    t = np.gradient(q, axis=0)
    t /= np.linalg.norm(t, axis=1, keepdims=True) + 1e-12
    reversals = np.flatnonzero(np.einsum("ij,ij->i", t[1:], t[:-1]) < 0.0) + 1
    n = int(window_m / STEP_M)
    found: list[float] = []
    for run in np.split(np.arange(grid.size), reversals):
        if run.size <= n:
            continue
        # Heading and climb along the pass (unwrapped), each a line over every window.
        yaw = np.unwrap(np.arctan2(t[run, 1], t[run, 0]))
        pitch = np.arcsin(np.clip(t[run, 2], -1.0, 1.0))
        x = STEP_M * np.arange(n)
        for a in range(0, run.size - n, max(n // 4, 1)):
            turn = np.polyfit(x, yaw[a : a + n], 1)[0]
            climb = np.polyfit(x, pitch[a : a + n], 1)[0]
            found.append(float(np.hypot(turn * np.cos(np.mean(pitch[a : a + n])), climb)))
    return float(np.percentile(found, PERCENTILE)) if found else 0.0
