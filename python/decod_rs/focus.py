"""A pass's stitching scale measured by how sharp it leaves the wall (beyond the paper).

A submap stitches its scans with the trajectory's relative poses. Where that trajectory's
scale along the axis is off, each scan's view of the wall lands shifted along the axis from
the next's, by the scale error times the distance between them, and whatever relief the
wall has is smeared: a ribbed pipe's ribs (3.5 cm apart, 1.2 mm high in the simulator's pe
pipe) cancel out, and so does the joint the descriptor is built around. The first round's
boundary tracks and loops measure a pass's scale (:mod:`decod_rs.odometry_scale`) and the
rebuilt round stitches it again (:mod:`decod_rs.refinement`); where that first round saw
too little to measure it, nothing did.

Autofocus measures it from the submaps themselves. A few windows of the pass are stitched
at a range of scales, each window's translations relative to its anchor multiplied by the
scale (rotations kept), and each is extracted as a submap: the robust spread of the DoG
profile (``dog_sigma_m``, the wall's clutter as the boundary detector sees it) is largest
where the scans agree, since agreeing scans add their relief up and disagreeing ones average
it away. Measured on the full tier's 16-beam pe pipe taken over a sweep (seed 1, reversing,
the return's odometry 15 % short, true scale 1.176): the median spread over 12 windows was
0.10 mm at the odometry's scale, 0.29-0.30 mm at 1.15-1.20 and back to 0.11 mm at 1.30; on
the outbound (true 1.053) 0.25 / 0.32 / 0.25 mm at 1.00 / 1.05 / 1.10; on the forward
sensor's pe pipe 0.10 -> 0.31 mm at 1.20; the 16-beam horseshoe 5.9 -> 7.9 mm at 1.20 (true
1.19). On a smooth wall (the hume pipe, no ribs) the curve is flat to +-10 % and nothing is
measured.

It runs only for passes whose scale the first round did not measure, and only changes what
the rebuilt round stitches its submaps on: the graph keeps the odometry's factors and the
rebuilt round's tracks and loops measure the scale the output takes, as for any rebuild.
A peak counts when it lies inside the scales tried and its spread, averaged with its
neighbouring scales', is at least :data:`FOCUS_GAIN` times the spread at the current scale,
averaged so; a scale within
:data:`MIN_CHANGE` of the current one is left alone.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.extraction import scans_submap
from decod_rs.io import ScanRecord, read_log
from decod_rs.progress import Progress
from decod_rs.tum import write_tum

FloatArray = NDArray[np.float64]

__all__ = [
    "FOCUS_GAIN",
    "FOCUS_SCALES",
    "FOCUS_WINDOWS",
    "MIN_CHANGE",
    "PassFocus",
    "focus_curve",
    "focused_stitching",
    "peak_scale",
]

#: The scales tried, relative to the stitching's own: 0.75-1.33 in 15 equal steps of their
#: logarithm (4.2 % apart). LiDAR odometry in a degenerate corridor is off by a few per cent
#: per leg and by 15 % on the return of the matrix's uneven profile; the peak is a few steps
#: wide (the spread halves 5-10 % from it), so a parabola through the best three places it.
FOCUS_SCALES: FloatArray = np.exp(np.linspace(math.log(0.75), math.log(1 / 0.75), 15))
#: Windows per pass, spread evenly over it (the median spread over them is the focus).
FOCUS_WINDOWS = 8
#: The peak's spread over the spread at the current scale (each averaged with its two
#: neighbours' scales) for the peak to count: 2.0-2.9x on the pe pipes with 16 beams and
#: the odometry 13-15 % off, 1.4-2.3x with the forward sensor, 1.02-1.14x on the hume
#: pipe's smooth wall (tiers m71-s71).
FOCUS_GAIN = 1.25
#: A focus scale closer to 1 than this leaves the stitching alone: 2 % of a window's travel
#: is 0.5 cm in the 0.4 m pipe, under its profile's large DoG sigma.
MIN_CHANGE = 0.02


@dataclass
class PassFocus:
    """One pass's focus: the scales tried, the median DoG spread at each (m), the scale
    found (None: no clear peak) and whether the stitching took it."""

    name: str
    scales: list[float] = field(default_factory=list)
    spread_m: list[float] = field(default_factory=list)
    scale: float | None = None
    gain: float | None = None
    applied: bool = False
    windows: int = 0

    def report(self) -> dict[str, Any]:
        return {
            "pass_name": self.name,
            "windows": self.windows,
            "scale": self.scale,
            "gain": self.gain,
            "applied": self.applied,
            "scales": [round(s, 4) for s in self.scales],
            "dog_spread_mm": [round(1e3 * v, 4) for v in self.spread_m],
        }


def _scaled_poses(poses: FloatArray, anchor: int, scale: float) -> FloatArray:
    """``poses`` (n, 4, 4) with their translations relative to ``poses[anchor]`` (in its
    frame) multiplied by ``scale``, rotations kept."""
    world_anchor = poses[anchor]
    relative = np.linalg.inv(world_anchor) @ poses
    relative[:, :3, 3] *= scale
    return np.asarray(world_anchor @ relative, dtype=np.float64)


def _spread(window: list[ScanRecord], scale: float, cfg_json: str) -> float | None:
    """The DoG spread of ``window`` stitched at ``scale`` (None: extraction stopped before
    the boundary profile)."""
    poses = _scaled_poses(np.stack([w.pose for w in window]), len(window) // 2, scale)
    submap = scans_submap(window, cfg_json, poses)
    spread = float(_core.extract_submap(submap, cfg_json).diagnostics.dog_sigma_m)
    return spread if math.isfinite(spread) and spread > 0.0 else None


def focus_curve(windows: list[list[ScanRecord]], cfg_json: str) -> FloatArray:
    """The median DoG spread over ``windows`` at each of :data:`FOCUS_SCALES` (NaN where no
    window reached the profile). Windows are built and extracted two at a time (the core
    releases the GIL)."""
    jobs = [(w, s) for s in FOCUS_SCALES for w in windows]
    with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
        values = list(pool.map(lambda job: _spread(job[0], job[1], cfg_json), jobs))
    curve = np.full(FOCUS_SCALES.size, np.nan)
    for k in range(FOCUS_SCALES.size):
        found = [v for v in values[k * len(windows) : (k + 1) * len(windows)] if v is not None]
        if found:
            curve[k] = float(np.median(found))
    return curve


def _smoothed(curve: FloatArray) -> FloatArray:
    """Each scale's spread averaged with its neighbours' (those measured; NaN where none
    is)."""
    out = np.full(curve.size, np.nan)
    for k in range(curve.size):
        near = curve[max(k - 1, 0) : k + 2]
        near = near[np.isfinite(near)]
        if near.size:
            out[k] = float(near.mean())
    return out


def peak_scale(curve: FloatArray) -> tuple[float | None, float | None]:
    """The scale at the peak of the curve averaged over three neighbouring scales (a
    parabola in log-scale through its best three) and the peak's gain over the current
    scale's, both averaged so; ``(None, gain)`` when the peak is at an end of the scales
    tried or gains less than :data:`FOCUS_GAIN` (``(None, None)``: no spread at the current
    scale or no peak at all). A real peak is several scales wide (the spread halves 5-10 %
    from it); one scale's outlier is not: a 1.2 m hume pipe's flat curve (0.114-0.129 mm)
    had one value of 0.151 mm, 1.25 times the current scale's alone, 1.14 times averaged."""
    curve = _smoothed(np.asarray(curve, dtype=np.float64))
    here = int(np.argmin(np.abs(np.log(FOCUS_SCALES))))
    if not np.isfinite(curve[here]) or curve[here] <= 0.0 or not np.isfinite(curve).any():
        return None, None
    best = int(np.nanargmax(curve))
    gain = float(curve[best] / curve[here])
    if best in (0, curve.size - 1) or gain < FOCUS_GAIN:
        return None, gain
    left, mid, right = curve[best - 1], curve[best], curve[best + 1]
    logs = np.log(FOCUS_SCALES)
    step = float(logs[best + 1] - logs[best])
    shift = 0.0
    if np.isfinite(left) and np.isfinite(right):
        denom = left - 2.0 * mid + right
        if denom < 0.0:
            shift = float(np.clip(0.5 * (left - right) / denom, -0.5, 0.5))
    return float(math.exp(logs[best] + shift * step)), gain


