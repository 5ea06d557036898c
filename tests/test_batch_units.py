"""Units of decod batch / sweep that need no log: the manifest (data, checked, refused with
file and key), log discovery and output names, the grid (settings, acceptance, config
overrides equal to a --config file, extraction groups) and the engines."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import decod_rs
from decod_rs.batch import engine as engine_mod
from decod_rs.batch.grid import (
    Setting,
    apply_params,
    check_params,
    extraction_params,
    params_toml,
    parse_param,
    settings_from_grid,
)
from decod_rs.batch.jobs import LogJob, RunOptions, build_jobs, discover_logs, unique_names
from decod_rs.batch.manifest import MAX_MANIFEST_BYTES, ManifestError, load_manifest
from decod_rs.batch.sweep import _tasks
from decod_rs.config import load_config


def _write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


# --- manifest -------------------------------------------------------------------------


def test_manifest_resolves_paths_and_merges_defaults_under_each_log(tmp_path: Path) -> None:
    m = _write(
        tmp_path / "m" / "batch.toml",
        """
version = 1
[defaults]
preset = "pipe"
imu_topic = "/imu"
[[log]]
path = "a/log"
gt = "a/gt.tum"
[[log]]
path = "/data/b.mcap"
name = "bee"
imu_topic = "/imu2"
use_imu = true
[sweep]
"matching.min_inliers" = [6, 9]
"matching.acceptance" = "fixed"
""",
    )
    man = load_manifest(m)
    a, b = man.logs
    assert a.path == (tmp_path / "m" / "a" / "log").resolve()
    assert a.gt == (tmp_path / "m" / "a" / "gt.tum").resolve()
    assert a.options == {"preset": "pipe", "imu_topic": "/imu"}
    assert b.path == Path("/data/b.mcap") and b.name == "bee"
    assert b.options == {"preset": "pipe", "imu_topic": "/imu2", "use_imu": True}
    assert man.grid == {"matching.min_inliers": [6, 9], "matching.acceptance": ["fixed"]}

    # The manifest's options beat the command line's; CLI logs keep the CLI's.
    jobs = build_jobs([], man, RunOptions(preset="tunnel", plots=False))
    assert [j.name for j in jobs] == ["log", "bee"]
    assert jobs[0].options.preset == "pipe" and jobs[0].options.plots is False
    assert jobs[1].options.imu_topic == "/imu2"


def test_manifest_json_is_the_same_format(tmp_path: Path) -> None:
    doc = {"version": 1, "log": [{"path": "x.mcap", "mode": "online", "loops": False}]}
    man = load_manifest(_write(tmp_path / "m.json", json.dumps(doc)))
    assert man.logs[0].options == {"mode": "online", "loops": False}


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        ('version = 1\ncolour = "red"', "unknown key colour"),
        ('version = 1\n[defaults]\nodom = "/o"', "unknown key defaults.odom"),
        ('version = 1\n[[log]]\npath = "a"\ngt_tum = "g"', "unknown key log[0].gt_tum"),
        ('[[log]]\npath = "a"', "version: expected 1"),
        ('version = 2\n[[log]]\npath = "a"', "version: expected 1, got 2"),
        ('version = 1\n[[log]]\nname = "a"', "log[0]: missing key `path`"),
        ('version = 1\n[[log]]\npath = "a"\nuse_imu = "no"', "log[0].use_imu: expected true"),
        ("version = 1\n[[log]]\npath = 3", "log[0].path: expected a non-empty string"),
        ('version = 1\n[[log]]\npath = "a"\npreset = "sewer"', "log[0].preset: 'sewer'"),
        ('version = 1\n[[log]]\npath = "a"\nname = "../x"', "not a plain directory name"),
        (
            'version = 1\n[[log]]\npath = "a"\nname = "x"\n[[log]]\npath = "b"\nname = "x"',
            "names used twice: x",
        ),
        ('version = 1\n[sweep]\n"matching.min_inliers" = []', "expected 1 to 100 values"),
        ("version = 1\n[sweep.matching]\nmin_inliers = [6]", "write dotted parameters"),
        ("version = 1\n[[log]\n", "not valid toml"),
    ],
)
def test_manifest_errors_name_the_file_and_key(tmp_path: Path, text: str, needle: str) -> None:
    path = _write(tmp_path / "bad.toml", text)
    with pytest.raises(ManifestError) as err:
        load_manifest(path)
    assert str(path) in str(err.value)
    assert needle.lower() in str(err.value).lower()


def test_manifest_size_is_checked(tmp_path: Path) -> None:
    path = _write(tmp_path / "big.toml", "version = 1\n" + "#" * MAX_MANIFEST_BYTES)
    with pytest.raises(ManifestError, match="bytes, more than"):
        load_manifest(path)
    with pytest.raises(FileNotFoundError, match="manifest"):
        load_manifest(tmp_path / "none.toml")


# --- discovery and names --------------------------------------------------------------


def test_discover_logs_directories_globs_and_files(tmp_path: Path) -> None:
    for run in ("a", "b"):
        _write(tmp_path / "runs" / run / "log" / "metadata.yaml", "x")
        _write(tmp_path / "runs" / run / "log" / "log_0.mcap", "x")
        _write(tmp_path / "runs" / run / "notes.txt", "x")
    _write(tmp_path / "runs" / "c.mcap", "x")
    _write(tmp_path / "other" / "d.bag", "x")
    root = tmp_path / "runs"
    expected = [root / "a" / "log", root / "b" / "log", root / "c.mcap"]
    assert discover_logs([str(root)]) == [p.resolve() for p in expected]
    # A rosbag2 directory is one log, a glob keeps logs only, duplicates are dropped.
    assert discover_logs([str(root / "*" / "log"), str(root / "a" / "log")]) == [
        p.resolve() for p in expected[:2]
    ]
    assert discover_logs([str(root / "*" / "*")]) == [p.resolve() for p in expected[:2]]
    assert discover_logs([str(tmp_path / "other" / "d.bag")]) == [
        (tmp_path / "other" / "d.bag").resolve()
    ]
    with pytest.raises(FileNotFoundError, match="no such file"):
        discover_logs([str(tmp_path / "missing.mcap")])
    with pytest.raises(FileNotFoundError, match="no log found"):
        discover_logs([str(tmp_path / "nothing*")])
    assert unique_names(discover_logs([str(root)])) == ["a_log", "b_log", "c"]
    assert unique_names([Path("/x/a/log.mcap")], taken={"log"}) == ["a_log"]
    with pytest.raises(ValueError, match="no log to run"):
        build_jobs([], None, RunOptions())


# --- grid -----------------------------------------------------------------------------


def test_parse_param_reads_toml_scalars_and_bare_words() -> None:
    assert parse_param("matching.min_inliers=6,9,15") == ("matching.min_inliers", [6, 9, 15])
    assert parse_param("matching.false_alarm_rate=1e-3, 1e-2") == (
        "matching.false_alarm_rate",
        [1e-3, 1e-2],
    )
    assert parse_param("matching.acceptance=fixed") == ("matching.acceptance", ["fixed"])
    assert parse_param("graph.sequential=true,false")[1] == [True, False]
    for bad in ("min_inliers=9", "matching.min_inliers", "matching.min_inliers="):
        with pytest.raises(ValueError, match=r"SECTION\.KEY"):
            parse_param(bad)


def test_settings_are_the_product_with_the_acceptance_their_parameter_needs() -> None:
    s = settings_from_grid({"matching.min_inliers": [6, 9], "submap.interval_s": [1.0, 2.0]})
    assert [x.id for x in s] == ["s00", "s01", "s02", "s03"]
    assert s[1].params == {
        "matching.min_inliers": 6,
        "submap.interval_s": 2.0,
        "matching.acceptance": "fixed",
    }
    far = settings_from_grid({"matching.false_alarm_rate": [1e-4, 1e-2]})
    assert all(x.params["matching.acceptance"] == "null_model" for x in far)
    given = settings_from_grid(
        {"matching.min_inliers": [9], "matching.acceptance": ["fixed", "null_model"]}
    )
    assert [x.params["matching.acceptance"] for x in given] == ["fixed", "null_model"]
    with pytest.raises(ValueError, match=r"add matching\.acceptance"):
        settings_from_grid({"matching.min_inliers": [9], "matching.false_alarm_rate": [0.1]})
    with pytest.raises(ValueError, match="more than 1000"):
        settings_from_grid({"matching.min_inliers": list(range(40)), "graph.huber_k": [1.0] * 30})
    with pytest.raises(ValueError, match="empty grid"):
        settings_from_grid({})


def test_apply_params_equals_a_config_file_with_those_parameters(tmp_path: Path) -> None:
    params = {
        "matching.min_inliers": 15,
        "matching.acceptance": "fixed",
        "submap.interval_s": 3,
        "graph.sequential": False,
    }
    toml = _write(tmp_path / "setting.toml", params_toml(params))
    for preset in ("pipe", "tunnel"):
        from_file = load_config(toml, preset).to_dict()
        assert apply_params(load_config(None, preset), params).to_dict() == from_file
        assert from_file["submap"]["interval_s"] == 3.0
    with pytest.raises(decod_rs.ConfigError, match="min_inlier"):
        apply_params(load_config(None, "pipe"), {"matching.min_inlier": 9})
    with pytest.raises(decod_rs.ConfigError, match="interval_s"):
        check_params([Setting("s00", {"submap.interval_s": -1.0})], "auto")
    with pytest.raises(decod_rs.ConfigError, match=r"SECTION\.KEY"):
        apply_params(load_config(None, "pipe"), {"min_inliers": 9})


def test_settings_differing_in_matching_or_graph_share_one_extraction_task() -> None:
    matching_only = settings_from_grid({"matching.min_inliers": [6, 9, 15]})
    assert {extraction_params(s.params) for s in matching_only} == {()}
    jobs = [LogJob("a", Path("/a"), RunOptions()), LogJob("b", Path("/b"), RunOptions())]
    tasks = _tasks(jobs, matching_only, Path("/out"))
    assert len(tasks) == 2  # one extraction per log
    assert [len(runs) for _, _, runs in tasks] == [3, 3]
    assert tasks[0][2][1][1] == Path("/out/s01/a")
    mixed = settings_from_grid({"submap.interval_s": [1.0, 2.0], "graph.huber_k": [1.0, 2.0]})
    tasks = _tasks(jobs, mixed, Path("/out"))
    assert len(tasks) == 4  # per log: one per interval, each replaying two huber_k values
    assert sorted(p["submap.interval_s"] for _, p, _ in tasks) == [1.0, 1.0, 2.0, 2.0]


# --- engines --------------------------------------------------------------------------


def test_engines_and_the_fallback_without_dask(monkeypatch: pytest.MonkeyPatch) -> None:
    with engine_mod.open_engine("serial") as eng:
        assert eng.executor.submit(math.hypot, 3.0, 4.0).result() == 5.0
        failed = eng.executor.submit(math.sqrt, -1.0)
        assert isinstance(failed.exception(), ValueError)
    with engine_mod.open_engine("processes", workers=2) as eng:
        assert eng.kind == "processes" and eng.workers == 2
        assert eng.executor.submit(math.hypot, 5.0, 12.0).result() == 13.0
    monkeypatch.setattr(engine_mod, "dask_available", lambda: False)
    with engine_mod.open_engine("auto", workers=1) as eng:
        assert eng.kind == "processes"
    with pytest.raises(ImportError, match=r"decod-rs\[batch\]"):
        with engine_mod.open_engine("dask"):
            pass
    with pytest.raises(ValueError, match="engine"):
        with engine_mod.open_engine("ray"):
            pass
    with pytest.raises(ValueError, match="address"):
        with engine_mod.open_engine("processes", address="tcp://127.0.0.1:1"):
            pass
    assert engine_mod.worker_env(2)["RAYON_NUM_THREADS"]
