"""``run_log`` in two halves, so that one extraction serves many matching settings.

:func:`extract_log` is ``run_log`` up to and including stage 1 (configure, extract);
:func:`run_from_extraction` replays stages 2-4 (match and select, factors, optimise, write,
report) with any config whose extraction sections equal the extraction's. Both call the
stage functions of :mod:`decod_rs.stages` in ``run_log``'s order, so a replay at a
setting writes the files a ``decod run --config`` at that setting writes.
"""

from __future__ import annotations

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
from decod_rs.pipeline import MODES, Extracted, RunSummary, Visuals, finish_run
from decod_rs.run_files import landmark_spill, staged_run_dir
from decod_rs.stages.axial import stage_one
from decod_rs.stages.extract import SubmapLandmarks, Topics, configure

FloatArray = NDArray[np.float64]

__all__ = ["Extraction", "extract_log", "run_from_extraction"]


@dataclass
class Extraction:
    """Stage 1 of one log, kept for replays: ``run_log``'s stage 1 result (the processor,
    the landmarks and anchors, the scans' odometry, the gap factors) and its ``ingest``
    section, the config it ran with and the base config before extraction parameters,
    ``auto``'s report and the seconds spent configuring and extracting."""

    log: Path
    options: RunOptions
    stage: Extracted
    ingest: dict[str, Any]
    base_cfg: Config
    cfg: Config
    auto: dict[str, Any] | None
    timings_s: dict[str, float]

    @property
    def processor(self) -> _core.LogProcessor:
        return self.stage.processor

    @property
    def extracted(self) -> SubmapLandmarks:
        return self.stage.extracted

    @property
    def scans(self) -> tuple[FloatArray, FloatArray]:
        return self.stage.scans

    @property
    def imu_topic(self) -> str | None:
        return self.stage.imu_topic


def _extraction_sections(cfg: Config) -> dict[str, Any]:
    return {k: v for k, v in cfg.to_dict().items() if k not in REPLAYED_SECTIONS}


def extract_log(
    log: Path, options: RunOptions, params: dict[str, Any], beside: Path | None = None
) -> Extraction:
    """Configure (``auto`` measures the corridor once) and extract ``log`` with ``options``
    and the extraction ``params`` (dotted key -> value) applied, as ``run_log`` would with
    those parameters in its ``--config``. ``beside``: a run directory beside which the
    landmarks' cells wait on disk, as ``run_log``'s do (None: in memory)."""
    if options.preset not in ("auto", "tunnel", "pipe"):
        raise ValueError(f"preset: {options.preset!r} is not one of ('auto', 'tunnel', 'pipe')")
    imu_topic = options.imu_topic
    if imu_topic is None and options.use_imu:
        imu_topic = find_imu_topic(log)
    topics = (options.points_topic, options.odom_topic, options.odom_tum, imu_topic)
    bases: list[Config] = []

    def configured(run_topics: Topics) -> tuple[Config, dict[str, Any] | None, Any]:
        base, auto, imu = configure(
            log, options.preset, options.config, run_topics, options.sequential
        )
        bases.append(base)
        return (apply_params(base, params) if params else base), auto, imu

    # Stage 1 as run_log's: the odometry checked along the axis too (decod_rs.stages.axial).
    spill = None if beside is None else landmark_spill(beside)
    one = stage_one(log, topics, configured, False, options.map, spill)
    return Extraction(
        log, options, one.extraction, one.ingest, bases[-1], one.cfg, one.auto, one.timings
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
    opts = extraction.options
    if opts.mode not in MODES:
        raise ValueError(f"mode: {opts.mode!r} is not one of {MODES}")
    head = {
        "preset": opts.preset,
        "auto": extraction.auto,
        "imu_topic": extraction.imu_topic,
        "ingest": extraction.ingest,
        **(report_extra or {}),
    }
    # Written into OUT.partial, published at the end (as decod run): never half-written.
    with staged_run_dir(out_dir) as staging:
        summary = finish_run(
            extraction.stage,
            staging,
            cfg,
            opts.mode,
            opts.loops,
            opts.plots,
            dict(extraction.timings_s),
            head,
            Visuals(map=opts.map),
        )
    summary.out_dir = out_dir
    return summary


def replay_params(extraction: Extraction, params: dict[str, Any]) -> Config:
    """The config of a setting: the extraction's base config with all of ``params``."""
    return apply_params(extraction.base_cfg, params) if params else extraction.base_cfg
