"""When decod builds the submaps again on the corrected trajectory (:mod:`decod_rs.refinement`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from decod_rs.config import load_config
from decod_rs.refinement import rebuild_decision, rebuild_threshold_m, travel_disagreement_m


def _straight(stamps: np.ndarray, speed: float) -> np.ndarray:
    poses = np.repeat(np.eye(4)[None], stamps.size, axis=0)
    poses[:, 0, 3] = speed * stamps
    return poses


STAMPS = np.arange(0.0, 60.0, 0.1)  # 10 Hz scans


def test_a_short_odometry_disagrees_by_its_scale_error_over_one_submap() -> None:
    truth = _straight(STAMPS, 1.3)
    short = _straight(STAMPS, 1.3 * 0.85)  # the return pass of the uneven profile
    # 20 scans = 2 s = 2.6 m of travel, of which the odometry misses 15 %.
    assert travel_disagreement_m(short, truth, 20) == pytest.approx(0.15 * 2.6, rel=1e-9)
    assert travel_disagreement_m(truth, truth, 20) == 0.0


def test_the_threshold_is_half_a_descriptor_row() -> None:
    cfg = load_config(None, "tunnel")
    rows, half = cfg.descriptor.rows, cfg.descriptor.half_length_m
    assert rebuild_threshold_m(cfg) == pytest.approx(0.5 * (2.0 * half / rows))


def test_only_a_scale_error_that_smears_a_boundary_beyond_half_a_row_rebuilds() -> None:
    cfg = load_config(None, "tunnel")
    n = cfg.submap.scans_per_submap
    travel = 1.3 * n * 0.1
    threshold = rebuild_threshold_m(cfg)
    truth = _straight(STAMPS, 1.3)
    for error, expected in ((0.5 * threshold / travel, False), (2.0 * threshold / travel, True)):
        decision = rebuild_decision(_straight(STAMPS, 1.3 * (1 - error)), truth, cfg)
        assert decision.needed is expected, (error, decision)
        assert decision.report()["rebuilt"] is expected


def test_a_few_windows_at_a_turn_do_not_decide_alone() -> None:
    truth = _straight(STAMPS, 1.0)
    bent = truth.copy()
    bent[300:310, 1, 3] = 0.5  # a 1 s excursion: 20 of ~580 windows disagree
    assert travel_disagreement_m(truth, bent, 20) == 0.0


def test_mismatched_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="differ in shape"):
        travel_disagreement_m(_straight(STAMPS, 1.0), _straight(STAMPS[:-1], 1.0), 20)
    with pytest.raises(ValueError, match="scans_per_submap"):
        travel_disagreement_m(_straight(STAMPS, 1.0), _straight(STAMPS, 1.0), 0)


def test_the_rebuilt_submaps_stand_if_they_measure_more_passes_or_close_more_loops() -> None:
    from dataclasses import replace

    from decod_rs.refinement import keep_rebuilt

    assert keep_rebuilt(4, 47) and keep_rebuilt(38, 38) and not keep_rebuilt(40, 37)
    decision = rebuild_decision(_straight(STAMPS, 1.0), _straight(STAMPS, 1.2), load_config())
    assert decision.needed and not decision.kept  # not rebuilt yet
    assert replace(decision, loops=(4, 47)).report()["kept"] is True
    assert replace(decision, loops=(38, 37)).report()["kept"] is False
    # A round that measured both passes' scales beats one that left a pass at the odometry's
    # drift, whatever the loops (pe, 16 beams, uneven: 4 loops with the return unmeasured
    # against 2 with it measured); with as many passes measured, the loops decide.
    assert keep_rebuilt(4, 2, 1, 2) and not keep_rebuilt(2, 4, 2, 1)
    assert keep_rebuilt(4, 4, 2, 2) and not keep_rebuilt(4, 3, 2, 2)
    measured = replace(decision, loops=(4, 2), rescaled=(1, 2)).report()
    assert measured["kept"] is True and measured["rescaled_passes_first_and_rebuilt"] == [1, 2]


def test_a_rebuilt_round_tracks_boundaries_in_the_corrected_frame(tmp_path: Path) -> None:
    # The return pass's odometry is 15 % short: consecutive anchors 2.4 m apart disagree by
    # 0.36 m about a boundary's position, beyond the track radius, so in the odometry frame
    # the return pass has almost no track and its scale is not measured (5 pairs, matrix
    # horseshoe-avia-turn-s0: endpoint 4.34 -> 1.75 m). Linked in the first round's corrected
    # trajectory, its tracks measure the scale, and the last metres (no loop: the sensor looks
    # out of the portal) get it too. Seed 22 is new to this rule.
    import json

    from decod_rs.evaluate import evaluate_run
    from decod_rs.pipeline import run_log
    from decod_rs.sim import simulate

    sim = tmp_path / "sim"
    simulate(
        "horseshoe",
        sim,
        seed=22,
        sensor="avia",
        speed_mps=1.0,
        length_m=30.0,
        drift="legs:-0.05,-0.15",
        progress=False,
    )
    out = tmp_path / "run"
    run_log(sim / "log", out, imu_topic="/imu", progress=False, plots=False)
    report = json.loads((out / "report.json").read_text())
    assert report["rebuild"]["kept"], report["rebuild"]
    passes = report["sequential"]["odometry_scale"]
    assert [p["rescaled"] for p in passes] == [True, True], passes
    # The odometry reports 85 % of the return: its scale is 1 / 0.85 = 1.18.
    assert passes[1]["measured_scale"] == pytest.approx(1 / 0.85, abs=0.03), passes
    result, _ = evaluate_run(out, sim / "gt.tum", sim / "joints.json")
    traj = result["trajectory"]
    assert traj["corrected"]["endpoint_error_m"] < 0.2 * traj["odometry"]["endpoint_error_m"]
    assert result["loops"]["coarse"]["false_positives"] == 0
