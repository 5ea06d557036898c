"""Defaults that scale themselves (``decod run`` without ``--preset``; beyond the paper).

The paper fixes its sampling for 5-10 m GEODE tunnels and scales it down ten times for
0.4-0.8 m pipes (§IV-E). A user's corridor is neither; so ``auto`` *measures* it and derives
every spatial parameter from what it measured:

1. **Cross-section.** The first scans of the log are accumulated into a few probe submaps
   (2 cm voxels, 40 m range, no corridor gates) and the reference contour is fitted: the
   median contour radius ``r`` over the probes whose median contour offset is below 0.1 r.
2. **Where the sensor samples the whole ring.** For each probe, the wall points are binned by
   their distance ahead of the sensor along the axis and by angle around the section (36
   sectors, bottom +-30 deg excluded, as in the descriptor): ``z_near`` is the nearest
   distance at which 90 % of the sectors are sampled, i.e. where a boundary's whole ring is
   first in view. A spinning sensor with +-22.5 deg sees the crown of a 6 m tunnel only from
   about 7 m (measured 7.0 m on the simulated shield tunnel), a forward-looking rosette a
   pipe's whole ring from about half a radius.
3. **Speed and scan rate** from the log's odometry and scan stamps.
4. **The wall's relief.** The probe windows are extracted again under the config derived
   from steps 1-3, and ``relief`` is the lower median over them of the 90th percentile of
   the points' offsets from the fitted contour (over each whole window but the slices that
   fail the gate at its ends: :func:`_relief`). A lining or a pipe wall is one surface (relief
   1-4 mm in the simulated hume and pe pipes, 13-60 mm in the shield linings, up to 93 mm
   where the sensor stood still in two of the four windows); steel arches 0.2 m before the
   rock are two (relief 0.13-0.15 m for every sensor and mount in the simulated 4-5 m
   horseshoe tunnels of the matrix's three tiers, 0.23-0.24 m in the 10 m one).
5. **Points per descriptor.** Per probe scan, the scan's own wall points (not voxel-filtered,
   bottom sector excluded) ahead of the sensor between ``z_near`` and the derived range,
   scaled to one descriptor length: how many points one scan puts into a boundary's
   descriptor, whose 16 x 256 cells are 3,413 outside the bottom mask. Measured over the
   generalisation matrix (m71): 16 beams 420-500 in the 0.4 and 0.6 m pipes and 380-600 in
   the horseshoe tunnel, the forward rosette 690-1,670, 64 beams 1,170-2,070. With them,
   the **wall share**: of the 30 sectors (10 deg) outside the bottom mask, the share holding
   at least ``SEEN_DENSITY`` (a fifth) of the median sector's points. Water in a pipe hides
   the wall below its surface and mirrors the beam away: a sewer 30 % full leaves 0.73 of
   the section in view, and the points of a scan all fall there. 1.0 in every run of the
   full tier (m2 of 2026-12-05).

Derived (the tunnel preset, measured on the simulated 6 m shield tunnel, is the reference
at ``r_ref = 3 m``; ``k = r / r_ref``; the pipe preset is the same rule at k = 0.1):

- voxel ``0.055 k``, contour inlier distance ``0.18 k`` or ``RELIEF_MARGIN`` (1.5) times the
  relief if that is more: the contour test is for what is not a corridor (a portal, a cap,
  a chamber), and a wall with two surfaces is a corridor. With the paper's 0.18 m, 46 % of
  the horseshoe submaps seen by 64 beams and 44 % by 16 beams were rejected (85-90 % of their
  points on the contour; the gate asks 90 %), and 5 of the 8 horseshoe + 64-beam runs of the
  matrix covered fewer than half of the arches; profile bin ``0.01 k``, DoG sigmas
  ``0.025 k`` / ``0.10 k``, minimum DoG response ``0.002 k``, descriptor half length
  ``2.4 k`` (0.8 r: the 16 rows then cover the same share of the section in every corridor),
  circumferential smoothing one column and a half of arc, duplicate radius ``0.4 k`` (within
  0.1-0.4 m); the minimum range ``0.5 k``;
- range window: out to where the wall is still seen at ``GRAZING_DEG`` (12 deg) or more
  (``r / tan``), and at least one descriptor length plus a radius beyond ``z_near`` (so a
  sensor that sees the whole ring late still puts whole boundaries into a submap). Measured
  (loops accepted, all correct; simulated corridors, 30-40 m out and back): 8 deg / 60 %
  coverage: hume-avia 62, pe-spin16 2, horseshoe-avia 7, shield-spin64 2; 12 deg / 90 %:
  82, 13, 9, and shield-spin64 at 14.8 m / 2 s, the tunnel preset's measured schedule;
  16 deg left hume and the horseshoe without landmarks (range below the descriptor);
- non-maximum suppression stays 0.8 m: it is about boundary spacing (pipe joints >= 1 m,
  tunnel rings >= 1.2 m), which does not scale with the section;
- schedule: an anchor every third of the visible window of travel, ``interval = (max_range -
  z_near) / (3 v)`` (each boundary is then seen from about three submaps per pass), with
  every scan in between accumulated, but at least the scans that put ``-ln(1 - f)`` = 1.23
  points per cell into a descriptor (step 5; Poisson: a share ``f`` = ``DESCRIPTOR_FILL`` =
  0.71 of the cells observed, so that two views of one boundary share half of them, twice
  the matcher's ``min_overlap_fraction``), counting only the cells of the wall share: the
  water's cells never fill, and asking for them made the windows of a 0.4 m pe pipe 30 %
  full seen by 16 beams 1.3 s long (13 scans, at the drift cap) instead of 1.0 s, and
  boundaries smeared by 15 % odometry left no loop (held out, fresh tier seed 7 and seed
  26; seeds 27-29 still close none). 16 beams in the pipes at 0.4 m/s cross the
  visible window in 0.5-0.8 s (5-8 scans, 2,400-3,400 points for 3,413 cells); in the pe
  pipe most queries were then rejected ``insufficient_overlap``. The rule asks 8-10 scans
  there; elsewhere in the matrix it moved only the 0.3 m hume pipe's anchors (0.59 -> 0.61
  s). Full matrix (m70 -> m71): pe runs with 16 beams covering under half the joints 7 ->
  1, under uneven drift 0 -> 6-7 loops each (endpoint 3.2 m -> 0.00-1.05 m), the hume pipe
  with 16 beams 861 -> 970 loops, no loop wrong anywhere. Filling is capped by the drift:
  a window lasts at most ``half_length / (SMEAR_DRIFTS * DRIFT_FRACTION * v)``, so that
  odometry drifting by ``DRIFT_FRACTION`` smears a boundary across it by at most half the
  descriptor's half length. The fresh tier's 0.6 m hume pipe with 16 beams rolled 30 deg
  and pitched 10 deg had one probe of four see the whole ring from 2.7 m and a scan put 35
  points into a descriptor there, so filling asked for 12 s windows (4.7 m of travel, 0.7 m
  of smear at 15 %): no loop under either drift. Capped (2.0-2.3 s): 65 and 63 loops, all
  right, RMSE 0.85 -> 0.04 m and 1.29 -> 0.01 m; nothing in the full matrix changed (m124:
  the cap never binds there). The schedule is chosen for the typical speed ``v``; where
  the robot drives faster (a crawler inspecting slowly on the way out and coming back
  fast), a window closes, and the next one starts, once the odometry has moved
  ``TRAVEL_SLACK`` (1.25) times ``interval * v`` (``submap.max_travel_m``), so a boundary
  is smeared, and seen from as many windows, as at ``v``; where filling the descriptor set
  the interval, a window needs its scans more than its travel, and it may travel as far as
  the drift cap allows at ``v`` (``drift_cap * v``, if more). Held out (seed 223, the return
  leg 2.5-3 times as fast as the outbound): with the time schedule alone the 6 m shield
  with 64 beams out at 0.8 m/s and back at 2 m/s, odometry 5 % / 15 % short, closed loops
  only near the turnaround and came out worse than its odometry (RMSE 3.04 -> 3.70 m).
  The minimum time between loop partners is
  ``max(10 s, 2 max_range / v + interval)``: two views of the same pass never pair;
- the elongation gate is only a PCA-ambiguity guard (1.1): a forward-looking sensor sees
  a 5 m tunnel to 12 m, ratio 1.3, and the corridor test is the contour fit, not how far the
  sensor sees;
- curve: ``axis.curved`` (each submap's centre line fitted as a parabola,
  ``src/centre_line.rs``) where the odometry's path curves
  (:func:`decod_rs.path_curve.path_curvature` over windows of twice the range window's far
  end, the stretch one submap sees, and at least ``CURVE_MIN_WINDOW_M``) enough that its
  sagitta over the range window, ``curvature * max_range^2 / 2``, is at least
  ``CURVE_SAGITTA_RADII`` of the radius (a 6 m tunnel seen to 15 m: curves of about 600 m or
  tighter; 162 straight runs of the matrix and the held-out sets reached at most 0.69 of
  that, 16 curved logs at least 1.11). Held out (seed 211, eight corridors on 20-500 m
  curves): the 6 m shield with 64 beams on a 300 m curve had its corrected RMSE at 0.43 m
  (symmetric drift, odometry 1.08 m), 0.018 m with the curve fitted.

``report.json`` records the measurements and every derived value (``auto``), and which of
the schedule's three rules set the anchor interval (``auto.schedule``: ``visible_window``,
``descriptor_fill``, ``drift_cap`` or ``minimum``, with each rule's interval).
"""

