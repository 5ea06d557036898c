"""``decod run LOG``: DeCOD on a log; writes the contract's files (DESIGN.md) into ``--out``."""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from decod_rs.allocator import peak_memory_mb
from decod_rs.config import MODES, PRESETS
from decod_rs.recording import require_rerun

if TYPE_CHECKING:
    from decod_rs.pipeline import RunSummary


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "run",
        help="detect, match and close loops on a log; write corrected.tum and a report",
        description="Run DeCOD on a log (.mcap, ROS 1 .bag, .db3 or a rosbag2 directory with "
        "MCAP or sqlite3 storage) and write odometry.tum, corrected.tum, loops.csv, "
        "landmarks.csv, joints.csv, report.json, survey.decod and plots into --out. A cut-off "
        "or corrupt log is read as far as it goes (report.json 'ingest' says what was lost); "
        "the files appear in --out only when the run is complete (it writes into OUT.partial "
        "first).",
    )
    p.add_argument("log", type=Path, help=".mcap, .bag or .db3 file, or rosbag2 directory")
    p.add_argument(
        "--preset",
        choices=("auto", *PRESETS),
        default="auto",
        help="auto (default): measure the cross-section, sensor sampling and speed and derive "
        "every spatial parameter (report.json 'auto' says what and why); pipe / tunnel: fixed",
    )
    p.add_argument("--points-topic", help="PointCloud2 / Livox CustomMsg topic (default: unique)")
    odom = p.add_mutually_exclusive_group()
    odom.add_argument("--odom-topic", help="odometry topic (default: the unique one)")
    odom.add_argument("--odom-tum", type=Path, help="odometry as a TUM file instead of a topic")
    imu = p.add_mutually_exclusive_group()
    imu.add_argument("--imu-topic", help="IMU topic for gravity (default: the unique one)")
    imu.add_argument(
        "--no-imu", action="store_true", help="ignore IMUs: gravity is the sensor's -z axis"
    )
    p.add_argument("--config", type=Path, help="TOML file overriding preset parameters")
    p.add_argument(
        "--mode",
        choices=MODES,
        default="auto",
        help="batch: outbound database, return queries; online: every landmark queries all "
        "older ones; auto: batch if the run comes back, else online",
    )
    p.add_argument("--no-loops", action="store_true", help="report matches, add no factor")
    p.add_argument(
        "--no-sequential",
        action="store_true",
        help="no sequential boundary factors within a pass (graph.sequential = false): the "
        "paper's loops-only graph",
    )
    p.add_argument(
        "--no-plots",
        action="store_true",
        help="skip the PNG figures (trajectory, descriptors; changes.png with --survey)",
    )
    p.add_argument(
        "--map",
        action="store_true",
        help="also write map_corrected.ply and map_odometry.ply (the submaps placed by the "
        "corrected poses and by the odometry, cyan outbound / orange return) and "
        "map_consistency.png: wall thickness where the passes overlap, before and after "
        "(report.json 'map'; no ground truth needed)",
    )
    p.add_argument(
        "--rerun",
        type=Path,
        metavar="FILE.rrd",
        help="write a 3D recording for the rerun viewer: trajectories, maps, submaps, "
        "boundaries, every query's Top-1 and verdict, descriptors of accepted pairs "
        "(needs rerun-sdk: pip install 'decod-rs[rerun]')",
    )
    p.add_argument(
        "--survey",
        type=Path,
        metavar="RUN_DIR",
        help="re-inspect the corridor of an earlier `decod run` (its output directory, which "
        "holds survey.decod): boundaries are matched against it, the trajectory comes out in "
        "its frame, joints.csv gives its chainage and joint ids, changes.csv / changes.png "
        "rank the joints that changed most (without --preset/--config: its config)",
    )
    p.add_argument("-o", "--out", type=Path, required=True, help="output directory")
    p.set_defaults(func=run)