def _pass_ranges(stamps: FloatArray, split: float | None) -> list[tuple[str, int, int]]:
    """Each pass's name and scan index range ``[lo, hi)``."""
    if split is None:
        return [("whole", 0, stamps.size)]
    cut = int(np.searchsorted(stamps, split, side="right"))
    return [("outbound", 0, cut), ("return", cut, stamps.size)]


def _window_starts(lo: int, hi: int, length: int) -> list[int]:
    """:data:`FOCUS_WINDOWS` first scans of windows of ``length`` spread evenly in
    ``[lo, hi)`` (none when the pass is shorter than two windows)."""
    if hi - lo < 2 * length:
        return []
    starts = np.linspace(lo, hi - length, FOCUS_WINDOWS).astype(int)
    return sorted(set(starts.tolist()))


def _read_windows(
    log: Path,
    topics: tuple[str | None, str | None],
    stamps: FloatArray,
    poses: FloatArray,
    starts: list[int],
    length: int,
    reading: tuple[bool, float],
    progress: bool = False,
) -> list[list[ScanRecord]]:
    """The scans of the windows at ``starts`` (indices into ``stamps``), each with its pose
    in ``poses``, read from ``log`` (points and IMU topics ``topics``; deskew and odometry
    gap periods ``reading``), up to the last one (a progress bar over them with
    ``progress``)."""
    wanted: dict[int, int] = {}
    for w, start in enumerate(starts):
        for k in range(start, start + length):
            wanted.setdefault(k, w)
    windows: list[list[ScanRecord]] = [[] for _ in starts]
    with tempfile.TemporaryDirectory(prefix="decod-focus-") as tmp:
        tum = Path(tmp) / "stitching.tum"
        write_tum(tum, stamps, poses)
        reader = read_log(
            log, topics[0], None, tum, topics[1], gap_periods=reading[1], deskew=reading[0]
        )
        last = max(wanted) if wanted else -1
        bar = Progress("focus", last + 1, enabled=progress)
        for rec in reader:
            bar.advance(1)
            k = int(np.searchsorted(stamps, rec.stamp))
            if k < stamps.size and abs(stamps[k] - rec.stamp) < 1e-6 and k in wanted:
                windows[wanted[k]].append(rec)
            if k >= last:
                break
        bar.close()
    return [w for w in windows if len(w) == length]