from __future__ import annotations

import json
import math
import os
import tomllib
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.config import Config
from decod_rs.extraction import scans_submap
from decod_rs.ingest import LogWarning
from decod_rs.io import ScanReader, read_log
from decod_rs.jitter import assess
from decod_rs.path_curve import path_curvature
from decod_rs.stall import odometry_speed
from decod_rs.tum import interpolate_poses, poses_from_tq

FloatArray = NDArray[np.float64]

R_REF_M = 3.0
GRAZING_DEG = 12.0
PROBE_SCANS = 10
PROBE_COUNT = 4
PROBE_MAX_SCANS = 300
COVERAGE_SECTORS = 36
COVERAGE_FRACTION = 0.9
DRIFT_FRACTION = 0.15
#: ``matching.consistency_drift_fraction`` is that drift per metre of the odometry's own
#: path, which is what the consistency gates measure separations along: odometry 15 % short
#: of the distance driven drifts 0.15 / 0.85 = 17.6 % of its own path. At 0.15 the gates
#: dropped 198 loops of the full tier as ``inconsistent``, 168 of them right (0.3 m, m12), 20
#: of 21 in the pitched horseshoe of the fresh tier under uneven drift (coverage 42 %); at
#: 0.176, 36 (9 right) and 18 (10 right) of the fresh tier's instead of 123 (113): m13 and f13
#: against m12 and f12, the same logs, 11,469 -> 11,640 and 7,281 -> 7,396 loops, none wrong,
#: that horseshoe's coverage 42 -> 55 %, RMSE geometric mean x1.004 and x1.015 (4 rows better
#: by more than 10 %, 9 worse, at most 0.016 -> 0.043 m where the odometry was 4 m off).
CONSISTENCY_DRIFT_FRACTION = DRIFT_FRACTION / (1.0 - DRIFT_FRACTION)
#: A window lasts at most ``half_length / (SMEAR_DRIFTS * DRIFT_FRACTION * v)``: odometry
#: drifting by DRIFT_FRACTION smears a boundary across a window by at most half of the
#: descriptor's half length (module docs, schedule).
SMEAR_DRIFTS = 2.0
#: ``submap.max_travel_m`` is this many times the travel the schedule was chosen for
#: (interval x the typical speed): a window closes, and the next starts, by travel only
#: where the robot drives faster than that (module docs, schedule). Above the odometry's
#: speed on one leg against the other's under the matrix's uneven drift (0.95 / 0.85 =
#: 1.12), so a log driven at one speed keeps the time schedule.
TRAVEL_SLACK = 1.25
RELIEF_MARGIN = 1.5
#: ``axis.curved`` where the path's curve puts the centre line this share of the radius off
#: the chord at the range window's far end (module docs, curve).
CURVE_SAGITTA_RADII = 0.05
#: The path's curve is measured over at least this many metres (module docs, curve), for the
#: crawler's steering wobble (a few metres long) to average out: over 5.6 m (twice the 1.2 m
#: pipe's range window) a straight 1.2 m pipe read as curved (m161).
CURVE_MIN_WINDOW_M = 10.0
BOTTOM_MASK_DEG = 30.0
#: Descriptor cells outside the bottom mask: 16 x 256 x (300 / 360).
DESCRIPTOR_CELLS = 16 * 256 * (360.0 - 2 * BOTTOM_MASK_DEG) / 360.0
#: Share of a descriptor's cells a submap should observe: two views of one boundary then
#: share half of them (0.707^2), twice the matcher's ``min_overlap_fraction`` (0.25).
DESCRIPTOR_FILL = math.sqrt(2 * 0.25)
#: Sectors (10 deg) of the section outside the bottom mask the wall share is counted in.
SHARE_SECTORS = 30
#: A sector is seen when it holds this share of the median sector's points or more (module
#: docs, step 5): water mirrors the beam away (the simulator returns 3 % of its rays), a
#: wall at another distance or incidence changes the density by a factor of 2-3.
SEEN_DENSITY = 0.2

