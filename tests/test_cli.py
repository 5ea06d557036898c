"""The ``decod`` command starts without the heavy parts it does not need yet: printing help,
or parsing a command's options, imports neither GTSAM, matplotlib, rosbags nor the pipeline
(``decod --help`` took 2.0-2.3 s when every command imported them, 0.3 s without). The
packages whose runners are imported when first used still hand them out by name."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from decod_rs.cli import COMMANDS

HEAVY = ("gtsam", "matplotlib", "rosbags", "decod_rs.pipeline", "decod_rs.sim.api", "dask")


def _fresh(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False
    )


def test_building_the_command_line_imports_nothing_heavy() -> None:
    code = (
        "import json, sys\n"
        "from decod_rs.cli import build_parser\n"
        "parser = build_parser()\n"
        "parser.parse_args(['run', 'x.mcap', '--out', 'o', '--map'])\n"
        "parser.parse_args(['simulate', 'hume', '--out', 'o'])\n"
        f"print(json.dumps([m for m in {list(HEAVY)!r} if m in sys.modules]))\n"
    )
    done = _fresh(code)
    assert done.returncode == 0, done.stderr
    assert json.loads(done.stdout) == []


def test_help_lists_every_command() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "decod_rs.cli", "--help"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    for name in COMMANDS:
        assert name.replace("_", "-") in done.stdout


def test_runners_are_still_importable_by_name() -> None:
    from decod_rs.batch import run_batch, run_sweep
    from decod_rs.sim import simulate

    assert callable(run_batch) and callable(run_sweep) and callable(simulate)
    import decod_rs.batch
    import decod_rs.sim

    for module in (decod_rs.batch, decod_rs.sim):
        with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
            _ = module.nonexistent  # type: ignore[attr-defined]


def test_the_summary_names_windows_closed_by_travel_and_end_faces(
    capsys: pytest.CaptureFixture[str],
) -> None:
    from pathlib import Path

    from decod_rs.commands.run import print_summary
    from decod_rs.stages.write import RunSummary

    summary = RunSummary(Path("out"), 100, 12, 30, 5, 2, "batch", None, 10.0)
    print_summary(summary)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("submaps"))
    assert line.split() == ["submaps", "12,", "landmarks", "30"]
    summary.end_face_submaps, summary.travel_submaps = 2, 5
    print_summary(summary)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("submaps"))
    assert "(2 cut before an end face in view; 5 closed by their travel" in line
    # The matching line says how many views of ground driven again stayed out of the
    # database (none on a log driven straight through: nothing said).
    print_summary(summary)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("matching"))
    assert line.split() == ["matching", "batch", "mode,", "5", "queries,", "2", "accepted"]
    summary.revisited_views = 7
    print_summary(summary)
    line = next(x for x in capsys.readouterr().out.splitlines() if x.startswith("matching"))
    assert line.endswith(
        "2 accepted; 7 views on ground driven again query but stay out of the database"
    )
