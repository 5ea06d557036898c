"""``decod simulate SCENE --out DIR``: a synthetic corridor log (rosbag2/MCAP) with ground
truth (``gt.tum``), drifting odometry (``odom.tum`` and ``/odom``) and ``joints.json``."""

from __future__ import annotations

import argparse
from pathlib import Path

from decod_rs.sim import DRIFT_PRESETS, SCENES, SENSORS


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate",
        help="simulate a pipe or tunnel and write a ROS 2 MCAP log with ground truth",
        description=(
            "Simulate an out-and-back run through a synthetic corridor and write DIR/log/ "
            "(rosbag2, MCAP: /points, /odom, /imu), DIR/gt.tum, DIR/odom.tum, DIR/joints.json."
        ),
    )
    p.add_argument("scene", choices=sorted(SCENES))
    p.add_argument("-o", "--out", required=True, type=Path, help="output directory")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--world-seed",
        type=int,
        help="build the corridor from this seed instead of --seed: a re-inspection of the same "
        "world with its own noise and drift (with --scene-param displaced_segment=K, "
        "wider_gap_joint=K, deposit_joint=K for changed joints)",
    )
    p.add_argument("--length", type=float, default=None, help="one-way length in metres")
    p.add_argument("--sensor", choices=sorted(SENSORS), default=None)
    p.add_argument("--h-res", type=float, default=None, help="spinning sensors: column step, deg")
    p.add_argument("--rays", type=int, default=None, help="avia: rays per scan")
    p.add_argument("--return", dest="return_mode", choices=["reverse", "turn"], default=None)
    p.add_argument(
        "--drift",
        default="medium",
        help=f"odometry endpoint error in metres, a preset {sorted(DRIFT_PRESETS)}, or scale "
        "errors per leg 'legs:OUT,RET' (e.g. legs:-0.05,-0.15), or scale errors that change "
        "every 3-15 m within 'slip:LO,HI' (e.g. slip:-0.15,-0.01)",
    )
    p.add_argument(
        "--scene-param",
        dest="scene_params",
        action="append",
        default=[],
        type=_scene_param,
        metavar="KEY=VALUE",
        help="override a scene geometry parameter (repeatable), e.g. radius_m=0.5 or "
        "segment_length_m=3; joints.json scene_params lists them",
    )
    p.add_argument("--distinctiveness", type=float, default=None, help="1 = default")
    p.add_argument("--identical-joints", action="store_true", help="an aliased corridor")
    p.add_argument("--speed", type=float, default=None, help="m/s")
    p.add_argument(
        "--return-speed",
        type=float,
        default=None,
        metavar="M/S",
        help="the return leg's speed (default: --speed), e.g. a crawler that inspects slowly "
        "on the way out and comes back fast",
    )
    p.add_argument(
        "--return-lateral",
        type=float,
        default=0.0,
        metavar="M",
        help="the return runs this far to the side (left of the outbound direction; within "
        "0.6 of the radius), e.g. a vehicle that comes back in a tunnel's other lane",
    )
    p.add_argument(
        "--mount",
        type=_mount,
        default=(0.0, 0.0),
        metavar="ROLL,PITCH",
        help="the sensor's static mount in degrees (pitch positive nose down), e.g. 90,0 or "
        "0,20; default 0,0",
    )
    p.add_argument(
        "--stop",
        dest="stops",
        action="append",
        default=[],
        type=_stop,
        metavar="LEG:FRACTION:SECONDS",
        help="halt along a leg (repeatable): leg out or back, the fraction of the leg's "
        "length, seconds standing still, e.g. out:0.5:20 (an inspection stop at a defect)",
    )
    p.add_argument(
        "--backup",
        dest="backups",
        action="append",
        default=[],
        type=_backup,
        metavar="LEG:FRACTION:METRES",
        help="back up along a leg (repeatable): leg out or back, the fraction of the leg's "
        "length, metres driven back the way it came and forward again, e.g. out:0.5:3 (an "
        "operator looking again at a defect)",
    )
    p.add_argument(
        "--standstill",
        type=_standstill,
        default=None,
        metavar="START,END",
        help="seconds standing still before moving off and after coming back, e.g. 60,30 (a "
        "recording started while the operator gets ready); default 2,1",
    )
    p.add_argument(
        "--curve-radius",
        type=float,
        default=None,
        metavar="M",
        help="the corridor curves in the horizontal plane with this radius in metres "
        "(positive to the left, negative to the right; at least 20 corridor radii); "
        "default straight",
    )
    p.add_argument(
        "--height",
        type=float,
        default=None,
        metavar="M",
        help="the sensor's height in metres above the section's lowest point (a pipe's "
        "invert, a tunnel's floor); default the scene's (near a pipe's centre, 1.6 m above a "
        "tunnel's floor)",
    )
    p.add_argument(
        "--odometry",
        choices=["drift", "kiss-icp"],
        default="drift",
        help="odometry in /odom and odom.tum: the drift model (default) or KISS-ICP on the scans",
    )
    p.add_argument(
        "--livox", action="store_true", help="also /livox/lidar (livox_ros_driver2 CustomMsg)"
    )
    p.add_argument("--ros1", action="store_true", help="also write DIR/log.bag (ROS 1)")
    p.add_argument(
        "--sweep",
        action="store_true",
        help="each point measured at its own time within the 0.1 s scan, in the sensor's frame "
        "then, with a per-point t field (Ouster's, ns; with --livox also offset_time), as a "
        "real LiDAR moving at speed",
    )
    p.add_argument("--force", action="store_true", help="replace an existing DIR/log")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def _pair(text: str, option: str, names: str, example: str) -> tuple[float, float]:
    first, _, second = text.partition(",")
    try:
        return float(first), float(second)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{option} takes {names} (e.g. {example}), got {text!r}"
        ) from None


