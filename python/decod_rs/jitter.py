"""Odometry that jitters from scan to scan (beyond the paper): submaps stitched on a smooth
fit of it.

A submap stitches ``scans_per_submap`` consecutive scans with the odometry's pose at each
(paper Sec. IV-A.2). Odometry that is right on average but noisy from pose to pose (a LIO
uncertain along a pipe's axis, poses written with a few millimetres of noise) places each
scan's copy of a joint a little apart from the next one's, and in a pipe the joints' relief
is millimetres: in the simulated 0.6 m hume pipe with 16 beams (5.5 mm voxels), odometry with
3 mm and 0.1 deg of independent noise per pose closed 46 loops instead of 143, with 1 cm and
0.3 deg none.

decod measures the jitter on the run's own odometry. At every scan a quadratic in time is
fitted by least squares to the positions of the scans within half a submap's span of it
(at least ``MIN_FIT_SCANS`` scans; an odometry gap's scans are absent, so no fit spans a
gap), and the jitter is the median distance of the positions from their fits: the median,
because where the robot turns or brakes a quadratic follows the true motion less well, and
that is not noise (the simulator's smooth odometry: 0.01-0.1 mm; with 3 mm of noise per
axis: 4 mm). Above a quarter of a voxel (``JITTER_VOXEL_FRACTION``: a point then moves by a
quarter of the voxel grid's spacing from one scan to the next, so a joint's profile widens by
a voxel over a few scans), the run's odometry is the fit: positions from the fits, rotations
from the same fit of the rotation vectors taken relative to each scan's own rotation; the
submaps are stitched on it, the graph's odometry factors and anchors are its (``odometry.tum``
is then the fit, and ``report.json`` ``ingest.odometry_jitter`` says so).

The fit then spans as many scans as bring its own noise to half the threshold (at its centre
about 1.5 / sqrt(n) of the scatter for n scans), at least a submap's span and at most
``FIT_MAX_S`` (2.5 s: a quadratic over 4 s follows a robot that starts or stops turning too
loosely, and the 0.4 m pipe with 16 beams, a turn and 1.5 mm of noise closed no loop; over 2
and 3 s 13 and 15). ``auto``'s probe measures the corridor on the fit too where the odometry
jitters so (with 1 cm of noise the raw poses put the wall's relief at 15 mm instead of 6).
Held out (``docs/measurements.md``, "Odometry that jitters"): with 1.5-3 mm of noise, 7 pipe
logs of 8 close loops with the fit, 3 of 8 without (one with a loop 0.3 m or more off).

Stitching on the fit while the graph's anchors and the boundary tracks kept the raw poses was
tried first: on the 0.6 m pipe with 3 mm of noise the first round closed no loop (its
queries' runner-ups matched as well as their best, and the corridor was taken for aliased).

``submap.smooth_jittery_odometry = false`` keeps the raw poses: odometry that tracks real
motion faster than a submap's span (a crawler's jolts at joints) should not be smoothed.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs.config import Config
from decod_rs.tum import so3_exp, so3_log

FloatArray = NDArray[np.float64]

__all__ = [
    "JITTER_VOXEL_FRACTION",
    "MIN_FIT_SCANS",
    "Smoothing",
    "assess",
    "local_fit",
    "smoothing",
]

#: Jitter above this fraction of the voxel edge is smoothed (module docs).
JITTER_VOXEL_FRACTION = 0.25
#: A fit needs at least this many scans (a quadratic through 3 would follow the noise).
MIN_FIT_SCANS = 5
#: Scans fitted per block (bounds the memory of the batched fits on hour-long logs).
BLOCK = 20_000
#: Neighbours on either side of a scan considered for its fit, at most.
MAX_REACH = 100
#: The longest fit, seconds (module docs): a quadratic over longer follows a robot that
#: starts or stops turning too loosely.
FIT_MAX_S = 2.5


def _fit_at_zero(dt: FloatArray, weight: FloatArray, values: FloatArray) -> FloatArray:
    """Least-squares quadratics in ``dt`` (N, K) through ``values`` (N, K, D) with 0/1
    ``weight``, evaluated at ``dt = 0`` (N, D); NaN where fewer than ``MIN_FIT_SCANS`` count."""
    basis = np.stack([np.ones_like(dt), dt, dt * dt], axis=-1)  # (N, K, 3)
    wb = basis * weight[..., None]
    normal = np.einsum("nki,nkj->nij", wb, basis)
    rhs = np.einsum("nki,nkd->nid", wb, values)
    out = np.full((dt.shape[0], values.shape[-1]), np.nan)
    ok = weight.sum(axis=1) >= MIN_FIT_SCANS
    if np.any(ok):
        out[ok] = np.linalg.solve(normal[ok], rhs[ok])[:, 0, :]
    return out


def local_fit(
    stamps: FloatArray, poses: FloatArray, half_window_s: float
) -> tuple[FloatArray, FloatArray]:
    """The poses (N, 4, 4) fitted at every scan (module docs) and each scan's distance from
    its fit (N,), metres; a scan with too few neighbours for a fit keeps its pose (distance
    NaN)."""
    t = np.asarray(stamps, dtype=np.float64)
    p = np.asarray(poses, dtype=np.float64)
    n = t.size
    fitted = p.copy()
    dist = np.full(n, np.nan)
    if n < MIN_FIT_SCANS:
        return fitted, dist
    steps = np.diff(t)
    # Neighbours by index, as many as the median period puts within the window (a pair of
    # stamps a microsecond apart must not size the arrays), and within it by time.
    step = float(np.median(steps[steps > 0])) if np.any(steps > 0) else 1.0
    reach = min(int(np.ceil(half_window_s / step)) + 1, MAX_REACH)
    offsets = np.arange(-reach, reach + 1)
    for lo in range(0, n, BLOCK):
        rows = np.arange(lo, min(lo + BLOCK, n))
        idx = rows[:, None] + offsets[None, :]
        inside = (idx >= 0) & (idx < n)
        idx = np.clip(idx, 0, n - 1)
        dt = t[idx] - t[rows, None]
        weight = (inside & (np.abs(dt) <= half_window_s + 1e-9)).astype(np.float64)
        centre = p[rows]
        moved = p[idx, :3, 3] - centre[:, None, :3, 3]
        shift = _fit_at_zero(dt, weight, moved)
        rel = np.einsum("nji,nkjl->nkil", centre[:, :3, :3], p[idx, :3, :3])
        turn = _fit_at_zero(dt, weight, so3_log(rel))
        ok = np.all(np.isfinite(shift), axis=1) & np.all(np.isfinite(turn), axis=1)
        r = rows[ok]
        fitted[r, :3, 3] = centre[ok, :3, 3] + shift[ok]
        fitted[r, :3, :3] = centre[ok, :3, :3] @ so3_exp(turn[ok])
        dist[r] = np.linalg.norm(shift[ok], axis=1)
    return fitted, dist


@dataclass(frozen=True)
class Smoothing:
    """What the odometry's jitter measured and whether submaps are stitched on its fit
    (``report.json`` ``ingest.odometry_jitter``)."""

    jitter_m: float
    threshold_m: float
    half_window_s: float
    enabled: bool

    @property
    def applied(self) -> bool:
        return self.enabled and self.jitter_m > self.threshold_m

    def fitted(self, stamps: FloatArray, poses: FloatArray) -> FloatArray:
        """``poses`` (N, 4, 4) at ``stamps`` replaced by their fits (module docs)."""
        return local_fit(stamps, poses, self.half_window_s)[0]

    def report(self) -> dict[str, Any]:
        return {
            "jitter_m": self.jitter_m,
            "threshold_m": self.threshold_m,
            "fit_window_s": 2.0 * self.half_window_s,
            "smoothed": self.applied,
            "enabled": self.enabled,
        }


def smoothing(stamps: FloatArray, poses: FloatArray, cfg: Config) -> Smoothing:
    """The jitter of the scan odometry ``poses`` at ``stamps`` about fits over a submap's
    span, and the decision (module docs), under the run's config."""
    submap = cfg.submap
    return assess(
        stamps,
        poses,
        int(submap.scans_per_submap),
        float(submap.voxel_m),
        bool(submap.smooth_jittery_odometry),
    )


