"""What ``--map`` and ``--rerun FILE`` add to a ``decod run`` (issue 13: at most 20 %).

``python -m decod_rs.bench.map_overhead --out DIR [--repeats N] [--case SCENE:SENSOR ...]
[--end-to-end [--skip-parts]]``

Each case is a short simulated out-and-back log (cached in ``DIR/sims``) under the default
(auto) configuration. On a shared machine the wall time of a whole run varies by more than
the 10-20 % being measured, so the added work is measured part by part, in CPU seconds of
this process and its threads (what other processes cannot take), best of ``--repeats``:

- the plain run (``run_log`` without map or recording, plots included);
- the voxel map kept while streaming: the extraction stage with and without it, interleaved;
- the stages after the run: ``write_visuals`` with ``map``, with ``rerun``, with both, on the
  finished run's processor and trajectories, the recording written in this process (as
  ``decod run --no-plots`` does);
- importing the rerun SDK (a fresh interpreter that has numpy and matplotlib already).

Overhead = added CPU / plain run CPU; the wall seconds of the same parts (best of) beside
them, and the load average. ``--end-to-end`` also times ``decod run`` in a fresh process,
plain / ``--map`` / ``--rerun`` / both, interleaved (wall and CPU of the child and of the
recording's worker process, which writes the ``.rrd`` while the figures are drawn): what a
user waits for.

Output: ``DIR/map_overhead.json`` and ``DIR/map_overhead.md``.
"""

from __future__ import annotations

import argparse
import importlib
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

from decod_rs import _core
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate

VARIANTS: dict[str, list[str]] = {
    "plain": [],
    "map": ["--map"],
    "rerun": ["--rerun", "{out}/run.rrd"],
    "both": ["--map", "--rerun", "{out}/run.rrd"],
}
#: (scene, sensor, one-way length m, endpoint drift m, seed).
CASES = [
    ("hume", "avia", 20.0, 1.7, 2),
    ("hume", "spin16", 20.0, 1.7, 2),
    ("pe", "avia", 20.0, 1.7, 1),
    ("pe", "spin64", 20.0, 1.7, 1),
    ("shield", "avia", 25.0, 1.7, 1),
    ("shield", "spin16", 25.0, 3.0, 3),
    ("horseshoe", "avia", 25.0, 3.0, 1),
    ("horseshoe", "spin64", 25.0, 3.0, 1),
]


def _children_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def _decod() -> str:
    exe = Path(sys.executable).with_name("decod")
    return str(exe) if exe.exists() else "decod"


def _sim(root: Path, scene: str, sensor: str, length: float, drift: float, seed: int) -> Path:
    out = root / "sims" / f"{scene}-{sensor}-{length:g}m-d{drift:g}-s{seed}"
    if not (out / "joints.json").exists():
        simulate(
            scene,
            out,
            sensor=sensor,
            seed=seed,
            length_m=length,
            drift=drift,
            progress=False,
            overwrite=True,
        )
    return out


def _run(log: Path, out: Path, variant: str) -> tuple[float, float, dict[str, float]]:
    shutil.rmtree(out, ignore_errors=True)
    extra = [a.format(out=out.parent / f"{out.name}-rrd") for a in VARIANTS[variant]]
    (out.parent / f"{out.name}-rrd").mkdir(parents=True, exist_ok=True)
    cmd = [_decod(), "run", str(log), "--out", str(out), "--imu-topic", "/imu", *extra]
    c0, t0 = _children_cpu(), time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    wall, cpu = time.perf_counter() - t0, _children_cpu() - c0
    timings = json.loads((out / "report.json").read_text())["timings_s"]
    return wall, cpu, timings


