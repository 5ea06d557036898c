"""decod batch and decod sweep end to end on short simulated logs (12 m of hume pipe out and
back): real MCAP logs, the Rust reader, GTSAM, Dask's local cluster.

* A batch of three logs, one corrupt, on Dask's LocalCluster through the command line: two
  complete outputs, one reported failure, a summary whose counts and metrics agree with
  the runs' own files and with ``evaluate_run``; a re-run skips complete logs, ``--force``
  redoes them.
* A sweep over two values of ``matching.min_inliers`` extracts each log once (counted by
  wrapping the extraction stage) and its runs and precision-recall points equal single
  ``run_log`` runs at those settings.
"""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any

import pytest

from decod_rs.batch.batch import run_batch
from decod_rs.batch.engine import dask_available, open_engine
from decod_rs.batch.grid import params_toml, settings_from_grid
from decod_rs.batch.jobs import LogJob, RunOptions
from decod_rs.batch.sweep import run_sweep
from decod_rs.cli import main
from decod_rs.evaluate import evaluate_run
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate
from decod_rs.stages import axial

LENGTH_M = 12.0
SEEDS = (3, 4)
#: Two thresholds of the paper's fixed rule with different accepted sets on these logs.
MIN_INLIERS = (6, 12)


@pytest.fixture(scope="module")
def sims(module_dir: Path) -> list[Path]:
    root = module_dir / "sims"
    out = []
    for seed in SEEDS:
        simulate("hume", root / f"hume{seed}", seed=seed, length_m=LENGTH_M, progress=False)
        out.append(root / f"hume{seed}")
    return out


@pytest.fixture(scope="module")
def corrupt(sims: list[Path]) -> Path:
    """A copy of a simulated log whose MCAP file starts with garbage."""
    log = sims[0].parent / "corrupt" / "log"
    shutil.copytree(sims[0] / "log", log)
    mcap = next(log.glob("*.mcap"))
    data = bytearray(mcap.read_bytes())
    data[:4096] = bytes(range(256)) * 16
    mcap.write_bytes(bytes(data))
    return log


