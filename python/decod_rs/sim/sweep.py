"""A scan as a real LiDAR takes it: one sweep of ``SCAN_PERIOD_S`` while the vehicle moves.

Without it every point of a scan is measured from the pose at the scan stamp. A spinning
sensor fires its columns one after the other over the 0.1 s of a turn, a rosette its rays
in the order of its pattern, and each point is reported in the sensor's frame *at the
moment it was measured*; the driver stamps the cloud at the sweep's start and gives every
point its time since then (Ouster's ``t``, nanoseconds). A consumer that takes all points
as seen from the stamp's pose (no deskewing) sees the world sheared by the distance driven
within the sweep: 0.13 m at 1.3 m/s, along the corridor axis, which is the direction the
boundaries are measured in.

:func:`swept_points` casts the rays of a scan in ``chunks`` groups by time, each from the
pose interpolated at its group's mid time (translation linear, rotation along the geodesic
between the scan's pose and the next), and returns the points in the frame of the pose
each was measured from, with their times. 32 groups quantise the time to 3.1 ms (4 mm at
1.3 m/s).
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.fields import F64
from decod_rs.sim.sensors import SCAN_PERIOD_S, SensorSpec

#: Ray groups per sweep (module docs).
SWEEP_CHUNKS = 32


def ray_times_s(spec: SensorSpec, n_rays: int) -> F64:
    """Each ray's time since the sweep's start (s), in the order of
    :func:`decod_rs.sim.sensors.ray_directions`: a spinning sensor's beams fire together per
    column, a rosette's rays one after the other."""
    if spec.pattern == "spinning" and spec.beams > 0:
        columns = max(n_rays // spec.beams, 1)
        return np.repeat(np.arange(columns) / columns, spec.beams)[:n_rays] * SCAN_PERIOD_S
    return np.arange(n_rays) / max(n_rays, 1) * SCAN_PERIOD_S


def _rotation_exp(w: F64) -> F64:
    """Rodrigues: the rotation of the rotation vector ``w`` (3,)."""
    angle = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    if angle < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(angle) / angle * k + (1.0 - np.cos(angle)) / angle**2 * (k @ k)


def _rotation_log(r: F64) -> F64:
    """The rotation vector of ``r`` (angles below pi)."""
    cos = float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    angle = float(np.arccos(cos))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    return angle / (2.0 * np.sin(angle)) * v


def pose_between(a: F64, b: F64, s: float) -> F64:
    """The pose at fraction ``s`` of the way from ``a`` to ``b`` (4x4 each)."""
    out = np.eye(4)
    out[:3, :3] = a[:3, :3] @ _rotation_exp(s * _rotation_log(a[:3, :3].T @ b[:3, :3]))
    out[:3, 3] = (1.0 - s) * a[:3, 3] + s * b[:3, 3]
    return out


def swept_points(
    poses: F64,
    k: int,
    dirs_body: F64,
    spec: SensorSpec,
    measure_from: Callable[[F64, F64], tuple[F64, NDArray[np.float32]]],
    chunks: int = SWEEP_CHUNKS,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint32]]:
    """Scan ``k`` swept (module docs): ``poses`` (N, 4, 4) at the scan stamps (the last scan
    sweeps on along the step before it), ``dirs_body`` (M, 3) the rays, ``measure_from(origin,
    dirs_world) -> (points_world, intensity)`` one group's cast and measurement.
    Returns the points (float32, each in the frame of its own pose), their intensities and
    their times since the sweep's start (ns)."""
    times = ray_times_s(spec, dirs_body.shape[0])
    if k + 1 < len(poses):
        start, end = poses[k], poses[k + 1]
    elif k > 0:
        # Past the last stamp: the last step continued (its pose relative to the one before).
        start, end = poses[k], poses[k] @ np.linalg.inv(poses[k - 1]) @ poses[k]
    else:
        start = end = poses[k]
    edges = np.linspace(0.0, SCAN_PERIOD_S, chunks + 1)
    group = np.clip(np.searchsorted(edges, times, side="right") - 1, 0, chunks - 1)
    parts_p, parts_i, parts_t = [], [], []
    for g in range(chunks):
        rays = group == g
        if not np.any(rays):
            continue
        mid = 0.5 * (edges[g] + edges[g + 1])
        pose = pose_between(start, end, mid / SCAN_PERIOD_S)
        rot, origin = pose[:3, :3], pose[:3, 3]
        pts_w, inten = measure_from(origin, dirs_body[rays] @ rot.T)
        parts_p.append((pts_w - origin) @ rot)
        parts_i.append(inten)
        parts_t.append(np.full(len(pts_w), round(mid * 1e9), dtype=np.uint32))
    if not parts_p:
        return (
            np.zeros((0, 3), np.float32),
            np.zeros(0, np.float32),
            np.zeros(0, np.uint32),
        )
    return (
        np.concatenate(parts_p).astype(np.float32),
        np.concatenate(parts_i).astype(np.float32),
        np.concatenate(parts_t),
    )
