"""``decod demo``: an interim demo of the extraction core on a generated pipe drive.

A crawler drives a 0.6 m pipe with 2 mm grooved joints every 2.43 m and 1.5 mm of wall
clutter (seeded analytic scene,
``decod_rs.scenes_analytic.pipe_drive``); its scans stream into submaps (20 scans every 8 s),
every submap goes through extraction, and the detected boundaries are compared with the
true joints. No arguments, no data needed. (The full simulate + run + evaluate demo
replaces this verb later.)
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from decod_rs import scenes_analytic
from decod_rs.config import load_config
from decod_rs.extraction import ExtractionResult, Submap, extract_submaps, submap_builder
from decod_rs.progress import track


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="extract boundaries from a generated pipe drive")
    p.add_argument("--seed", type=int, default=0, help="scene seed (default 0)")
    p.add_argument("--scans", type=int, default=1000, help="scans at 10 Hz (default 1000)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    config = load_config(preset="pipe")
    t0 = time.perf_counter()
    log = scenes_analytic.pipe_drive(
        np.random.default_rng(args.seed),
        n_scans=args.scans,
        points_per_scan=5000,
        groove_depth_m=0.002,
        clutter_m=0.0015,
    )
    t_scene = time.perf_counter() - t0
    print(
        f"scene: {len(log.stamps)} scans over {log.stamps[-1]:.0f} s, pipe r = 0.30 m, "
        f"2 mm grooves every 2.43 m at x = {[round(j, 3) for j in log.joints_x_m]}, "
        "1.5 mm wall clutter "
        f"({t_scene:.1f} s to generate)"
    )

    t0 = time.perf_counter()
    builder = submap_builder(config)
    submaps: list[Submap] = []
    for stamp, points, pose in track(
        zip(log.stamps, log.points, log.poses, strict=True), "submaps", total=len(log.stamps)
    ):
        submap = builder.push(float(stamp), points, pose)
        if submap is not None:
            submaps.append(submap)
    last = builder.finish()
    if last is not None:
        submaps.append(last)
    t_submaps = time.perf_counter() - t0

    t0 = time.perf_counter()
    results = extract_submaps(submaps, config=config)
    t_extract = time.perf_counter() - t0

    joints = np.asarray(log.joints_x_m)
    detected_errors: list[float] = []
    print(f"\n{'anchor s':>8} {'points':>7} {'axis err':>9} {'contour':>15} landmarks / rejections")
    for submap, result in zip(submaps, results, strict=True):
        print(_row(submap, result, joints, detected_errors))
    n_landmarks = sum(len(r.landmarks) for r in results)
    n_rejected = sum(len(r.rejections) for r in results)
    errors = np.abs(np.asarray(detected_errors))
    print(
        f"\n{len(submaps)} submaps: {n_landmarks} landmarks, {n_rejected} rejections; "
        f"boundary error vs true joints: median {1e3 * np.median(errors):.1f} mm, "
        f"max {1e3 * errors.max():.1f} mm"
        if errors.size
        else f"\n{len(submaps)} submaps: no landmarks"
    )
    print(
        f"time: submaps {t_submaps:.2f} s, extraction {1e3 * t_extract:.1f} ms "
        f"({1e3 * t_extract / max(len(submaps), 1):.1f} ms per submap, rayon)"
    )
    return 0


def _row(submap: Submap, result: ExtractionResult, joints: np.ndarray, errors: list[float]) -> str:
    d = result.diagnostics
    pose = submap.world_from_anchor
    axis_world = pose[:3, :3] @ np.asarray(d.axis)
    axis_err = np.degrees(np.arccos(min(1.0, abs(float(axis_world[0])))))
    contour = f"{d.contour_model} r={d.contour_radius_m:.3f}" if d.contour_model else "-"
    found = []
    for lm in result.landmarks:
        x = float((pose @ np.append(lm.origin, 1.0))[0])
        err = x - float(joints[np.argmin(np.abs(joints - x))])
        errors.append(err)
        found.append(f"x={x:.3f} m ({1e3 * err:+.1f} mm, {1e3 * lm.strength:.2f} mm)")
    found += [r.message for r in result.rejections]
    return (
        f"{submap.anchor_stamp:8.1f} {len(submap):7d} {axis_err:8.3f}° {contour:>15} "
        + "; ".join(found)
    )
