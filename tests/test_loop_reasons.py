"""The matrix diagnostic that places every loop with the ground truth: right and wrong loops
per reason, and the accepted loops whose offset ties them beside their candidate's boundary
(decod_rs.bench.loop_reasons)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from decod_rs.bench.loop_reasons import ReasonCounts, count_reasons, main
from decod_rs.run_files import LoopTable, write_loops_csv
from decod_rs.tum import read_tum, write_tum


def _straight_gt(path: Path) -> None:
    # Along world x at 1 m/s for 100 s, body axes = world axes.
    stamps = np.arange(0.0, 100.0, 0.1)
    poses = np.repeat(np.eye(4)[None], stamps.size, axis=0)
    poses[:, 0, 3] = stamps
    write_tum(path, stamps, poses)


def _loops() -> LoopTable:
    # Query at t = 80 s (x = 80), candidates at t = 10 s (x = 10); the query's boundary at
    # x = 12 (origin -68 m along x). Rows: a right accepted loop (candidate boundary at 12.05);
    # a right loop dropped as inconsistent; a wrong one dropped as inconsistent (1.5 m off);
    # and an accepted loop to the ring 1.5 m on whose verified offset (1.5 m) brings it back.
    db_x = [2.05, 2.0, 3.5, 3.5]
    dz = ["0.0", "0.0", "0.0", "-1.5"]
    n = len(db_x)
    axis = np.tile([1.0, 0.0, 0.0], (n, 1))
    return LoopTable(
        query_stamp=np.full(n, 80.0),
        db_stamp=np.full(n, 10.0),
        query_origin=np.tile([-68.0, 0.0, 0.0], (n, 1)),
        query_axis=axis,
        db_origin=np.array([[x, 0.0, 0.0] for x in db_x]),
        db_axis=axis.copy(),
        inliers=np.full(n, 20, dtype=np.int64),
        score=np.ones(n),
        accepted=np.array([True, False, False, True]),
        extra={
            "dz_m": dz,
            "heading_deg": ["0"] * n,
            "reason": ["", "inconsistent", "inconsistent", ""],
        },
    )


def test_loops_are_counted_right_or_wrong_per_reason(tmp_path) -> None:
    _straight_gt(tmp_path / "gt.tum")
    counts = ReasonCounts()
    shifted = count_reasons(_loops(), read_tum(tmp_path / "gt.tum"), 0.4, counts, "run")
    assert counts.rows == {"accepted": 2, "inconsistent": 2}
    assert counts.right == {"accepted": 2, "inconsistent": 1}
    # Only the loop a ring apart is beyond twice the radius; its views are 1.5 m apart.
    assert [(s.dz_m, round(s.views_apart_m, 3)) for s in shifted] == [(-1.5, 1.5)]
    # With a radius of 1 m its offset is within twice it.
    assert count_reasons(_loops(), read_tum(tmp_path / "gt.tum"), 1.0, ReasonCounts()) == []


def test_the_command_reads_a_matrix_directory(tmp_path, capsys) -> None:
    cell = tmp_path / "cells" / "c"
    run = cell / "uneven" / "run"
    run.mkdir(parents=True)
    (cell / "sim").mkdir()
    _straight_gt(cell / "sim" / "gt.tum")
    write_loops_csv(run / "loops.csv", _loops())
    report = {"config": {"matching": {"duplicate_radius_m": 0.4}}}
    (run / "report.json").write_text(json.dumps(report))
    assert main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "| inconsistent | 2 | 1 |" in out
    assert "| c uneven | -1.50 | 1.50 |" in out