def _manifest(path: Path, sims: list[Path], corrupt: Path) -> Path:
    lines = ["version = 1", "[defaults]", 'preset = "pipe"', 'imu_topic = "/imu"']
    for sim in sims:
        lines += [
            "[[log]]",
            f'path = "{sim / "log"}"',
            f'name = "{sim.name}"',
            f'gt = "{sim / "gt.tum"}"',
            f'joints = "{sim / "joints.json"}"',
        ]
    lines += ["[[log]]", f'path = "{corrupt}"', 'name = "corrupt"']
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _csv_rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.mark.skipif(not dask_available(), reason="the batch extra (dask) is not installed")
def test_batch_on_the_dask_local_cluster(
    sims: list[Path], corrupt: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    manifest = _manifest(tmp_path / "batch.toml", sims, corrupt)
    out = tmp_path / "out"
    argv = ["batch", "--manifest", str(manifest), "--out", str(out), "--no-plots"]
    code = main([*argv, "--engine", "dask", "--workers", "2"])
    printed = capsys.readouterr().out
    assert code == 1  # a log failed; the others ran
    assert "dask local cluster, 2 workers" in printed

    rows = {r["name"]: r for r in _csv_rows(out / "summary.csv")}
    assert sorted(rows) == ["corrupt", "hume3", "hume4"]
    assert rows["corrupt"]["status"] == "failed"
    assert rows["corrupt"]["error"].startswith("LogFormatError")
    assert "LogFormatError" in (out / "corrupt" / "error.txt").read_text()
    assert not (out / "corrupt" / "report.json").exists()
    for sim in sims:
        row, run = rows[sim.name], out / sim.name
        assert row["status"] == "ok"
        for name in ("odometry.tum", "corrected.tum", "loops.csv", "landmarks.csv", "report.json"):
            assert (run / name).is_file(), name
        # The summary agrees with the run's own files and with an independent evaluation.
        loops = _csv_rows(run / "loops.csv")
        assert int(row["queries"]) == len(loops)
        assert int(row["accepted"]) == sum(r["accepted"] in ("1", "true", "True") for r in loops)
        assert int(row["landmarks"]) == len(_csv_rows(run / "landmarks.csv"))
        result, _ = evaluate_run(run, sim / "gt.tum", sim / "joints.json")
        fine = result["loops"]["fine"]
        assert int(row["tp_fine"]) == fine["true_positives"]
        assert int(row["common_fine"]) == fine["common_queries"]
        rmse = result["trajectory"]["corrected"]["rmse_m"]
        assert float(row["corrected_rmse_m"]) == pytest.approx(rmse, rel=1e-5)
        section = json.loads((run / "report.json").read_text())["unmeasured"]
        only = sum(s["length_m"] for s in section["stretches"])
        assert float(row["odometry_only_m"]) == pytest.approx(only, rel=1e-5, abs=1e-9)
    assert int(rows["hume3"]["accepted"]) > 0  # the logs close loops: the metrics mean something
    md = (out / "summary.md").read_text()
    assert "| corrupt | failed |" in md and "2 run, 0 skipped" in md and "1 failed" in md

    # Re-run: complete logs are skipped, the failed one is tried again; --force redoes all.
    stamp = (out / "hume3" / "report.json").stat().st_mtime_ns
    assert main([*argv, "--engine", "serial"]) == 1
    rows = {r["name"]: r for r in _csv_rows(out / "summary.csv")}
    assert [rows[n]["status"] for n in ("hume3", "hume4", "corrupt")] == [
        "skipped",
        "skipped",
        "failed",
    ]
    assert rows["hume3"]["tp_fine"]  # a skipped run still has its metrics
    assert (out / "hume3" / "report.json").stat().st_mtime_ns == stamp
    jobs = [LogJob("hume3", sims[0] / "log", RunOptions(preset="pipe", plots=False))]
    with open_engine("serial") as engine:
        again = run_batch(jobs, out, engine, force=True)
    assert again.rows[0]["status"] == "ok"
    assert (out / "hume3" / "report.json").stat().st_mtime_ns != stamp


def test_batch_falls_back_to_a_process_pool(corrupt: Path, tmp_path: Path) -> None:
    jobs = [LogJob("corrupt", corrupt, RunOptions(preset="pipe", plots=False))]
    with open_engine("processes", workers=1) as engine:
        result = run_batch(jobs, tmp_path / "out", engine)
    assert result.failed == 1
    assert result.rows[0]["error"].startswith("LogFormatError")
    assert (tmp_path / "out" / "summary.md").is_file()


def _count_extractions(monkeypatch: pytest.MonkeyPatch) -> list[Path]:
    calls: list[Path] = []
    extract = axial.extract_stage

    def counting(log: Path, *args: Any, **kwargs: Any) -> Any:
        calls.append(log)
        return extract(log, *args, **kwargs)

    monkeypatch.setattr(axial, "extract_stage", counting)
    return calls


def _comparable(report: dict[str, Any]) -> dict[str, Any]:
    return {
        k: v
        for k, v in report.items()
        if k
        not in (
            "timings_s",
            "realtime_factor",
            "peak_memory_mb",
            "sweep",
            "landmarks_on_disk_bytes",
        )
    }


def test_sweep_extracts_each_log_once_and_matches_single_runs(
    sims: list[Path], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    options = RunOptions(preset="pipe", imu_topic="/imu", plots=False)
    jobs = [LogJob(s.name, s / "log", options, s / "gt.tum", s / "joints.json") for s in sims]
    settings = settings_from_grid({"matching.min_inliers": list(MIN_INLIERS)})
    calls = _count_extractions(monkeypatch)
    with open_engine("serial") as engine:
        result = run_sweep(jobs, settings, tmp_path / "sweep", engine)
    assert sorted(calls) == sorted(s / "log" for s in sims)  # each log extracted once
    assert result.extractions == {s.name: 1 for s in sims}

    for setting, pooled in zip(settings, result.setting_rows, strict=True):
        assert setting.params["matching.acceptance"] == "fixed"
        toml = tmp_path / f"{setting.id}.toml"
        toml.write_text(params_toml(setting.params), encoding="utf-8")
        totals = dict.fromkeys(("tp", "accepted", "common"), 0)
        for job in jobs:
            single = tmp_path / "single" / setting.id / job.name
            run_log(job.log, single, **{**options.run_kwargs(), "config_path": toml})
            swept = tmp_path / "sweep" / setting.id / job.name
            for name in ("loops.csv", "corrected.tum", "landmarks.csv", "joints.csv"):
                assert (swept / name).read_bytes() == (single / name).read_bytes(), name
            reports = [json.loads((d / "report.json").read_text()) for d in (swept, single)]
            assert _comparable(reports[0]) == _comparable(reports[1])
            # The replayed extraction's landmarks waited on disk, as a single run's do.
            assert reports[0]["landmarks_on_disk_bytes"] > 0
            fine = evaluate_run(single, job.gt, job.joints)[0]["loops"]["fine"]
            totals["tp"] += fine["true_positives"]
            totals["accepted"] += fine["accepted"]
            totals["common"] += fine["common_queries"]
        assert pooled["tp_fine"] == totals["tp"]
        assert pooled["precision_fine"] == (
            totals["tp"] / totals["accepted"] if totals["accepted"] else None
        )
        assert pooled["recall_fine"] == totals["tp"] / totals["common"]
    # The two thresholds are two different points of the curve.
    accepted = [r["accepted_fine"] for r in result.setting_rows]
    assert accepted[0] > accepted[1]
    assert (tmp_path / "sweep" / "pr_curve.png").is_file()
    sweep_rows = _csv_rows(tmp_path / "sweep" / "sweep.csv")
    assert [r["setting"] for r in sweep_rows] == ["s00", "s01"]

    # A re-run finds every run complete: nothing is extracted again.
    calls.clear()
    with open_engine("serial") as engine:
        again = run_sweep(jobs, settings, tmp_path / "sweep", engine)
    assert calls == [] and again.extractions == {s.name: 0 for s in sims}
    assert again.setting_rows == result.setting_rows
