"""``decod demo``, a new user's first command: a drifting pipe inspection simulated as a real
LiDAR takes it (each point at its own time within its sweep), corrected and evaluated, with
the lines ``decod run`` prints and the plots it names."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from decod_rs.cli import main as cli_main
from decod_rs.commands import demo


def test_the_demo_corrects_a_swept_pipe_inspection_and_says_how(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    # 15 m instead of 40 m a way, to keep the suite short; the seed and the rest are the
    # demo's own.
    monkeypatch.setattr(demo, "DEMO_LENGTH_M", 15.0)
    out = tmp_path / "decod_demo"
    assert cli_main(["demo", "--out", str(out), "--drift", "1.5"]) == 0
    printed = capsys.readouterr().out
    result = json.loads((out / "demo.json").read_text(encoding="utf-8"))
    # The targets: the endpoint error reduced by 80 % or more where the odometry
    # drifted 1 m or more, the RMSE not above the odometry's.
    assert result["endpoint_before_m"] > 1.0
    assert result["endpoint_after_m"] < 0.2 * result["endpoint_before_m"], result
    assert result["rmse_after_m"] < result["rmse_before_m"], result
    # The scans were swept and decod moved their points by their times, and said so, as
    # `decod run` does, with what auto measured.
    assert json.loads((out / "sim" / "joints.json").read_text())["sweep"] is True
    assert "moved to their stamp's pose" in printed
    assert "auto           pipe" in printed
    for name in ("trajectory.png", "trajectory_vs_gt.png", "error_over_time.png"):
        assert (out / "run" / name).stat().st_size > 0, name