def print_summary(summary: RunSummary) -> None:
    t = summary.timings_s
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in t.items())
    unused = summary.clouds_outside_odometry
    outside = f"; {unused} clouds outside the odometry's span not used" if unused else ""
    print(f"scans          {summary.scans} ({summary.log_duration_s:.1f} s of log{outside})")
    notes = []
    if summary.end_face_submaps:
        notes.append(f"{summary.end_face_submaps} cut before an end face in view")
    if summary.travel_submaps:
        notes.append(
            f"{summary.travel_submaps} closed by their travel, faster than the schedule's speed"
        )
    ends = f" ({'; '.join(notes)})" if notes else ""
    print(f"submaps        {summary.submaps}, landmarks {summary.landmarks}{ends}")
    rej = ", ".join(f"{k} {v}" for k, v in sorted(summary.rejections.items())) or "none"
    print(f"rejected       {rej}")
    again = summary.revisited_views
    revisit = (
        f"; {again} views on ground driven again query but stay out of the database"
        if again
        else ""
    )
    print(
        f"matching       {summary.mode} mode, {summary.queries} queries, "
        f"{summary.accepted} accepted{revisit}"
    )
    peak = peak_memory_mb()
    memory = "" if peak is None else f", peak memory {peak:,.0f} MB"
    print(f"time           {stages}; {summary.realtime_factor:.0f}x real time{memory}")
    print(f"output         {summary.out_dir}")


def run(args: argparse.Namespace) -> int:
    if args.rerun is not None:
        try:
            require_rerun()
        except ImportError as exc:
            print(f"decod run: error: {exc}", file=sys.stderr)
            return 2
    # Imported here, not with the parser: GTSAM is not needed to print a command's help.
    from decod_rs.pipeline import run_log

    summary = run_log(
        args.log,
        args.out,
        preset=args.preset,
        config_path=args.config,
        points_topic=args.points_topic,
        odom_topic=args.odom_topic,
        odom_tum=args.odom_tum,
        imu_topic=args.imu_topic,
        use_imu=not args.no_imu,
        mode=args.mode,
        loops=not args.no_loops,
        sequential=False if args.no_sequential else None,
        plots=not args.no_plots,
        map=args.map,
        rerun=args.rerun,
        survey=args.survey,
    )
    print_summary(summary)
    print_outcome(args.out, survey=args.survey is not None, mapped=bool(args.map))
    return 0


def print_outcome(out: Path, survey: bool = False, mapped: bool = False) -> None:
    """The lines after the run's summary, from ``out``'s report: what auto chose, the
    rebuilt rounds, the joints, the factors within the passes, what was not measured; the
    survey's and the map's when the run made them."""
    report = read_report(out)
    print_setup(report)
    print_rebuild(report)
    print_focus(report)
    print_joints(out)
    print_within_passes(report)
    print_cross_axis(report)
    print_unmeasured(report)
    if survey:
        print_survey(report)
    if mapped:
        print_map(report)


def read_report(out: Path) -> dict[str, Any]:
    """The run's ``report.json`` (read once; the summary lines below take it)."""
    report: dict[str, Any] = json.loads((out / "report.json").read_text(encoding="utf-8"))
    return report


def print_setup(report: dict[str, Any]) -> None:
    """What ``auto`` measured and chose (``report.json`` ``auto``), in one line, and why no
    loop was closed when none was (``no_loop_reason``)."""
    auto = report.get("auto")
    if auto:
        submap, schedule = auto["derived"]["submap"], auto.get("schedule") or {}
        rule = str(schedule.get("rule", "")).replace("_", " ")
        travel = float(submap.get("max_travel_m") or 0.0)  # absent from older reports
        print(
            f"auto           {auto['corridor']}, radius {auto['measured']['radius_m']:.2f} m, "
            f"voxel {1e3 * submap['voxel_m']:.1f} mm, range {submap['min_range_m']:.2f}-"
            f"{submap['max_range_m']:.2f} m, a submap every {submap['interval_s']:.2f} s "
            f"({submap['scans_per_submap']} scans{'; set by the ' + rule if rule else ''})"
            + (f" or {travel:.2f} m of travel" if travel > 0.0 else "")
        )
        curvature = auto["measured"].get("curvature_per_m") or 0.0
        if (auto["derived"].get("axis") or {}).get("curved") and curvature > 0:
            print(
                f"curve          the path curves (radius {1.0 / curvature:.0f} m): "
                "centre lines fitted per submap"
            )
        share = auto["measured"].get("wall_share", 1.0)
        if share < 1.0:
            print(
                f"wall seen      {100 * share:.0f} % of the section above the bottom (water or "
                "debris hides the rest): submaps fill that part"
            )
    jitter = (report.get("ingest") or {}).get("odometry_jitter")
    if jitter and jitter["smoothed"]:
        scatter, limit = 1e3 * jitter["jitter_m"], 1e3 * jitter["threshold_m"]
        print(
            f"jitter         the odometry's poses scatter {scatter:.1f} mm about a smooth fit "
            f"(> {limit:.1f} mm, a quarter voxel): the run's odometry is its fit over "
            f"{jitter['fit_window_s']:.1f} s"
        )
    print_stall((report.get("ingest") or {}).get("odometry_stall"))
    print_deskew(report)
    if report.get("no_loop_reason"):
        print(f"no loop        {report['no_loop_reason']}")


