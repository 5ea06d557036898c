"""Summarise a generalisation matrix (``matrix.json``) per scene and sensor, tuned and
held-out rows apart: the README's table. Usage: ``python scripts/matrix_summary.py DIR``."""

from __future__ import annotations

import json
import sys
from collections import defaultdict
from pathlib import Path
from typing import Any


def _pct(values: list[float]) -> str:
    return f"{100 * sum(values) / len(values):.0f} %" if values else "-"


def _group(rows: list[dict[str, Any]]) -> str:
    ok = [r for r in rows if r.get("status") == "ok"]
    acc = sum(r["accepted"] for r in ok)
    tp = sum(r.get("true_positives_fine") or 0 for r in ok)
    fp_coarse = sum(r.get("false_positives_coarse") or 0 for r in ok)
    seen = sum(r.get("joints_seen_both") or 0 for r in ok if not r.get("aliased"))
    closed = sum(r.get("joints_closed") or 0 for r in ok if not r.get("aliased"))
    drifted = [r for r in ok if (r.get("odom_endpoint_m") or 0) >= 1.0 and not r.get("aliased")]
    end_ok = [(r.get("endpoint_reduction_percent") or -1e9) >= 80.0 for r in drifted]
    rmse_ok = [(r["corr_rmse_m"] <= r["odom_rmse_m"] + 1e-3) for r in ok]
    rmse_red = sorted(r.get("rmse_reduction_percent") or 0.0 for r in ok if not r.get("aliased"))
    rt = sorted(r["realtime_factor"] for r in ok if r.get("realtime_factor"))
    prec = f"{100 * tp / acc:.1f} %" if acc else "-"
    med = rmse_red[len(rmse_red) // 2] if rmse_red else float("nan")
    return (
        f"| {len(ok)} | {acc} | {prec} | {fp_coarse} | "
        f"{100 * closed / seen:.0f} % | {_pct(end_ok)} | {_pct(rmse_ok)} | {med:.0f} % | "
        f"{rt[0]:.0f}-{rt[-1]:.0f}x |"
        if rt and seen
        else f"| {len(ok)} | {acc} | {prec} | {fp_coarse} | - | {_pct(end_ok)} | "
        f"{_pct(rmse_ok)} | - | - |"
    )


def main(path: str) -> None:
    rows = json.loads((Path(path) / "matrix.json").read_text())["rows"]
    header = (
        "| rows | runs | loops accepted | precision@1 0.3 m | beyond coarse | joint coverage "
        "| endpoint -80 % where drift >= 1 m | RMSE not above odometry | median RMSE reduction "
        "| x real time |"
    )
    for held in (False, True):
        groups: dict[str, list[dict[str, Any]]] = defaultdict(list)
        for r in rows:
            if bool(r.get("held_out")) != held:
                continue
            key = f"{r['scene']} {r['sensor']}" + (" aliased" if r.get("aliased") else "")
            key += f" ({r['profile']})"
            groups[key].append(r)
        print("held out" if held else "tuned")
        print(header.replace("| rows |", "| scene, sensor (drift) |"))
        print("|" + " --- |" * (header.count("|") - 1))
        for key in sorted(groups):
            print(f"| {key} " + _group(groups[key]))
        print()


if __name__ == "__main__":
    main(sys.argv[1])
