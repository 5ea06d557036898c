"""Drifting odometry: ground truth composed with a slowly varying error that lives mostly
along the corridor axis, as LiDAR odometry drifts in a degenerate corridor (the walls
constrain lateral motion and attitude; nothing constrains the axial translation).

Error model, all as functions of the travelled distance ``d`` (no drift while standing still):

- axial: ``e_x(d) = a * (integral of s(d) dx + W(d)) + (E_x - a * raw(D)) * d / D``, i.e. a
  slowly varying scale error ``s(d)`` (mean ~1 %, varying over ~5 m), a smoothed random walk
  ``W`` (correlation ~1 m), and a constant creep that brings the endpoint exactly to ``E_x``;
  ``a`` scales the random part to at most half the endpoint error;
- yaw and pitch: random-walk bridges of ~``2 mrad * sqrt(E / 1 m)`` (yaw) and half that
  (pitch), applied in the world frame; the lateral/vertical position errors are their
  integrals along the path (the odometry map bends consistently), capped at 20 % of ``E``;
- ``E_x`` is chosen so the endpoint translation error ``|p_odom - p_gt|`` at the last stamp
  equals the requested ``endpoint_m`` exactly (to float precision).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from decod_rs.sim.fields import F64
from decod_rs.sim.trajectory import rot_y, rot_z

DRIFT_PRESETS: dict[str, float] = {
    # hume_02, hume_03 and hume_01 of the paper's pipe table (endpoint errors, metres).
    "none": 0.0,
    "low": 0.2,
    "medium": 1.7,
    "high": 13.3,
}


def resolve_drift(drift: float | str) -> float:
    """Endpoint error in metres from a number or a preset name (``DRIFT_PRESETS``)."""
    if isinstance(drift, str):
        if drift in DRIFT_PRESETS:
            return DRIFT_PRESETS[drift]
        try:
            drift = float(drift)
        except ValueError:
            raise ValueError(
                f"drift must be metres or one of {sorted(DRIFT_PRESETS)}, got {drift!r}"
            ) from None
    value = float(drift)
    if not np.isfinite(value) or value < 0.0:
        raise ValueError(f"drift must be a finite endpoint error >= 0 m, got {value}")
    return value


@dataclass(frozen=True)
class DriftResult:
    """Odometry poses ``(N, 4, 4)`` (frame ``odom`` = world at the first stamp) and the
    realised error components at the last stamp."""

    odom_poses: F64
    endpoint_error_m: float
    endpoint_axial_m: float
    endpoint_lateral_m: float
    max_axial_m: float
    yaw_end_rad: float
    pitch_end_rad: float


def _smoothed_walk(rng: np.random.Generator, d: F64, step: float, corr: float) -> F64:
    """Random walk in distance (unit variance per metre), Gaussian-smoothed over ``corr``."""
    total = float(d[-1]) if d.size else 0.0
    n = max(int(np.ceil(total / step)) + 2, 2)
    grid = np.arange(n) * step
    walk = np.cumsum(rng.standard_normal(n) * np.sqrt(step))
    half = max(int(3 * corr / step), 1)
    k = np.exp(-0.5 * (np.arange(-half, half + 1) * step / corr) ** 2)
    k /= k.sum()
    padded = np.concatenate([np.full(half, walk[0]), walk, np.full(half, walk[-1])])
    smooth = np.convolve(padded, k, mode="valid")
    out = np.interp(d, grid, smooth)
    return out - out[0]


def _bridge(rng: np.random.Generator, d: F64, end: float, corr: float) -> F64:
    walk = _smoothed_walk(rng, d, 0.1, corr)
    total = float(d[-1]) if d[-1] > 0 else 1.0
    span = float(np.max(np.abs(walk))) or 1.0
    return 0.5 * abs(end) * walk / span + (end - 0.5 * abs(end) * walk[-1] / span) * d / total


def drift_odometry(
    gt_poses: F64, travelled_m: F64, endpoint_m: float, rng: np.random.Generator
) -> DriftResult:
    """Apply the drift model to ground-truth ``world_from_body`` poses ``(N, 4, 4)`` sampled
    at scan stamps with travelled distance ``travelled_m (N,)``."""
    n = gt_poses.shape[0]
    if gt_poses.shape != (n, 4, 4) or travelled_m.shape != (n,):
        raise ValueError(
            f"gt_poses must be (N, 4, 4) and travelled_m (N,), got {gt_poses.shape}, "
            f"{travelled_m.shape}"
        )
    if endpoint_m == 0.0 or n < 2 or travelled_m[-1] <= 0:
        return DriftResult(gt_poses.copy(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    d = travelled_m
    dx = np.diff(gt_poses[:, 0, 3], prepend=gt_poses[0, 0, 3])
    # Raw axial process: scale error (mean ~1 %, varying) integrated along x + random walk.
    scale = 0.01 * rng.standard_normal() + 0.005 * _smoothed_walk(rng, d, 0.1, 5.0)
    raw = np.cumsum(scale * dx) + 0.05 * _smoothed_walk(rng, d, 0.05, 1.0)
    raw -= raw[0]

    yaw = _bridge(rng, d, 0.002 * np.sqrt(endpoint_m) * rng.standard_normal(), 5.0)
    pitch = _bridge(rng, d, 0.001 * np.sqrt(endpoint_m) * rng.standard_normal(), 5.0)
    e_y = np.cumsum(yaw * dx)
    e_z = -np.cumsum(pitch * dx)
    lat_end = float(np.hypot(e_y[-1], e_z[-1]))
    cap = 0.2 * endpoint_m
    if lat_end > cap:
        e_y *= cap / lat_end
        e_z *= cap / lat_end
        lat_end = cap
    e_x_end = np.sqrt(max(endpoint_m**2 - lat_end**2, 0.0)) * rng.choice([-1.0, 1.0])
    span = float(np.max(np.abs(raw))) or 1.0
    a = 0.5 * abs(e_x_end) / span
    e_x = a * raw + (e_x_end - a * raw[-1]) * d / d[-1]

    odom = gt_poses.copy()
    err_rot = rot_z(yaw) @ rot_y(pitch)
    odom[:, :3, :3] = err_rot @ gt_poses[:, :3, :3]
    odom[:, :3, 3] = gt_poses[:, :3, 3] + np.stack([e_x, e_y, e_z], axis=1)
    end = float(np.linalg.norm(odom[-1, :3, 3] - gt_poses[-1, :3, 3]))
    return DriftResult(
        odom_poses=odom,
        endpoint_error_m=end,
        endpoint_axial_m=float(e_x[-1]),
        endpoint_lateral_m=lat_end,
        max_axial_m=float(np.max(np.abs(e_x))),
        yaw_end_rad=float(yaw[-1]),
        pitch_end_rad=float(pitch[-1]),
    )
