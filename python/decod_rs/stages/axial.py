"""Stage 1 with the odometry checked along the corridor's axis (:mod:`decod_rs.stall`):
configure and extract; where the odometry hardly moves, the log extracted again in short
windows and the boundaries' motion through the sensor's view measured; where that motion is
the larger, the run's odometry is restitched on it and the run configured and extracted
again on it."""

from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.config import Config
from decod_rs.stages.extract import Extracted, Topics, extract_stage
from decod_rs.stages.extract import restitched as restitched_on
from decod_rs.stall import (
    AXIAL_PASSES,
    CHANCE_SIGMAS,
    MIN_VOTES,
    MIN_WINDOW_SCANS,
    SAMPLE_EVERY_S,
    SAMPLE_S,
    SAMPLE_SIGMAS,
    STALL_RATIO,
    STALL_TIME_S,
    AxialMotion,
    BlockSpeeds,
    block_speeds,
    chance_votes,
    odometry_speed,
    path_length,
    restitched,
    sensor_fixed,
)
from decod_rs.tum import write_tum

FloatArray = NDArray[np.float64]
#: ``configure`` for a run's topics: its config, ``auto``'s report (None for a preset) and
#: the IMU samples the probe read.
Configure = Callable[[Topics], tuple[Config, dict[str, Any] | None, FloatArray | None]]

__all__ = ["StageOne", "stage_one", "stall_check"]


@dataclass
class StageOne:
    """Stage 1's result: the config, ``auto``'s report, the extraction, ``report.json``'s
    ``ingest`` section (with ``odometry_stall``) and the stages' times."""

    cfg: Config
    auto: dict[str, Any] | None
    extraction: Extracted
    ingest: dict[str, Any]
    timings: dict[str, float]


