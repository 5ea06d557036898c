"""Pipe scenes: ``hume`` (precast concrete, 0.6 m ID, 2.43 m segments) and ``pe`` (ribbed
polyethylene, 0.4 m, couplers every 6 m).

Joints are nominally identical: every per-joint variation is zero-mean around the
circumference (groove depth/width/centre harmonics, eccentric lips), so the circumferentially
averaged axial profile of two joints is nearly the same, while the unrolled 2D offset maps
differ. ``distinctiveness`` scales every per-joint variation; ``identical`` makes all joints
and segments the same geometry (an aliased pipe).

Every builder starts from its module-level parameter dict (``HUME_PARAMS``, ``PE_PARAMS``)
with the caller's overrides (:func:`hume_params`, :func:`pe_params`, :func:`merge_params`: an
unknown key is a ``ValueError`` listing the valid ones); ``joints.json`` records the result
as ``scene_params``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from decod_rs.sim.changes import CHANGE_PARAMS, apply_changes
from decod_rs.sim.fields import (
    F64,
    Grid2D,
    flat_bump,
    harmonic_series,
    smooth_noise,
)
from decod_rs.sim.surface import (
    KIND_CAP,
    KIND_FLOOR,
    KIND_WALL,
    PatchSet,
    Scene,
    SegmentTable,
    theta_grid,
)

N_THETA_PATCH = 512
#: Fraction of the rays reaching a water surface that return: calm water mirrors a LiDAR's
#: beam away, and the few returns come from foam, debris or turbidity (a sewer's flow).
WATER_RETURN_FRACTION = 0.03
#: The water's reflectivity (intensity of those few returns).
WATER_REFLECTIVITY = 5.0

HUME_PARAMS: dict[str, Any] = {
    "radius_m": 0.3,
    "segment_length_m": 2.43,
    "first_joint_x_m": 1.2,
    "joint_position_jitter_m": 0.002,
    "groove_depth_m": 0.004,
    "groove_width_m": 0.016,
    "groove_depth_var_m": 0.0012,
    "groove_width_var_m": 0.002,
    "groove_centre_var_m": 0.0015,
    "chips_per_joint": 2.0,
    "chip_depth_m": [0.001, 0.002],
    "lip_eccentricity_m": 0.0015,
    "roughness_m": 0.001,
    "roughness_corr_m": 0.012,
    "lateral_connection_every_m": 15.0,
    "lateral_connection_radius_m": 0.075,
    "lateral_connection_depth_m": 0.25,
    "range_noise_m": 0.0015,
    "x_min_m": -0.3,
    "water_depth_m": 0.0,
    **CHANGE_PARAMS,
}

PE_PARAMS: dict[str, Any] = {
    "radius_m": 0.2,
    "segment_length_m": 6.0,
    "ribs_per_segment": 171,
    "rib_height_m": 0.0012,
    "first_joint_x_m": 2.0,
    "joint_position_jitter_m": 0.003,
    "gap_depth_m": 0.005,
    "gap_width_m": 0.02,
    "gap_depth_var_m": 0.0012,
    "gap_width_var_m": 0.003,
    "gap_centre_var_m": 0.002,
    "chips_per_joint": 1.0,
    "chip_depth_m": [0.001, 0.002],
    "lip_eccentricity_m": 0.001,
    "roughness_m": 0.0003,
    "roughness_corr_m": 0.01,
    "range_noise_m": 0.0015,
    "x_min_m": -0.3,
    "water_depth_m": 0.0,
    **CHANGE_PARAMS,
}
#: Per scene, the parameter that sets the spacing of the boundaries (joints, rings, arches).
SPACING_KEYS = {
    "hume": "segment_length_m",
    "pe": "segment_length_m",
    "shield": "ring_width_m",
    "horseshoe": "arch_spacing_m",
}
#: Smallest boundary spacing an override may ask for (m): the joint patches (+-5 cm) and a
#: pipe's lateral connections must fit between two boundaries.
MIN_SPACING_M = 0.5


def _coerce(scene: str, key: str, default: Any, value: Any) -> Any:
    """``value`` in the type of ``default`` (int, float or a list of the same length)."""
    if isinstance(default, list):
        if not isinstance(value, list | tuple) or len(value) != len(default):
            raise ValueError(
                f"{scene} scene parameter {key!r} takes a list of {len(default)} numbers, "
                f"got {value!r}"
            )
        return [float(v) for v in value]
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{scene} scene parameter {key!r} takes a number, got {value!r}") from None
    if not np.isfinite(number):
        raise ValueError(f"{scene} scene parameter {key!r} must be finite, got {value!r}")
    if isinstance(default, int):
        if number != round(number):
            raise ValueError(f"{scene} scene parameter {key!r} takes an integer, got {value!r}")
        return round(number)
    return number


def merge_params(
    scene: str, defaults: dict[str, Any], overrides: dict[str, Any] | None
) -> dict[str, Any]:
    """A fresh copy of ``defaults`` with ``overrides`` applied. An unknown key, a value of the
    wrong type or a non-positive radius/spacing raises ``ValueError`` naming the key (and,
    for an unknown key, listing the valid ones)."""
    p: dict[str, Any] = {k: list(v) if isinstance(v, list) else v for k, v in defaults.items()}
    for key, value in (overrides or {}).items():
        if key not in defaults:
            raise ValueError(
                f"unknown {scene} scene parameter {key!r}; valid: {', '.join(sorted(defaults))}"
            )
        p[key] = _coerce(scene, key, defaults[key], value)
    if p["radius_m"] <= 0.0:
        raise ValueError(f"{scene} scene parameter 'radius_m' must be > 0, got {p['radius_m']}")
    depth = p.get("water_depth_m", 0.0)
    if not 0.0 <= depth < p["radius_m"]:
        raise ValueError(
            f"{scene} scene parameter 'water_depth_m' must be in [0, radius_m = "
            f"{p['radius_m']}) (a pipe at most half full), got {depth}"
        )
    spacing = SPACING_KEYS[scene]
    if p[spacing] < MIN_SPACING_M:
        raise ValueError(
            f"{scene} scene parameter {spacing!r} must be >= {MIN_SPACING_M} m, got {p[spacing]}"
        )
    return p


def water_level(p: dict[str, Any]) -> float | None:
    """Height of the water surface in a pipe (the section centre at z = 0), or None for a dry
    pipe: the water hides the wall below it and the sensor sees its surface as a floor that
    seldom returns (:data:`WATER_RETURN_FRACTION`)."""
    depth = float(p.get("water_depth_m", 0.0))
    return -float(p["radius_m"]) + depth if depth > 0.0 else None


def hume_params(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The hume builder's parameters (``HUME_PARAMS`` with ``overrides``)."""
    return merge_params("hume", HUME_PARAMS, overrides)


