"""Tunnel scenes: ``shield`` (6 m segmental lining, 1.5 m rings, flat invert) and
``horseshoe`` (rough rock, steel arches every ~1.2 m, flat floor).

Section centre at y = 0, z = 0 (world); the floor is the plane ``z = floor_z_m``.

Every builder starts from its module-level parameter dict (``SHIELD_PARAMS``,
``HORSESHOE_PARAMS``) with the caller's overrides (:func:`shield_params`,
:func:`horseshoe_params`); another ``radius_m`` (tunnel width / 2) moves the floor with it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from decod_rs.sim.fields import (
    F64,
    Grid2D,
    flat_bump,
    harmonic_series,
    smooth_noise,
    wrap_angle,
)
from decod_rs.sim.pipes import _groove_table, _joint_positions, _roughness, merge_params
from decod_rs.sim.surface import (
    KIND_ARCH,
    KIND_CAP,
    KIND_FLOOR,
    KIND_WALL,
    ArchSet,
    PatchSet,
    Scene,
    SegmentTable,
    theta_grid,
)

SHIELD_PARAMS: dict[str, Any] = {
    "radius_m": 3.0,
    "floor_z_m": -2.0,
    "ring_width_m": 1.5,
    "first_joint_x_m": 1.0,
    "joint_position_jitter_m": 0.003,
    "segment_angles_deg": [22.5, 67.5, 67.5, 67.5, 67.5, 67.5],
    "stagger_deg": 33.75,
    "lipping_m": 0.003,
    "seam_depth_m": 0.015,
    "seam_width_m": 0.02,
    "seam_depth_var_m": 0.003,
    "seam_width_var_m": 0.004,
    "seam_centre_var_m": 0.003,
    "spalls_per_seam": 2.0,
    "spall_depth_m": [0.003, 0.008],
    "long_seam_depth_m": 0.012,
    "long_seam_width_m": 0.02,
    "pockets_per_side": 16,
    "pocket_offset_m": 0.2,
    "pocket_axial_m": 0.18,
    "pocket_circ_m": 0.28,
    "pocket_depth_m": 0.08,
    "pocket_depth_var_m": 0.006,
    "roughness_m": 0.002,
    "roughness_corr_m": 0.04,
    "floor_roughness_m": 0.005,
    "range_noise_m": 0.01,
    "x_min_m": -1.0,
}

HORSESHOE_PARAMS: dict[str, Any] = {
    "radius_m": 2.5,
    "floor_z_m": -1.5,
    "arch_spacing_m": 1.2,
    "first_joint_x_m": 1.0,
    "arch_spacing_jitter_m": 0.01,
    "arch_width_m": 0.15,
    "arch_tilt_m": 0.01,
    "arch_wave_m": 0.01,
    "arch_deform_m": 0.015,
    "rock_offset_m": 0.2,
    "rock_overbreak_m": 0.05,
    "rock_overbreak_corr_m": 0.5,
    "rock_roughness_m": 0.015,
    "rock_roughness_corr_m": 0.05,
    "floor_roughness_m": 0.02,
    "range_noise_m": 0.015,
    "x_min_m": -1.0,
}


def _tunnel_params(
    scene: str, defaults: dict[str, Any], overrides: dict[str, Any] | None
) -> dict[str, Any]:
    """``defaults`` with ``overrides``; another radius moves the floor with it (the floor keeps
    its height as a fraction of the radius) unless ``floor_z_m`` is given too."""
    p = merge_params(scene, defaults, overrides)
    if overrides and "radius_m" in overrides and "floor_z_m" not in overrides:
        p["floor_z_m"] = defaults["floor_z_m"] * p["radius_m"] / defaults["radius_m"]
    if not -p["radius_m"] < p["floor_z_m"] < 0.0:
        raise ValueError(
            f"{scene} scene parameter 'floor_z_m' must lie between -radius_m and 0, got "
            f"{p['floor_z_m']} (radius_m {p['radius_m']})"
        )
    return p


def shield_params(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The shield builder's parameters (``SHIELD_PARAMS`` with ``overrides``)."""
    return _tunnel_params("shield", SHIELD_PARAMS, overrides)


