"""``decod run``: a log in, a corrected trajectory and an honest report out (paper Alg. 1).

Stages, each timed in ``report.json`` and each in its module of :mod:`decod_rs.stages`,
called here in Algorithm 1's order:

1. **extract** (:mod:`~decod_rs.stages.extract`) - the Rust ``LogProcessor`` streams scans
   from the log, builds submaps and extracts landmarks a few submaps at a time (memory
   bounded by the submaps in flight); where the odometry hardly moves, the boundaries
   passing the sensor measure the motion along the axis, and where the odometry stalled the
   run is configured and extracted again on it (:mod:`~decod_rs.stages.axial`);
2. **match** and **select** (:mod:`~decod_rs.stages.match`) - outbound landmarks form the
   database, return landmarks query it (batch, the paper's protocol), or every landmark
   queries all older ones (online); the jointly consistent loops are kept;
3. **optimise** (:mod:`~decod_rs.stages.solve`) - kept loops and boundary tracks become
   5-DoF factors in the GTSAM graph over the submap anchors; every scan gets a corrected
   pose; where that trajectory stitches the submaps differently enough, stages 1-3 run
   again on it (:mod:`~decod_rs.stages.refine`), and with ``--survey`` the run is placed in
   the survey's frame (:mod:`~decod_rs.stages.survey`);
4. **write** (:mod:`~decod_rs.stages.write`) - the files of the contract (DESIGN.md) and the
   plots.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np

from decod_rs.config import MODES, Config
from decod_rs.end_faces import tied_anchors
from decod_rs.io import find_imu_topic
from decod_rs.refinement import rebuild_report
from decod_rs.run_files import check_run_dir, landmark_spill, staged_run_dir
from decod_rs.stages.axial import stage_one
from decod_rs.stages.extract import Extracted, Topics, configure
from decod_rs.stages.match import match_and_select
from decod_rs.stages.refine import rebuilt
from decod_rs.stages.solve import solve
from decod_rs.stages.survey import reinspect_run
from decod_rs.stages.write import RunSummary, run_plots, run_report, run_summary, write_outputs
from decod_rs.survey import Survey, check_compatible, load_survey
from decod_rs.unmeasured import unmeasured, unmeasured_report
from decod_rs.visuals import Visuals, finish_visuals, start_visuals

PRESET_CHOICES = ("auto", "tunnel", "pipe")

__all__ = ["MODES", "Extracted", "RunSummary", "Visuals", "finish_run", "run_log"]


def run_log(
    log: str | Path,
    out_dir: str | Path,
    *,
    preset: str = "auto",
    config_path: str | Path | None = None,
    points_topic: str | None = None,
    odom_topic: str | None = None,
    odom_tum: str | Path | None = None,
    imu_topic: str | None = None,
    use_imu: bool = True,
    mode: str = "auto",
    loops: bool = True,
    sequential: bool | None = None,
    plots: bool = True,
    progress: bool = True,
    map: bool = False,
    rerun: str | Path | None = None,
    survey: str | Path | None = None,
    landmarks_on_disk: bool = True,
) -> RunSummary:
    """Run DeCOD on ``log`` and write the contract's files into ``out_dir`` (paper Alg. 1:
    extract -> match -> select -> optimise -> write).

    ``preset="auto"`` measures the corridor from the first scans and derives the spatial
    parameters (:mod:`decod_rs.autoscale`); ``"pipe"`` / ``"tunnel"`` take the fixed presets.
    ``imu_topic=None`` takes the log's unique IMU topic if there is one (``use_imu=False``:
    never; gravity is then the sensor's -z). ``loops=False`` disables every factor (the
    output trajectory is then the odometry); the matching still runs and is reported.
    ``sequential`` overrides ``graph.sequential`` (False: the paper's loops-only graph).
    ``map=True`` also writes the corrected and odometry maps (PLY) and the map-consistency
    figure; ``rerun=FILE.rrd`` a 3D recording (rerun-sdk, extra ``rerun``): see
    :mod:`decod_rs.visuals`. ``survey=OLD_RUN_DIR`` re-inspects an earlier run's corridor:
    the trajectory comes out in its frame, with its joint ids and a change report
    (:mod:`decod_rs.reinspection`); without ``preset``/``config_path`` its config is used.
    ``landmarks_on_disk``: the landmarks' cells wait in a file beside ``out_dir`` (unlinked
    at once on Unix: it leaves nothing behind) from their extraction on, and their views'
    patches while they are matched, so that memory grows by about 3 KB a landmark with the
    log instead of about 50 (:mod:`decod_rs.stages.extract`); a survey's landmarks and
    their database's patches wait there too. False keeps all of them in memory. The
    outputs are the same either way, byte for byte.
    """
    _check_arguments(mode, preset, rerun)  # fail before the run, not after it
    log, out = Path(log), check_run_dir(Path(out_dir))
    spill = landmark_spill(out) if landmarks_on_disk else None
    # The survey's landmarks wait beside the run's (a whole earlier run's cells).
    srv = None if survey is None else load_survey(survey, spill)
    if imu_topic is None and use_imu:
        # Gravity from the IMU when the log has exactly one; the sensor's -z otherwise.
        imu_topic = find_imu_topic(log)
    topics = (points_topic, odom_topic, None if odom_tum is None else Path(odom_tum), imu_topic)

    # The recording is written by a worker process while the figures are drawn, if any.
    recording = None if rerun is None else Path(rerun)
    visuals = Visuals(map=map, rerun=recording, worker=plots)

    def configured(run_topics: Topics) -> tuple[Config, dict[str, Any] | None, Any]:
        cfg, auto, imu = configure(log, preset, config_path, run_topics, sequential, srv)
        if srv is not None:
            check_compatible(srv, cfg)
        visuals.prepare()  # the end's imports overlap the extraction, not the probe
        return cfg, auto, imu

    # The voxel map costs 2-12 % of the stream: kept only when a map or recording is asked.
    one = stage_one(log, topics, configured, progress, map or rerun is not None, spill)
    head = {"preset": preset, "auto": one.auto, "imu_topic": imu_topic, "ingest": one.ingest}
    # Written into OUT.partial, published into OUT at the end: never a half-written OUT.
    with staged_run_dir(out) as staging:
        summary = finish_run(
            one.extraction,
            staging,
            one.cfg,
            mode,
            loops,
            plots,
            one.timings,
            head,
            visuals,
            progress,
            survey=srv,
        )
    summary.out_dir = out
    return summary


def _check_arguments(mode: str, preset: str, rerun: str | Path | None) -> None:
    """``run_log``'s choices checked and rerun-sdk found if a recording is asked for (the
    survey is loaded next): every refusal before the run, not after it."""
    if mode not in MODES:
        raise ValueError(f"mode: {mode!r} is not one of {MODES}")
    if preset not in PRESET_CHOICES:
        raise ValueError(f"preset: {preset!r} is not one of {PRESET_CHOICES}")
    if rerun is not None:
        from decod_rs.recording import require_rerun

        require_rerun()


def finish_run(
    extraction: Extracted,
    out: Path,
    cfg: Config,
    mode: str,
    loops: bool,
    plots: bool,
    timings: dict[str, float],
    report_head: dict[str, Any],
    visuals: Visuals,
    progress: bool = False,
    survey: Survey | None = None,
) -> RunSummary:
    """Stages 2-5 of Algorithm 1 on an extraction: match -> select -> optimise -> write
    (report.json last, with ``report_head`` merged in). ``decod run`` and ``decod sweep``
    (which replays one extraction under several matching/graph settings) share it."""
    ex, scans, processor = extraction.extracted.restored(), extraction.scans, extraction.processor
    t0 = time.perf_counter()
    matched = match_and_select(ex, cfg, mode, *scans, progress=progress)
    timings["match"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    matched, solved = solve(ex, matched, cfg, scans, loops, extraction.gap_factors, progress)
    timings["optimise"] = time.perf_counter() - t0

    rebuild = None
    if loops and cfg.submap.rebuild_on_correction and survey is None:
        t0 = time.perf_counter()
        ex, matched, solved, rebuild = rebuilt(extraction, ex, matched, solved, cfg, mode, progress)
        timings["rebuild"] = time.perf_counter() - t0
    constraints, seq, correction = solved.constraints, solved.seq, solved.correction
    scale, start = solved.scale, solved.start

    stage = None
    if survey is not None:
        # Against the earlier survey: match, keep the consistent pairs, move into its frame.
        t0 = time.perf_counter()
        stage, correction = reinspect_run(survey, ex, matched.tracks, scans, correction, cfg)
        timings["survey"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    joints, changes = write_outputs(
        out, ex, matched, (scans, start), correction, constraints, cfg, stage, plots
    )
    used = constraints if len(correction.graph.loop_weights) else []  # none: odometry stood
    anchors = np.asarray(ex.anchor_stamps, dtype=np.float64)
    odometry_only = unmeasured(scans[0], correction.poses, anchors, used, matched.split)
    timings["write"] = time.perf_counter() - t0
    # Maps rendered, the recording's worker started: it writes while the figures are drawn.
    pending = start_visuals(processor, scans, correction.poses, ex.landmarks, matched, visuals)
    if plots:
        t0 = time.perf_counter()
        kept = [r for r, ok in zip(matched.results, matched.keep, strict=True) if ok]
        faces = tied_anchors(None if seq is None else seq.end_faces, anchors)
        run_plots(out, *scans, correction.poses, kept, ex.landmarks, odometry_only[0], faces)
        timings["plots"] = time.perf_counter() - t0

    summary = run_summary(out, ex, matched, scans, timings, processor)
    report = run_report(
        summary, extraction.log, ex, processor, cfg, matched, constraints, correction, seq, joints
    )
    report.update(loops_enabled=loops, rebuild=None if rebuild is None else rebuild_report(rebuild))
    spill = extraction.spill  # what waited on disk instead of memory (None: nothing did)
    report["landmarks_on_disk_bytes"] = None if spill is None else spill.bytes
    report["unmeasured"] = unmeasured_report(*odometry_only)
    report["cross_axis"] = None if solved.cross is None else solved.cross.report()
    report["survey"] = None if stage is None else {**stage.report(), "changes": changes}
    if scale is not None and report["sequential"] is not None:
        report["sequential"]["odometry_scale"] = scale.passes
    report.update(report_head)
    (out / "report.json").write_text(json.dumps(report, indent=2), encoding="utf-8")
    if pending is not None:
        summary.timings_s.update(finish_visuals(out, pending))
    return summary