def print_deskew(report: dict[str, Any]) -> None:
    """How many scans were moved to their stamp's pose by their points' times, and how many
    had a time field that could not be read so (``report.json`` ``ingest.clouds``)."""
    for topic, c in ((report.get("ingest") or {}).get("clouds") or {}).items():
        done, unused = int(c.get("deskewed", 0)), int(c.get("times_unused", 0))
        if done or unused:
            scans = done + unused
            rest = (
                f"; {unused} with times not within one scan (or no trajectory around them), "
                "taken as written"
                if unused
                else ""
            )
            print(
                f"deskew         {done} of {scans} scans on {topic} moved to their stamp's pose "
                f"by their points' times{rest}"
            )


def print_stall(stall: dict[str, Any] | None) -> None:
    """The axial check's line (``report.json`` ``ingest.odometry_stall``), when it ran."""
    if not stall or not stall["checked"]:
        return
    seen = (
        f"the odometry moves {stall['odometry_travel_m']:.2f} m in all; the boundaries passing "
        f"the sensor {stall['measured_travel_m']:.1f} m ({stall['stretches_measured']} of "
        f"{stall['stretches']} stretches measured)"
    )
    verdict = (
        "the run's odometry is restitched on them along the axis"
        if stall["applied"]
        else "the odometry is kept"
    )
    print(f"stall          {seen}: {verdict}")


def print_rebuild(report: dict[str, Any]) -> None:
    """Whether the submaps were built again on the corrected trajectory (``report.json``
    ``rebuild``, :mod:`decod_rs.refinement`), round by round: why, the loops before and
    after, and whether the rebuilt submaps were kept. Nothing where a run never rebuilds
    (``--no-loops``, ``--survey``, ``submap.rebuild_on_correction = false``)."""
    section = report.get("rebuild")
    if not section:
        return

    def cm(metres: float) -> str:
        return f"{100 * metres:.1f} cm"

    parts = []
    for k, r in enumerate(section["rounds"], 1):
        moved, limit = cm(r["travel_disagreement_m"]), cm(r["threshold_m"])
        if not r["rebuilt"]:
            why = f"the correction moves a submap's travel by {moved} <= {limit}"
            parts.append(f"{'no' if k == 1 else 'no more'} ({why})")
            break
        before, after = r["loops_first_and_rebuilt"]
        verdict = "kept" if r["kept"] else "not kept"
        why = f"the correction moves a submap's travel by {moved} > {limit}"
        parts.append(f"round {k} ({why}): loops {before} -> {after}, {verdict}")
    print(f"rebuilt        {'; '.join(parts)}")


def print_focus(report: dict[str, Any]) -> None:
    """The passes the first round did not measure, focused before the rebuild
    (``report.json`` ``rebuild.focus``, :mod:`decod_rs.focus`): the scale each was stitched
    at and how much sharper the wall was there, or why it was left. Nothing when every pass
    was measured."""
    section = report.get("rebuild") or {}
    parts = []
    for f in section.get("focus", []):
        gain = "" if f["gain"] is None else f"{f['gain']:.2f}x"
        if f["applied"]:
            parts.append(f"{f['pass_name']} stitched at {f['scale']:.3f} (the wall {gain} sharper)")
        elif f["scale"] is not None:
            parts.append(f"{f['pass_name']} sharpest at {f['scale']:.3f}, close enough to leave")
        elif f["windows"] == 0:
            parts.append(f"{f['pass_name']} too short to focus")
        else:
            parts.append(f"{f['pass_name']} no clear peak ({gain or 'no profile'})")
    if parts:
        print(f"focus          {'; '.join(parts)}")


