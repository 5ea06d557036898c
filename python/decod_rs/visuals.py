"""What ``decod run --map`` and ``--rerun FILE`` add once the contract's files are written
(issue 13): the corrected and odometry maps as PLY, the map-consistency figure that needs no
ground truth (``report.json`` ``map`` and ``map_consistency.png``), and the 3D recording.

Files (``--map``):

| file | content |
| --- | --- |
| ``map_corrected.ply`` | the submaps placed by the corrected poses, one point per voxel and pass |
| ``map_odometry.ply`` | the same placed by the input odometry |
| ``map_consistency.png`` | wall thickness where the passes overlap, per metre, before and after |

``report.json`` gains ``map`` (voxel, memory, points per pass, the consistency figure before
and after, per bin) and ``rerun`` (the recording's contents); ``timings_s`` gains the stages
``map`` and ``rerun``.
"""

from __future__ import annotations

import json
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from decod_rs import _core
from decod_rs._core import Landmark, QueryResult
from decod_rs.allocator import peak_memory_mb
from decod_rs.map_quality import Consistency, map_consistency, outbound_path
from decod_rs.maps import PASS_NAMES, MapCloud, anchor_poses, render_map, write_map_ply
from decod_rs.recording import RecordingInput, RecordingJob

FloatArray = NDArray[np.float64]

__all__ = [
    "MAP_FILES",
    "PendingVisuals",
    "Visuals",
    "finish_visuals",
    "start_visuals",
    "write_visuals",
]

MAP_FILES = {"corrected": "map_corrected.ply", "odometry": "map_odometry.ply"}
CONSISTENCY_PNG = "map_consistency.png"
#: Pose entries (metres, rotation-matrix entries) closer than this are the same trajectory.
SAME_POSE_ATOL = 1e-9


class Matched(Protocol):
    """The matching stage's outcome as ``run_log`` holds it."""

    results: list[QueryResult]
    keep: list[bool]
    reasons: list[str]
    split: float | None


@dataclass(frozen=True)
class Visuals:
    """What to draw after the run: the PLY maps and their figure, a rerun recording."""

    map: bool = False
    rerun: Path | None = None
    #: Write the recording in a worker process, while the caller draws its figures
    #: (:class:`decod_rs.recording.RecordingJob`); otherwise in this process.
    worker: bool = False

    def prepare(self) -> None:
        """Once the run is configured (not before: the import took the GIL from the corridor
        probe's Python), a recording written in this process starts importing the rerun SDK
        in the background, to overlap the extraction. (Matplotlib imported that way for the
        figures moved 0.3 s from the figures to the extraction, whose two threads then share
        the two cores with it: no gain.)"""
        if self.rerun is not None and not self.worker:
            from decod_rs.recording import import_rerun_in_background

            import_rerun_in_background()


@dataclass
class PendingVisuals:
    """The maps rendered and the recording under way (:func:`start_visuals`), for
    :func:`finish_visuals` to complete."""

    processor: _core.LogProcessor
    scans: tuple[FloatArray, FloatArray]
    corrected: FloatArray
    split: float | None
    map: bool
    clouds: dict[str, MapCloud]
    same: bool
    recording: RecordingJob | None
    timings: dict[str, float] = field(default_factory=dict)


def write_visuals(
    out: Path,
    processor: _core.LogProcessor,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
    landmarks: Sequence[Landmark],
    matched: Matched,
    *,
    map: bool,
    rerun: str | Path | None,
) -> dict[str, float]:
    """Maps, figure and recording of a finished run in ``out`` (``scans``: stamps (N,) and
    odometry (N, 4, 4); ``corrected`` (N, 4, 4)); updates ``report.json``; returns the time
    per stage in seconds. :func:`start_visuals` then :func:`finish_visuals`."""
    asked = Visuals(map=map, rerun=None if rerun is None else Path(rerun))
    pending = start_visuals(processor, scans, corrected, landmarks, matched, asked)
    return {} if pending is None else finish_visuals(out, pending)


def start_visuals(
    processor: _core.LogProcessor,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
    landmarks: Sequence[Landmark],
    matched: Matched,
    asked: Visuals,
) -> PendingVisuals | None:
    """Render the maps and start the recording (``asked.rerun``: the ``.rrd`` path; with
    ``asked.worker`` a worker process writes it while the caller goes on: ``decod run`` draws
    its figures); None when neither a map nor a recording is asked for."""
    if not (asked.map or asked.rerun is not None):
        return None
    stamps, odometry = scans
    t0 = time.perf_counter()
    # A trajectory no loop moved (--no-loops, or no loop accepted: the solver returns the
    # odometry to within 1e-14) places the map where the odometry does, to far below the
    # PLY's float precision: one render and one figure serve both.
    same = odometry.shape == corrected.shape and bool(
        np.allclose(odometry, corrected, rtol=0.0, atol=SAME_POSE_ATOL)
    )
    clouds = {"odometry": render_map(processor, stamps, odometry, matched.split)}
    clouds["corrected"] = (
        clouds["odometry"] if same else render_map(processor, stamps, corrected, matched.split)
    )
    timings = {"map": time.perf_counter() - t0}
    job = None
    if asked.rerun is not None:
        t0 = time.perf_counter()
        job = _start_recording(
            (asked.rerun, asked.worker), processor, scans, corrected, clouds, landmarks, matched
        )
        timings["rerun"] = time.perf_counter() - t0
    return PendingVisuals(
        processor, scans, corrected, matched.split, asked.map, clouds, same, job, timings
    )