def _mount(text: str) -> tuple[float, float]:
    return _pair(text, "--mount", "ROLL,PITCH in degrees", "0,20")


def _leg_triple(text: str, option: str, last: str, example: str) -> tuple[float, float, float]:
    try:
        leg, fraction, value = text.split(":")
        if leg not in ("out", "back"):
            raise ValueError
        return (0.0 if leg == "out" else 1.0), float(fraction), float(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{option} takes LEG:FRACTION:{last} with LEG out or back (e.g. {example}), "
            f"got {text!r}"
        ) from None


def _stop(text: str) -> tuple[float, float, float]:
    return _leg_triple(text, "--stop", "SECONDS", "out:0.5:20")


def _backup(text: str) -> tuple[float, float, float]:
    return _leg_triple(text, "--backup", "METRES", "out:0.5:3")


def _standstill(text: str) -> tuple[float, float]:
    return _pair(text, "--standstill", "START,END in seconds", "60,30")


def _scene_param(text: str) -> tuple[str, float]:
    key, sep, value = text.partition("=")
    try:
        number = float(value)
    except ValueError:
        number = float("nan")
    if not sep or not key.strip() or number != number:
        raise argparse.ArgumentTypeError(f"expected KEY=NUMBER, got {text!r}")
    return key.strip(), number


def run(args: argparse.Namespace) -> int:
    # Imported here, not with the parser: the log writer is not needed for help.
    from decod_rs.sim import simulate

    overrides: dict[str, float | int] = {}
    if args.h_res is not None:
        overrides["h_res_deg"] = args.h_res
    if args.rays is not None:
        overrides["rays_per_scan"] = args.rays
    res = simulate(
        args.scene,
        args.out,
        seed=args.seed,
        length_m=args.length,
        sensor=args.sensor,
        return_mode=args.return_mode,
        drift=args.drift,
        distinctiveness=args.distinctiveness,
        identical_joints=args.identical_joints,
        speed_mps=args.speed,
        return_speed_mps=args.return_speed,
        return_lateral_m=args.return_lateral,
        sensor_overrides=overrides or None,
        scene_overrides=dict(args.scene_params) or None,
        world_seed=args.world_seed,
        mount_deg=args.mount,
        sensor_height_m=args.height,
        stops=args.stops,
        backups=args.backups,
        standstill_s=args.standstill,
        curve_radius_m=args.curve_radius,
        odometry=args.odometry,
        livox=args.livox,
        ros1=args.ros1,
        progress=not args.quiet,
        overwrite=args.force,
        sweep=args.sweep,
    )
    mb = res.log_size_bytes / 1e6
    print(f"scene          {res.scene} (sensor {res.sensor}, seed {args.seed})")
    print(
        f"scans          {res.n_scans} at 10 Hz, {res.n_points} points "
        f"({res.n_points / max(res.n_scans, 1):.0f} per scan), {res.n_imu} IMU samples"
    )
    print(f"duration       {res.duration_s:.1f} s of log")
    for leg, fraction, seconds in args.stops:
        where = "out" if leg == 0.0 else "back"
        print(f"stop           {seconds:g} s standing, {100 * fraction:g} % of the way {where}")
    for leg, fraction, metres in args.backups:
        where = "out" if leg == 0.0 else "back"
        print(f"backup         {metres:g} m back and on, {100 * fraction:g} % of the way {where}")
    if args.curve_radius is not None:
        side = "left" if args.curve_radius > 0 else "right"
        print(f"corridor       curves with radius {args.curve_radius:g} m to the {side}")
    print(f"joints         {res.n_joints} true boundaries in {res.joints_json}")
    print(f"odometry       endpoint error {res.endpoint_error_m:.3f} m")
    print(f"log            {res.log_dir} ({mb:.1f} MB)")
    print(
        f"time           {res.time_total_s:.1f} s total, "
        f"{1000 * res.time_per_scan_s:.1f} ms per scan (ray casting), "
        f"{res.time_write_s:.1f} s writing"
        + (f", {res.time_odometry_s:.1f} s odometry" if res.time_odometry_s else "")
    )
    return 0
