"""``decod run`` on real logs as they come (issue 11): a cut-off recording, a ROS 1 bag, an
odometry gap, an interrupted run. One short simulated pipe (8 m out and back, 491 scans,
~3 s to simulate, ~2 s per run) written as rosbag2/MCAP and as a ROS 1 bag.
"""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

import decod_rs
import decod_rs.pipeline
from decod_rs import _core
from decod_rs.cli import main as cli_main
from decod_rs.config import load_config
from decod_rs.ingest import WEAK_GAP_SIGMA_FACTOR, gap_bridges, outside_odometry, unused_ends
from decod_rs.io import read_log
from decod_rs.pipeline import run_log
from decod_rs.sim import simulate

OUTPUTS = ("odometry.tum", "corrected.tum", "loops.csv", "landmarks.csv", "joints.csv")


@pytest.fixture(scope="module")
def sim(module_dir: Path) -> Path:
    out = module_dir / "pipe" / "sim"
    simulate("hume", out, progress=False, length_m=8.0, drift=0.5, ros1=True)
    return out


def _run(log: Path, out: Path, **kwargs: object) -> dict:
    run_log(log, out, preset="pipe", progress=False, plots=False, **kwargs)  # type: ignore[arg-type]
    return json.loads((out / "report.json").read_text(encoding="utf-8"))