def stage_one(
    log: Path,
    topics: Topics,
    configure: Configure,
    progress: bool,
    keep_map: bool,
    spill: _core.Spill | None = None,
) -> StageOne:
    """Configure and extract ``log``; where the odometry stalled along the axis
    (:func:`stall_check`), configure and extract again on the restitched odometry.
    ``spill``: where the landmarks' cells wait (:mod:`decod_rs.stages.extract`)."""
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    cfg, auto, imu = configure(topics)
    timings["configure"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    extraction, ingest = extract_stage(log, cfg, topics, progress, keep_map, imu, spill)
    timings["extract"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    motion = stall_check(extraction, cfg, auto, progress)
    if motion.poses is not None:
        with tempfile.TemporaryDirectory(prefix="decod-axial-") as tmp:
            tum = Path(tmp) / "axial.tum"
            write_tum(tum, extraction.scans[0], motion.poses)
            steady = (extraction.processor.points_topic, None, tum, extraction.imu_topic)
            cfg, auto, imu = configure(steady)
            extraction, ingest = extract_stage(log, cfg, steady, progress, keep_map, imu, spill)
    if motion.checked:
        timings["axial_check"] = time.perf_counter() - t0
    ingest["odometry_stall"] = motion.report()
    return StageOne(cfg, auto, extraction, ingest, timings)


def _window_scans(auto: dict[str, Any] | None, rate: float) -> int:
    """Scans per short window: those that fill a descriptor (``auto``'s schedule), at least
    ``MIN_WINDOW_SCANS``."""
    schedule = {} if auto is None else auto.get("schedule") or {}
    return max(MIN_WINDOW_SCANS, math.ceil(float(schedule.get("descriptor_fill_s", 0.0)) * rate))


def _oriented_axes(axes: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The views' axes flipped onto one direction (the principal one, signed towards the
    body's +x), and that direction."""
    _, vectors = np.linalg.eigh(axes.T @ axes)
    ref = vectors[:, -1]
    ref = ref if ref[0] >= 0 else -ref
    signs = np.where(axes @ ref >= 0.0, 1.0, -1.0)
    return axes * signs[:, None], ref


@dataclass(frozen=True)
class _Measured:
    """One measurement of the speed along the axis: the views, those at sensor-fixed
    distances, the stretches' speeds, the votes of the same views shuffled and the
    body-frame axis the speeds are along."""

    views: int
    fixed: int
    blocks: BlockSpeeds
    chance: tuple[float, float]
    axis: FloatArray


def _measure(
    extraction: Extracted,
    short: Config,
    stitch: FloatArray,
    window_s: float,
    progress: bool,
    keep: NDArray[np.bool_] | None = None,
) -> _Measured | None:
    """The log (its scans ``keep``, default all) in short windows stitched on ``stitch``
    (N, 4, 4), and the speed its boundaries' distances give (module docs of
    :mod:`decod_rs.stall`); None with fewer than two views."""
    landmarks = restitched_on(extraction, short, stitch, progress, "stall", keep).landmarks
    if len(landmarks) < 2:
        return None
    axes, ref = _oriented_axes(np.array([lm.axis for lm in landmarks]))
    axial = np.einsum("ij,ij->i", np.array([lm.origin for lm in landmarks]), axes)
    stamps = np.array([lm.submap_stamp for lm in landmarks])
    fixed = sensor_fixed(stamps, axial, 2.0 * short.boundary.dog_sigma_large_m)
    reach = short.submap.max_range_m - short.submap.min_range_m
    kept = (stamps[~fixed], axial[~fixed], window_s, reach / window_s)
    return _Measured(
        len(landmarks), int(fixed.sum()), block_speeds(*kept), chance_votes(*kept), ref
    )


def stall_check(
    extraction: Extracted, cfg: Config, auto: dict[str, Any] | None, progress: bool
) -> AxialMotion:
    """The axial check (module docs of :mod:`decod_rs.stall`) on a run's first extraction:
    a sample of the log measured on windows stitched on the odometry; where it stalled, the
    whole log, then once more on windows stitched on that measurement (which smears a
    window's boundaries less)."""
    stamps, poses = extraction.scans
    speed, path = odometry_speed(stamps, poses[:, :3, 3]), path_length(poses[:, :3, 3])
    if speed >= cfg.descriptor.half_length_m / STALL_TIME_S or stamps.size < 2 * MIN_WINDOW_SCANS:
        return AxialMotion(speed, path, checked=False)
    rate = float(1.0 / np.median(np.diff(stamps)))
    n = _window_scans(auto, rate)
    values = cfg.to_dict()
    values["submap"].update(scans_per_submap=n, interval_s=n / rate, max_travel_m=0.0)
    short = Config(values)
    sample = _sample(stamps)
    if sample is not None:
        motion = _verdict(extraction, short, poses, n / rate, progress, speed, path, sample)
        if not motion.applied:
            return motion
    # Stalled (in the sample): the whole log measured, then once more on windows stitched on
    # that measurement.
    stitch, motion = poses, AxialMotion(speed, path, checked=True)
    for _ in range(AXIAL_PASSES):
        motion = _verdict(extraction, short, stitch, n / rate, progress, speed, path, None)
        if motion.poses is None:
            break
        stitch = motion.poses
    return motion


def _sample(stamps: FloatArray) -> NDArray[np.bool_] | None:
    """The scans of the check's sample: ``SAMPLE_S`` of every ``SAMPLE_EVERY_S`` of the log;
    None (every scan) for a log shorter than two of those."""
    offset = stamps - stamps[0]
    if offset[-1] < 2.0 * SAMPLE_EVERY_S:
        return None
    return np.asarray(np.mod(offset, SAMPLE_EVERY_S) < SAMPLE_S)


def _verdict(
    extraction: Extracted,
    short: Config,
    stitch: FloatArray,
    window_s: float,
    progress: bool,
    speed: float,
    path: float,
    keep: NDArray[np.bool_] | None,
) -> AxialMotion:
    """One measurement (of the scans ``keep``, default all) and whether it restitches the
    odometry: its travel at least ``STALL_RATIO`` times the odometry's over the same scans,
    its votes ``CHANCE_SIGMAS`` (a sample's: ``SAMPLE_SIGMAS``) above the shuffled views'.
    ``poses``: the odometry restitched on it (over the whole log), where it does."""
    stamps, poses = extraction.scans
    measured = _measure(extraction, short, stitch, window_s, progress, keep)
    if measured is None or measured.blocks.speeds.size == 0:
        return AxialMotion(speed, path, True, 0 if measured is None else measured.views)
    blocks = measured.blocks
    scan_speed = np.interp(stamps, blocks.centres, blocks.speeds)
    steps = 0.5 * np.abs(scan_speed[:-1] + scan_speed[1:]) * np.diff(stamps)
    odometry_steps = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    if keep is not None:
        both = keep[:-1] & keep[1:]
        steps, odometry_steps = steps[both], odometry_steps[both]
    travel, votes = float(steps.sum()), int(blocks.votes.sum())
    sigmas = CHANCE_SIGMAS if keep is None else SAMPLE_SIGMAS
    applied = (
        travel >= STALL_RATIO * float(odometry_steps.sum())
        and votes >= measured.chance[0] + sigmas * measured.chance[1]
    )
    return AxialMotion(
        speed,
        path,
        True,
        measured.views,
        measured.fixed,
        int(blocks.speeds.size),
        int(np.sum(blocks.votes >= MIN_VOTES)),
        votes,
        measured.chance,
        travel,
        applied,
        restitched(stamps, poses, scan_speed, measured.axis) if applied else None,
        sampled=keep is not None,
    )
