"""``decod convert BAG OUT``: a ROS 1 bag to a rosbag2 directory with MCAP storage, through
rosbags (whose converter defaults to sqlite3: we ask for MCAP), then read back natively."""

from __future__ import annotations

import argparse
from pathlib import Path

from decod_rs.commands.inspect import format_log_info
from decod_rs.io import LogInfo, TopicCheck, check_log, inspect_log


def convert_bag(bag: Path, out: Path) -> tuple[LogInfo, list[TopicCheck]]:
    """Converts the ROS 1 ``bag`` into the rosbag2 directory ``out`` (MCAP storage, CDR
    messages, ROS 1 types mapped by rosbags), then reads ``out`` back natively: its summary
    and every message decoded.

    Raises:
        FileNotFoundError: ``bag`` does not exist.
        FileExistsError: ``out`` exists (rosbags never overwrites).
        ValueError: rosbags cannot read or convert the bag (its message is kept), or a
            converted message of a type decod reads does not decode.
    """
    from rosbags.convert.converter import ConverterError, convert

    if not bag.is_file():
        raise FileNotFoundError(2, "no such ROS 1 bag", str(bag))
    if out.exists():
        raise FileExistsError(17, "output exists; choose a new directory", str(out))
    try:
        convert(
            srcs=[bag],
            dst=out,
            dst_storage="mcap",
            dst_version=9,
            compress=None,
            compress_mode="file",
            default_typestore=None,
            typestore=None,
            exclude_topics=[],
            include_topics=[],
            exclude_msgtypes=[],
            include_msgtypes=[],
        )
    except ConverterError as exc:
        raise ValueError(f"{bag}: rosbags could not convert it: {exc}") from exc
    checks = check_log(out)
    bad = [c for c in checks if not c.ok]
    if bad:
        details = "; ".join(f"{c.topic}: {c.first_error}" for c in bad)
        raise ValueError(f"{out}: converted messages do not decode natively: {details}")
    return inspect_log(out), checks


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("convert", help="convert a ROS 1 bag to a rosbag2 directory (MCAP)")
    p.add_argument("bag", type=Path, help="the ROS 1 .bag file")
    p.add_argument("out", type=Path, help="the rosbag2 directory to create")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    info, checks = convert_bag(args.bag, args.out)
    print(f"converted {args.bag} -> {args.out} (MCAP), read back natively:")
    print(format_log_info(info))
    decoded = sum(c.decoded for c in checks if c.supported)
    total = sum(c.messages for c in checks if c.supported)
    points = sum(c.points for c in checks)
    print(f"verified: {decoded}/{total} messages of supported types decoded, {points} points")
    return 0