__all__ = ["CorridorProbe", "auto_config", "derive", "probe_corridor"]


@dataclass(frozen=True)
class CorridorProbe:
    """What ``auto`` measured: contour radius (m), nearest fully sampled distance ahead of
    the sensor (m), speed (m/s), scan rate (Hz), probe submaps used, the wall's relief
    about the contour (m, step 4), the wall points one scan puts into a descriptor-long
    stretch of the range window and the share of the section outside the bottom mask those
    points fall on (step 5)."""

    radius_m: float
    z_near_m: float
    speed_mps: float
    scan_rate_hz: float
    probes: int
    relief_m: float = 0.0
    descriptor_points: float = math.inf
    wall_share: float = 1.0
    curvature_per_m: float = 0.0


def _probe_config() -> str:
    cfg = json.loads(_core.resolve_config_json("tunnel", ""))
    cfg["submap"].update(voxel_m=0.02, min_range_m=0.1, max_range_m=40.0, min_points=50)
    cfg["axis"]["min_elongation"] = 1.0
    cfg["contour"].update(model="auto", inlier_distance_m=100.0, min_inlier_fraction=0.0)
    return json.dumps(cfg)


def _speed(odometry: FloatArray) -> float:
    """The typical moving speed: median over 1 s windows where the robot moves."""
    return odometry_speed(odometry[:, 0], odometry[:, 1:4])


