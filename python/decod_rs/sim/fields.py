"""Random smooth fields and tabulated surface detail, evaluated vectorised at arbitrary points.

Every surface perturbation of the simulated corridors (wall roughness, rock overbreak, joint
grooves, chips) is a table on a regular grid, looked up by bilinear interpolation. Tables keep
the ray caster free of per-ray Python loops: one lookup is ~10 numpy operations on the whole
batch of rays, whatever the detail in the table.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


@dataclass(frozen=True)
class Grid2D:
    """A field ``f(u, v)`` sampled on ``u0 + i du``, ``v0 + j dv`` (``values`` is ``(nu, nv)``).

    ``wrap_v`` makes ``v`` periodic with period ``nv * dv`` (the circumferential angle);
    ``wrap_u`` makes ``u`` periodic with period ``nu * du`` (used for aliased corridors whose
    texture repeats every segment). Outside a non-wrapped range the field is clamped.
    """

    u0: float
    du: float
    v0: float
    dv: float
    values: NDArray[np.float32]
    wrap_v: bool = True
    wrap_u: bool = False

    def repeating_from(self, u0: float) -> Grid2D:
        """The same samples, periodic along both axes, ``u`` from ``u0``: the texture of an
        aliased corridor, the same in every segment from the first joint."""
        return replace(self, u0=u0, wrap_v=True, wrap_u=True)

    def __call__(self, u: F64, v: F64) -> F64:
        nu, nv = self.values.shape
        fu = (u - self.u0) / self.du
        fv = (v - self.v0) / self.dv
        iu = np.floor(fu)
        iv = np.floor(fv)
        au = fu - iu
        av = fv - iv
        iu = iu.astype(np.int64)
        iv = iv.astype(np.int64)
        if self.wrap_u:
            iu0 = iu % nu
            iu1 = (iu + 1) % nu
        else:
            iu0 = np.clip(iu, 0, nu - 1)
            iu1 = np.clip(iu + 1, 0, nu - 1)
        if self.wrap_v:
            iv0 = iv % nv
            iv1 = (iv + 1) % nv
        else:
            iv0 = np.clip(iv, 0, nv - 1)
            iv1 = np.clip(iv + 1, 0, nv - 1)
        # One flat gather per corner (np.take on the raveled table is ~2x faster than 2D
        # fancy indexing; measured 1.7 -> 0.8 ms for 14k rays on a 3.4M-cell table).
        flat = self.values.reshape(-1)
        r0 = iu0 * nv
        r1 = iu1 * nv
        top = flat.take(r0 + iv0) * (1.0 - av) + flat.take(r0 + iv1) * av
        bot = flat.take(r1 + iv0) * (1.0 - av) + flat.take(r1 + iv1) * av
        return np.asarray(top * (1.0 - au) + bot * au, dtype=np.float64)


def smooth_noise(
    rng: np.random.Generator,
    shape: tuple[int, int],
    corr_cells: tuple[float, float],
    sigma: float,
) -> NDArray[np.float32]:
    """Zero-mean Gaussian random field on a periodic grid with Gaussian correlation.

    ``corr_cells`` is the correlation length (standard deviation of the smoothing kernel) in
    grid cells along each axis; the result is rescaled to standard deviation ``sigma``.
    Smoothing is done in the Fourier domain, so the field is periodic in both axes.
    """
    white = rng.standard_normal(shape)
    k0 = np.fft.fftfreq(shape[0])[:, None]
    k1 = np.fft.rfftfreq(shape[1])[None, :]
    kernel = np.exp(-2.0 * np.pi**2 * ((k0 * corr_cells[0]) ** 2 + (k1 * corr_cells[1]) ** 2))
    field = np.fft.irfft2(np.fft.rfft2(white) * kernel, s=shape)
    field -= field.mean()
    std = float(field.std())
    if std > 0.0:
        field *= sigma / std
    return field.astype(np.float32)


def harmonic_series(
    rng: np.random.Generator, theta: F64, amplitude: float, n_harmonics: int
) -> F64:
    """Zero-mean random periodic function of ``theta`` (rad): sum of harmonics 1..n with
    amplitudes falling as 1/sqrt(k), scaled so its standard deviation is ``amplitude``."""
    out = np.zeros_like(theta)
    for k in range(1, n_harmonics + 1):
        a, b = rng.standard_normal(2) / np.sqrt(k)
        out += a * np.cos(k * theta) + b * np.sin(k * theta)
    std = float(out.std())
    if std > 0.0:
        out *= amplitude / std
    return out


def smooth_step(s: F64) -> F64:
    """C1 ramp from 0 (s <= 0) to 1 (s >= 1)."""
    c = np.clip(s, 0.0, 1.0)
    return c * c * (3.0 - 2.0 * c)


def flat_bump(s: F64, flat: float = 0.5) -> F64:
    """Flat-topped bump: 1 for ``|s| <= flat``, smooth fall to 0 at ``|s| = 1``."""
    a = np.abs(s)
    return 1.0 - smooth_step((a - flat) / (1.0 - flat))


def wrap_angle(theta: F64) -> F64:
    """Angles wrapped to [-pi, pi)."""
    return (theta + np.pi) % (2.0 * np.pi) - np.pi