def focused_stitching(
    log: Path,
    topics: tuple[str | None, str | None],
    stamps: FloatArray,
    stitching: FloatArray,
    split: float | None,
    unmeasured: list[bool],
    cfg: Any,
    progress: bool = False,
) -> tuple[FloatArray, list[PassFocus]]:
    """``stitching`` (N, 4, 4 at ``stamps``) with each pass flagged in ``unmeasured`` (one
    flag per pass of :func:`_pass_ranges`) rescaled about its first scan by its focus scale,
    where one is found (module docs), and every pass's focus. ``topics``: the points and IMU
    topics; ``cfg``: the run's config; ``progress``: a bar while the log is read."""
    cfg_json = json.dumps(cfg.to_dict())
    length = int(cfg.submap.scans_per_submap)
    reading = (bool(cfg.submap.deskew), float(cfg.submap.odometry_gap_periods))
    out = np.array(stitching, dtype=np.float64, copy=True)
    found: list[PassFocus] = []
    for (name, lo, hi), flagged in zip(_pass_ranges(stamps, split), unmeasured, strict=True):
        if not flagged:
            continue
        focus = PassFocus(name, scales=[float(s) for s in FOCUS_SCALES])
        windows = _read_windows(
            log,
            topics,
            stamps,
            stitching,
            _window_starts(lo, hi, length),
            length,
            reading,
            progress,
        )
        focus.windows = len(windows)
        if windows:
            curve = focus_curve(windows, cfg_json)
            focus.spread_m = [float(v) for v in curve]
            focus.scale, focus.gain = peak_scale(curve)
        if focus.scale is not None and abs(focus.scale - 1.0) >= MIN_CHANGE:
            start = out[lo, :3, 3].copy()
            moved = start + focus.scale * (out[lo:hi, :3, 3] - start)
            shift = moved[-1] - out[hi - 1, :3, 3]
            out[lo:hi, :3, 3] = moved
            out[hi:, :3, 3] += shift
            focus.applied = True
        found.append(focus)
    return out, found
