"""Stage 1 of Algorithm 1 (paper Sec. III-A, III-B): the config (measured by ``auto`` or a
preset), then the Rust ``LogProcessor`` streaming the log into submaps and landmarks a few
submaps at a time (memory bounded by the submaps in flight). Given a spill
(:class:`decod_rs._core.Spill`), each submap's landmarks go there as they come, their cells
read back when the matcher prepares them and when the survey is written: a few hundred bytes
a landmark stay in memory instead of about 29 KB (``docs/measurements.md``, "Long logs")."""

from __future__ import annotations

import json
import sys
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark
from decod_rs.autoscale import auto_config, probe_corridor
from decod_rs.config import Config, load_config
from decod_rs.end_faces import FaceView
from decod_rs.ingest import StreamHealth, ingest_section, warn_once
from decod_rs.jitter import smoothing
from decod_rs.parking import Parked
from decod_rs.progress import Progress
from decod_rs.survey import Survey, survey_config
from decod_rs.tum import interpolate_poses, write_tum

FloatArray = NDArray[np.float64]
#: A run's topics: points, odometry, odometry TUM file, IMU (None: found or not used).
Topics = tuple[str | None, str | None, Path | None, str | None]


@dataclass
class SubmapLandmarks:
    """What the submaps of a log gave: their anchors (stamp, world pose in the odometry
    frame), their landmarks, and every extraction rejection (counts by kind, messages)."""

    anchor_stamps: list[float] = field(default_factory=list)
    anchor_poses: list[FloatArray] = field(default_factory=list)
    landmarks: list[Landmark] = field(default_factory=list)
    rejections: dict[str, int] = field(default_factory=dict)
    rejection_messages: list[str] = field(default_factory=list)
    #: Submaps cut before an end face in view (a tunnel's end, a pipe's cap) whose part before
    #: it was a corridor (``decod_rs._core.SubmapDiagnostics.end_face``).
    end_face_submaps: int = 0
    #: Windows closed by ``submap.max_travel_m`` before ``scans_per_submap`` scans (the
    #: robot faster than the speed the schedule was chosen for).
    travel_submaps: int = 0
    #: End faces in view of the anchors (:mod:`decod_rs.end_faces`).
    faces: list[FaceView] = field(default_factory=list)
    #: Where ``landmarks`` wait on disk, the list empty, since a rebuilt round replaced this
    #: one (:mod:`decod_rs.parking`); :meth:`restored` brings them back.
    parked: Parked | None = None
    #: Where the landmarks' cells wait (module docs), and their views' patches while they are
    #: matched (:class:`decod_rs.matching.PairMemo`); None: in memory.
    spill: _core.Spill | None = None

    def restored(self) -> SubmapLandmarks:
        """This round with its landmarks in memory: read back if a rebuilt round that
        replaced it left them on disk (``decod sweep`` replays one extraction)."""
        if self.parked is not None:
            self.parked.restore()
            self.parked = None
        return self


@dataclass(frozen=True)
class Extracted:
    """Stage 1's result, what stages 2-5 need: the log, the processor that streamed it (its
    voxel map, its skip lists), the landmarks and anchors, and the scan odometry."""

    log: Path
    processor: _core.LogProcessor
    extracted: SubmapLandmarks
    scans: tuple[FloatArray, FloatArray]
    gap_factors: FloatArray | None = None
    imu_topic: str | None = None
    #: Where the landmarks' cells wait (None: in memory); the rebuilt rounds' go there too.
    spill: _core.Spill | None = None


def restitched(
    extraction: Extracted,
    cfg: Config,
    poses: FloatArray,
    progress: bool,
    label: str,
    keep: NDArray[np.bool_] | None = None,
) -> SubmapLandmarks:
    """Stage 1 again, the submaps stitched on ``poses`` (N, 4, 4) at the scan stamps, the
    anchors placed on the odometry like the first ones (the graph's nodes; a submap's frame is
    its anchor scan's body frame whichever poses stitched it): for the corrected trajectory
    (:mod:`decod_rs.refinement`) and for the odometry's smooth fit (:mod:`decod_rs.jitter`),
    then also the run's odometry. ``keep`` (N,): only those scans (the others are left out as
    an odometry gap's are), for a sample of the log (:mod:`decod_rs.stages.axial`)."""
    stamps, odometry = extraction.scans
    with tempfile.TemporaryDirectory(prefix="decod-restitch-") as tmp:
        tum = Path(tmp) / "stitching.tum"
        write_tum(tum, *((stamps, poses) if keep is None else (stamps[keep], poses[keep])))
        points = extraction.processor.points_topic
        # The IMU the first extraction read: with the odometry from the file above, the log is
        # then read once, for its scans (not once more for the IMU).
        imu = extraction.processor.imu_samples()
        topic = extraction.imu_topic if imu is None else None
        _, ex = extract(
            extraction.log,
            cfg,
            points,
            None,
            tum,
            topic,
            progress,
            imu_samples=imu,
            label=label,
            spill=extraction.spill,
        )
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    ex.anchor_poses = list(interpolate_poses(stamps, odometry, anchors)) if anchors.size else []
    return ex