def pe_params(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The pe builder's parameters (``PE_PARAMS`` with ``overrides``). Another segment length
    keeps the rib pitch (~35 mm) unless ``ribs_per_segment`` is given too."""
    p = merge_params("pe", PE_PARAMS, overrides)
    if overrides and "segment_length_m" in overrides and "ribs_per_segment" not in overrides:
        pitch = PE_PARAMS["segment_length_m"] / PE_PARAMS["ribs_per_segment"]
        p["ribs_per_segment"] = max(1, round(p["segment_length_m"] / pitch))
    return p


def _joint_positions(
    rng: np.random.Generator, first: float, spacing: float, x_max: float, jitter: float
) -> F64:
    n = int(np.floor((x_max - 0.2 - first) / spacing)) + 1
    xs = first + spacing * np.arange(n)
    return np.asarray(xs + rng.normal(0.0, jitter, n) if jitter > 0 else xs, dtype=np.float64)


def _roughness(
    rng: np.random.Generator,
    x_min: float,
    x_max: float,
    du: float,
    n_theta: int,
    corr_m: float,
    radius: float,
    sigma: float,
    period: float | None,
) -> Grid2D:
    """Isotropic wall roughness (std ``sigma``, correlation ``corr_m`` on the wall surface).
    With ``period`` the texture repeats along x every ``period`` metres (aliased pipe)."""
    if period is not None:
        n_u = max(8, round(period / du))
        du = period / n_u
        x0 = 0.0
    else:
        n_u = int(np.ceil((x_max - x_min) / du)) + 2
        x0 = x_min
    dtheta_m = 2.0 * np.pi * radius / n_theta
    values = smooth_noise(rng, (n_u, n_theta), (corr_m / du, corr_m / dtheta_m), sigma)
    # Every cross-section keeps the nominal mean radius: roughness only redistributes material
    # around the circumference, so the mean axial profile carries the nominal shape alone
    # (measured: with the row mean left in, the hume profile of one joint told it from the
    # others 88 % of the time at 1.5 mm range noise; without, the 2D maps are needed).
    values -= values.mean(axis=1, keepdims=True)
    return Grid2D(x0, du, -np.pi, 2.0 * np.pi / n_theta, values, True, period is not None)


def _groove_table(
    rng: np.random.Generator,
    u: F64,
    th: F64,
    depth_m: float,
    width_m: float,
    distinct: float,
    depth_var_m: float,
    width_var_m: float,
    centre_var_m: float,
    chips_mean: float,
    chip_depth_m: tuple[float, float],
) -> np.ndarray:
    """One annular groove ``(len(u), len(th))``: depth, width and axial centre vary around the
    circumference (zero-mean harmonics), plus chipped edges (small local recesses)."""
    depth = np.clip(depth_m + harmonic_series(rng, th, depth_var_m * distinct, 8), 0.3e-3, None)
    width = np.clip(width_m + harmonic_series(rng, th, width_var_m * distinct, 5), 4e-3, None)
    centre = harmonic_series(rng, th, centre_var_m * distinct, 4)
    uu = u[:, None]
    table = depth[None, :] * flat_bump((uu - centre[None, :]) / (0.5 * width[None, :]), 0.4)
    for _ in range(int(rng.poisson(chips_mean * distinct))):
        th_c = rng.uniform(-np.pi, np.pi)
        sig_t = rng.uniform(0.03, 0.12)
        side = rng.choice([-1.0, 1.0])
        u_c = side * (0.5 * width_m + rng.uniform(2e-3, 8e-3))
        sig_u = rng.uniform(2e-3, 6e-3)
        dth = (th - th_c + np.pi) % (2.0 * np.pi) - np.pi
        chip = rng.uniform(*chip_depth_m) * np.exp(-0.5 * (dth / sig_t) ** 2)[None, :]
        table = np.maximum(table, chip * np.exp(-0.5 * ((uu - u_c) / sig_u) ** 2))
    return table.astype(np.float32)


def _stack(tables: list[np.ndarray], n_u: int, n_t: int) -> np.ndarray:
    if not tables:
        return np.zeros((0, n_u, n_t), dtype=np.float32)
    return np.stack(tables).astype(np.float32)


def _joint_patches(
    rng: np.random.Generator,
    p: dict[str, Any],
    kind: str,
    joints: np.ndarray,
    th: np.ndarray,
    distinct: float,
    identical: bool,
) -> PatchSet:
    """One groove table per joint, +-5 cm around it, from the ``{kind}_depth_m`` ...
    ``{kind}_centre_var_m`` parameters (hume grooves, pe coupler gaps); identical joints
    share one table."""
    half = 0.05
    u = np.linspace(-half, half, 101)

    def one(g: np.random.Generator) -> np.ndarray:
        return _groove_table(
            g,
            u,
            th,
            p[f"{kind}_depth_m"],
            p[f"{kind}_width_m"],
            distinct,
            p[f"{kind}_depth_var_m"],
            p[f"{kind}_width_var_m"],
            p[f"{kind}_centre_var_m"],
            p["chips_per_joint"],
            tuple(p["chip_depth_m"]),
        )

    if identical:
        table = one(rng)
        tables = [table for _ in joints]
    else:
        tables = [one(rng) for _ in joints]
    return PatchSet(joints, half, _stack(tables, u.size, th.size))


def _lips(
    rng: np.random.Generator,
    p: dict[str, Any],
    joints: np.ndarray,
    th: np.ndarray,
    distinct: float,
    identical: bool,
) -> SegmentTable:
    """Each segment's centre offset by a small random eccentricity (``lip_eccentricity_m``):
    a radial step at every joint that is zero-mean around the circumference."""
    n_seg = joints.size + 1
    ecc = (
        np.zeros((n_seg, 2))
        if identical
        else rng.normal(0.0, p["lip_eccentricity_m"] * distinct, (n_seg, 2))
    )
    return SegmentTable(
        joints,
        (ecc[:, :1] * np.cos(th)[None, :] + ecc[:, 1:] * np.sin(th)[None, :]).astype(np.float32),
    )


def build_hume(
    rng: np.random.Generator,
    x_max: float,
    distinct: float,
    identical: bool,
    overrides: dict[str, Any] | None = None,
) -> Scene:
    """Precast concrete pipe: 0.6 m ID, 2.43 m segments, annular joint grooves (~4 mm deep,
    ~16 mm wide, varying around), eccentric lips (~1.5 mm), chipped edges, occasional lateral
    connections, ~1 mm wall roughness, 1.5 mm range noise."""
    p = hume_params(overrides)
    radius = p["radius_m"]
    x_min = p["x_min_m"]
    seg = p["segment_length_m"]
    jitter = 0.0 if identical else p["joint_position_jitter_m"] * distinct
    joints = _joint_positions(rng, p["first_joint_x_m"], seg, x_max, jitter)
    th = theta_grid(N_THETA_PATCH)
    grooves = _joint_patches(rng, p, "groove", joints, th, distinct, identical)

    # Lips: each segment's centre is offset by a small eccentricity (zero-mean around the
    # circumference, so the mean axial profile is unchanged).
    lips = _lips(rng, p, joints, th, distinct, identical)
    rough = _roughness(
        rng,
        x_min,
        x_max,
        0.006,
        320,
        p["roughness_corr_m"],
        radius,
        p["roughness_m"],
        seg if identical else None,
    )
    if identical:
        # Roughness repeats every segment in phase with the joints.
        rough = rough.repeating_from(joints[0])

    # Lateral connections: a round opening (a stub pipe) mid-segment on the upper half.
    conn_x: list[float] = []
    conn_tables: list[np.ndarray] = []
    c_half = 0.1
    cu = np.linspace(-c_half, c_half, 51)
    if not identical:
        n_conn = int(rng.poisson((x_max - x_min) / p["lateral_connection_every_m"]))
        segs = rng.choice(max(joints.size - 1, 1), size=min(n_conn, max(joints.size - 1, 0)))
        for s in np.sort(np.unique(segs)):
            # 0.6 m from the joints (a quarter segment in short segments).
            margin = min(0.6, 0.25 * seg)
            xc = joints[s] + rng.uniform(margin, seg - margin)
            # Upper half, 17..75 deg above either side (theta = atan2(z, y)).
            elev = rng.uniform(0.3, 1.3)
            th_c = elev if rng.random() < 0.5 else np.pi - elev
            dth = (th - th_c + np.pi) % (2.0 * np.pi) - np.pi
            dist = np.hypot(cu[:, None], radius * dth[None, :])
            r_h = p["lateral_connection_radius_m"]
            hole = p["lateral_connection_depth_m"] * flat_bump(dist / r_h, 0.85)
            conn_x.append(float(xc))
            conn_tables.append(hole.astype(np.float32))
    connections = PatchSet(np.asarray(conn_x), c_half, _stack(conn_tables, cu.size, th.size))

    p["identical_joints"] = identical
    grooves, lips = apply_changes(p, grooves, lips, th)
    return Scene(
        name="hume",
        radius_m=radius,
        floor_z_m=water_level(p),
        x_min_m=x_min,
        x_max_m=x_max,
        joints_x_m=joints,
        range_noise_m=p["range_noise_m"],
        wall_terms=[rough, lips, grooves, connections],
        reflectivity={KIND_WALL: 40.0, KIND_CAP: 30.0, KIND_FLOOR: WATER_REFLECTIVITY},
        return_fraction={KIND_FLOOR: WATER_RETURN_FRACTION},
        params={**p, "lateral_connections_x_m": [round(v, 4) for v in conn_x]},
    )


def build_pe(
    rng: np.random.Generator,
    x_max: float,
    distinct: float,
    identical: bool,
    overrides: dict[str, Any] | None = None,
) -> Scene:
    """Ribbed polyethylene pipe: 0.4 m ID, inner ribs every ~35 mm (1.2 mm peak to peak, a
    periodic micro-structure that must not be taken for joints), 6 m segments joined by
    couplers whose gap (~20 mm wide, ~5 mm deep) varies around the circumference."""
    p = pe_params(overrides)
    radius = p["radius_m"]
    x_min = p["x_min_m"]
    seg = p["segment_length_m"]
    pitch = seg / p["ribs_per_segment"]
    p["rib_pitch_m"] = pitch
    jitter = 0.0 if identical else p["joint_position_jitter_m"] * distinct
    joints = _joint_positions(rng, p["first_joint_x_m"], seg, x_max, jitter)
    th = theta_grid(N_THETA_PATCH)
    couplers = _joint_patches(rng, p, "gap", joints, th, distinct, identical)

    # Ribs restart at every coupler (pipes are cut at the same point of the rib pattern).
    starts = np.concatenate([[joints[0] - seg], joints])
    rib_h = p["rib_height_m"]

    def ribs(x: F64, theta: F64) -> F64:
        s = np.searchsorted(joints, x)
        local = x - starts[s]
        wave = np.tanh(3.0 * np.cos(2.0 * np.pi * local / pitch)) / np.tanh(3.0)
        return 0.5 * rib_h * wave

    lips = _lips(rng, p, joints, th, distinct, identical)
    rough = _roughness(
        rng,
        x_min,
        x_max,
        0.006,
        256,
        p["roughness_corr_m"],
        radius,
        p["roughness_m"],
        seg if identical else None,
    )
    if identical:
        rough = rough.repeating_from(joints[0])
    p["identical_joints"] = identical
    couplers, lips = apply_changes(p, couplers, lips, th)
    return Scene(
        name="pe",
        radius_m=radius,
        floor_z_m=water_level(p),
        x_min_m=x_min,
        x_max_m=x_max,
        joints_x_m=joints,
        range_noise_m=p["range_noise_m"],
        wall_terms=[rough, ribs, lips, couplers],
        reflectivity={KIND_WALL: 60.0, KIND_CAP: 30.0, KIND_FLOOR: WATER_REFLECTIVITY},
        return_fraction={KIND_FLOOR: WATER_RETURN_FRACTION},
        params=p,
    )