def print_joints(out: Path) -> None:
    """The joint registry (``joints.csv``) in one line: its rows, how many a loop confirmed,
    how many both passes saw, and how many are a single unconfirmed view (wall features
    more often than joints: filter on ``views`` and ``loop_confirmed``)."""
    with (out / "joints.csv").open(encoding="utf-8", newline="") as fh:
        rows = list(csv.DictReader(fh))
    confirmed = sum(r["loop_confirmed"] == "1" for r in rows)
    both = sum(int(r["passes"]) >= 2 for r in rows)
    once = sum(int(r["views"]) == 1 and r["loop_confirmed"] != "1" for r in rows)
    print(
        f"joints         {len(rows)} in joints.csv: {confirmed} loop-confirmed, "
        f"{both} seen on both passes, {once} a single unconfirmed view"
    )


def print_within_passes(report: dict[str, Any]) -> None:
    """The factors within each pass (``report.json`` ``sequential``): boundaries tracked
    from anchor to anchor, among them those of an end face in view, and the side offset
    removed from them (:mod:`decod_rs.side_offset`), if one was."""
    section = report["sequential"]
    if section is None:
        print("within passes  none (graph.sequential = false, or --no-loops)")
        return
    faces = section.get("end_face_factors", 0)
    side = section.get("side_offset") or {}
    removed = ""
    if side.get("applied"):
        removed = (
            f"; boundaries placed {100 * side['offset_m']:+.1f} cm away from the sensor "
            f"(+-{100 * side['sigma_m']:.1f}), removed"
        )
    print(
        f"within passes  {section['factors'] - faces} boundary factors, "
        f"{faces} from an end face in view{removed}"
    )


def print_cross_axis(report: dict[str, Any]) -> None:
    """Whether the landmark factors took the boundaries' heights or left them to the
    odometry (``report.json`` ``cross_axis``, :mod:`decod_rs.cross_axis`)."""
    section = report.get("cross_axis")
    if not report.get("loops_enabled", True):
        print("heights        from the odometry (--no-loops: no landmark factors)")
        return
    if section is None:
        print("heights        from the boundaries (too few tracked views to measure their spread)")
        return
    spread, odom = 100 * section["vertical_spread_m"], 100 * section["odometry_sigma_m"]
    if section["height_left_to_odometry"]:
        why = f"the views scatter {spread:.1f} cm vertically, the odometry holds {odom:.1f} cm"
        print(f"heights        left to the odometry ({why})")
    else:
        why = f"the views scatter {spread:.2f} cm vertically, the odometry {odom:.1f} cm"
        print(f"heights        from the boundaries ({why})")


def print_unmeasured(report: dict[str, Any]) -> None:
    """The stretches only the odometry places (``report.json`` ``unmeasured``), per pass."""
    section = report["unmeasured"]
    names = {"start": "first", "end": "last", "middle": "a gap of", "whole": "all"}
    parts = []
    for name, share in section["share_of_pass"].items():
        spans = [s for s in section["stretches"] if s["pass_name"] == name]
        if spans:
            where = ", ".join(f"{names[s['where']]} {s['length_m']:.1f} m" for s in spans)
            parts.append(f"{100 * share:.0f} % of the {name} ({where})")
    print(f"odometry only  {'; '.join(parts) or 'none: factors reach every stretch'}")


def print_map(report: dict[str, Any]) -> None:
    """The map files and the consistency figure (``report.json`` ``map``)."""
    section = report["map"]
    figure = section.get("consistency", {})
    before = figure.get("odometry", {}).get("median_overlap_mm")
    after = figure.get("corrected", {}).get("median_overlap_mm")
    if before is None or after is None:
        wall = "the passes do not overlap: no consistency figure"
    else:
        wall = f"wall where the passes overlap {before:.1f} mm (odometry) -> {after:.1f} mm"
    points = sum(section["points"]["corrected"].values())
    print(f"map            {points} points ({section['voxel_m'] * 1e3:.1f} mm voxels); {wall}")


def print_survey(report: dict[str, Any]) -> None:
    """The survey stage's outcome (``report.json`` ``survey``)."""
    section = report["survey"]
    frame = "survey frame" if section["placed_in_survey_frame"] else "own frame (no pair kept)"
    print(
        f"survey         {section['kept']} of {section['accepted']} accepted cross-session "
        f"pairs kept; trajectory in the {frame}"
    )
    changes = section.get("changes") or {}
    top = ", ".join(
        f"joint {c['survey_joint_id']} ({c['change']:.2f})"
        for c in changes.get("most_changed", [])[:3]
    )
    if top:
        print(f"changed most   {top}")
