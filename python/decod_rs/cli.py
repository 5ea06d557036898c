"""The ``decod`` command. Each verb lives in ``decod_rs/commands/<verb>.py`` and exposes
``add_parser(subparsers)``, which registers the verb and sets ``func``; ``main`` dispatches."""

from __future__ import annotations

import argparse
import importlib
import sys
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

from decod_rs import __version__
from decod_rs.allocator import keep_freed_memory
from decod_rs.ingest import LogWarning

# Module names under decod_rs.commands, in the order `decod --help` lists them.
COMMANDS = [
    "batch",
    "dump_config",
    "evaluate",
    "inspect",
    "convert",
    "demo",
    "run",
    "simulate",
    "sweep",
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="decod",
        description="DeCOD loop closure for LiDAR SLAM in pipes and tunnels.",
    )
    parser.add_argument("--version", action="version", version=f"decod {__version__}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"decod_rs.commands.{name}").add_parser(sub)
    return parser


@contextmanager
def _plain_log_warnings(command: str) -> Iterator[None]:
    """A damaged log's warning as one line ``decod run: warning: ...`` (not Python's
    ``file:line`` form with a source line); other warnings as usual."""
    default = warnings.showwarning

    def show(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        if issubclass(category, LogWarning):
            print(f"decod {command}: warning: {message}", file=sys.stderr)
        else:
            default(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        yield
    finally:
        warnings.showwarning = default


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    keep_freed_memory()  # the process is decod's: the allocator tuned for it (allocator.py)
    try:
        with _plain_log_warnings(args.command):
            return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("decod: interrupted", file=sys.stderr)
        return 130
    except (OSError, ValueError, LookupError) as exc:
        # Errors on the user's input: one clear line, no traceback.
        print(f"decod {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
