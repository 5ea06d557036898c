"""Drifting odometry: ground truth composed with a slowly varying error that lives mostly
along the corridor axis, as LiDAR odometry drifts in a degenerate corridor (the walls
constrain lateral motion and attitude; nothing constrains the axial translation).

Two models, chosen by a *profile* (``drift=`` of the simulator, :func:`odometry_for_profile`):

**Endpoint model** (a number of metres, or a preset of ``DRIFT_PRESETS``: ``none``, ``low``,
``medium``, ``high``). All as functions of the travelled distance ``d`` (no drift while
standing still):

- axial: ``e_x(d) = a * (integral of s(d) dx + W(d)) + (E_x - a * raw(D)) * d / D``, i.e. a
  slowly varying scale error ``s(d)`` (mean ~1 %, varying over ~5 m), a smoothed random walk
  ``W`` (correlation ~1 m), and a constant creep that brings the endpoint exactly to ``E_x``;
  ``a`` scales the random part to at most half the endpoint error;
- yaw and pitch: random-walk bridges of ~``2 mrad * sqrt(E / 1 m)`` (yaw) and half that
  (pitch), applied in the world frame; the lateral/vertical position errors are their
  integrals along the path (the odometry map bends consistently), capped at 20 % of ``E``;
- ``E_x`` is chosen so the endpoint translation error ``|p_odom - p_gt|`` at the last stamp
  equals the requested ``endpoint_m`` exactly (to float precision). The error is symmetric in
  the sense that nothing distinguishes the two legs.

**Leg-scale model** (``"legs:OUT,RET"``, e.g. ``"legs:-0.05,-0.15"``): the odometry measures
every displacement of the outbound leg scaled by ``1 + OUT`` and every displacement of the
return leg by ``1 + RET`` (``-0.05``: it reports 95 % of the distance driven), as a LiDAR
odometry whose axial under-estimate depends on the direction of travel (sensor looking
forward on one leg and backward on the other, a different speed). The legs are split at the
turnaround: ``split_index`` (the simulator passes the far-end arrival scan of the
trajectory; by default the scan farthest from the start). Added to the scale error, all
functions of the travelled distance ``d`` and seeded:

- an axial random walk of ``1 cm / sqrt(m)`` (smoothed over ~1 m);
- yaw and pitch random walks of ``0.1 mrad / sqrt(m)`` and ``0.05 mrad / sqrt(m)`` (smoothed
  over ~5 m), applied in the world frame as in the endpoint model, with their integrals along
  the path as lateral/vertical position error.

With a one-way length ``L`` the axial error is ``OUT * L`` at the turnaround and
``(OUT - RET) * L`` at the end (``legs:-0.05,-0.15``: -5 % of ``L`` at the far end, ``+0.10
L`` back at the start), plus the random walk.

**Slip model** (``"slip:LO,HI"``, e.g. ``"slip:-0.15,-0.01"``): the scale error changes along
the way, as wheels slip more on some stretches of a pipe than on others, or a LiDAR odometry
under-reads featureless stretches more than those with fittings. The path is cut into sections
of 3-15 m of travel (seeded), each with a scale error drawn uniformly in ``[LO, HI]``, blended
over about half a metre; the random walks are the leg model's. No scale holds for a whole leg,
so neither a scale per pass nor the far end's position describes the error.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

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


LEGS_PREFIX = "legs:"
SLIP_PREFIX = "slip:"


def resolve_drift(drift: float | str) -> float:
    """Endpoint error in metres from a number or a preset name (``DRIFT_PRESETS``)."""
    if isinstance(drift, str):
        if drift in DRIFT_PRESETS:
            return DRIFT_PRESETS[drift]
        try:
            drift = float(drift)
        except ValueError:
            raise ValueError(
                f"drift must be metres, one of {sorted(DRIFT_PRESETS)}, "
                f"'{LEGS_PREFIX}OUT,RET' (scale errors per leg) or '{SLIP_PREFIX}LO,HI' (scale "
                f"errors changing along the way), got {drift!r}"
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
    model: str = "endpoint"
    split_index: int | None = None
    turnaround_axial_m: float | None = None


@dataclass(frozen=True)
class LegProfile:
    """The leg-scale model's parameters (module doc): scale errors of the outbound and the
    return leg (``-0.05`` = the odometry reports 95 % of the distance) and the random walks."""

    outbound_scale: float
    return_scale: float
    axial_walk_m_per_sqrt_m: float = 0.01
    yaw_walk_rad_per_sqrt_m: float = 1e-4
    pitch_walk_rad_per_sqrt_m: float = 5e-5

    @property
    def text(self) -> str:
        return f"{LEGS_PREFIX}{self.outbound_scale:g},{self.return_scale:g}"


@dataclass(frozen=True)
class SlipProfile:
    """The slip model's parameters (module doc): the range ``[low, high]`` of the sections'
    scale errors, the sections' lengths in metres of travel, and the leg model's walks."""

    low: float
    high: float
    section_m: tuple[float, float] = (3.0, 15.0)
    blend_m: float = 0.5
    axial_walk_m_per_sqrt_m: float = 0.01
    yaw_walk_rad_per_sqrt_m: float = 1e-4
    pitch_walk_rad_per_sqrt_m: float = 5e-5

    @property
    def text(self) -> str:
        return f"{SLIP_PREFIX}{self.low:g},{self.high:g}"


#: The profiles that are scale errors (not an endpoint error in metres).
ScaleProfile = LegProfile | SlipProfile


def _two_scales(profile: str, prefix: str, example: str) -> tuple[float, float]:
    """The two scale errors after ``prefix`` (finite, > -1), or a ``ValueError`` naming the
    profile."""
    body = profile.strip()[len(prefix) :]
    try:
        a, b = (float(v) for v in body.split(","))
    except ValueError:
        raise ValueError(
            f"drift profile {profile!r}: expected '{prefix}' and two scale errors, e.g. '{example}'"
        ) from None
    if not (np.isfinite(a) and np.isfinite(b) and a > -1.0 and b > -1.0):
        raise ValueError(
            f"drift profile {profile!r}: scale errors must be finite and > -1, got {a}, {b}"
        )
    return a, b


def parse_profile(profile: float | str) -> float | ScaleProfile:
    """A drift profile: an endpoint error in metres (a number or a ``DRIFT_PRESETS`` name),
    a :class:`LegProfile` from ``"legs:OUT,RET"`` or a :class:`SlipProfile` from
    ``"slip:LO,HI"`` (``LO <= HI``)."""
    text = profile.strip() if isinstance(profile, str) else ""
    if text.startswith(LEGS_PREFIX):
        return LegProfile(*_two_scales(text, LEGS_PREFIX, "legs:-0.05,-0.15"))
    if text.startswith(SLIP_PREFIX):
        low, high = _two_scales(text, SLIP_PREFIX, "slip:-0.15,-0.01")
        if low > high:
            raise ValueError(f"drift profile {profile!r}: LO {low:g} is above HI {high:g}")
        return SlipProfile(low, high)
    return resolve_drift(profile)


def turnaround_index(gt_poses: F64) -> int:
    """The scan farthest from the start (the far end of an out-and-back run)."""
    p = gt_poses[:, :3, 3]
    return int(np.argmax(np.linalg.norm(p - p[0], axis=1)))


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


def leg_odometry(
    gt_poses: F64,
    travelled_m: F64,
    profile: LegProfile,
    rng: np.random.Generator,
    split_index: int | None = None,
) -> DriftResult:
    """Apply the leg-scale model (module doc) to ground-truth poses ``(N, 4, 4)`` with
    travelled distance ``travelled_m (N,)``; the outbound leg ends at ``split_index``
    (default: the scan farthest from the start)."""
    n, split = _checked_split(gt_poses, travelled_m, split_index)
    scale = np.where(np.arange(n) <= split, profile.outbound_scale, profile.return_scale)
    return _scaled_odometry(gt_poses, travelled_m, scale, profile, rng, split)


def slip_scale(profile: SlipProfile, travelled_m: F64, rng: np.random.Generator) -> F64:
    """The slip model's scale error at each travelled distance (module doc): sections of
    ``profile.section_m`` metres, each uniform in ``[low, high]``, blended over
    ``profile.blend_m``."""
    total = float(travelled_m[-1]) if travelled_m.size else 0.0
    lo_m, hi_m = profile.section_m
    ends = [0.0]
    while ends[-1] <= total:
        ends.append(ends[-1] + float(rng.uniform(lo_m, hi_m)))
    values = rng.uniform(profile.low, profile.high, len(ends) - 1)
    step = 0.05
    grid = np.arange(0.0, ends[-1] + step, step)
    raw = values[np.clip(np.searchsorted(ends, grid, side="right") - 1, 0, len(values) - 1)]
    half = max(int(3 * profile.blend_m / step), 1)
    kernel = np.exp(-0.5 * (np.arange(-half, half + 1) * step / (profile.blend_m / 2)) ** 2)
    padded = np.concatenate([np.full(half, raw[0]), raw, np.full(half, raw[-1])])
    smooth = np.convolve(padded, kernel / kernel.sum(), mode="valid")
    return np.asarray(np.interp(travelled_m, grid, smooth), dtype=np.float64)


def slip_odometry(
    gt_poses: F64,
    travelled_m: F64,
    profile: SlipProfile,
    rng: np.random.Generator,
    split_index: int | None = None,
) -> DriftResult:
    """Apply the slip model (module doc) to ground-truth poses ``(N, 4, 4)`` with travelled
    distance ``travelled_m (N,)``; ``split_index`` only says where the turnaround's error is
    read (default: the scan farthest from the start)."""
    _, split = _checked_split(gt_poses, travelled_m, split_index)
    scale = slip_scale(profile, travelled_m, rng)
    return replace(
        _scaled_odometry(gt_poses, travelled_m, scale, profile, rng, split), model="slip"
    )


def _checked_split(gt_poses: F64, travelled_m: F64, split_index: int | None) -> tuple[int, int]:
    """The scan count and the last outbound scan, or a ``ValueError`` on bad shapes."""
    n = gt_poses.shape[0]
    if gt_poses.shape != (n, 4, 4) or travelled_m.shape != (n,):
        raise ValueError(
            f"gt_poses must be (N, 4, 4) and travelled_m (N,), got {gt_poses.shape}, "
            f"{travelled_m.shape}"
        )
    split = turnaround_index(gt_poses) if split_index is None else int(split_index)
    if not 0 <= split < max(n, 1):
        raise ValueError(f"split_index must be in [0, {n}), got {split}")
    return n, split


def _scaled_odometry(
    gt_poses: F64,
    travelled_m: F64,
    scale: F64,
    profile: ScaleProfile,
    rng: np.random.Generator,
    split: int,
) -> DriftResult:
    """Ground truth whose every displacement is scaled by ``1 + scale`` (per scan), plus the
    profile's axial, yaw and pitch walks (module doc)."""
    n = gt_poses.shape[0]
    if n < 2 or travelled_m[-1] <= 0:
        return DriftResult(gt_poses.copy(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, "legs", split, 0.0)
    d = travelled_m
    steps = np.diff(gt_poses[:, :3, 3], axis=0, prepend=gt_poses[:1, :3, 3])
    err = np.cumsum(scale[:, None] * steps, axis=0)
    err[:, 0] += profile.axial_walk_m_per_sqrt_m * _smoothed_walk(rng, d, 0.05, 1.0)
    yaw = profile.yaw_walk_rad_per_sqrt_m * _smoothed_walk(rng, d, 0.1, 5.0)
    pitch = profile.pitch_walk_rad_per_sqrt_m * _smoothed_walk(rng, d, 0.1, 5.0)
    err[:, 1] += np.cumsum(yaw * steps[:, 0])
    err[:, 2] -= np.cumsum(pitch * steps[:, 0])

    odom = gt_poses.copy()
    odom[:, :3, :3] = rot_z(yaw) @ rot_y(pitch) @ gt_poses[:, :3, :3]
    odom[:, :3, 3] = gt_poses[:, :3, 3] + err
    return DriftResult(
        odom_poses=odom,
        endpoint_error_m=float(np.linalg.norm(err[-1])),
        endpoint_axial_m=float(err[-1, 0]),
        endpoint_lateral_m=float(np.hypot(err[-1, 1], err[-1, 2])),
        max_axial_m=float(np.max(np.abs(err[:, 0]))),
        yaw_end_rad=float(yaw[-1]),
        pitch_end_rad=float(pitch[-1]),
        model="legs",
        split_index=split,
        turnaround_axial_m=float(err[split, 0]),
    )


def odometry_for_profile(
    gt_poses: F64,
    travelled_m: F64,
    profile: float | str,
    rng: np.random.Generator,
    split_index: int | None = None,
) -> DriftResult:
    """Odometry poses from ground truth for a drift ``profile`` (module doc: metres or a
    preset for the endpoint model, ``"legs:OUT,RET"`` for the leg-scale model, ``"slip:LO,HI"``
    for the slip model), without
    simulating scans: e.g. several odometry TUM files for one simulated log (``decod run
    --odom-tum``). ``split_index``: the last outbound scan (default: the farthest from the
    start); the endpoint model reports the axial error there too."""
    parsed = parse_profile(profile)
    if isinstance(parsed, LegProfile):
        return leg_odometry(gt_poses, travelled_m, parsed, rng, split_index)
    if isinstance(parsed, SlipProfile):
        return slip_odometry(gt_poses, travelled_m, parsed, rng, split_index)
    res = drift_odometry(gt_poses, travelled_m, parsed, rng)
    split = turnaround_index(gt_poses) if split_index is None else int(split_index)
    axial = res.odom_poses[split, 0, 3] - gt_poses[split, 0, 3]
    return replace(res, split_index=split, turnaround_axial_m=float(axial))
