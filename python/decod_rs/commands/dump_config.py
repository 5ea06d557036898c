"""``decod dump-config [--preset]``: every parameter with its default, as TOML."""

from __future__ import annotations

import argparse

from decod_rs.config import PRESETS, dump_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("dump-config", help="print the full config with its defaults (TOML)")
    p.add_argument("--preset", choices=PRESETS, default="tunnel")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    print(dump_config(args.preset), end="")
    return 0
