"""The generalisation matrix's pure helpers: cell list, visibility, coverage, tables, targets
(no simulation, no run)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from decod_rs.bench.detection_bias import band_labels, format_section, view_bias
from decod_rs.bench.matrix import (
    MAX_FULL_RING_M,
    OVERLONG,
    QUICK,
    SLIP,
    SYMMETRIC,
    UNEVEN,
    _cached_sweep,
    evaluate_targets,
    format_markdown,
    format_row,
    full_cells,
    full_ring_distance_m,
    joint_coverage,
    loop_summary,
    main,
    profile_odometry,
    registry_chainage_errors,
    ring_distance_for,
    sees_walls,
    tier_cells,
    zero_loop_reason,
)
from decod_rs.sim import scene_params
from decod_rs.sim.sensors import sensor_spec


@pytest.fixture(scope="module")
def cells():
    return full_cells()


def test_full_tier_spans_the_matrix(cells) -> None:
    names = [c.name for c in cells]
    assert len(names) == len(set(names))
    combos = {(c.scene, c.sensor) for c in cells if not c.variant}
    assert combos == {
        ("hume", "avia"),
        ("hume", "spin16"),
        ("pe", "avia"),
        ("pe", "spin16"),
        ("shield", "spin64"),
        ("shield", "avia"),
        ("horseshoe", "avia"),
        ("horseshoe", "spin16"),
        ("horseshoe", "spin64"),
    }
    for scene, sensor in combos:
        base = [c for c in cells if (c.scene, c.sensor) == (scene, sensor) and not c.variant]
        assert {(c.return_mode, c.seed) for c in base} == {
            (m, s) for m in ("reverse", "turn") for s in (0, 1)
        }
    assert all(set(c.profiles) == {SYMMETRIC, UNEVEN} for c in cells)
    assert all(25.0 <= c.length_m <= 40.0 for c in cells)
    # Every cell's sensor sees the whole ring within 12 m; the shield with 16 beams does not.
    assert all(ring_distance_for(c.scene, c.sensor, c.scene_overrides) <= 12.0 for c in cells)
    assert ring_distance_for("shield", "spin16") > MAX_FULL_RING_M


def test_variants_span_the_ranges_and_some_are_held_out(cells) -> None:
    diam = [2 * scene_params(c.scene, c.scene_overrides)["radius_m"] for c in cells]
    pipes = [d for d, c in zip(diam, cells, strict=True) if c.scene in ("hume", "pe")]
    tunnels = [d for d, c in zip(diam, cells, strict=True) if c.scene not in ("hume", "pe")]
    assert min(pipes) == pytest.approx(0.3) and max(pipes) == pytest.approx(1.2)
    assert min(tunnels) == pytest.approx(3.0) and max(tunnels) == pytest.approx(10.0)
    key = {"hume": "segment_length_m", "pe": "segment_length_m"}
    spacing = [
        scene_params(c.scene, c.scene_overrides)[key[c.scene]] for c in cells if c.scene in key
    ]
    assert min(spacing) == 1.0 and max(spacing) == 6.0
    speeds = [c.speed_mps for c in cells if c.speed_mps is not None]
    assert min(speeds) == 0.2 and max(speeds) == 2.0
    held = {c.name for c in cells if c.held_out}
    assert held == {
        "hume-avia-reverse-s0-d1.0",
        "pe-avia-reverse-s0-j3",
        "shield-avia-turn-s0-w9",
        "horseshoe-spin16-turn-s0-v2.0",
    }
    assert [c.name for c in cells if c.identical_joints] == ["hume-avia-reverse-s0-aliased"]


def test_quick_tier_and_filter() -> None:
    quick = tier_cells("quick")
    assert [c.name for c in quick] == list(QUICK)
    assert {c.scene for c in quick} == {"hume", "pe", "shield", "horseshoe"}
    assert any(UNEVEN in c.profiles for c in quick) and any(c.held_out for c in quick)
    assert any(c.identical_joints for c in quick)
    assert [c.name for c in tier_cells("full", "w9")] == ["shield-avia-turn-s0-w9"]
    with pytest.raises(ValueError, match="tier"):
        tier_cells("huge")


def test_the_fresh_tier_is_held_out_and_outside_the_full_tier() -> None:
    fresh = tier_cells("fresh")
    full = tier_cells("full")
    assert len(fresh) == 20 and all(c.held_out for c in fresh)
    assert not {c.name for c in fresh} & {c.name for c in full}
    # Each cell a size, spacing, speed, sensor mount, stops, water, return speed, lane or
    # back-up its scene does not have in the full tier (every full-tier sensor is level,
    # every full-tier run drives straight through at one speed, every full-tier pipe is dry).
    assert all(
        c.mount_deg == (0.0, 0.0)
        and not c.stops
        and c.return_speed_mps is None
        and c.return_lateral_m == 0.0
        and not c.backups
        for c in full
    )
    full_keys = {
        (c.scene, key, value) for c in full for key, value in c.scene_overrides.items()
    } | {(c.scene, "speed", c.speed_mps) for c in full}
    for c in fresh:
        assert sees_walls(c.scene, c.sensor, c.scene_overrides), c.name
        keys = {(c.scene, key, value) for key, value in c.scene_overrides.items()}
        keys |= {(c.scene, "speed", c.speed_mps)} if c.speed_mps is not None else set()
        keys |= {(c.scene, "mount", c.mount_deg)} if c.mount_deg != (0.0, 0.0) else set()
        keys |= {(c.scene, "stops", c.stops)} if c.stops else set()
        back = c.return_speed_mps
        keys |= {(c.scene, "return speed", back)} if back is not None else set()
        side = c.return_lateral_m
        keys |= {(c.scene, "return lateral", side)} if side else set()
        keys |= {(c.scene, "backups", c.backups)} if c.backups else set()
        assert keys and not keys & full_keys, c.name
    assert [c.name for c in tier_cells("fresh", "d0.8")] == ["pe-spin16-reverse-s7-d0.8"]
    assert len(tier_cells("fresh", "water")) == 4
    faster = [c.return_speed_mps for c in tier_cells("fresh", "back") if not c.backups]
    assert sorted(x or 0.0 for x in faster) == [0.9, 1.5]
    assert [len(c.backups) for c in tier_cells("fresh", "backup")] == [2, 1]
    assert {c.return_lateral_m for c in tier_cells("fresh", "lane")} == {1.5, 1.2}
    assert all(c.profiles == (SYMMETRIC, UNEVEN, OVERLONG) for c in fresh)


def _ground_truth_only(tmp_path: Path, length_m: float) -> tuple[Any, Any, int, Path]:
    """A cell's ``sim`` directory with only what odometry profiles are made from (``gt.tum``,
    ``joints.json``), for an out-and-back of ``length_m`` at 1 m/s: the trajectory, its
    stamps, the last outbound scan and the directory."""
    from decod_rs.sim.trajectory import Trajectory, TrajectorySpec
    from decod_rs.tum import write_tum

    spec = TrajectorySpec(x_start_m=0.5, length_m=length_m, speed_mps=1.0, return_mode="reverse")
    traj = Trajectory(spec, np.random.default_rng(0))
    stamps = np.arange(0.0, traj.duration_s, 0.1)
    split = int(np.argmax(traj.travelled(stamps) >= traj.travelled(traj.t_far_arrive)))
    sim = tmp_path / "sim"
    sim.mkdir()
    write_tum(sim / "gt.tum", stamps, traj.poses(stamps))
    meta = {"trajectory": spec.as_dict(), "time_split": {"outbound_scans": [0, split]}}
    (sim / "joints.json").write_text(json.dumps(meta), encoding="utf-8")
    return traj, stamps, split, sim


@pytest.mark.parametrize(("profile", "scales"), [(UNEVEN, (0.95, 0.85)), (OVERLONG, (1.05, 1.15))])
def test_leg_profiles_scale_each_leg_of_the_odometry(tmp_path, profile, scales) -> None:
    """``uneven`` and ``overlong`` odometry, made from a cell's ground truth: each leg's
    travel is the true one times the profile's scale (the axial random walk of the drift
    model, 1 cm/sqrt(m), is far inside 1 %)."""
    from decod_rs.tum import read_tum

    traj, stamps, split, sim = _ground_truth_only(tmp_path, 20.0)
    cell = tier_cells("fresh")[0]

    _, odom = read_tum(profile_odometry(cell, sim, profile, tmp_path / "odom.tum"))

    x = odom[:, 0, 3]
    out, back = x[split] - x[0], x[split] - x[-1]
    true_out = traj.axial(stamps[split]) - traj.axial(stamps[0])
    true_back = traj.axial(stamps[split]) - traj.axial(stamps[-1])
    assert out / true_out == pytest.approx(scales[0], abs=0.01)
    assert back / true_back == pytest.approx(scales[1], abs=0.01)


def test_slip_profile_and_the_profiles_option(tmp_path, capsys) -> None:
    """``--profiles slip`` runs the slip profile in every cell (``--list`` shows it); the
    slip odometry of a cell's ground truth reads between 85 % and 99 % of each 2 m stretch;
    an unknown profile is refused before anything runs."""
    from decod_rs.tum import read_tum

    assert (
        main(["--out", str(tmp_path / "m"), "--tier", "quick", "--profiles", SLIP, "--list"]) == 0
    )
    listed = capsys.readouterr().out.strip().splitlines()
    assert listed and all(": slip " in line for line in listed)
    assert main(["--out", str(tmp_path / "m"), "--profiles", "slip,sideways"]) == 2
    assert "sideways" in capsys.readouterr().err and not (tmp_path / "m").exists()

    traj, stamps, _, sim = _ground_truth_only(tmp_path, 30.0)
    _, odom = read_tum(profile_odometry(tier_cells("full")[0], sim, SLIP, tmp_path / "o.tum"))
    true_x, x = traj.axial(stamps), odom[:, 0, 3]
    d = traj.travelled(stamps)
    for lo in np.arange(2.0, d[-1] - 4.0, 2.0):
        k = np.flatnonzero((d >= lo) & (d < lo + 2.0))
        step_true, step = true_x[k[-1]] - true_x[k[0]], x[k[-1]] - x[k[0]]
        if abs(step_true) > 1.5:  # a stretch of steady driving (not the turnaround)
            # 1 cm/sqrt(m) of axial walk: 0.03 of slack
            assert 0.85 - 0.03 < step / step_true < 0.99 + 0.03


def test_sweep_option_and_a_cached_log_taken_the_same_way(tmp_path, capsys) -> None:
    """``--sweep`` simulates every cell swept (``--list`` says so); a cached log counts only
    if it was simulated the same way (a log from before the simulator's sweep was not swept),
    so a swept matrix never runs on a log taken from one pose per scan."""
    assert main(["--out", str(tmp_path / "m"), "--tier", "quick", "--sweep", "--list"]) == 0
    listed = capsys.readouterr().out.strip().splitlines()
    assert listed and all("[swept]" in line for line in listed)
    assert main(["--out", str(tmp_path / "m"), "--tier", "quick", "--list"]) == 0
    assert "[swept]" not in capsys.readouterr().out

    joints = tmp_path / "joints.json"
    assert _cached_sweep(joints) is None  # nothing cached
    for text, swept in (('{"sweep": true}', True), ('{"sweep": false}', False), ("{}", False)):
        joints.write_text(text)
        assert _cached_sweep(joints) is swept
    joints.write_text("{not json")
    assert _cached_sweep(joints) is None  # a damaged cache is simulated again


def test_full_ring_distance_follows_the_field_of_view() -> None:
    spin16 = sensor_spec("spin16")
    # On the axis of a round pipe: the crown enters the +-15 deg fan at r / tan(15 deg).
    d = full_ring_distance_m(spin16, 1.0, 0.0)
    assert d == pytest.approx(1.0 / math.tan(math.radians(15.0)), abs=0.05)
    # A sensor lower in the section needs more distance; a floor hides nothing above it.
    assert full_ring_distance_m(spin16, 1.0, -0.5) > d
    assert full_ring_distance_m(spin16, 1.0, 0.0, floor_z_m=-0.6) == pytest.approx(d, abs=0.05)
    assert full_ring_distance_m(spin16, 100.0, 0.0) == math.inf


def test_joint_coverage_counts_joints_seen_twice() -> None:
    joints = np.array([1.0, 3.0, 5.0, 7.0])
    out_x = np.array([1.1, 3.05, 5.2, 9.0])
    ret_x = np.array([0.95, 3.2, 7.0])  # joint 5 only outbound, 7 only on the return
    closed = np.array([3.1, 7.0])  # a loop at 7 does not count: 7 was not seen twice
    assert joint_coverage(joints, out_x, ret_x, closed) == (2, 1, 0.5)
    assert joint_coverage(joints, out_x, np.zeros(0), closed) == (0, 0, None)


def test_registry_error_is_each_joints_nearest_row(tmp_path) -> None:
    # Ground truth: the body moves along +x from x = 0; landmarks sit at the origin of the body
    # frame of their stamp, so a landmark's true position is its stamp (1 m/s).
    poses = np.stack([np.eye(4), np.eye(4)])
    poses[1, 0, 3] = 100.0
    gt = (np.array([0.0, 100.0]), poses)
    meta = {
        "joints_x_m": [2.5, 10.0, 20.0],
        "trajectory": {"x_start_m": 0.5},
        "axis": {"origin_m": [0.0, 0.0, 0.0], "direction": [1.0, 0.0, 0.0]},
    }

    class Landmarks:
        # joint 0: the 2.5 m joint (chainage 2.0 true, 2.03 in the file: 1.5 %); joint 1: a
        # chip 0.25 m from the 10 m joint; joint 2: that joint (0.1 %); joint 3: a row at
        # 15 m, no joint near; joint 4: the 20 m joint but not loop-confirmed.
        joint_id = np.array([0, 0, 1, 2, 2, 3, 4])
        stamp = np.array([2.5, 2.5, 10.25, 10.0, 10.0, 15.0, 20.0])
        origin = np.zeros((7, 3))

    (tmp_path / "joints.csv").write_text(
        "joint_id,chainage_m,loop_confirmed\n0,2.03,1\n1,9.75,1\n2,9.5095,1\n3,14.5,1\n4,30.0,0\n",
        encoding="utf-8",
    )
    errors, elsewhere = registry_chainage_errors(tmp_path, meta, gt, Landmarks())
    assert errors == pytest.approx([1.5, 0.1])
    assert elsewhere == 2  # the chip beside the 10 m joint and the row at 15 m
    # Without the joint's own row, the chip is that joint's row, and its error counts.
    (tmp_path / "joints.csv").write_text(
        "joint_id,chainage_m,loop_confirmed\n1,9.75,1\n", encoding="utf-8"
    )
    errors, elsewhere = registry_chainage_errors(tmp_path, meta, gt, Landmarks())
    assert errors == pytest.approx([100 * 0.25 / 9.5]) and elsewhere == 0


def test_zero_loop_reason_names_the_first_missing_piece() -> None:
    report = {
        "counts": {"landmarks": 0, "queries": 0},
        "extraction_rejections": {"few_points": 5, "no_axis": 2},
    }
    assert zero_loop_reason(report, 0, 0) == "no landmark extracted (few_points 5, no_axis 2)"
    report["counts"] = {"landmarks": 10, "queries": 0}
    assert zero_loop_reason(report, 10, 0) == "no landmark on the return pass"
    report["counts"] = {"landmarks": 20, "queries": 9}
    report["query_rejections"] = {"not_unique": 6, "too_few_inliers": 3}
    assert zero_loop_reason(report, 10, 10) == (
        "all 9 queries rejected: not_unique 6, too_few_inliers 3"
    )


def _fake_result() -> dict:
    loops = {
        "fine": {
            "tolerance_m": 0.3,
            "common_queries": 4,
            "accepted": 2,
            "true_positives": 2,
            "false_positives": 0,
            "recall_at_1": 0.5,
            "precision_at_1": 1.0,
        },
        "coarse": {
            "tolerance_m": 1.2,
            "common_queries": 5,
            "accepted": 2,
            "true_positives": 2,
            "false_positives": 0,
            "recall_at_1": 0.4,
            "precision_at_1": 1.0,
        },
    }
    rows = [
        {"accepted": True, "axial_error_m": 0.01, "lateral_offset_m": 0.01},
        {"accepted": True, "axial_error_m": 0.2, "lateral_offset_m": 0.01},
        {"accepted": False, "axial_error_m": 0.9, "lateral_offset_m": 0.01},
        {"accepted": False, "axial_error_m": 5.0, "lateral_offset_m": 0.01},
        {"accepted": False, "axial_error_m": None, "lateral_offset_m": None},
    ]
    return {"queries": 5, "accepted": 2, "lateral_gate_m": 2.4, "loops": loops, "loop_rows": rows}


def _row(**kw) -> dict:
    row = {
        "cell": "hume-avia-reverse-s0",
        "profile": SYMMETRIC,
        "variant": "",
        "held_out": False,
        "aliased": False,
        "status": "ok",
        "preset": "pipe",
        **loop_summary(_fake_result()),
        "landmarks_per_submap": 1.5,
        "joints_seen_both": 4,
        "joints_closed": 3,
        "coverage": 0.75,
        "odom_endpoint_m": 3.0,
        "corr_endpoint_m": 0.1,
        "odom_rmse_m": 1.5,
        "corr_rmse_m": 0.5,
        "endpoint_reduction_percent": 96.7,
        "turnaround_odom_percent": -5.0,
        "turnaround_corr_percent": -4.9,
        "realtime_factor": 80.0,
        "reason": "",
    }
    row.update(kw)
    return row


def test_loop_summary_reads_evaluate_run() -> None:
    s = loop_summary(_fake_result())
    assert (s["top1_correct_fine"], s["top1_correct_coarse"]) == (2, 3)
    assert (s["precision_fine"], s["recall_coarse"], s["false_positives_coarse"]) == (1.0, 0.4, 0)


def test_table_rows_and_sections() -> None:
    line = format_row(_row())
    assert line.startswith("| hume-avia-reverse-s0 |  | symmetric | pipe | 1.50 | 5 | 2 / 3 | 2 |")
    assert "| 100 % | 50 % | 100 % | 40 % | 75 % (3/4) | 3.00 → 0.10 | 1.50 → 0.50 |" in line
    assert "| -5.0 → -4.9 | - | 80 |" in line
    err = format_row({"cell": "x", "profile": UNEVEN, "status": "error", "error": "E: a|b"})
    assert err.endswith("| ERROR: E: a/b |") and err.count("|") == line.count("|")
    rows = [_row(), _row(cell="pe-avia-reverse-s0-j3", held_out=True, variant="joint spacing 3 m")]
    md = format_markdown(rows, {"tier": "quick", "elapsed_s": 60.0})
    tuned, held = md.split("## Held-out cells")
    assert "hume-avia-reverse-s0 |" in tuned and "pe-avia-reverse-s0-j3" not in tuned
    assert "pe-avia-reverse-s0-j3 | joint spacing 3 m" in held.split("## Targets")[0]
    assert "- **every cell ran**: PASS" in md


def test_targets_name_the_failing_cells() -> None:
    rows = [
        _row(),
        _row(cell="a", precision_fine=0.9, false_positives_coarse=1),
        _row(cell="b", coverage=None, corr_rmse_m=2.0, endpoint_reduction_percent=50.0),
        _row(cell="c", odom_endpoint_m=0.5, endpoint_reduction_percent=10.0),
        _row(cell="alias", aliased=True, accepted=1, coverage=None),
        _row(cell="h", held_out=True, coverage=0.2),
        {"cell": "boom", "profile": SYMMETRIC, "status": "error", "error": "x"},
    ]
    t = {e["target"]: e for e in evaluate_targets(rows)}
    prec = t["precision@1 >= 98 % at 0.3 m"]
    assert prec["tuned"]["status"] == "FAIL" and prec["tuned"]["failing"] == ["a/symmetric"]
    assert prec["held_out"]["status"] == "PASS"
    assert t["no accepted loop beyond the coarse tolerance"]["tuned"]["failing"] == ["a/symmetric"]
    cov = t["joint coverage >= 50 %"]
    assert cov["tuned"]["failing"] == ["b/symmetric"]  # aliased cell not counted
    assert cov["held_out"]["failing"] == ["h/symmetric"]
    endpoint = t["endpoint reduced >= 80 % where odometry drifted >= 1 m"]["tuned"]
    assert endpoint["failing"] == ["b/symmetric"] and endpoint["cells"] == 4  # c drifted < 1 m
    assert t["RMSE never above odometry"]["tuned"]["failing"] == ["b/symmetric"]
    assert t["aliased cell has no accepted loop"]["tuned"]["failing"] == ["alias/symmetric"]
    assert t["aliased cell has no accepted loop"]["held_out"]["status"] == "n/a"
    md = format_markdown(rows, {})
    assert "- **every cell ran**: FAIL: boom/symmetric" in md


def test_view_bias_measures_a_range_proportional_detection_error() -> None:
    # Joints every 1.5 m; anchors every 0.25 m; each anchor sees the joints within 8 m, placed
    # 0.4 % of the range farther from it than they are, plus 5 mm of noise, and one wall
    # feature 0.5 m from a joint (beyond the tolerance: not a view of a joint).
    rng = np.random.default_rng(3)
    joints = np.arange(0.0, 40.0, 1.5)
    anchors = np.arange(0.0, 40.0, 0.25)
    view_x, anchor_x = [], []
    for a in anchors:
        for j in joints[np.abs(joints - a) <= 8.0]:
            view_x.append(j + 0.004 * (j - a) + rng.normal(0.0, 0.005))
            anchor_x.append(a)
    # Other features within the tolerance, all 0.2 m ahead of a joint seen 1.2-2.4 m ahead (a
    # wall feature, a twin band): a plain least-squares fit would give 0.50 %.
    for j in joints[1:]:
        for back in (1.2, 1.6, 2.0, 2.4):
            view_x.append(j + 0.2)
            anchor_x.append(j - back)
    view_x.append(joints[3] + 0.5)
    anchor_x.append(anchors[0])
    got = view_bias(np.array(view_x), np.array(anchor_x), joints, 0.3)
    assert got["view_bias_views"] == len(view_x) - 1
    # Thousands of views: the slope within 0.05 points of the 0.4 % put in.
    assert got["view_bias_slope_percent"] == pytest.approx(0.4, abs=0.05)
    bands = got["view_bias_cm_by_range"]
    assert len(bands) == len(band_labels()) == 7
    # Behind the anchor (-8..-6 m) about -2.8 cm, ahead (6..8 m) about +2.8 cm, +-1 m about 0.
    assert bands[0] == pytest.approx(-2.8, abs=0.3)
    assert bands[-1] == pytest.approx(2.8, abs=0.3)
    assert bands[3] == pytest.approx(0.0, abs=0.2)
    # An unbiased detection has no slope; no view, no figure.
    flat = view_bias(np.array(anchor_x[:-1]) * 0 + joints[0], np.array(anchor_x[:-1]), joints, 0.3)
    assert flat["view_bias_slope_percent"] == pytest.approx(0.0, abs=1e-9)
    assert view_bias(np.zeros(0), np.zeros(0), joints, 0.3)["view_bias_slope_percent"] is None
    # Joints seen only from 0-1.5 m ahead (a forward sensor in a pipe): no slope; the bands stay.
    ahead = np.array(view_x) - np.array(anchor_x)
    near = (ahead >= 0.0) & (ahead <= 1.5)
    short = view_bias(np.array(view_x)[near], np.array(anchor_x)[near], joints, 0.3)
    assert short["view_bias_slope_percent"] is None
    assert short["view_bias_cm_by_range"][3] == pytest.approx(0.2, abs=0.15)  # 0.4 % of 0-1 m
    with pytest.raises(ValueError, match="differ in shape"):
        view_bias(np.zeros(3), np.zeros(2), joints, 0.3)
    section = format_section(
        [
            {
                "scene": "horseshoe",
                "sensor": "spin64",
                "variant": "",
                "turnaround_corr_percent": 0.3,
                **got,
            },
            {
                "scene": "hume",
                "sensor": "avia",
                "variant": "",
                **view_bias(np.zeros(0), np.zeros(0), joints, 0.3),
            },
        ]
    )
    assert section[0] == "## Detection error against range"
    assert any(line.startswith("| horseshoe, spin64 | 1 |") and "+0.30" in line for line in section)
    assert not any("hume" in line for line in section)