def _section_axes(axis: FloatArray, gravity: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The cross-section's unit axes: ``e1`` towards gravity (angle 0 = down), ``e2`` =
    ``axis x e1``."""
    e1 = gravity - axis * float(gravity @ axis)
    e1 /= max(float(np.linalg.norm(e1)), 1e-12)
    return e1, np.cross(axis, e1)


def _z_near(points: FloatArray, axis: FloatArray, centre: FloatArray, gravity: FloatArray) -> float:
    """Nearest distance ahead of the sensor (at the origin) at which COVERAGE_FRACTION of the
    non-bottom sectors hold wall points."""
    e1, e2 = _section_axes(axis, gravity)
    rel = points - centre
    z = points @ axis
    ang = np.degrees(np.arctan2(rel @ e2, rel @ e1))  # 0 deg = down (gravity)
    keep = (np.abs(ang) > 30.0) & (z > 0)
    z, ang = z[keep], ang[keep]
    if z.size == 0:
        return math.inf
    step = max(float(np.ptp(z)) / 200.0, 0.01)
    zb = np.floor(z / step).astype(np.int64)
    sb = np.floor((ang + 180.0) / 360.0 * COVERAGE_SECTORS).astype(np.int64) % COVERAGE_SECTORS
    usable = COVERAGE_SECTORS * (300.0 / 360.0)
    seen = np.zeros((int(zb.max()) + 1, COVERAGE_SECTORS), dtype=bool)
    seen[zb, sb] = True
    covered = np.flatnonzero(seen.sum(axis=1) >= COVERAGE_FRACTION * usable)
    return float(covered[0] * step) if covered.size else math.inf


def _probe_windows(windows: list[list[Any]], cfg: str) -> list[tuple[Any, Any]]:
    """Each window's probe submap and its extraction result under config JSON ``cfg``, in
    order. The windows are independent and the core releases the GIL, so two threads build
    and extract them side by side (the probe was 0.75 s of a 4.7 s run on a 64-beam log,
    building and extracting its eight submaps one at a time)."""

    def one(window: list[Any]) -> tuple[Any, Any]:
        submap = scans_submap(window, cfg)
        return submap, _core.extract_submap(submap, cfg)

    if len(windows) < 2:
        return [one(w) for w in windows]
    with ThreadPoolExecutor(max_workers=min(len(windows), os.cpu_count() or 1)) as pool:
        return list(pool.map(one, windows))


def _probe_starts(count: int) -> list[int]:
    """The first scan of each probe window among ``count`` scans (windows spread evenly)."""
    starts = np.linspace(0, count - PROBE_SCANS, PROBE_COUNT).astype(int)
    return sorted(set(starts.tolist()))


def _read_probe_scans(
    log: Path,
    points_topic: str | None,
    odom_topic: str | None,
    odom_tum: Path | None,
    imu_topic: str | None,
    deskew: bool = True,
) -> tuple[list[list[Any]], FloatArray, FloatArray, FloatArray | None]:
    """The probe windows among the first PROBE_MAX_SCANS scans of ``log`` (:func:`_probe_starts`
    of their count), the stamps of all those scans, the log's odometry and its IMU samples.

    Only the windows' scans are kept (40 of 300: a 64-beam log's probe held 160 MB of points
    for the 300). The windows are planned on the count the log announces; when fewer scans
    pair with the odometry than that, the log is read once more with the count it gave."""
    reader = read_log(log, points_topic, odom_topic, odom_tum, imu_topic, deskew=deskew)
    planned = min(PROBE_MAX_SCANS, max(int(reader.total_scans_hint), PROBE_SCANS))
    windows, stamps = _read_windows(reader, _probe_starts(planned))
    if len(stamps) < PROBE_SCANS:
        raise ValueError(
            f"{log}: auto configuration needs >= {PROBE_SCANS} scans, got {len(stamps)}"
        )
    if len(stamps) != planned:  # scans left out (outside the odometry, in a gap): plan again
        reader = read_log(log, points_topic, odom_topic, odom_tum, imu_topic, deskew=deskew)
        windows, stamps = _read_windows(reader, _probe_starts(len(stamps)))
    return windows, stamps, reader.odometry(), reader.imu_samples()


def _read_windows(reader: ScanReader, starts: list[int]) -> tuple[list[list[Any]], FloatArray]:
    """The windows of PROBE_SCANS scans at ``starts`` (scan indices) and the stamps of every
    scan read, at most PROBE_MAX_SCANS."""
    windows: list[list[Any]] = [[] for _ in starts]
    stamps = []
    with warnings.catch_warnings():
        # A damaged log is reported once, by the run that follows (decod_rs.ingest).
        warnings.simplefilter("ignore", LogWarning)
        for k, rec in enumerate(reader):
            stamps.append(rec.stamp)
            for start, window in zip(starts, windows, strict=True):
                if start <= k < start + PROBE_SCANS:  # windows overlap in a short log
                    window.append(rec)
            if k + 1 >= PROBE_MAX_SCANS:
                break
    return windows, np.asarray(stamps, dtype=np.float64)


def _relief(windows: list[list[Any]], probe: CorridorProbe) -> float:
    """The wall's relief (module docs, step 4): the lower median over the probe windows of
    the 90th percentile of the points' contour offsets, under the config derived without it
    (its range window, voxel and contour gate: it is measured whether the gate passes or
    not, and the gate's model choice stays the run's); 0 if no window has a contour.

    Over the whole window but its ends (``contour.corridor_span = "ends"``): a window that
    fails the gate loses the failing slices at either end (a corridor's end face in view),
    not every slice that fails. Cut to its longest run of slices that pass, as a run's
    submap is, a window in a steel-arch tunnel that straddles the gate kept only the slices
    between two arches: a replicate log of the matrix (seed 251, 16 beams pitched 20 deg)
    read 0.096 m under its drifting odometry and 0.153 m on ground truth, and its run's
    gate at 0.146 m rejected 14 of 32 submaps (no loop); now 0.147 m under both. Not cut at
    all, the window at the start of a log reads the end face behind it (0.7-0.9 m).

    The lower median (the second of four): what is not the wall only ever adds to a window's
    offsets. A sensor standing still in a 6 m shield lining sees the flat floor around it
    off the circle its window is fitted with (a tenth of the points, all near the sensor,
    where the moving windows spread them along); two of that replicate log's four windows
    stood (0.18 m each, the other two 0.08 m with the start's end face, and 0.02 m), and
    their median read 0.13 m, where the lining's is 0.02 m."""
    derived = derive(probe)
    derived["contour"]["corridor_span"] = "ends"
    cfg_json = _core.resolve_config_json("tunnel", _toml(derived))
    reliefs = []
    for _, result in _probe_windows(windows, cfg_json):
        d = result.diagnostics
        if np.isfinite(d.contour_radius_m) and d.contour_radius_m > 0:
            reliefs.append(d.contour_p90_abs_offset_m)
    return sorted(reliefs)[(len(reliefs) - 1) // 2] if reliefs else 0.0


def _descriptor_points(
    windows: list[list[Any]], probed: list[tuple[Any, FloatArray]], probe: CorridorProbe
) -> tuple[float, float]:
    """Wall points one scan puts into a descriptor-long stretch of the range window, and the
    share of the section outside the bottom mask they fall on (module docs, step 5): per
    probe window, the corridor axis of the window's submap (``probed``: the submap and axis
    :func:`probe_corridor` measured, not built again); per scan of it (three), the scan's
    own points (not voxel-filtered) ahead of the sensor, bottom sector excluded, between
    ``z_near`` and the derived ``max_range``, times one descriptor length over that window;
    the median over the scans. The share: of the :data:`SHARE_SECTORS` sectors outside the
    bottom mask, those holding at least :data:`SEEN_DENSITY` of the median sector's points
    (all scans together). ``(inf, 1)`` when nothing could be measured (the schedule then
    follows the visible window alone)."""
    derived = derive(probe)
    length = 2.0 * float(derived["descriptor"]["half_length_m"])
    z_lo = probe.z_near_m if np.isfinite(probe.z_near_m) else 0.0
    z_hi = float(derived["submap"]["max_range_m"])
    if z_hi - z_lo < length:
        z_lo = max(z_hi - length, 0.0)
    counts = []
    sectors = np.zeros(SHARE_SECTORS)
    span = 360.0 - 2.0 * BOTTOM_MASK_DEG
    for window, (window_submap, window_axis) in zip(windows, probed, strict=True):
        axis = window_axis.copy()
        if float(np.asarray(window_submap.forward) @ axis) < 0:
            axis = -axis  # ahead of the sensor (a window is a second: its heading is one)
        gravity = np.asarray(window_submap.gravity)
        e1, e2 = _section_axes(axis, gravity)
        for scan in window[:: max(len(window) // 3, 1)]:
            points = np.asarray(scan.points, dtype=np.float64)
            z = points @ axis
            ang = np.degrees(np.arctan2(points @ e2, points @ e1))
            keep = (np.abs(ang) > BOTTOM_MASK_DEG) & (z >= z_lo) & (z < z_hi)
            counts.append(np.count_nonzero(keep) * length / (z_hi - z_lo))
            # Angle from the mask's edge, through the crown, to its other edge.
            from_edge = np.mod(ang[keep] - BOTTOM_MASK_DEG, 360.0)
            k = np.minimum((from_edge / span * SHARE_SECTORS).astype(np.int64), SHARE_SECTORS - 1)
            sectors += np.bincount(k, minlength=SHARE_SECTORS)
    if not counts:
        return math.inf, 1.0
    median = float(np.median(sectors))
    share = float(np.mean(sectors >= SEEN_DENSITY * median)) if median > 0 else 1.0
    return float(np.median(counts)), max(share, 1.0 / SHARE_SECTORS)


def probe_corridor(
    log: Path,
    points_topic: str | None,
    odom_topic: str | None,
    odom_tum: Path | None,
    imu_topic: str | None,
    deskew: bool = True,
) -> tuple[CorridorProbe, FloatArray | None]:
    """Measure the corridor from the first scans of ``log`` (module docs, steps 1-4), their
    points moved by their own times where the clouds carry them and ``deskew`` (the run's
    ``submap.deskew``). Also returns the IMU samples the probe's pass over the log read
    (``None`` without an IMU): the run's processor takes them instead of reading the whole
    file for them again."""
    candidates, stamps, odometry, imu = _read_probe_scans(
        log, points_topic, odom_topic, odom_tum, imu_topic, deskew
    )
    probe = _measure(log, candidates, stamps, odometry)
    steady = _steadied(candidates, stamps, odometry, probe)
    return (probe if steady is None else _measure(log, steady, stamps, odometry)), imu


def _steadied(
    windows: list[list[Any]], stamps: FloatArray, odometry: FloatArray, probe: CorridorProbe
) -> list[list[Any]] | None:
    """The probe windows with their scans' poses from the odometry's fit, where the odometry
    jitters beyond what the run will smooth (:mod:`decod_rs.jitter`, under the voxel and the
    submap span derived from ``probe``); ``None`` where it does not. The corridor is then
    measured on steady windows: on the 0.6 m pipe whose poses scatter 1 cm, the raw ones
    measured the wall's relief at 15 mm instead of 6 mm."""
    submap = derive(probe)["submap"]
    poses = poses_from_tq(odometry[:, 1:4], odometry[:, 4:8])
    at_scans = interpolate_poses(odometry[:, 0], poses, stamps)
    decision = assess(stamps, at_scans, int(submap["scans_per_submap"]), submap["voxel_m"])
    if not decision.applied:
        return None
    fitted = decision.fitted(stamps, at_scans)
    index = {float(t): k for k, t in enumerate(stamps)}
    return [[replace(rec, pose=fitted[index[float(rec.stamp)]]) for rec in w] for w in windows]


def _measure(
    log: Path, candidates: list[list[Any]], stamps: FloatArray, odometry: FloatArray
) -> CorridorProbe:
    """Steps 1-5 of the module docs on the probe windows ``candidates``."""
    cfg = _probe_config()
    radii, nears, windows = [], [], []
    probed: list[tuple[Any, FloatArray]] = []  # each kept window's submap and axis
    for window, (submap, result) in zip(candidates, _probe_windows(candidates, cfg), strict=True):
        d = result.diagnostics
        r = d.contour_radius_m
        if not (np.isfinite(r) and r > 0 and d.contour_median_abs_offset_m < 0.1 * r):
            continue
        radii.append(r)
        windows.append(window)
        axis = np.asarray(d.axis)
        probed.append((submap, axis))
        gravity = np.asarray(submap.gravity)
        e1, e2 = _section_axes(axis, gravity)
        cu, cv = d.contour_centre_e1e2
        centre = np.asarray(d.centroid) + cu * e1 + cv * e2
        nears.append(_z_near(np.asarray(submap.points), axis, centre, gravity))
    if not radii:
        raise ValueError(
            f"{log}: auto configuration found no corridor cross-section in the first "
            f"{len(stamps)} scans; pass --preset pipe|tunnel or --config"
        )
    rate = float(1.0 / np.median(np.diff(stamps))) if stamps.size > 1 else 10.0
    finite = [z for z in nears if np.isfinite(z)]
    probe = CorridorProbe(
        radius_m=float(np.median(radii)),
        z_near_m=float(np.median(finite)) if finite else math.inf,
        speed_mps=_speed(odometry),
        scan_rate_hz=rate,
        probes=len(radii),
    )
    probe = replace(probe, relief_m=_relief(windows, probe))
    points, share = _descriptor_points(windows, probed, probe)
    probe = replace(probe, descriptor_points=points, wall_share=share)
    curve_window = max(2.0 * _reach(probe)[2], CURVE_MIN_WINDOW_M)
    return replace(probe, curvature_per_m=path_curvature(odometry[:, 1:4], curve_window))


def _reach(probe: CorridorProbe) -> tuple[float, float, float]:
    """The descriptor's half length, ``z_near`` (where the whole ring is first sampled, or
    where the wall is seen at ``GRAZING_DEG`` when it never is) and the range window's far
    end (m; module docs, range window)."""
    r = probe.radius_m
    half = 2.4 * (r / R_REF_M)
    grazing = r / math.tan(math.radians(GRAZING_DEG))
    z_near = probe.z_near_m if np.isfinite(probe.z_near_m) else grazing
    return half, z_near, max(grazing, z_near + 2.0 * half + r)


def _schedule(probe: CorridorProbe) -> dict[str, Any]:
    """The anchor interval (s) and the three rules behind it (module docs, schedule): an
    anchor every third of the visible window of travel, at least the time that fills a
    descriptor, at most the time over which the drift decod allows for smears a boundary
    by half the descriptor's half length; ``rule`` names the one that set the interval
    (``minimum``: 0.5 s, when both the window and the fill ask for less)."""
    half, z_near, max_range = _reach(probe)
    v = max(probe.speed_mps, 0.05)
    visible = (max_range - min(z_near, max_range / 2)) / (3.0 * v)
    points = -math.log(1.0 - DESCRIPTOR_FILL) * DESCRIPTOR_CELLS * probe.wall_share
    fill = points / max(probe.descriptor_points, 1.0) / probe.scan_rate_hz
    cap = max(half / (SMEAR_DRIFTS * DRIFT_FRACTION * v), 0.5)
    interval = min(max(visible, fill, 0.5), cap)
    if max(visible, fill) <= 0.5:
        rule = "minimum"
    elif interval == cap:
        rule = "drift_cap"
    else:
        rule = "descriptor_fill" if fill > visible else "visible_window"
    return {
        "interval_s": interval,
        "rule": rule,
        "visible_window_s": visible,
        "descriptor_fill_s": fill,
        "drift_cap_s": cap,
    }


def derive(probe: CorridorProbe) -> dict[str, dict[str, Any]]:
    """The config overrides (on the tunnel preset) for a measured corridor (module docs)."""
    r = probe.radius_m
    k = r / R_REF_M
    half, _, max_range = _reach(probe)
    v = max(probe.speed_mps, 0.05)
    schedule = _schedule(probe)
    interval = schedule["interval_s"]
    scans = int(np.clip(round(interval * probe.scan_rate_hz), 5, 40))
    # A window's travel at speeds above v (module docs, schedule): the visible window's, or
    # where filling the descriptor set the time, what the drift cap allows.
    travel = TRAVEL_SLACK * interval
    if schedule["rule"] == "descriptor_fill":
        travel = max(travel, schedule["drift_cap_s"])
    return {
        "submap": {
            "scans_per_submap": scans,
            "interval_s": round(interval, 3),
            "max_travel_m": round(travel * v, 3),
            "voxel_m": 0.055 * k,
            "min_range_m": 0.5 * k,
            "max_range_m": round(max_range, 3),
        },
        "axis": {
            "min_elongation": 1.1,
            "curved": probe.curvature_per_m * max_range**2 / 2.0 >= CURVE_SAGITTA_RADII * r,
        },
        "contour": {"inlier_distance_m": max(0.18 * k, RELIEF_MARGIN * probe.relief_m)},
        "boundary": {
            "profile_bin_m": 0.01 * k,
            "dog_sigma_small_m": 0.025 * k,
            "dog_sigma_large_m": 0.10 * k,
            "min_strength_m": 0.002 * k,
        },
        "descriptor": {"half_length_m": half, "axial_interpolation": True},
        "matching": {
            "field_smoothing_sigma_m": 1.5 * 2.0 * math.pi * r / 256.0,
            "duplicate_radius_m": float(np.clip(0.4 * k, 0.1, 0.4)),
            "min_time_separation_s": round(max(10.0, 2.0 * max_range / v + interval), 1),
            "consistency_drift_fraction": CONSISTENCY_DRIFT_FRACTION,
        },
        "graph": {"landmark_position_sigma_m": float(np.clip(0.05 * k, 0.01, 0.05))},
    }


def _toml(tables: dict[str, dict[str, Any]]) -> str:
    lines = []
    for section, values in tables.items():
        lines.append(f"[{section}]")
        lines.extend(f"{key} = {json.dumps(value)}" for key, value in values.items())
    return "\n".join(lines) + "\n"


def auto_config(probe: CorridorProbe, user_toml: Path | None) -> tuple[Config, dict[str, Any]]:
    """The derived config with the user's TOML (if any) applied on top, and the report
    section saying what was measured and chosen."""
    derived = derive(probe)
    merged = {s: dict(v) for s, v in derived.items()}
    if user_toml is not None:
        user = tomllib.loads(Path(user_toml).read_text(encoding="utf-8"))
        for section, values in user.items():
            if isinstance(values, dict):
                merged.setdefault(section, {}).update(values)
    cfg = Config(json.loads(_core.resolve_config_json("tunnel", _toml(merged))))
    report = {
        # JSON has no infinity: a distance never fully sampled is null.
        "measured": {
            k: None if isinstance(v, float) and not math.isfinite(v) else v
            for k, v in asdict(probe).items()
        },
        "derived": derived,
        # Which rule set the anchor interval, and each rule's interval (s).
        "schedule": {
            k: round(v, 3) if isinstance(v, float) and math.isfinite(v) else v
            for k, v in _schedule(probe).items()
            if k != "interval_s"
        },
        "corridor": "pipe" if probe.radius_m < 1.0 else "tunnel",
        "user_overrides": None if user_toml is None else str(user_toml),
    }
    return cfg, report
