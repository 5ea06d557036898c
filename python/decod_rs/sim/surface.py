"""Building blocks of a corridor surface: per-joint patch tables, per-segment angular tables,
steel arches, and the :class:`Scene` that sums them.

Conventions (world frame): the corridor axis is world +x starting at x = 0; the transverse
section lies in the y-z plane with its reference centre at y = 0, z = 0; ``theta =
atan2(z, y)`` is the circumferential angle (0 = +y, pi/2 = up). Wall perturbations ``dr`` are
radial and positive outwards (a groove is a positive ``dr``); floor perturbations ``dz`` are
vertical and positive upwards.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.fields import F64, Grid2D

# Hit kinds returned by the ray caster (also used to pick the reflectivity).
KIND_WALL = 0
KIND_FLOOR = 1
KIND_CAP = 2
KIND_ARCH = 3


@dataclass(frozen=True)
class PatchSet:
    """Local 2D detail around axial centres (joints, lateral connections).

    ``tables`` is ``(J, nu, ntheta)``: the radial offset on ``u = x - centres[j]`` in
    ``[-half_width, half_width]`` (``nu`` samples) by ``theta`` in ``[-pi, pi)``. Zero outside
    the band. Patches must not overlap (the nearest centre is used).
    """

    centres: F64
    half_width: float
    tables: NDArray[np.float32]

    def __call__(self, x: F64, theta: F64) -> F64:
        shape = np.broadcast(x, theta).shape
        n_j, n_u, n_t = self.tables.shape
        if n_j == 0:
            return np.zeros(shape)
        x = np.broadcast_to(x, shape).reshape(-1)
        theta = np.broadcast_to(theta, shape).reshape(-1)
        k = np.searchsorted(self.centres, x)
        k_lo = np.clip(k - 1, 0, n_j - 1)
        k_hi = np.clip(k, 0, n_j - 1)
        d_lo = np.abs(x - self.centres[k_lo])
        d_hi = np.abs(x - self.centres[k_hi])
        j = np.where(d_lo <= d_hi, k_lo, k_hi)
        u = x - self.centres[j]
        # Only the rays inside a band are looked up (a few % of them in a pipe).
        sel = np.nonzero(np.abs(u) < self.half_width)[0]
        out = np.zeros(x.size)
        if sel.size == 0:
            return out.reshape(shape)
        du = 2.0 * self.half_width / (n_u - 1)
        fu = np.clip((u[sel] + self.half_width) / du, 0.0, n_u - 1.000001)
        iu = np.floor(fu).astype(np.int64)
        au = fu - iu
        grid = Grid2D(0.0, 1.0, -np.pi, 2.0 * np.pi / n_t, self.tables.reshape(n_j * n_u, n_t))
        row = (j[sel] * n_u + iu).astype(np.float64) + au
        out[sel] = grid(row, theta[sel])
        return out.reshape(shape)

    def grid_u(self) -> F64:
        """Axial sample positions of a table row, metres relative to the centre."""
        return np.linspace(-self.half_width, self.half_width, self.tables.shape[1])


def theta_grid(n: int) -> F64:
    """``n`` circumferential sample angles covering [-pi, pi)."""
    return -np.pi + 2.0 * np.pi * np.arange(n) / n


@dataclass(frozen=True)
class SegmentTable:
    """Per-segment angular offset ``(S, ntheta)``; segment ``s`` spans
    ``[boundaries[s-1], boundaries[s])`` (segment 0 starts before the first boundary)."""

    boundaries: F64
    table: NDArray[np.float32]

    def __call__(self, x: F64, theta: F64) -> F64:
        s = np.searchsorted(self.boundaries, x).astype(np.float64)
        n_t = self.table.shape[1]
        return Grid2D(0.0, 1.0, -np.pi, 2.0 * np.pi / n_t, self.table, wrap_u=False)(s, theta)


@dataclass(frozen=True)
class ArchSet:
    """Protruding rings (steel arches): axial band ``|x - (centres[a] + shift[a](theta))| <=
    half_width`` with inner radius ``inner_radius[a](theta)``; solid out to the rock."""

    centres: F64
    half_width: float
    inner_radius: NDArray[np.float32]  # (A, ntheta), metres
    shift: NDArray[np.float32]  # (A, ntheta), metres along x
    nominal_inner_radius: float

    def _table(self, values: NDArray[np.float32], a: NDArray[np.int64], theta: F64) -> F64:
        n_t = values.shape[1]
        return Grid2D(0.0, 1.0, -np.pi, 2.0 * np.pi / n_t, values, wrap_u=False)(
            a.astype(np.float64), theta
        )

    def radius(self, a: NDArray[np.int64], theta: F64) -> F64:
        return self._table(self.inner_radius, a, theta)

    def centre(self, a: NDArray[np.int64], theta: F64) -> F64:
        return self.centres[a] + self._table(self.shift, a, theta)

    def nearest(self, x: F64) -> NDArray[np.int64]:
        n = self.centres.size
        k = np.searchsorted(self.centres, x)
        k_lo = np.clip(k - 1, 0, n - 1)
        k_hi = np.clip(k, 0, n - 1)
        near_lo = np.abs(x - self.centres[k_lo]) <= np.abs(x - self.centres[k_hi])
        return np.asarray(np.where(near_lo, k_lo, k_hi), dtype=np.int64)


WallTerm = Callable[[F64, F64], F64]
FloorTerm = Callable[[F64, F64], F64]


@dataclass
class Scene:
    """A corridor: a circular section of ``radius_m`` (optionally cut by a flat floor at
    ``floor_z_m``) along world x in ``[x_min_m, x_max_m]`` (capped by planes), with radial
    wall perturbations, floor perturbations and optional arches.

    ``joints_x_m`` are the true boundary positions (metres from x = 0 along the axis), the
    ground truth for landmark evaluation.
    """

    name: str
    radius_m: float
    floor_z_m: float | None
    x_min_m: float
    x_max_m: float
    joints_x_m: F64
    range_noise_m: float
    wall_terms: list[WallTerm]
    floor_terms: list[FloorTerm] = field(default_factory=list)
    arches: ArchSet | None = None
    reflectivity: dict[int, float] = field(default_factory=dict)
    #: Fraction of the sensor's returns each surface kind gives back (a kind not listed: all
    #: of them). A water surface (a pipe's ``water_depth_m``) mirrors the beam away.
    return_fraction: dict[int, float] = field(default_factory=dict)
    params: dict[str, Any] = field(default_factory=dict)

    def wall_dr(self, x: F64, theta: F64) -> F64:
        """Radial wall offset (m, outward positive) at axial ``x`` and angle ``theta``."""
        out = np.zeros(np.broadcast(x, theta).shape)
        for term in self.wall_terms:
            out = out + term(x, theta)
        return out

    def floor_dz(self, x: F64, y: F64) -> F64:
        """Vertical floor offset (m, up positive) at ``(x, y)``."""
        out = np.zeros(np.broadcast(x, y).shape)
        for term in self.floor_terms:
            out = out + term(x, y)
        return out

    def joint_offset_map(self, joint: int, half_width_m: float, n_u: int, n_theta: int) -> F64:
        """The wall offset ``(n_u, n_theta)`` around joint ``joint`` (axial ``+-half_width_m``,
        full circumference): the geometry a descriptor of that boundary samples."""
        u = np.linspace(-half_width_m, half_width_m, n_u)
        th = theta_grid(n_theta)
        uu, tt = np.meshgrid(u, th, indexing="ij")
        xx = self.joints_x_m[joint] + uu
        dr = self.wall_dr(xx, tt)
        if self.arches is not None:
            a = self.arches.nearest(xx.ravel()).reshape(xx.shape)
            in_band = np.abs(xx - self.arches.centre(a, tt)) <= self.arches.half_width
            arch_dr = self.arches.radius(a, tt) - self.radius_m
            dr = np.where(in_band, np.minimum(dr, arch_dr), dr)
        return dr