def finish_visuals(out: Path, pending: PendingVisuals) -> dict[str, float]:
    """The map files and figure (when asked), the recording waited for; ``report.json`` in
    ``out`` updated; returns the time per stage in seconds (``rerun``: this process's share,
    starting the worker and waiting for it)."""
    p = pending
    stamps, odometry = p.scans
    trajectories = {"odometry": odometry, "corrected": p.corrected}
    timings = dict(p.timings)
    t0 = time.perf_counter()
    section = _map_section(p.processor, p.clouds)
    if p.map:
        anchors = np.asarray(p.processor.map_submap_stamps(), dtype=np.float64)
        voxel = float(p.processor.map_voxel_m or 0.0)  # the map is kept: never None here

        def finish(name: str) -> Consistency | None:
            write_map_ply(out / MAP_FILES[name], p.clouds[name], float(stamps[0]), name)
            if p.same and name == "corrected":
                return None
            poses = trajectories[name]
            return _consistency(anchors, p.clouds[name], stamps, poses, p.split, voxel)

        # The PLY files and the figures of both maps at once (numpy's large-array work
        # releases the GIL).
        with ThreadPoolExecutor(max_workers=2) as pool:
            done = dict(zip(trajectories, pool.map(finish, trajectories), strict=True))
        figures: dict[str, Consistency] = {}
        for name in trajectories:
            figure = done[name] or done["odometry"]
            if figure is not None:
                figures[name] = figure
        section["files"] = dict(MAP_FILES)
        section["consistency"] = _consistency_section(figures)
        from decod_rs.plots import plot_map_consistency

        plot_map_consistency(out / CONSISTENCY_PNG, figures)
        section["files"]["consistency"] = CONSISTENCY_PNG
    timings["map"] += time.perf_counter() - t0
    recorded = None
    if p.recording is not None:
        t0 = time.perf_counter()
        recorded = p.recording.wait()
        timings["rerun"] += time.perf_counter() - t0
    _update_report(out / "report.json", section, recorded, timings)
    return timings


def _map_section(processor: _core.LogProcessor, clouds: dict[str, MapCloud]) -> dict[str, Any]:
    return {
        "voxel_m": processor.map_voxel_m,
        "segment_length_m": processor.map_segment_length_m,
        "segments": processor.map_segments,
        "stored_voxels": processor.map_stored_voxels,
        "points": {
            name: {p: int(np.count_nonzero(c.pass_ == k)) for k, p in enumerate(PASS_NAMES)}
            for name, c in clouds.items()
        },
    }


def _consistency(
    anchors: FloatArray,
    cloud: MapCloud,
    stamps: FloatArray,
    poses: FloatArray,
    split: float | None,
    voxel_m: float,
) -> Consistency:
    """The figure of one map; ``anchors``: the map's submap stamps (K,)."""
    positions = anchor_poses(anchors, stamps, poses)[:, :3, 3]
    return map_consistency(cloud, positions, outbound_path(stamps, poses, split), voxel_m)


def _consistency_section(figures: dict[str, Consistency]) -> dict[str, Any]:
    """Before (odometry) and after (corrected), with what the number means."""
    section: dict[str, Any] = {
        "what": "wall thickness where the outbound and return passes overlap: RMS distance "
        "of both passes' points from their common plane in cells of 3 map voxels (cell_m), "
        "per metre of corridor (the floors: each pass about its own planes); misalignment "
        "across the wall only, blind to the axial error of a uniform corridor",
        "unit": "mm",
    }
    for name, fig in figures.items():
        section[name] = fig.summary()
    before = figures["odometry"].median_m()
    after = figures["corrected"].median_m()
    section["reduction_percent"] = (
        None if before is None or after is None or before <= 0 else 100 * (1 - after / before)
    )
    return section


def _start_recording(
    file: tuple[Path, bool],
    processor: _core.LogProcessor,
    scans: tuple[FloatArray, FloatArray],
    corrected: FloatArray,
    clouds: dict[str, MapCloud],
    landmarks: Sequence[Landmark],
    matched: Matched,
) -> RecordingJob:
    """The recording's job: ``file`` is its path and whether a worker process writes it."""
    points, index = processor.map_points_by_submap()
    return RecordingJob(
        file[0],
        RecordingInput(
            scan_stamps=scans[0],
            odometry=scans[1],
            corrected=corrected,
            split_stamp=matched.split,
            anchor_stamps=np.asarray(processor.map_submap_stamps(), dtype=np.float64),
            maps=clouds,
            submap_points=points,
            submap_index=index,
            landmarks=landmarks,
            results=matched.results,
            keep=matched.keep,
            reasons=matched.reasons,
        ),
        worker=file[1],
    )


def _update_report(
    path: Path,
    section: dict[str, Any],
    recorded: dict[str, Any] | None,
    timings: dict[str, float],
) -> None:
    report = json.loads(path.read_text(encoding="utf-8"))
    report["map"] = section
    report["rerun"] = recorded
    report.setdefault("timings_s", {}).update(timings)
    report["peak_memory_mb"] = peak_memory_mb()  # this process's, after the figures
    total = sum(report["timings_s"].values())
    if total > 0 and report.get("log_duration_s"):
        report["realtime_factor"] = report["log_duration_s"] / total
    path.write_text(json.dumps(report, indent=2), encoding="utf-8")
