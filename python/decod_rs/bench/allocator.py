"""What :mod:`decod_rs.allocator` saves on a log: ``decod run`` with glibc's defaults and
with the allocator tuned, alternately, in fresh processes.

``python -m decod_rs.bench.allocator LOG [--runs N] [-- decod run options]``, e.g.
``python -m decod_rs.bench.allocator sim/log --runs 3 -- --odom-tum sim/odom.tum``.
Prints per run and as medians: wall time, user and system CPU time, minor page faults (the
child's ``getrusage``) and x real time (``report.json``). Outputs go to a temporary
directory and are compared file by file between the two settings (they must not differ).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path

from decod_rs.allocator import OFF_SWITCH

#: Files of a run compared between the two settings.
COMPARED = ("corrected.tum", "landmarks.csv", "loops.csv", "joints.csv", "graph.g2o")
SETTINGS = {"glibc defaults": "0", "tuned": "1"}


def one_run(log: Path, out: Path, extra: Sequence[str], switch: str) -> dict[str, float]:
    """``decod run LOG --out OUT --no-plots EXTRA`` in a fresh process; its resources."""
    env = {**os.environ, OFF_SWITCH: switch}
    cmd = [sys.executable, "-m", "decod_rs.cli", "run", str(log), "--out", str(out)]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run([*cmd, "--no-plots", *extra], env=env, check=True, capture_output=True)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    report = json.loads((out / "report.json").read_text(encoding="utf-8"))
    return {
        "wall_s": wall,
        "user_s": after.ru_utime - before.ru_utime,
        "system_s": after.ru_stime - before.ru_stime,
        "minor_faults": float(after.ru_minflt - before.ru_minflt),
        "x_real_time": float(report["realtime_factor"]),
    }


def differing_outputs(a: Path, b: Path) -> list[str]:
    """The compared files that differ between two runs."""
    return [f for f in COMPARED if (a / f).read_bytes() != (b / f).read_bytes()]


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    cut = argv.index("--") if "--" in argv else len(argv)
    p = argparse.ArgumentParser(
        prog="python -m decod_rs.bench.allocator",
        description=__doc__,
        epilog="after --: more `decod run` options",
    )
    p.add_argument("log", type=Path)
    p.add_argument("--runs", type=int, default=3, help="runs per setting (alternating)")
    args = p.parse_args(argv[:cut])
    args.extra = argv[cut + 1 :]
    results: dict[str, list[dict[str, float]]] = {name: [] for name in SETTINGS}
    with tempfile.TemporaryDirectory(prefix="decod-bench-allocator-") as tmp:
        for k in range(max(args.runs, 1)):
            for name, switch in SETTINGS.items():
                out = Path(tmp) / f"{switch}-{k}"
                row = one_run(args.log, out, args.extra, switch)
                results[name].append(row)
                cells = ", ".join(f"{key} {value:.2f}" for key, value in row.items())
                print(f"run {k + 1} {name}: {cells}", flush=True)
        differ = differing_outputs(Path(tmp) / "0-0", Path(tmp) / "1-0")
    for name, rows in results.items():
        medians = {key: statistics.median(r[key] for r in rows) for key in rows[0]}
        cells = ", ".join(f"{key} {value:.2f}" for key, value in medians.items())
        print(f"median {name}: {cells}")
    print("outputs identical" if not differ else f"outputs DIFFER: {', '.join(differ)}")
    return 1 if differ else 0


if __name__ == "__main__":
    sys.exit(main())
