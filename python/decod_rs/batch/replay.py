"""``run_log`` in two halves, so that one extraction serves many matching settings.

:func:`extract_log` is ``run_log`` up to and including stage 1 (configure, extract);
:func:`run_from_extraction` replays stages 2-4 (match and select, factors, optimise, write,
report) with any config whose extraction sections equal the extraction's. Both call the
stage functions of :mod:`decod_rs.pipeline` in ``run_log``'s order, so a replay at a
setting writes the files a ``decod run --config`` at that setting writes.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs.batch.grid import REPLAYED_SECTIONS, apply_params
from decod_rs.batch.jobs import RunOptions
from decod_rs.config import Config
from decod_rs.io import find_imu_topic
from decod_rs.pipeline import (
    MODES,
    RunSummary,
    _configure,
    _extract,
    _Extracted,
    _factors,
    _match_and_select,
    _Matched,
    _optimise,
    _plots,
    _report,
    _write,
)

FloatArray = NDArray[np.float64]

__all__ = ["Extraction", "extract_log", "run_from_extraction"]


@dataclass
class Extraction:
    """Stage 1 of one log, kept for replays: the processor (scan stamps, topics, what was
    skipped), the landmarks and anchors, the scans' odometry, the config it ran with and the
    base config before extraction parameters, ``auto``'s report, the IMU topic and the
    seconds spent configuring and extracting."""

    log: Path
    options: RunOptions
    processor: _core.LogProcessor
    extracted: _Extracted
    scans: tuple[FloatArray, FloatArray]
    base_cfg: Config
    cfg: Config
    auto: dict[str, Any] | None
    imu_topic: str | None
    timings_s: dict[str, float]


def _extraction_sections(cfg: Config) -> dict[str, Any]:
    return {k: v for k, v in cfg.to_dict().items() if k not in REPLAYED_SECTIONS}


def extract_log(log: Path, options: RunOptions, params: dict[str, Any]) -> Extraction:
    """Configure (``auto`` measures the corridor once) and extract ``log`` with ``options``
    and the extraction ``params`` (dotted key -> value) applied, as ``run_log`` would with
    those parameters in its ``--config``."""
    if options.preset not in ("auto", "tunnel", "pipe"):
        raise ValueError(f"preset: {options.preset!r} is not one of ('auto', 'tunnel', 'pipe')")
    imu_topic = options.imu_topic
    if imu_topic is None and options.use_imu:
        imu_topic = find_imu_topic(log)
    topics = (options.points_topic, options.odom_topic, options.odom_tum, imu_topic)
    t0 = time.perf_counter()
    base, auto = _configure(log, options.preset, options.config, topics, options.sequential)
    cfg = apply_params(base, params) if params else base
    configure_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    processor, extracted = _extract(log, cfg, *topics, False, keep_map=options.map)
    extract_s = time.perf_counter() - t0
    scans = (
        np.asarray(processor.scan_stamps(), dtype=np.float64),
        np.asarray(processor.scan_poses(), dtype=np.float64),
    )
    if scans[0].size == 0:
        raise ValueError(f"{log}: no scan could be paired with odometry")
    timings = {"configure": configure_s, "extract": extract_s}
    return Extraction(
        log, options, processor, extracted, scans, base, cfg, auto, imu_topic, timings
    )


def _summary(
    extraction: Extraction, out_dir: Path, matched: _Matched, timings: dict[str, float]
) -> RunSummary:
    ex, stamps = extraction.extracted, extraction.scans[0]
    return RunSummary(
        out_dir=out_dir,
        scans=int(stamps.size),
        submaps=len(ex.anchor_stamps),
        landmarks=len(ex.landmarks),
        queries=len(matched.results),
        accepted=int(sum(matched.keep)),
        mode=matched.mode,
        split_stamp=matched.split,
        log_duration_s=float(stamps[-1] - stamps[0]),
        timings_s=timings,
        rejections=ex.rejections,
    )


def run_from_extraction(
    extraction: Extraction,
    out_dir: Path,
    cfg: Config,
    report_extra: dict[str, Any] | None = None,
) -> RunSummary:
    """Stages 2-4 of ``run_log`` on ``extraction`` with ``cfg`` (its extraction sections
    must equal the extraction's: else ``ValueError``), writing the contract's files into
    ``out_dir``; ``report.json`` (written last) also gets ``report_extra``."""
    if _extraction_sections(cfg) != _extraction_sections(extraction.cfg):
        raise ValueError(
            f"run_from_extraction: the config changes extraction parameters; only "
            f"{', '.join(REPLAYED_SECTIONS)} may differ from the extraction's"
        )
    opts, ex, scans = extraction.options, extraction.extracted, extraction.scans
    if opts.mode not in MODES:
        raise ValueError(f"mode: {opts.mode!r} is not one of {MODES}")
    out_dir.mkdir(parents=True, exist_ok=True)
    timings = dict(extraction.timings_s)
    t0 = time.perf_counter()
    matched = _match_and_select(ex, cfg, opts.mode, *scans)
    timings["match"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    constraints, seq = _factors(ex, matched, cfg, scans) if opts.loops else ([], None)
    correction, scale, start = _optimise(scans, ex, matched.split, constraints, seq, cfg)
    timings["optimise"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    joints = _write(out_dir, ex, matched, (scans, start), correction, constraints, cfg)
    timings["write"] = time.perf_counter() - t0
    if opts.plots:
        t0 = time.perf_counter()
        kept = [r for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
        _plots(out_dir, *scans, correction.poses, kept, ex.landmarks)
        timings["plots"] = time.perf_counter() - t0
    summary = _summary(extraction, out_dir, matched, timings)
    report = _report(
        summary,
        extraction.log,
        ex,
        extraction.processor,
        cfg,
        matched,
        constraints,
        correction,
        seq,
        joints,
    )
    report.update(
        preset=opts.preset,
        auto=extraction.auto,
        imu_topic=extraction.imu_topic,
        loops_enabled=opts.loops,
    )
    if scale is not None and report["sequential"] is not None:
        report["sequential"]["odometry_scale"] = scale.passes
    report.update(report_extra or {})
    (out_dir / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    if opts.map:
        from decod_rs.visuals import write_visuals

        maps = write_visuals(
            out_dir,
            extraction.processor,
            scans,
            correction.poses,
            ex.landmarks,
            matched,
            map=True,
            rerun=None,
        )
        summary.timings_s.update(maps)
    return summary


def replay_params(extraction: Extraction, params: dict[str, Any]) -> Config:
    """The config of a setting: the extraction's base config with all of ``params``."""
    return apply_params(extraction.base_cfg, params) if params else extraction.base_cfg