def measure(root: Path, case: tuple[str, str, float, float, int], repeats: int) -> dict[str, Any]:
    """``decod run`` plain / --map / --rerun / both, interleaved ``repeats`` times. Each
    variant's overhead is the median over the repeats of its time against the plain run of
    the same repeat (paired: the machine's speed drifts by more than the effect between
    repeats a minute apart), and the best-of times beside it."""
    sim = _sim(root, *case)
    best: dict[str, dict[str, Any]] = {
        v: {"wall_s": float("inf"), "cpu_s": float("inf"), "runs": []} for v in VARIANTS
    }
    loads = []
    for _ in range(repeats):
        for variant in VARIANTS:
            loads.append(os.getloadavg()[0])
            wall, cpu, timings = _run(sim / "log", root / "runs" / sim.name / variant, variant)
            b = best[variant]
            b["runs"].append([round(wall, 3), round(cpu, 3)])
            if wall < b["wall_s"]:
                b.update(wall_s=wall, stages_s={k: round(v, 3) for k, v in timings.items()})
            b["cpu_s"] = min(b["cpu_s"], cpu)
    plain = best["plain"]
    for b in best.values():
        b["wall_overhead_percent"] = 100 * (b["wall_s"] / plain["wall_s"] - 1)
        b["cpu_overhead_percent"] = 100 * (b["cpu_s"] / plain["cpu_s"] - 1)
        for k, name in enumerate(("wall", "cpu")):
            paired = [r[k] / p[k] - 1 for r, p in zip(b["runs"], plain["runs"], strict=True)]
            b[f"{name}_overhead_median_percent"] = 100 * statistics.median(paired)
    return {"case": sim.name, "variants": best, "load": [min(loads), max(loads)]}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _best(work: Callable[[], object], repeats: int) -> tuple[float, float]:
    """Best CPU and best wall seconds of ``work`` over ``repeats`` calls."""
    cpu, wall = float("inf"), float("inf")
    for _ in range(repeats):
        c0, t0 = _cpu(), time.perf_counter()
        work()
        cpu, wall = min(cpu, _cpu() - c0), min(wall, time.perf_counter() - t0)
    return cpu, wall


def _finished_run(log: Path, out: Path) -> tuple[dict[str, Any], Path]:
    """A run with ``--map`` whose ``write_visuals`` arguments (those ``decod run`` gives
    ``start_visuals``) are kept for replays."""
    import decod_rs.pipeline as pipeline

    kept: dict[str, Any] = {}
    original = pipeline.start_visuals

    def keep(*args: Any) -> Any:
        kept.update(args=args[:-1])  # all but what was asked for (Visuals)
        return original(*args)

    shutil.rmtree(out, ignore_errors=True)
    pipeline.start_visuals = keep  # type: ignore[assignment]
    try:
        run_log(log, out, imu_topic="/imu", progress=False, map=True)
    finally:
        pipeline.start_visuals = original
    return kept, out


def _stream(log: Path, config: str, keep_map: bool) -> None:
    processor = _core.LogProcessor(str(log), config, imu_topic="/imu", map=keep_map)
    while processor.step() is not None:
        pass


def _rerun_import(repeats: int) -> tuple[float, float]:
    code = (
        "import resource, time, numpy, matplotlib.pyplot\n"
        "r = resource.getrusage(resource.RUSAGE_SELF); c = r.ru_utime + r.ru_stime\n"
        "t = time.perf_counter(); import rerun\n"
        "r = resource.getrusage(resource.RUSAGE_SELF)\n"
        "print(r.ru_utime + r.ru_stime - c, time.perf_counter() - t)"
    )
    runs = [
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
        for _ in range(repeats)
    ]
    values = [tuple(float(v) for v in r.stdout.split()) for r in runs]
    return min(v[0] for v in values), min(v[1] for v in values)


def components(
    root: Path, case: tuple[str, str, float, float, int], repeats: int
) -> dict[str, Any]:
    """The added CPU (and wall) seconds part by part (module doc)."""
    from decod_rs.visuals import write_visuals

    sim = _sim(root, *case)
    log, runs = sim / "log", root / "runs" / sim.name
    load = [os.getloadavg()[0]]

    def plain() -> None:
        shutil.rmtree(runs / "plain", ignore_errors=True)
        run_log(log, runs / "plain", imu_topic="/imu", progress=False)

    parts: dict[str, tuple[float, float]] = {"plain": _best(plain, repeats)}
    config = json.dumps(json.loads((runs / "plain" / "report.json").read_text())["config"])
    best = {True: (float("inf"), float("inf")), False: (float("inf"), float("inf"))}
    for _ in range(repeats):
        for keep_map in (True, False):
            c, w = _best(partial(_stream, log, config, keep_map), 1)
            best[keep_map] = (min(best[keep_map][0], c), min(best[keep_map][1], w))
    parts["stream_map"] = (best[True][0] - best[False][0], best[True][1] - best[False][1])
    kept, out = _finished_run(log, runs / "visuals")
    rrd = out / "run.rrd"
    importlib.import_module("rerun")  # measured on its own below
    for name, kwargs in (
        ("map", {"map": True, "rerun": None}),
        ("rerun", {"map": False, "rerun": rrd}),
        ("both", {"map": True, "rerun": rrd}),
    ):
        parts[f"after_{name}"] = _best(
            partial(write_visuals, out, *kept["args"], **kwargs), repeats
        )
    parts["rerun_import"] = _rerun_import(repeats)
    load.append(os.getloadavg()[0])
    plain_cpu, plain_wall = parts["plain"]

    def added(*names: str) -> dict[str, float]:
        cpu = sum(parts[n][0] for n in names)
        wall = sum(parts[n][1] for n in names)
        return {"cpu_percent": 100 * cpu / plain_cpu, "wall_percent": 100 * wall / plain_wall}

    return {
        "case": sim.name,
        "parts_s": {k: [round(v[0], 3), round(v[1], 3)] for k, v in parts.items()},
        "map": added("stream_map", "after_map"),
        "rerun": added("stream_map", "after_rerun", "rerun_import"),
        "both": added("stream_map", "after_both", "rerun_import"),
        "load": load,
    }


