"""Evaluation metrics on a hand-built run directory with known true/false positives, and
the `decod evaluate` command."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from decod_rs.cli import main
from decod_rs.evaluate import evaluate_run, loop_metrics, tolerances_for
from decod_rs.plots import DescriptorPair, plot_descriptor_pair, plot_descriptor_pairs
from decod_rs.run_files import (
    LandmarkTable,
    LoopTable,
    read_landmarks_csv,
    read_loops_csv,
    write_landmarks_csv,
    write_loops_csv,
)
from decod_rs.tum import so3_exp, write_tum

# Ground truth: 1 m/s out along +x for 50 s, then back (heading reversed) for 50 s.
STAMPS = np.arange(0.0, 100.5, 0.5)


def gt_poses() -> np.ndarray:
    poses = np.stack([np.eye(4)] * STAMPS.size)
    back = STAMPS > 50.0
    poses[:, 0, 3] = np.where(back, 100.0 - STAMPS, STAMPS)
    poses[back, :3, :3] = so3_exp(np.array([0.0, 0.0, np.pi]))
    return poses


def loop_row(q_stamp, db_stamp, db_offset_x=0.0, inliers=20, accepted=True):
    """A query boundary at the sensor (origin 0) on the return; the database boundary at the
    sensor of the outbound pose at db_stamp, shifted db_offset_x along the body x axis."""
    return (
        q_stamp,
        db_stamp,
        [0.0, 0, 0],
        [1.0, 0, 0],
        [db_offset_x, 0, 0],
        [1.0, 0, 0],
        inliers,
        accepted,
    )


ROWS = [
    loop_row(95.0, 5.0),  # x = 5 vs 5: exact -> TP at both tolerances
    loop_row(90.0, 10.0, db_offset_x=0.5, inliers=15),  # 0.5 m off: FP at 0.3, TP at 2.4
    loop_row(85.0, 25.0, inliers=12),  # x = 15 vs 25: FP at both
    loop_row(80.0, 20.0, inliers=5, accepted=False),  # right but rejected
    loop_row(75.0, np.nan, inliers=0, accepted=False),  # no candidate; landmark x=25 exists
    loop_row(60.0, 30.0, inliers=7, accepted=False),  # x = 40: no database landmark near
    loop_row(120.0, 5.0, inliers=30, accepted=True),  # after the ground truth: dropped
]


def write_run(run, corrected_offset_y=0.1, drift_per_s=0.02):
    run.mkdir(parents=True, exist_ok=True)
    gt = gt_poses()
    write_tum(run.parent / "gt.tum", STAMPS, gt)
    odom = gt.copy()
    odom[:, 0, 3] += drift_per_s * STAMPS
    corrected = gt.copy()
    corrected[:, 1, 3] += corrected_offset_y
    write_tum(run / "odometry.tum", STAMPS, odom)
    write_tum(run / "corrected.tum", STAMPS, corrected)
    n = len(ROWS)
    table = LoopTable(
        query_stamp=np.array([r[0] for r in ROWS]),
        db_stamp=np.array([r[1] for r in ROWS]),
        query_origin=np.array([r[2] for r in ROWS]),
        query_axis=np.array([r[3] for r in ROWS]),
        db_origin=np.array([r[4] for r in ROWS]),
        db_axis=np.array([r[5] for r in ROWS]),
        inliers=np.array([r[6] for r in ROWS]),
        score=np.full(n, 0.5),
        accepted=np.array([r[7] for r in ROWS]),
        extra={"reason": ["", "", "", "inliers", "no candidate", "inliers", ""]},
    )
    write_loops_csv(run / "loops.csv", table)
    # Outbound boundaries every 5 m (x = 5..30) plus the return queries' own boundaries.
    lm_st = np.array([5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 60.0, 75.0, 80.0, 85.0, 90.0, 95.0])
    m = lm_st.size
    write_landmarks_csv(
        run / "landmarks.csv",
        LandmarkTable(
            stamp=lm_st,
            origin=np.zeros((m, 3)),
            axis=np.tile([1.0, 0, 0], (m, 1)),
            radius_m=np.full(m, 3.0),
            chainage_m=np.full(m, np.nan),
        ),
    )
    (run / "report.json").write_text(json.dumps({"config": {"preset": "tunnel"}}))
    return gt


def test_run_files_round_trip(tmp_path):
    write_run(tmp_path / "run")
    loops = read_loops_csv(tmp_path / "run" / "loops.csv")
    assert len(loops) == len(ROWS)
    assert loops.accepted.tolist() == [r[7] for r in ROWS]
    assert np.isnan(loops.db_stamp[4]) and loops.extra["reason"][4] == "no candidate"
    lm = read_landmarks_csv(tmp_path / "run" / "landmarks.csv")
    assert len(lm) == 12 and np.all(np.isnan(lm.chainage_m)) and np.all(lm.radius_m == 3.0)
    text = (tmp_path / "run" / "loops.csv").read_text().splitlines()
    text[2] = text[2].replace("0.500000000", "zero", 1)
    (tmp_path / "run" / "loops.csv").write_text("\n".join(text))
    with pytest.raises(ValueError, match=r"loops\.csv:3: column db_origin_x"):
        read_loops_csv(tmp_path / "run" / "loops.csv")


def test_batch_mode_database_is_the_outbound_pass():
    # Near the turnaround the two passes see a boundary seconds apart. In batch mode the
    # return pass queries the whole outbound pass (report.json eligibility
    # "across_passes"), so the outbound boundary 4 s older is in the query's database;
    # under the time separation (online mode) it is not, and nor is the query's own.
    loops = LoopTable(
        query_stamp=np.array([52.0]),  # on the return at x = 48
        db_stamp=np.array([np.nan]),
        query_origin=np.zeros((1, 3)),
        query_axis=np.array([[1.0, 0, 0]]),
        db_origin=np.zeros((1, 3)),
        db_axis=np.array([[1.0, 0, 0]]),
        inliers=np.array([0]),
        score=np.zeros(1),
        accepted=np.array([False]),
    )
    landmarks = LandmarkTable(
        stamp=np.array([48.0, 52.0]),  # x = 48 on the way out, and the query's own
        origin=np.zeros((2, 3)),
        axis=np.tile([1.0, 0, 0], (2, 1)),
        radius_m=np.full(2, 3.0),
        chainage_m=np.full(2, np.nan),
    )
    gt = gt_poses()
    within = loop_metrics(loops, landmarks, STAMPS, gt, 0.3, 4.8, 30.0)
    across = loop_metrics(loops, landmarks, STAMPS, gt, 0.3, 4.8, 30.0, split_stamp=50.0)
    assert within["common_queries"] == 0
    assert across["common_queries"] == 1


def test_metrics_on_known_run(tmp_path):
    write_run(tmp_path / "run")
    result, errors = evaluate_run(tmp_path / "run", tmp_path / "gt.tum")
    assert result["queries"] == 6 and result["queries_without_gt"] == 1
    assert result["accepted"] == 3
    fine, coarse = result["loops"]["fine"], result["loops"]["coarse"]
    assert (fine["tolerance_m"], coarse["tolerance_m"]) == (0.3, 2.4)
    # Common: x = 5, 10, 15, 20, 25 have an outbound landmark within 0.3 m; x = 40 not.
    assert fine["common_queries"] == 5 and coarse["common_queries"] == 5
    assert (fine["true_positives"], fine["false_positives"]) == (1, 2)
    assert (coarse["true_positives"], coarse["false_positives"]) == (2, 1)
    assert fine["precision_at_1"] == pytest.approx(1 / 3)
    assert fine["recall_at_1"] == pytest.approx(1 / 5)
    assert coarse["precision_at_1"] == pytest.approx(2 / 3)
    assert coarse["recall_at_1"] == pytest.approx(2 / 5)
    curve = {p["min_inliers"]: p for p in result["pr_curve"]["coarse"]}
    # K = 5 admits the rejected but correct row 4 and row 6 (x = 40 vs 30: 10 m off).
    assert (curve[5]["accepted"], curve[5]["true_positives"]) == (5, 3)
    assert (curve[15]["accepted"], curve[15]["true_positives"]) == (2, 2)
    assert [row["axial_error_m"] for row in result["loop_rows"][:3]] == pytest.approx(
        [0.0, 0.5, 10.0]
    )
    traj = result["trajectory"]
    assert traj["corrected"]["rmse_m"] == pytest.approx(0.1, abs=1e-6)
    assert traj["odometry"]["endpoint_error_m"] == pytest.approx(2.0, abs=1e-6)
    expected_rmse = 0.02 * np.sqrt(np.mean(STAMPS**2))
    assert traj["odometry"]["rmse_m"] == pytest.approx(expected_rmse, rel=1e-6)
    assert traj["endpoint_reduction_percent"] == pytest.approx(95.0, abs=1e-4)
    assert errors["odometry"].errors_m.shape == STAMPS.shape
    # Alignment removes the constant offset of the corrected trajectory.
    aligned, _ = evaluate_run(tmp_path / "run", tmp_path / "gt.tum", align=True)
    assert aligned["trajectory"]["corrected"]["rmse_m"] == pytest.approx(0.0, abs=1e-6)


def test_pipe_tolerance_is_half_the_joint_spacing(tmp_path):
    assert tolerances_for("pipe", np.array([0.0, 2.4, 4.8, 7.2])) == (0.3, 1.2)
    with pytest.raises(ValueError, match="joints"):
        tolerances_for("pipe")
    write_run(tmp_path / "run")
    joints = tmp_path / "joints.json"
    joints.write_text(json.dumps({"joints_x_m": [0.0, 0.8, 1.6, 2.4]}))
    result, _ = evaluate_run(tmp_path / "run", tmp_path / "gt.tum", joints, preset="pipe")
    assert result["loops"]["coarse"]["tolerance_m"] == pytest.approx(0.4)
    assert result["loops"]["coarse"]["true_positives"] == 1  # the 0.5 m row is now false


def test_evaluate_cli_writes_evaluation_json(tmp_path, capsys):
    write_run(tmp_path / "run")
    out = tmp_path / "eval"
    code = main(
        ["evaluate", str(tmp_path / "run"), "--gt", str(tmp_path / "gt.tum"), "--out", str(out)]
    )
    assert code == 0
    doc = json.loads((out / "evaluation.json").read_text())
    assert doc["loops"]["coarse"]["true_positives"] == 2
    assert (out / "error_over_time.png").stat().st_size > 1000
    assert (out / "pr_curve.png").stat().st_size > 1000
    printed = capsys.readouterr().out
    assert "precision@1" in printed and "66.7 %" in printed
    assert main(["evaluate", str(tmp_path / "nope"), "--gt", str(tmp_path / "gt.tum")]) == 2


def test_descriptor_pair_plot(tmp_path):
    rng = np.random.default_rng(0)
    d = rng.normal(size=(16, 256)) * 0.01
    mask = rng.random((16, 256)) > 0.3
    out = plot_descriptor_pair(tmp_path / "pair.png", d, mask, -d, mask, "pair")
    assert out.stat().st_size > 1000
    with pytest.raises(ValueError, match=r"database: expected .* same shape"):
        plot_descriptor_pair(tmp_path / "bad.png", d, mask, d, mask[:, :10])


def test_descriptor_pairs_on_one_figure_are_the_figures_one_by_one(tmp_path):
    # A run draws its four strongest pairs on one figure (faster): the same PNGs, byte for
    # byte, as one figure each, including an unobserved pair and another grid size; a bad
    # pair is refused before anything is drawn.
    rng = np.random.default_rng(3)
    pairs = []
    for k, shape in enumerate([(16, 256), (16, 256), (16, 256), (8, 128)]):
        d, m = rng.normal(size=shape) * 0.01 * (k + 1), rng.random(shape) > 0.4
        if k == 2:
            m[:] = False
        pairs.append(DescriptorPair(tmp_path / f"b{k}.png", d, m, -d, ~m, f"pair {k}"))
    batch = plot_descriptor_pairs(pairs)
    for k, p in enumerate(pairs):
        one = plot_descriptor_pair(
            tmp_path / f"o{k}.png", p.query, p.query_mask, p.database, p.database_mask, p.title
        )
        assert one.read_bytes() == batch[k].read_bytes()
    bad = DescriptorPair(tmp_path / "bad.png", pairs[0].query, pairs[0].query_mask[:, :3], 0, 0)
    with pytest.raises(ValueError, match=r"query: expected .* same shape"):
        plot_descriptor_pairs([replace(pairs[1], path=tmp_path / "x.png"), bad])
    assert not (tmp_path / "x.png").exists()
