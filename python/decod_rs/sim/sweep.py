"""A scan as a real LiDAR takes it: one sweep of ``SCAN_PERIOD_S`` while the vehicle moves.

Without it every point of a scan is measured from the pose at the scan stamp. A spinning
sensor fires its columns one after the other over the 0.1 s of a turn, a rosette its rays
in the order of its pattern, and each point is reported in the sensor's frame *at the
moment it was measured*; the driver stamps the cloud at the sweep's start and gives every
point its time since then (Ouster's ``t``, nanoseconds). A consumer that takes all points
as seen from the stamp's pose (no deskewing) sees the world sheared by the distance driven
within the sweep: 0.13 m at 1.3 m/s, along the corridor axis, which is the direction the
boundaries are measured in.

:func:`swept_points` casts every ray of a scan from the pose interpolated at the ray's own
time (translation linear, rotation along the geodesic between the scan's pose and the next),
all in one call, and returns the points in the frame of the pose each was measured from,
with their times as the drivers report them (whole ns): a spinning sensor's column time, a
rosette's ray time. In a curving corridor (:mod:`decod_rs.sim.bend`) the rays are cast in
the straight world, as a scan from one pose is, and each point is bent and seen from the
bent pose at its time.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.bend import Bend
from decod_rs.sim.fields import F64
from decod_rs.sim.sensors import SCAN_PERIOD_S, SensorSpec


def ray_times_s(spec: SensorSpec, n_rays: int) -> F64:
    """Each ray's time since the sweep's start (s), in the order of
    :func:`decod_rs.sim.sensors.ray_directions`: a spinning sensor's beams fire together per
    column, a rosette's rays one after the other."""
    if spec.pattern == "spinning" and spec.beams > 0:
        columns = max(n_rays // spec.beams, 1)
        return np.repeat(np.arange(columns) / columns, spec.beams)[:n_rays] * SCAN_PERIOD_S
    return np.arange(n_rays) / max(n_rays, 1) * SCAN_PERIOD_S


def _rotations_exp(w: F64, fractions: F64) -> F64:
    """Rodrigues for many angles about one axis: the rotations of ``fractions[i] * w``
    (``w`` (3,), ``fractions`` (T,)), (T, 3, 3)."""
    angle = float(np.linalg.norm(w))
    k = np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
    s = np.asarray(fractions, dtype=np.float64)[:, None, None]
    if angle < 1e-12:
        return np.eye(3) + s * k
    a = np.sin(s * angle) / angle
    b = (1.0 - np.cos(s * angle)) / angle**2
    return np.eye(3) + a * k + b * (k @ k)


def _rotation_log(r: F64) -> F64:
    """The rotation vector of ``r`` (angles below pi)."""
    cos = float(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0))
    angle = float(np.arccos(cos))
    v = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    if angle < 1e-9:
        return 0.5 * v
    return angle / (2.0 * np.sin(angle)) * v


def poses_between(a: F64, b: F64, fractions: F64) -> F64:
    """The poses (T, 4, 4) at ``fractions`` (T,) of the way from ``a`` to ``b`` (4x4 each)."""
    s = np.asarray(fractions, dtype=np.float64)
    out = np.tile(np.eye(4), (s.size, 1, 1))
    out[:, :3, :3] = a[:3, :3] @ _rotations_exp(_rotation_log(a[:3, :3].T @ b[:3, :3]), s)
    out[:, :3, 3] = (1.0 - s[:, None]) * a[:3, 3] + s[:, None] * b[:3, 3]
    return out


def swept_points(
    poses: F64,
    k: int,
    dirs_body: F64,
    spec: SensorSpec,
    measure_from: Callable[[F64, F64], tuple[F64, NDArray[np.float32], NDArray[np.bool_]]],
    curve: tuple[Bend, float, float | None] | None = None,
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint32]]:
    """Scan ``k`` swept (module docs): ``poses`` (N, 4, 4) at the scan stamps (the last scan
    sweeps on along the step before it), ``dirs_body`` (M, 3) the rays, ``measure_from(origins,
    dirs_world) -> (points_world, intensity, kept)`` the cast and measurement of every ray from
    its own origin (M, 3), ``kept`` (M,) the rays that returned a point; ``curve`` the bend
    (``poses`` straight) with the corridor's radius and floor height, for what its inside
    wall hides (:meth:`~decod_rs.sim.bend.Bend.in_sight`).
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
    # One pose per distinct time (a spinning sensor's column), then one per ray.
    distinct, ray_of = np.unique(times, return_inverse=True)
    at = poses_between(start, end, distinct / SCAN_PERIOD_S)
    rot_t, origin_t = at[:, :3, :3], at[:, :3, 3]
    dirs_world = np.einsum("nij,nj->ni", rot_t[ray_of], dirs_body)
    pts_w, inten, kept = measure_from(origin_t[ray_of], dirs_world)
    ray_of, times = ray_of[kept], times[kept]
    if curve is not None:
        bend, radius_m, floor_z_m = curve
        pts_w = bend.points(pts_w)
        bent = bend.poses(at)
        rot_t, origin_t = bent[:, :3, :3], bent[:, :3, 3]
        seen = bend.in_sight(origin_t[ray_of], pts_w, radius_m, floor_z_m)
        pts_w, inten, ray_of, times = pts_w[seen], inten[seen], ray_of[seen], times[seen]
    pts_b = np.einsum("nji,nj->ni", rot_t[ray_of], pts_w - origin_t[ray_of])
    stamp_ns = np.round(times * 1e9).astype(np.uint32)
    return pts_b.astype(np.float32), inten.astype(np.float32), stamp_ns
