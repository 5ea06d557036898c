"""``decod inspect LOG``: topics, types, encodings, message counts and time span."""

from __future__ import annotations

import argparse

from decod_rs.io import LogInfo, inspect_log


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "inspect", help="list the topics of a log (.mcap, ROS 1 .bag, .db3, rosbag2 directory)"
    )
    p.add_argument("log", help="a .mcap, .bag or .db3 file, or a rosbag2 directory")
    p.set_defaults(func=run)


def format_log_info(info: LogInfo) -> str:
    """A readable table of ``info`` (one row per topic, then totals)."""
    header = ("topic", "type", "encoding", "messages")
    rows = [(t.topic, t.message_type, t.encoding, str(t.count)) for t in info.topics]
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(4)]
    lines = [f"log: {', '.join(str(f) for f in info.files)}"]
    fmt = "  {:<{w0}}  {:<{w1}}  {:<{w2}}  {:>{w3}}"
    w = {f"w{i}": widths[i] for i in range(4)}
    lines.append(fmt.format(*header, **w))
    lines.append(fmt.format(*("-" * n for n in widths), **w))
    lines.extend(fmt.format(*r, **w) for r in rows)
    if info.start is not None and info.end is not None:
        lines.append(
            f"{info.message_count} messages, {info.duration:.3f} s "
            f"(log time {info.start:.3f} .. {info.end:.3f})"
        )
    else:
        lines.append("no messages")
    if info.problem:
        lines.append(f"warning: the log is damaged, counts are of what is readable: {info.problem}")
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    print(format_log_info(inspect_log(args.log)))
    return 0
