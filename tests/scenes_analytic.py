"""Analytic corridor scenes with known answers (seeded numpy), for the extraction tests.

Every generator returns points in a local frame where the corridor axis is ``+x``, gravity
is ``-z`` and the section centre is on the x axis, together with the per-point true offset
from the nominal section (positive outwards) so that tests can check descriptors against
the truth. ``rigid`` moves a scene into any frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


@dataclass
class Scene:
    """Points ``(N, 3)`` and the true signed offset of each point from the nominal section."""

    points: Array
    true_offset_m: Array
    joints_x_m: list[float] = field(default_factory=list)


def groove_depth(theta: Array, depth_m: float) -> Array:
    """Groove depth around the circumference: ``depth * (1 + 0.4 cos theta)``, theta from
    gravity (the bottom) towards ``+y``. Varies around the joint as in real pipes."""
    return depth_m * (1.0 + 0.4 * np.cos(theta))


def wall_clutter(
    rng: np.random.Generator, x: Array, theta: Array, std_m: float, waves: int = 40
) -> Array:
    """Correlated wall roughness of standard deviation ``std_m``: a sum of ``waves`` random
    waves with axial wavelengths of 2-30 cm and circumferential orders 0-6 (order 0 is what
    survives the circumferential averaging of the boundary profile)."""
    if std_m <= 0.0:
        return np.zeros_like(x)
    wavelength = rng.uniform(0.02, 0.3, waves)
    order = rng.integers(0, 7, waves)
    phase = rng.uniform(0.0, 2 * np.pi, waves)
    out = np.zeros_like(x)
    for lam, m, ph in zip(wavelength, order, phase, strict=True):
        out += np.sin(2 * np.pi * x / lam + m * theta + ph)
    return out * std_m * np.sqrt(2.0 / waves)


def pipe(
    rng: np.random.Generator,
    *,
    radius_m: float = 0.3,
    length_m: float = 3.0,
    joints_x_m: tuple[float, ...] = (0.37,),
    groove_width_m: float = 0.012,
    groove_depth_m: float = 0.003,
    noise_m: float = 0.0003,
    n_points: int = 100_000,
) -> Scene:
    """A pipe along ``x`` in ``[-L/2, L/2]`` with annular grooves centred at ``joints_x_m``."""
    x = rng.uniform(-length_m / 2, length_m / 2, n_points)
    theta = rng.uniform(0.0, 2 * np.pi, n_points)
    offset = rng.normal(0.0, noise_m, n_points)
    for xj in joints_x_m:
        inside = np.abs(x - xj) < groove_width_m / 2
        offset[inside] += groove_depth(theta[inside], groove_depth_m)
    r = radius_m + offset
    # theta = 0 at gravity (-z), increasing towards +y (e2 = x cross -z = +y).
    pts = np.column_stack([x, r * np.sin(theta), -r * np.cos(theta)])
    return Scene(pts, offset, list(joints_x_m))


def horseshoe(
    rng: np.random.Generator,
    *,
    radius_m: float = 3.0,
    floor_depth_m: float = 2.0,
    length_m: float = 20.0,
    arch_spacing_m: float = 1.2,
    arch_width_m: float = 0.15,
    arch_height_m: float = 0.1,
    noise_m: float = 0.01,
    n_points: int = 100_000,
) -> Scene:
    """A horseshoe tunnel: a circular vault of ``radius_m`` cut by a flat floor
    ``floor_depth_m`` below the centre, with steel arches (protruding ``arch_height_m``
    inwards) every ``arch_spacing_m`` on the vault; joints are the arch centres."""
    x = rng.uniform(-length_m / 2, length_m / 2, n_points)
    theta = rng.uniform(0.0, 2 * np.pi, n_points)
    c = np.cos(theta)
    on_floor = c > floor_depth_m / radius_m
    r = np.where(on_floor, floor_depth_m / np.maximum(c, 1e-9), radius_m)
    first = -length_m / 2 + arch_spacing_m / 2
    joints = list(np.arange(first, length_m / 2, arch_spacing_m))
    phase = np.abs((x - first + arch_spacing_m / 2) % arch_spacing_m - arch_spacing_m / 2)
    arch = (phase < arch_width_m / 2) & ~on_floor
    offset = rng.normal(0.0, noise_m, n_points) - np.where(arch, arch_height_m, 0.0)
    # On the floor the offset is along the floor normal (vertical), elsewhere radial.
    rr = r + np.where(on_floor, 0.0, offset)
    y = rr * np.sin(theta)
    z = -rr * c + np.where(on_floor, -offset, 0.0)
    return Scene(np.column_stack([x, y, z]), offset, [float(j) for j in joints])


def box_room(
    rng: np.random.Generator,
    *,
    size_m: tuple[float, float, float] = (6.0, 5.0, 3.0),
    noise_m: float = 0.01,
    n_points: int = 60_000,
) -> Scene:
    """An open box room (floor and four walls, no ceiling): not a corridor."""
    sx, sy, sz = size_m
    faces = rng.integers(0, 5, n_points)
    u, v = rng.uniform(-0.5, 0.5, n_points), rng.uniform(0.0, 1.0, n_points)
    pts = np.zeros((n_points, 3))
    floor = faces == 0
    pts[floor] = np.column_stack([u[floor] * sx, (v[floor] - 0.5) * sy, np.zeros(floor.sum())])
    for face, (axis, sign) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1)], start=1):
        m = faces == face
        other = 1 - axis
        size_other = sy if axis == 0 else sx
        pts[m, axis] = sign * (sx if axis == 0 else sy) / 2
        pts[m, other] = u[m] * size_other
        pts[m, 2] = v[m] * sz
    pts += rng.normal(0.0, noise_m, pts.shape)
    pts[:, 2] -= 1.5
    return Scene(pts, np.zeros(n_points))


def rotation(yaw: float, pitch: float, roll: float) -> Array:
    """``Rz(yaw) Ry(pitch) Rx(roll)``."""
    cy, sy, cp, sp, cr, sr = (
        np.cos(yaw),
        np.sin(yaw),
        np.cos(pitch),
        np.sin(pitch),
        np.cos(roll),
        np.sin(roll),
    )
    rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    rx = np.array([[1.0, 0.0, 0.0], [0.0, cr, -sr], [0.0, sr, cr]])
    return rz @ ry @ rx


def rigid(points: Array, rot: Array, trans: Array | tuple[float, float, float]) -> Array:
    """``rot @ p + trans`` for every row of ``points``."""
    return points @ np.asarray(rot).T + np.asarray(trans, dtype=np.float64)


@dataclass
class ScanLog:
    """A simulated drive: per-scan stamps, body-frame points and ``world_from_body`` poses."""

    stamps: Array
    points: list[Array]
    poses: Array
    joints_x_m: list[float]


def pipe_drive(
    rng: np.random.Generator,
    *,
    radius_m: float = 0.3,
    length_m: float = 12.0,
    joint_spacing_m: float = 2.43,
    speed_m_s: float = 0.1,
    rate_hz: float = 10.0,
    n_scans: int = 200,
    view_m: tuple[float, float] = (0.2, 2.5),
    points_per_scan: int = 8000,
    groove_width_m: float = 0.012,
    groove_depth_m: float = 0.003,
    noise_m: float = 0.0003,
    clutter_m: float = 0.0,
) -> ScanLog:
    """A crawler driving along a pipe (axis = world ``+x``, centre at ``y = z = 0``) with a
    forward-looking sensor that sees the wall ``view_m`` ahead; small lateral and roll
    wobble. Joints (grooves) every ``joint_spacing_m``; ``clutter_m`` of wall roughness
    (``wall_clutter``, fixed for the drive); poses are ground truth."""
    wall_rng = np.random.default_rng(rng.integers(2**63))
    wall_state = wall_rng.bit_generator.state
    joints = list(np.arange(joint_spacing_m / 2, length_m, joint_spacing_m))
    stamps = np.arange(n_scans) / rate_hz
    poses = np.zeros((n_scans, 4, 4))
    clouds = []
    for k, t in enumerate(stamps):
        pos = np.array([speed_m_s * t, 0.02 * np.sin(0.3 * t), -0.05 + 0.01 * np.cos(0.2 * t)])
        rot = rotation(0.01 * np.sin(0.1 * t), 0.005 * np.cos(0.15 * t), 0.05 * np.sin(0.05 * t))
        poses[k] = np.eye(4)
        poses[k, :3, :3], poses[k, :3, 3] = rot, pos
        x = rng.uniform(pos[0] + view_m[0], pos[0] + view_m[1], points_per_scan)
        theta = rng.uniform(0.0, 2 * np.pi, points_per_scan)
        offset = rng.normal(0.0, noise_m, points_per_scan)
        wall_rng.bit_generator.state = wall_state  # the same wall in every scan
        offset += wall_clutter(wall_rng, x, theta, clutter_m)
        for xj in joints:
            inside = np.abs(x - xj) < groove_width_m / 2
            offset[inside] += groove_depth(theta[inside], groove_depth_m)
        r = radius_m + offset
        world = np.column_stack([x, r * np.sin(theta), -r * np.cos(theta)])
        clouds.append((world - pos) @ rot)
    return ScanLog(stamps, clouds, poses, [float(j) for j in joints])