def horseshoe_params(overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The horseshoe builder's parameters (``HORSESHOE_PARAMS`` with ``overrides``)."""
    return _tunnel_params("horseshoe", HORSESHOE_PARAMS, overrides)


def _floor_texture(
    rng: np.random.Generator,
    x_min: float,
    x_max: float,
    sigma: float,
    corr_m: float,
    period: float | None = None,
    x0: float = 0.0,
    half_width: float = 4.0,
) -> Grid2D:
    """Floor roughness on (x, y), ``|y| <= max(4 m, half_width)``; with ``period`` it repeats
    along x every ``period`` metres from ``x0`` (aliased tunnels: the floor beside every
    boundary is the same too)."""
    du = 0.05
    half = max(4.0, half_width)
    n_v = round(2.0 * half / du)
    if period is not None:
        n_u = max(4, round(period / du))
        du_x = period / n_u
        values = smooth_noise(rng, (n_u, n_v), (corr_m / du_x, corr_m / du), sigma)
        return Grid2D(x0, du_x, -half, du, values, wrap_v=False, wrap_u=True)
    n_u = int(np.ceil((x_max - x_min) / du)) + 2
    values = smooth_noise(rng, (n_u, n_v), (corr_m / du, corr_m / du), sigma)
    return Grid2D(x_min, du, -half, du, values, wrap_v=False)


def _shield_rings(
    rng: np.random.Generator,
    p: dict[str, Any],
    joints: F64,
    rot: F64,
    edges_rel: F64,
    distinct: float,
    identical: bool,
) -> SegmentTable:
    """Per-ring angular table: segment radial offsets (lipping) and longitudinal seams."""
    radius = p["radius_m"]
    n_ring = joints.size + 1
    n_t = 2048
    th = theta_grid(n_t)
    ring_tab = np.zeros((n_ring, n_t), dtype=np.float32)
    ident_seed = int(rng.integers(2**62))
    for i in range(n_ring):
        # Aliased tunnel: every ring draws the same variations.
        g = np.random.default_rng(ident_seed) if identical else rng
        offs = g.normal(0.0, p["lipping_m"] * distinct, len(edges_rel))
        offs -= offs.mean()
        rel = (th - rot[i]) % (2.0 * np.pi)
        seg_idx = np.searchsorted(edges_rel, rel, side="right") - 1
        row = offs[seg_idx]
        for e in edges_rel:
            d_arc = radius * wrap_angle(th - rot[i] - e)
            depth = p["long_seam_depth_m"] * (1.0 + 0.15 * distinct * g.standard_normal())
            row = row + depth * flat_bump(d_arc / (0.5 * p["long_seam_width_m"]), 0.3)
        ring_tab[i] = row
    return SegmentTable(joints, ring_tab)


def _shield_seams(
    rng: np.random.Generator, p: dict[str, Any], joints: F64, distinct: float, identical: bool
) -> PatchSet:
    """Ring seams: circumferential grooves with varying depth/width, spalled edges."""
    half = 0.04
    u = np.linspace(-half, half, 33)
    th_s = theta_grid(1024)

    def one_seam(g: np.random.Generator) -> np.ndarray:
        return _groove_table(
            g,
            u,
            th_s,
            p["seam_depth_m"],
            p["seam_width_m"],
            distinct,
            p["seam_depth_var_m"],
            p["seam_width_var_m"],
            p["seam_centre_var_m"],
            p["spalls_per_seam"],
            tuple(p["spall_depth_m"]),
        )

    if identical:
        s0 = one_seam(rng)
        seam_tables = np.stack([s0 for _ in joints])
    else:
        seam_tables = np.stack([one_seam(rng) for _ in joints])
    return PatchSet(joints, half, seam_tables.astype(np.float32))


def _shield_pockets(
    rng: np.random.Generator,
    p: dict[str, Any],
    joints: F64,
    seams_ext: F64,
    rot: F64,
    distinct: float,
    identical: bool,
) -> Callable[[F64, F64], F64]:
    """Bolt pockets: recesses in a band beside each ring seam, rotating with the ring."""
    radius = p["radius_m"]
    n_ring = joints.size + 1
    n_p = int(p["pockets_per_side"])
    pocket_depth = p["pocket_depth_m"] + (
        np.zeros((n_ring, 2, n_p))
        if identical
        else rng.normal(0.0, p["pocket_depth_var_m"] * distinct, (n_ring, 2, n_p))
    )
    pitch = 2.0 * np.pi / n_p

    def pockets(x: F64, theta: F64) -> F64:
        i = np.searchsorted(joints, x)
        out = np.zeros_like(x)
        for side, dist in ((0, x - seams_ext[i]), (1, seams_ext[i + 1] - x)):
            band = flat_bump((dist - p["pocket_offset_m"]) / (0.5 * p["pocket_axial_m"]), 0.7)
            phi = (theta - rot[i] - (0.5 * pitch if side == 0 else 0.0)) % (2.0 * np.pi)
            k = np.round(phi / pitch)
            arc = radius * (phi - k * pitch)
            circ = flat_bump(arc / (0.5 * p["pocket_circ_m"]), 0.7)
            depth = pocket_depth[i, side, k.astype(np.int64) % n_p]
            out = out + depth * band * circ
        return out

    return pockets


def build_shield(
    rng: np.random.Generator,
    x_max: float,
    distinct: float,
    identical: bool,
    overrides: dict[str, Any] | None = None,
) -> Scene:
    """Shield tunnel: 6 m ID, 1.5 m rings of 6 segments (a 22.5 deg key), ring seams
    (~15 mm groove) with lipping (per-segment radial offsets, zero-mean per ring), staggered
    longitudinal seams (ring rotation alternates), 16 bolt pockets on each side of every ring
    seam (a band 0.11-0.29 m off the seam), flat invert 1 m above the ring bottom."""
    p = shield_params(overrides)
    radius = p["radius_m"]
    x_min = p["x_min_m"]
    ring = p["ring_width_m"]
    jitter = 0.0 if identical else p["joint_position_jitter_m"] * distinct
    joints = _joint_positions(rng, p["first_joint_x_m"], ring, x_max, jitter)
    n_ring = joints.size + 1
    seams_ext = np.concatenate([[joints[0] - ring], joints, [joints[-1] + ring]])
    stagger = np.deg2rad(p["stagger_deg"])
    rot = np.zeros(n_ring) if identical else stagger * (np.arange(n_ring) % 2)
    edges_rel = np.deg2rad(np.concatenate([[0.0], np.cumsum(p["segment_angles_deg"])[:-1]]))
    # Rotate so the key sits at the crown for ring 0.
    rot = rot + np.pi / 2 - np.deg2rad(p["segment_angles_deg"][0]) / 2

    rings = _shield_rings(rng, p, joints, rot, edges_rel, distinct, identical)
    seams = _shield_seams(rng, p, joints, distinct, identical)
    pockets = _shield_pockets(rng, p, joints, seams_ext, rot, distinct, identical)

    rough = _roughness(
        rng,
        x_min,
        x_max,
        0.03,
        768,
        p["roughness_corr_m"],
        radius,
        p["roughness_m"],
        ring if identical else None,
    )
    if identical:
        rough = rough.repeating_from(joints[0])
    floor = _floor_texture(
        rng,
        x_min,
        x_max,
        p["floor_roughness_m"],
        0.08,
        ring if identical else None,
        joints[0],
        radius,
    )
    p["identical_joints"] = identical
    p["ring_rotation_deg"] = [round(float(np.rad2deg(r)), 3) for r in rot]
    return Scene(
        name="shield",
        radius_m=radius,
        floor_z_m=p["floor_z_m"],
        x_min_m=x_min,
        x_max_m=x_max,
        joints_x_m=joints,
        range_noise_m=p["range_noise_m"],
        wall_terms=[rough, rings, seams, pockets],
        floor_terms=[floor],
        reflectivity={KIND_WALL: 45.0, KIND_FLOOR: 30.0, KIND_CAP: 30.0},
        params=p,
    )


def build_horseshoe(
    rng: np.random.Generator,
    x_max: float,
    distinct: float,
    identical: bool,
    overrides: dict[str, Any] | None = None,
) -> Scene:
    """Rough rock tunnel (5 m span, rock 0.2 m outside the nominal section with ~5 cm
    overbreak and ~1.5 cm fine roughness) with steel arches (0.15 m flange) every ~1.2 m:
    each arch is slightly tilted and deformed; flat floor 1.5 m below the centre."""
    p = horseshoe_params(overrides)
    radius = p["radius_m"]
    x_min = p["x_min_m"]
    spacing = p["arch_spacing_m"]
    jitter = 0.0 if identical else p["arch_spacing_jitter_m"] * distinct
    joints = _joint_positions(rng, p["first_joint_x_m"], spacing, x_max, jitter)
    arches = _horseshoe_arches(rng, p, joints, distinct, identical)
    coarse, fine = _rock_roughness(rng, p, x_min, x_max, joints, identical)
    offset = p["rock_offset_m"]

    def rock_base(x: F64, theta: F64) -> F64:
        return np.full(np.broadcast(x, theta).shape, offset)

    floor = _floor_texture(
        rng,
        x_min,
        x_max,
        p["floor_roughness_m"],
        0.1,
        spacing if identical else None,
        joints[0],
        radius,
    )
    p["identical_joints"] = identical
    return Scene(
        name="horseshoe",
        radius_m=radius,
        floor_z_m=p["floor_z_m"],
        x_min_m=x_min,
        x_max_m=x_max,
        joints_x_m=joints,
        range_noise_m=p["range_noise_m"],
        wall_terms=[rock_base, coarse, fine],
        floor_terms=[floor],
        arches=arches,
        reflectivity={KIND_WALL: 25.0, KIND_FLOOR: 20.0, KIND_CAP: 25.0, KIND_ARCH: 120.0},
        params=p,
    )


def _horseshoe_arches(
    rng: np.random.Generator,
    p: dict[str, Any],
    joints: F64,
    distinct: float,
    identical: bool,
) -> ArchSet:
    """The horseshoe's steel arches at ``joints``: each tilted, waved and deformed by its own
    draw (``distinct`` scales them), or all one draw when ``identical``."""
    radius = p["radius_m"]
    th = theta_grid(1024)

    def one_arch(g: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        a, b = g.normal(0.0, p["arch_tilt_m"] * distinct, 2)
        shift = (
            a * np.cos(th) + b * np.sin(th) + harmonic_series(g, th, p["arch_wave_m"] * distinct, 4)
        )
        r_in = radius + harmonic_series(g, th, p["arch_deform_m"] * distinct, 5)
        return r_in.astype(np.float32), shift.astype(np.float32)

    if identical:
        r0, s0 = one_arch(rng)
        arch_data = [(r0, s0) for _ in joints]
    else:
        arch_data = [one_arch(rng) for _ in joints]
    return ArchSet(
        centres=joints,
        half_width=0.5 * p["arch_width_m"],
        inner_radius=np.stack([a for a, _ in arch_data]),
        shift=np.stack([s for _, s in arch_data]),
        nominal_inner_radius=radius,
    )


def _rock_roughness(
    rng: np.random.Generator,
    p: dict[str, Any],
    x_min: float,
    x_max: float,
    joints: F64,
    identical: bool,
) -> tuple[Grid2D, Grid2D]:
    """The rock's overbreak (coarse, 0.1 m cells) and fine roughness (0.025 m), periodic with
    the arch spacing from the first joint when ``identical``."""
    period = p["arch_spacing_m"] if identical else None
    grids = []
    for cell_m, cells, name in ((0.1, 256, "overbreak"), (0.025, 640, "roughness")):
        grid = _roughness(
            rng,
            x_min,
            x_max,
            cell_m,
            cells,
            p[f"rock_{name}_corr_m"],
            p["radius_m"],
            p[f"rock_{name}_m"],
            period,
        )
        grids.append(grid.repeating_from(joints[0]) if identical else grid)
    coarse, fine = grids
    return coarse, fine