def markdown_parts(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| case | plain run CPU / wall [s] | stream with map [s CPU] | after: map / rerun / both "
        "[s CPU] | rerun import [s CPU] | --map | --rerun | both | load |",
        "|" + " --- |" * 9,
    ]
    for r in rows:
        p = r["parts_s"]

        def pct(name: str, r: dict[str, Any] = r) -> str:
            return f"{r[name]['cpu_percent']:.1f} % ({r[name]['wall_percent']:.0f} % wall)"

        lines.append(
            f"| {r['case']} | {p['plain'][0]:.2f} / {p['plain'][1]:.2f} | "
            f"{p['stream_map'][0]:+.3f} | {p['after_map'][0]:.3f} / {p['after_rerun'][0]:.3f} / "
            f"{p['after_both'][0]:.3f} | {p['rerun_import'][0]:.3f} | {pct('map')} | "
            f"{pct('rerun')} | {pct('both')} | {r['load'][0]:.1f}-{r['load'][1]:.1f} |"
        )
    return "\n".join(lines) + "\n"


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| case | plain wall / CPU [s] | --map | --rerun | both | both, best of: wall / CPU "
        "| map + rerun stages [s] | load (1 min) |",
        "|" + " --- |" * 8,
    ]
    for r in rows:
        v = r["variants"]

        def pct(name: str, v: dict[str, Any] = v) -> str:
            return (
                f"{v[name]['wall_overhead_median_percent']:+.0f} % / "
                f"{v[name]['cpu_overhead_median_percent']:+.0f} %"
            )

        both = v["both"]
        st = both.get("stages_s", {})
        lines.append(
            f"| {r['case']} | {v['plain']['wall_s']:.2f} / {v['plain']['cpu_s']:.2f} | "
            f"{pct('map')} | {pct('rerun')} | {pct('both')} | "
            f"{both['wall_overhead_percent']:+.0f} % / {both['cpu_overhead_percent']:+.0f} % | "
            f"{st.get('map', 0):.2f} + {st.get('rerun', 0):.2f} | "
            f"{r['load'][0]:.1f}-{r['load'][1]:.1f} |"
        )
    note = (
        "\nEnd to end (``decod run`` in a fresh process, figures drawn): overhead as wall / "
        "CPU, the median over the repeats of each variant against the plain run of the same "
        "repeat; plain: best of the repeats.\n"
    )
    return note + "\n" + "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--case", action="append", help="SCENE:SENSOR (default: all CASES)")
    p.add_argument("--end-to-end", action="store_true", help="also time decod run processes")
    p.add_argument(
        "--skip-parts", action="store_true", help="with --end-to-end: only the processes"
    )
    args = p.parse_args(argv)
    cases = CASES
    if args.case:
        wanted = {tuple(c.split(":")) for c in args.case}
        cases = [c for c in CASES if (c[0], c[1]) in wanted]
    rows, ends = [], []
    for case in cases:
        if not (args.skip_parts and args.end_to_end):
            rows.append(components(args.out, case, args.repeats))
            print(markdown_parts(rows[-1:]).splitlines()[-1], flush=True)
        if args.end_to_end:
            ends.append(measure(args.out, case, args.repeats))
            print(markdown(ends[-1:]).splitlines()[-1], flush=True)
    (args.out / "map_overhead.json").write_text(
        json.dumps({"parts": rows, "end_to_end": ends}, indent=2)
    )
    text = (markdown_parts(rows) if rows else "") + (markdown(ends) if ends else "")
    (args.out / "map_overhead.md").write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