def test_cut_off_log_runs_to_the_end_and_reports_the_cut(sim: Path, tmp_path: Path) -> None:
    raw = (sim / "log" / "log.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: int(len(raw) * 0.55)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        report = _run(cut, tmp_path / "out")
    ours = [w for w in caught if issubclass(w.category, decod_rs.LogWarning)]
    assert len(ours) == 1 and "cut.mcap: truncated at byte" in str(ours[0].message)
    ingest = report["ingest"]
    (fault,) = ingest["faults"]
    assert fault["kind"] == "truncated" and fault["file"] == str(cut)
    assert 0 < fault["byte_offset"] <= len(raw) * 0.55
    assert fault["last_complete_log_time_s"] > 0 and not ingest["complete"]
    assert 100 < report["counts"]["scans"] < 491
    assert all((tmp_path / "out" / name).is_file() for name in OUTPUTS)


def test_auto_preset_on_a_cut_off_log_warns_once(sim: Path, tmp_path: Path) -> None:
    raw = (sim / "log" / "log.mcap").read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: int(len(raw) * 0.3)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        run_log(cut, tmp_path / "out", progress=False, plots=False)
    assert sum(issubclass(w.category, decod_rs.LogWarning) for w in caught) == 1
    report = json.loads((tmp_path / "out" / "report.json").read_text(encoding="utf-8"))
    assert report["auto"] is not None and report["ingest"]["faults"][0]["kind"] == "truncated"


def test_ros1_bag_runs_like_the_mcap_log(sim: Path, tmp_path: Path) -> None:
    bag = _run(sim / "log.bag", tmp_path / "bag")
    ref = _run(sim / "log", tmp_path / "mcap")
    assert bag["counts"] == ref["counts"] and bag["ingest"]["complete"]
    for name in OUTPUTS:
        assert (tmp_path / "bag" / name).read_bytes() == (tmp_path / "mcap" / name).read_bytes()


def test_odometry_gap_is_listed_and_never_inside_a_submap(sim: Path, tmp_path: Path) -> None:
    rows = np.loadtxt(sim / "odom.tum")
    t0 = rows[0, 0]
    keep = ~((rows[:, 0] > t0 + 20.05) & (rows[:, 0] < t0 + 26.0))
    tum = tmp_path / "gap.tum"
    np.savetxt(tum, rows[keep], fmt="%.9f")
    with pytest.warns(decod_rs.LogWarning, match="1 odometry gap"):
        report = _run(sim / "log", tmp_path / "out", odom_tum=tum)
    (gap,) = report["ingest"]["odometry_gaps"]
    assert gap["kind"] == "gap" and gap["bridge"] == "odometry"
    assert gap["start_s"] == pytest.approx(t0 + 20.0) and gap["end_s"] == pytest.approx(t0 + 26.0)
    assert 50 <= gap["scans_skipped"] <= 60
    assert report["counts"]["skipped_in_odometry_gaps"] == gap["scans_skipped"]
    stamps = np.loadtxt(tmp_path / "out" / "odometry.tum")[:, 0]
    assert not np.any((stamps > gap["start_s"]) & (stamps < gap["end_s"]))
    # No submap holds scans from both sides of the gap.
    cfg = load_config(None, "pipe")
    processor = _core.LogProcessor(
        str(sim / "log"), json.dumps(cfg.to_dict()), odom_tum=str(tum), map=False
    )
    while (batch := processor.step()) is not None:
        for submap in batch:
            s = np.asarray(submap.scan_stamps)
            assert s.max() <= gap["start_s"] or s.min() >= gap["end_s"], s


def test_restarted_odometry_is_bridged_by_a_weak_factor(sim: Path, tmp_path: Path) -> None:
    rows = np.loadtxt(sim / "odom.tum")
    t0 = rows[0, 0]
    after = rows[:, 0] >= t0 + 26.0
    keep = ~((rows[:, 0] > t0 + 20.05) & ~after)
    rows[after, 1] += 50.0  # the LIO restarted in a frame 50 m away
    tum = tmp_path / "restart.tum"
    np.savetxt(tum, rows[keep], fmt="%.9f")
    with pytest.warns(decod_rs.LogWarning):
        report = _run(sim / "log", tmp_path / "out", odom_tum=tum)
    (gap,) = report["ingest"]["odometry_gaps"]
    assert gap["bridge"] == "weak" and gap["scans_skipped"] > 0
    corrected = np.loadtxt(tmp_path / "out" / "corrected.tum")
    assert np.all(np.isfinite(corrected))


def test_clouds_without_odometry_at_either_end_are_named(sim: Path, tmp_path: Path) -> None:
    """An odometry file that starts 6 s late and stops 10 s early (a recording started
    before the SLAM, a TUM export cut short): the clouds outside it are not used, and the
    run says how many, when and for how long, instead of shrinking the log silently."""
    rows = np.loadtxt(sim / "odom.tum")
    t0, t1 = rows[0, 0], rows[-1, 0]
    tum = tmp_path / "short.tum"
    np.savetxt(tum, rows[(rows[:, 0] >= t0 + 6.0) & (rows[:, 0] <= t1 - 10.0)], fmt="%.9f")
    with pytest.warns(decod_rs.LogWarning) as caught:
        report = _run(sim / "log", tmp_path / "out", odom_tum=tum)
    (text,) = [str(w.message) for w in caught if issubclass(w.category, decod_rs.LogWarning)]
    assert "clouds before the odometry's first pose" in text
    assert "clouds after the odometry's last pose" in text
    ends = report["ingest"]["scans_outside_odometry"]
    # 10 scans a second: about 60 clouds before, 100 after.
    assert 55 <= ends["before"]["clouds"] <= 61 and 95 <= ends["after"]["clouds"] <= 101
    assert ends["before"]["span_s"][0] == pytest.approx(t0, abs=0.11)
    assert ends["after"]["span_s"][1] == pytest.approx(t1, abs=0.11)
    total = ends["before"]["clouds"] + ends["after"]["clouds"]
    assert report["counts"]["skipped_outside_odometry"] == total
    assert report["counts"]["scans"] + total == 491


def test_a_cloud_or_two_before_the_odometry_is_not_a_warning() -> None:
    stamps = np.arange(100.0, 110.0, 0.1)
    section = outside_odometry([99.9, 99.95, 110.0], stamps)
    assert section["before"]["clouds"] == 2 and section["after"]["clouds"] == 1
    assert unused_ends(section, stamps, gap_periods=5.0) == []
    late = outside_odometry(np.arange(99.0, 100.0, 0.1), stamps)
    (phrase,) = unused_ends(late, stamps, gap_periods=5.0)
    assert phrase.startswith("10 clouds before the odometry's first pose")


def test_gap_bridge_is_weak_when_the_odometry_jumps() -> None:
    stamps = np.arange(0.0, 10.0, 0.1)
    poses = np.tile(np.eye(4), (stamps.size, 1, 1))
    poses[:, 0, 3] = 0.2 * stamps  # 0.2 m/s
    stamps = stamps[(stamps < 4.0) | (stamps > 6.0)]
    poses = poses[np.isin(np.arange(100) * 0.1, stamps)]
    bridges, factors = gap_bridges(stamps, poses, [(3.9, 6.1, "gap")])
    assert bridges == ["odometry"] and factors is None
    restarted = poses.copy()
    restarted[stamps > 6.0, :3, 3] -= restarted[stamps > 6.0][0, :3, 3]  # a new frame
    restarted[stamps > 6.0, 0, 3] += 40.0
    bridges, factors = gap_bridges(stamps, restarted, [(3.9, 6.1, "gap")])
    assert bridges == ["weak"] and factors is not None
    after = int(np.searchsorted(stamps, 6.1))
    assert factors[after] == WEAK_GAP_SIGMA_FACTOR and np.sum(factors != 1.0) == 1
    # Up to the first submap anchor after the gap, so the anchors' edge is weak too.
    _, factors = gap_bridges(stamps, restarted, [(3.9, 6.1, "gap")], np.array([2.0, 6.55, 9.0]))
    assert factors is not None
    weak = stamps[factors == WEAK_GAP_SIGMA_FACTOR]
    np.testing.assert_allclose(weak, [6.1, 6.2, 6.3, 6.4, 6.5, 6.6])
    bridges, _ = gap_bridges(stamps, poses, [(-1.0, 0.0, "gap")])
    assert bridges == ["none"]


def test_interrupted_run_never_looks_finished(
    sim: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    real_write = decod_rs.pipeline.write_outputs

    def write_then_fail(*args: object, **kwargs: object) -> object:
        real_write(*args, **kwargs)  # type: ignore[arg-type]
        raise KeyboardInterrupt  # Ctrl-C after the CSV files, before report.json

    monkeypatch.setattr(decod_rs.pipeline, "write_outputs", write_then_fail)
    with pytest.raises(KeyboardInterrupt):
        _run(sim / "log", out)
    partial = tmp_path / "out.partial"
    assert not out.exists() and (partial / "loops.csv").is_file()
    assert not (partial / "report.json").exists()
    # Over an earlier complete run (and a file of the user's): untouched until the end.
    monkeypatch.setattr(decod_rs.pipeline, "write_outputs", real_write)
    first = _run(sim / "log", out)
    assert not partial.exists()
    (out / "notes.txt").write_text("mine")
    monkeypatch.setattr(decod_rs.pipeline, "write_outputs", write_then_fail)
    with pytest.raises(KeyboardInterrupt):
        _run(sim / "log", out)
    assert json.loads((out / "report.json").read_text(encoding="utf-8")) == first
    monkeypatch.setattr(decod_rs.pipeline, "write_outputs", real_write)
    _run(sim / "log", out)
    assert (out / "notes.txt").read_text() == "mine" and not partial.exists()
    shutil.rmtree(out)


def test_run_into_the_current_directory(
    sim: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    _run(sim / "log", Path("."))
    assert (here / "report.json").is_file() and not (tmp_path / "here.partial").exists()
    (tmp_path / "file").write_text("")
    with pytest.raises(NotADirectoryError):
        _run(sim / "log", tmp_path / "file")


def test_cli_prints_the_damage_once_on_one_line(
    sim: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    raw = (sim / "log.bag").read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(raw[: len(raw) // 2])
    args = ["run", str(cut), "--preset", "pipe", "--no-plots", "-o", str(tmp_path / "o")]
    assert cli_main(args) == 0
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if "warning" in line]
    assert len(lines) == 1 and lines[0].startswith(f"decod run: warning: {cut}: truncated at byte")
    # Every long stage shows its progress: the extraction, the track links, the queries, the
    # graphs solved.
    stages = {line.split()[0]: line for line in err.splitlines() if line[:1].isalpha()}
    assert {"extract", "link", "match", "optimise"} <= set(stages)
    linked = stages["link"].split()[2].split("/")
    assert linked[0] == linked[1] and int(linked[0]) > 0
    done = stages["match"].split()[2].split("/")
    assert done[0] == done[1] and int(done[0]) > 0
    assert " graphs " in stages["optimise"]


def test_imu_samples_handed_on_give_the_same_submaps(sim: Path, tmp_path: Path) -> None:
    """The rebuilt round takes the IMU the first extraction read (no second pass over the log
    for it): the same landmarks (their gravity-referenced frame, their descriptors) as
    reading the topic, and a refusal of a wrong shape naming the argument."""
    cfg = json.dumps(load_config(None, "pipe").to_dict())
    log, tum = str(sim / "log"), str(sim / "odom.tum")

    def landmarks(processor: _core.LogProcessor) -> list[np.ndarray]:
        out = []
        while (batch := processor.step()) is not None:
            for s in batch:
                out += [np.concatenate([lm.e1, lm.descriptor.ravel()]) for lm in s.result.landmarks]
        return out

    first = _core.LogProcessor(log, cfg, odom_tum=tum, imu_topic="/imu", map=False)
    read = landmarks(first)
    imu = first.imu_samples()
    assert imu is not None and imu.shape[1] == 4 and imu.shape[0] > 1000
    assert np.all(np.diff(imu[:, 0]) >= 0)
    again = _core.LogProcessor(log, cfg, odom_tum=tum, imu_samples=imu, map=False)
    handed = landmarks(again)
    assert len(handed) == len(read) > 5
    for a, b in zip(handed, read, strict=True):
        np.testing.assert_array_equal(a, b)
    assert _core.LogProcessor(log, cfg, odom_tum=tum, map=False).imu_samples() is None
    with pytest.raises(ValueError, match="imu_samples"):
        _core.LogProcessor(log, cfg, odom_tum=tum, imu_samples=imu[:, :3], map=False)
    # The auto probe's reader hands its pass's IMU to the first extraction: the same samples.
    reader = read_log(sim / "log", None, None, sim / "odom.tum", "/imu")
    probed = reader.imu_samples()
    assert probed is not None
    np.testing.assert_array_equal(probed, imu)
    assert read_log(sim / "log", None, None, sim / "odom.tum", None).imu_samples() is None
