"""Simulated LiDARs: a Livox Avia-like forward non-repetitive rosette and spinning
multi-beam sensors (16 and 64 beams), with range noise, dropouts, min/max range, a grazing
incidence cut-off and intensity.

Body frame = sensor frame, FLU (x forward, y left, z up). Points are returned in the body frame
at the scan stamp, without per-point motion distortion.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.sim.fields import F64
from decod_rs.sim.raycast import Hits

SCAN_PERIOD_S = 0.1


@dataclass(frozen=True)
class SensorSpec:
    """One LiDAR model. ``pattern`` is ``"rosette"`` (forward, limited FoV, non-repetitive:
    two counter-rotating prisms with an irrational speed ratio, so the pattern never repeats
    and coverage grows with integration time) or ``"spinning"`` (``beams`` rings evenly over
    ``v_fov_deg``, one column every ``h_res_deg``). ``range_noise_m = None`` takes the
    scene's (mm in pipes, cm in tunnels)."""

    name: str
    pattern: str
    h_fov_deg: float
    v_fov_deg: float
    rays_per_scan: int = 0
    beams: int = 0
    h_res_deg: float = 0.0
    min_range_m: float = 0.3
    max_range_m: float = 100.0
    dropout: float = 0.01
    grazing_min_deg: float = 1.0
    range_noise_m: float | None = None

    def n_rays(self) -> int:
        if self.pattern == "rosette":
            return self.rays_per_scan
        return self.beams * round(360.0 / self.h_res_deg)

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


SENSORS: dict[str, SensorSpec] = {
    # Livox Avia: 70.4 x 77.2 deg FoV. 6,000 rays per 100 ms scan (the real unit fires
    # 24,000); 6k keeps a 60 m out-and-back pipe log under a minute and ~100k points per
    # 20-scan submap, the extraction target size.
    "avia": SensorSpec(
        "avia", "rosette", 70.4, 77.2, rays_per_scan=6000, min_range_m=0.3, max_range_m=100.0
    ),
    # Velodyne VLP-16-like: +-15 deg, 0.4 deg columns (900 x 16 = 14,400 rays).
    "spin16": SensorSpec(
        "spin16", "spinning", 360.0, 30.0, beams=16, h_res_deg=0.4, min_range_m=0.5
    ),
    # Ouster OS1-64-like: 45 deg vertical FoV, 512 columns (32,768 rays).
    "spin64": SensorSpec(
        "spin64",
        "spinning",
        360.0,
        45.0,
        beams=64,
        h_res_deg=360.0 / 512,
        min_range_m=0.3,
        max_range_m=120.0,
    ),
}


def sensor_spec(name: str, **overrides: Any) -> SensorSpec:
    """A named sensor (``avia``, ``spin16``, ``spin64``) with field overrides, e.g.
    ``sensor_spec("spin16", h_res_deg=0.2)``."""
    if name not in SENSORS:
        raise ValueError(f"unknown sensor {name!r}; choose one of {sorted(SENSORS)}")
    spec = replace(SENSORS[name], **overrides)
    if spec.n_rays() <= 0:
        raise ValueError(f"sensor {name!r} has no rays ({spec})")
    return spec


# Prism rates of the rosette (Hz). Their ratio is irrational, so the pattern never repeats.
ROSETTE_F1_HZ = 173.7
ROSETTE_F2_HZ = -131.3 * np.sqrt(1.01)
ROSETTE_CHANNELS = 6


def ray_directions(spec: SensorSpec, scan_index: int) -> F64:
    """Unit ray directions ``(N, 3)`` in the body frame for scan ``scan_index``."""
    if spec.pattern == "rosette":
        n = spec.rays_per_scan
        t = (scan_index + np.arange(n) / n) * SCAN_PERIOD_S
        w1 = 2.0 * np.pi * ROSETTE_F1_HZ * t
        w2 = 2.0 * np.pi * ROSETTE_F2_HZ * t
        chan = (np.arange(n) % ROSETTE_CHANNELS) - 0.5 * (ROSETTE_CHANNELS - 1)
        u = 0.5 * (np.cos(w1) + np.cos(w2))
        v = 0.5 * (np.sin(w1) + np.sin(w2)) + 0.012 * chan
        az = np.deg2rad(0.5 * spec.h_fov_deg) * u
        el = np.deg2rad(0.5 * spec.v_fov_deg) * np.clip(v, -1.0, 1.0)
    elif spec.pattern == "spinning":
        n_col = round(360.0 / spec.h_res_deg)
        az_c = np.deg2rad(np.arange(n_col) * 360.0 / n_col - 180.0)
        el_b = np.deg2rad(np.linspace(-0.5 * spec.v_fov_deg, 0.5 * spec.v_fov_deg, spec.beams))
        az = np.repeat(az_c, spec.beams)
        el = np.tile(el_b, n_col)
    else:
        raise ValueError(f"unknown scan pattern {spec.pattern!r}")
    ce = np.cos(el)
    return np.stack([ce * np.cos(az), ce * np.sin(az), np.sin(el)], axis=1)


def measure(
    spec: SensorSpec,
    hits: Hits,
    origin: F64,
    reflectivity: NDArray[np.float64],
    noise_m: float,
    rng: np.random.Generator,
    return_fraction: NDArray[np.float64] | None = None,
) -> tuple[F64, NDArray[np.float32], NDArray[np.bool_]]:
    """Turn exact hits into measurements (world frame; ``origin`` (3,) or one per hit
    (N, 3), as :func:`~decod_rs.sim.raycast.cast`'s): range noise along the ray, dropouts
    (random, grazing incidence, out of range, and per surface kind ``return_fraction``,
    indexed like ``reflectivity``, e.g. water) and intensity. Returns ``(points (M, 3),
    intensity (M,), keep (N,))``."""
    vec = hits.points - origin
    rng_true = np.linalg.norm(vec, axis=1)
    n = rng_true.size
    noise = rng.standard_normal(n) * noise_m
    rng_meas = rng_true + noise
    grazing = np.rad2deg(np.arcsin(np.clip(hits.cos_incidence, 0.0, 1.0)))
    # Returns fade out linearly from twice the grazing cut-off down to the cut-off.
    p_keep = np.clip((grazing - spec.grazing_min_deg) / spec.grazing_min_deg, 0.0, 1.0)
    if return_fraction is not None:
        p_keep = p_keep * return_fraction[hits.kind]
    u = rng.random(n)
    u2 = rng.random(n)
    keep = (
        hits.valid
        & (u < p_keep)
        & (u2 >= spec.dropout)
        & (rng_meas >= spec.min_range_m)
        & (rng_meas <= spec.max_range_m)
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = vec / rng_true[:, None]
    pts = (origin[keep] if origin.ndim == 2 else origin) + unit[keep] * rng_meas[keep, None]
    refl = reflectivity[hits.kind[keep]]
    inten = (
        refl
        * (0.25 + 0.75 * hits.cos_incidence[keep])
        * (1.0 + 0.05 * rng.standard_normal(int(keep.sum())))
    )
    return pts, np.clip(inten, 0.0, 255.0).astype(np.float32), keep