def assess(
    stamps: FloatArray,
    poses: FloatArray,
    scans_per_submap: int,
    voxel_m: float,
    enabled: bool = True,
) -> Smoothing:
    """:func:`smoothing` with the submap's span (in scans) and the voxel given directly (the
    ``auto`` probe, before there is a config)."""
    t = np.asarray(stamps, dtype=np.float64)
    period = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    scans = max(int(scans_per_submap), MIN_FIT_SCANS)
    # A quarter period more: the scans half a span away are in, whatever the stamps' rounding.
    half = (0.5 * scans + 0.25) * period
    _, dist = local_fit(t, np.asarray(poses, dtype=np.float64), half)
    finite = dist[np.isfinite(dist)]
    jitter = float(np.median(finite)) if finite.size else 0.0
    threshold = JITTER_VOXEL_FRACTION * float(voxel_m)
    # The fit's own noise at its centre is about 1.5 / sqrt(n) of the scatter for n scans:
    # as many as bring it to half the threshold, between a submap's span and FIT_MAX_S.
    needed = (1.5 * jitter / (0.5 * threshold)) ** 2 if threshold > 0 else 0.0
    longest = max(half, 0.5 * FIT_MAX_S)
    half = min(max(half, (0.5 * needed + 0.25) * period), longest)
    return Smoothing(
        jitter_m=jitter,
        threshold_m=threshold,
        half_window_s=half,
        enabled=enabled,
    )