def configure(
    log: Path,
    preset: str,
    config_path: str | Path | None,
    topics: Topics,
    sequential: bool | None,
    survey: Survey | None = None,
) -> tuple[Config, dict[str, Any] | None, FloatArray | None]:
    """The config: measured and derived (``auto``) or a preset, plus the user's TOML; with a
    survey and neither a preset nor a TOML, the survey's own (same grid and matcher). Also
    the IMU samples the ``auto`` probe read, if it read any (for the extraction)."""
    auto: dict[str, Any] | None = None
    imu: FloatArray | None = None
    if survey is not None and preset == "auto" and config_path is None:
        cfg = survey_config(survey)
    elif preset == "auto":
        # The user's TOML read first: refused before the probe, and its submap.deskew the
        # probe's too.
        deskew = config_path is None or bool(load_config(config_path, "tunnel").submap.deskew)
        probe, imu = probe_corridor(log, *topics, deskew=deskew)
        cfg, auto = auto_config(probe, None if config_path is None else Path(config_path))
    else:
        cfg = load_config(config_path, preset)
    if sequential is not None:
        values = cfg.to_dict()
        values["graph"]["sequential"] = bool(sequential)
        cfg = Config(values)
    return cfg, auto, imu


def extract(
    log: Path,
    cfg: Config,
    points_topic: str | None,
    odom_topic: str | None,
    odom_tum: Path | None,
    imu_topic: str | None,
    progress: bool,
    keep_map: bool = False,
    imu_samples: FloatArray | None = None,
    label: str = "extract",
    spill: _core.Spill | None = None,
) -> tuple[_core.LogProcessor, SubmapLandmarks]:
    """The log streamed into submaps and landmarks (``label``: the progress bar's name;
    ``spill``: where the landmarks' cells go as they come, module docs)."""
    processor = _core.LogProcessor(
        str(log),
        json.dumps(cfg.to_dict()),
        points_topic=points_topic,
        odom_topic=odom_topic,
        odom_tum=None if odom_tum is None else str(odom_tum),
        imu_topic=imu_topic,
        map=keep_map,
        imu_samples=imu_samples,
    )
    bar = Progress(label, processor.total_scans_hint or None, enabled=progress)
    out = SubmapLandmarks(spill=spill)
    read = 0
    while (batch := processor.step()) is not None:
        for submap in batch:
            out.anchor_stamps.append(submap.anchor_stamp)
            out.anchor_poses.append(submap.world_from_anchor)
            found = submap.result.landmarks
            if spill is not None and found:
                try:
                    found = spill.put(found)
                except OSError as exc:  # a full disk: the rest stay in memory, as before
                    print(f"warning: {exc}; the landmarks stay in memory", file=sys.stderr)
                    spill = out.spill = None
            out.landmarks.extend(found)
            diag = submap.result.diagnostics
            out.end_face_submaps += int(diag.end_face)
            if diag.face_point is not None and diag.face_normal is not None:
                out.faces.append(
                    FaceView(
                        submap.anchor_stamp,
                        np.asarray(diag.face_point, dtype=np.float64),
                        np.asarray(diag.face_normal, dtype=np.float64),
                    )
                )
            for rejection in submap.result.rejections:
                out.rejections[rejection.kind] = out.rejections.get(rejection.kind, 0) + 1
                out.rejection_messages.append(str(rejection))
        bar.advance(processor.scans_read - read)
        read = processor.scans_read
    bar.close()
    out.travel_submaps = processor.windows_closed_by_travel
    return processor, out


def scan_odometry(processor: _core.LogProcessor) -> tuple[FloatArray, FloatArray]:
    """The stamps and odometry poses, (N,) and (N, 4, 4), of the scans ``processor`` read."""
    return (
        np.asarray(processor.scan_stamps(), dtype=np.float64),
        np.asarray(processor.scan_poses(), dtype=np.float64),
    )


def extract_stage(
    log: Path,
    cfg: Config,
    topics: Topics,
    progress: bool,
    keep_map: bool,
    imu_samples: FloatArray | None,
    spill: _core.Spill | None = None,
) -> tuple[Extracted, dict[str, Any]]:
    """Stage 1 on a configured run: the log streamed into submaps and landmarks; the
    stream's damage, gaps and clouds left without odometry at either end warned about once
    (the run goes on with what the log holds); and ``report.json``'s ``ingest`` section;
    ``ValueError`` naming the log when no scan pairs with odometry. ``keep_map``: keep the
    voxel map (2-12 % of the stream's time); ``spill``: where the landmarks' cells wait."""
    processor, ex = extract(
        log, cfg, *topics, progress, keep_map=keep_map, imu_samples=imu_samples, spill=spill
    )
    scans = scan_odometry(processor)
    health = StreamHealth.from_core(processor.health(), processor.skipped_outside_odometry)
    gap_periods = float(cfg.submap.odometry_gap_periods)
    warn_once(log, health, scans[0], gap_periods)
    if scans[0].size == 0:
        raise ValueError(f"{log}: no scan could be paired with odometry")
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    ingest, gap_factors = ingest_section(
        health, processor.points_topic, scans, gap_periods, anchors
    )
    smooth = smoothing(*scans, cfg)
    ingest["odometry_jitter"] = smooth.report()
    extraction = Extracted(log, processor, ex, scans, gap_factors, topics[3], spill)
    if smooth.applied:  # the run's odometry is the fit: the submaps again, stitched on it
        scans = (scans[0], smooth.fitted(*scans))
        extraction = replace(extraction, scans=scans)
        extraction = replace(
            extraction, extracted=restitched(extraction, cfg, scans[1], progress, "smoothed")
        )
    return extraction, ingest
