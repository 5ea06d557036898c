"""What ``--map`` and ``--rerun FILE`` add to a ``decod run`` (issue 13: at most 20 %).

``python -m decod_rs.bench.map_overhead --out DIR [--repeats N] [--case SCENE:SENSOR ...]``

Each case is a short simulated out-and-back log (cached in ``DIR/sims``) run as a user runs
it, ``decod run LOG --out ...`` in a fresh process (imports, plots, everything), in four
variants: plain, ``--map``, ``--rerun F``, and both; the variants are interleaved ``--repeats``
times so that a busy machine slows them alike. Per variant the best wall time and the best
CPU time (user + system of the process and its threads) are kept; the overhead is the
variant's best over the plain run's best. CPU time is the steadier figure on a shared
machine (other processes take wall time, not this process's CPU time); both are reported,
with the load average beside them.

Output: ``DIR/map_overhead.json`` and ``DIR/map_overhead.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

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
    sim = _sim(root, *case)
    best: dict[str, dict[str, Any]] = {
        v: {"wall_s": float("inf"), "cpu_s": float("inf")} for v in VARIANTS
    }
    loads = []
    for _ in range(repeats):
        for variant in VARIANTS:
            loads.append(os.getloadavg()[0])
            wall, cpu, timings = _run(sim / "log", root / "runs" / sim.name / variant, variant)
            b = best[variant]
            if wall < b["wall_s"]:
                b.update(wall_s=wall, stages_s={k: round(v, 3) for k, v in timings.items()})
            b["cpu_s"] = min(b["cpu_s"], cpu)
    plain = best["plain"]
    for b in best.values():
        b["wall_overhead_percent"] = 100 * (b["wall_s"] / plain["wall_s"] - 1)
        b["cpu_overhead_percent"] = 100 * (b["cpu_s"] / plain["cpu_s"] - 1)
    return {"case": sim.name, "variants": best, "load": [min(loads), max(loads)]}


def markdown(rows: list[dict[str, Any]]) -> str:
    lines = [
        "| case | plain wall / CPU [s] | map wall / CPU | rerun wall / CPU | both wall / CPU "
        "| map + rerun stages [s] | load (1 min) |",
        "|" + " --- |" * 7,
    ]
    for r in rows:
        v = r["variants"]

        def pct(name: str, v: dict[str, Any] = v) -> str:
            return (
                f"{v[name]['wall_overhead_percent']:+.0f} % / "
                f"{v[name]['cpu_overhead_percent']:+.0f} %"
            )

        st = v["both"].get("stages_s", {})
        lines.append(
            f"| {r['case']} | {v['plain']['wall_s']:.2f} / {v['plain']['cpu_s']:.2f} | "
            f"{pct('map')} | {pct('rerun')} | {pct('both')} | "
            f"{st.get('map', 0):.2f} + {st.get('rerun', 0):.2f} | "
            f"{r['load'][0]:.1f}-{r['load'][1]:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=(__doc__ or "").split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--case", action="append", help="SCENE:SENSOR (default: all CASES)")
    args = p.parse_args(argv)
    cases = CASES
    if args.case:
        wanted = {tuple(c.split(":")) for c in args.case}
        cases = [c for c in CASES if (c[0], c[1]) in wanted]
    rows = []
    for case in cases:
        rows.append(measure(args.out, case, args.repeats))
        print(markdown(rows[-1:]).splitlines()[-1], flush=True)
    (args.out / "map_overhead.json").write_text(json.dumps(rows, indent=2))
    (args.out / "map_overhead.md").write_text(markdown(rows))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
