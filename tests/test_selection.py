"""Loop selection, boundary tracks, sequential noise and the auto configuration, on inputs
whose right answer is known by construction."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest

from decod_rs.aliasing import (
    ALIASED_MIN_QUERIES,
    ALIASED_NEAR_TIE_SHARE,
    aliasing,
)
from decod_rs.autoscale import CorridorProbe, derive
from decod_rs.matching import synthetic_landmark
from decod_rs.selection import (
    LoopEvidence,
    drop_if_aliased,
    drop_if_untracked,
    select_consistent,
)
from decod_rs.sequential import detection_noise_m
from decod_rs.tracks import group_views, tracked_loops, views_per_landmark

SPACING_M = 2.4
DRIFT = 0.05  # the return pass drifts 5 % per metre more than the outbound one


def _loops(wrong: dict[int, float]) -> list[LoopEvidence]:
    """A loop at every joint of a 30 m out-and-back; loop k's correction is the smooth drift
    plus ``wrong[k]`` metres (a wrong joint)."""
    out = []
    for k in range(12):
        x = 1.0 + k * SPACING_M
        db_path, q_path = x, 2 * 30.0 - x
        c = DRIFT * (q_path - db_path) + wrong.get(k, 0.0)
        out.append(
            LoopEvidence(
                correction=np.array([c, 0.0, 0.0]),
                query_path_m=q_path,
                db_path_m=db_path,
                query_stamp=float(k),
                inliers=20,
                chance=1e-12,
            )
        )
    return out


def _select(loops: list[LoopEvidence], drift: float = 0.15):
    return select_consistent(
        loops, tolerance_m=0.3, drift_fraction=drift, window_m=20.0, min_corroborating=1
    )


def test_a_loop_to_the_neighbouring_joint_is_inconsistent() -> None:
    chosen = _select(_loops({5: SPACING_M}))
    assert chosen.reasons[5] == "inconsistent"
    assert all(chosen.kept[k] for k in range(12) if k != 5)


def test_smooth_drift_keeps_every_true_loop() -> None:
    chosen = _select(_loops({}))
    assert all(chosen.kept), chosen.reasons


def test_a_return_read_15_percent_short_keeps_every_right_loop_under_auto() -> None:
    # A turn run, 40 m out: the outbound odometry reads 5 % short, the return 15 % short
    # (the matrix's uneven drift). One outbound view (a boundary 28 m in, seen from its
    # anchor 28 m along the odometry's path) matched by return views every 3 m of the
    # return's odometry, each with 3 cm of noise; the implied correction changes by the
    # return's drift, 0.15 / 0.85 of each odometry metre. Under auto's allowance all stay;
    # under 0.15 per odometry metre, views 18 m apart conflicted.
    from decod_rs.autoscale import CONSISTENCY_DRIFT_FRACTION, DRIFT_FRACTION

    rng = np.random.default_rng(3)
    db_path = 0.95 * 28.0
    loops = []
    for k, q_path in enumerate(0.95 * 40.0 + np.arange(2.0, 26.0, 3.0)):
        true_back = (q_path - 0.95 * 40.0) / 0.85  # metres driven back
        drift = 0.05 * 28.0 - 0.05 * 40.0 - 0.15 * true_back  # world error, db minus query
        loops.append(
            LoopEvidence(
                correction=np.array([drift + rng.normal(0.0, 0.03), 0.0, 0.0]),
                query_path_m=float(q_path),
                db_path_m=db_path,
                query_stamp=float(k),
                inliers=20,
                chance=1e-12,
            )
        )
    assert CONSISTENCY_DRIFT_FRACTION == pytest.approx(DRIFT_FRACTION / (1.0 - DRIFT_FRACTION))
    assert all(_select(loops, CONSISTENCY_DRIFT_FRACTION).kept)
    assert not all(_select(loops, DRIFT_FRACTION).kept)
    # A wrong one among them, one arch (1.2 m) off, is still dropped.
    wrong = list(loops)
    wrong[4] = replace(loops[4], correction=loops[4].correction + np.array([1.2, 0.0, 0.0]))
    chosen = _select(wrong, CONSISTENCY_DRIFT_FRACTION)
    assert chosen.reasons[4] == "inconsistent"
    assert sum(chosen.kept) == len(loops) - 1


def test_loops_that_agree_with_each_other_but_not_the_odometry_are_dropped() -> None:
    # Two wrong loops, both one 12 m jump off (an aliased pipe), alone: they corroborate each
    # other but imply far more drift than the odometry can have over their path.
    loops = [
        LoopEvidence(np.array([12.0, 0, 0]), 50.0 + d, 10.0 - d, float(d), 14, 1e-15)
        for d in (0.0, 1.0)
    ]
    chosen = _select(loops)
    assert chosen.reasons == ["inconsistent", "inconsistent"]
    # The same corrections after 200 m of path are plausible drift (6 %).
    far = [
        LoopEvidence(np.array([12.0, 0, 0]), 210.0 + d, 10.0 - d, float(d), 14, 1e-15)
        for d in (0.0, 1.0)
    ]
    assert all(_select(far).kept)


def test_an_isolated_loop_is_uncorroborated() -> None:
    loops = _loops({})[:1]
    assert _select(loops).reasons == ["uncorroborated"]


def test_a_loop_set_of_single_detections_alone_is_dropped() -> None:
    keep, reasons = [True, True, False], ["", "", "not_unique"]
    # No kept loop joins a tracked boundary: all go, named; the matcher's reasons stay.
    assert drop_if_untracked(keep, reasons, [False, False, True]) == (
        [False, False, False],
        ["untracked", "untracked", "not_unique"],
    )
    # One kept loop with a tracked side keeps the whole (consistent) set.
    assert drop_if_untracked(keep, reasons, [False, True, False]) == (keep, reasons)
    assert drop_if_untracked(keep, reasons, None) == (keep, reasons)
    assert drop_if_untracked([], [], []) == ([], [])


def test_a_loop_is_tracked_when_either_boundary_has_several_views() -> None:
    views = views_per_landmark(np.array([0, 0, 1, 2, 2, 2, -1], dtype=np.int64))
    np.testing.assert_array_equal(views, [2, 2, 1, 3, 3, 3, 1])
    landmarks = [synthetic_landmark(1, k, stamp=float(k)) for k in range(3)]
    db_views = np.array([1, 4])

    def result(query: int, candidate: int | None) -> Any:
        lm = landmarks[query]
        return SimpleNamespace(
            query_stamp=lm.submap_stamp, query_origin=lm.origin, candidate_index=candidate
        )

    query_views = np.array([1, 2, 1])
    found = tracked_loops(
        [result(0, 0), result(1, 0), result(2, 1), result(2, None)],
        landmarks,
        query_views,
        db_views,
    )
    assert found == [False, True, True, False]


def _ambiguous(ratios: list[float], other: int = 0) -> list[Any]:
    """Stand-ins for query results: ``not_unique`` ones with runner-up / best inlier ratios
    ``ratios`` (best 20 inliers), and ``other`` accepted ones."""
    return [
        SimpleNamespace(rejection="not_unique", inliers=20, runner_up_inliers=round(20 * r))
        for r in ratios
    ] + [SimpleNamespace(rejection=None, inliers=30, runner_up_inliers=3)] * other


def test_a_corridor_whose_runner_ups_tie_with_the_best_is_aliased() -> None:
    n = ALIASED_MIN_QUERIES
    ties = math.ceil(ALIASED_NEAR_TIE_SHARE * n)
    # Identical joints: near ties (>= 90 % of the best's inliers) are common.
    found = aliasing(_ambiguous([0.95] * ties + [0.6] * (n - ties), other=5))
    assert (found.ambiguous, found.near_ties) == (n, ties) and found.aliased
    # One near tie fewer: not aliased; too few ambiguous queries: not aliased either.
    assert not aliasing(_ambiguous([0.95] * (ties - 1) + [0.6] * (n - ties + 1))).aliased
    assert not aliasing(_ambiguous([1.0] * (n - 1))).aliased
    # Rings that share structure but differ (the shield): ambiguous, rarely tied.
    assert not aliasing(_ambiguous([0.7] * 100 + [0.9] * 20)).aliased
    keep, reasons = [True, False], ["", "not_unique"]
    aliased = _ambiguous([1.0] * n)
    assert drop_if_aliased(aliased, keep, reasons) == ([False, False], ["aliased", "not_unique"])
    assert drop_if_aliased(_ambiguous([0.5] * n), keep, reasons) == (keep, reasons)


def test_detection_noise_is_measured_without_the_drift() -> None:
    rng = np.random.default_rng(3)
    stamps, axial, tracks = [], [], []
    for t in range(40):
        times = t * 10.0 + np.arange(5) * 1.5
        # 10 % drift of a 0.4 m/s crawler within the track, 1 cm detection noise.
        axial.extend(t * 2.4 + 0.04 * (times - times[0]) + rng.normal(0, 0.01, 5))
        stamps.extend(times)
        tracks.extend([t] * 5)
    sigma = detection_noise_m(np.array(stamps), np.array(axial), np.array(tracks), 0.001)
    assert sigma == pytest.approx(0.01, rel=0.25)
    single = detection_noise_m(np.array([0.0]), np.array([1.0]), np.array([0]), 0.002)
    assert single == 0.002


def test_views_close_in_time_and_space_form_one_track() -> None:
    views = [
        synthetic_landmark(1, 1, stamp=0.0),
        synthetic_landmark(1, 1, stamp=1.0),
        synthetic_landmark(1, 2, stamp=2.0),
        synthetic_landmark(1, 1, stamp=100.0),  # the same place on the way back
    ]
    identity = np.eye(4)
    moved = np.eye(4)
    moved[0, 3] = 2.0  # the third view's anchor is 2 m further: another boundary
    anchors = {0.0: identity, 1.0: identity, 2.0: moved, 100.0: identity}
    ids = group_views(views, anchors, radius_m=0.4, window_s=30.0)
    assert ids[0] == ids[1]
    assert len({ids[0], ids[2], ids[3]}) == 3


def test_no_track_crosses_the_turnaround() -> None:
    # Near the turnaround both passes see a boundary seconds apart and, the drift between
    # them being small, at one place: without the split they form one track; with it, each
    # pass keeps its own (what ties the passes is a loop, not a track).
    views = [synthetic_landmark(1, 1, stamp=t) for t in (0.0, 1.0, 3.0, 4.0)]
    anchors = {t: np.eye(4) for t in (0.0, 1.0, 3.0, 4.0)}
    joined = group_views(views, anchors, radius_m=0.4, window_s=30.0)
    assert len(set(joined.tolist())) == 1
    split = group_views(views, anchors, radius_m=0.4, window_s=30.0, split_stamp=2.0)
    assert split[0] == split[1] and split[2] == split[3] and split[0] != split[2]


def _probe(radius: float, z_near: float, speed: float) -> CorridorProbe:
    return CorridorProbe(
        radius_m=radius, z_near_m=z_near, speed_mps=speed, scan_rate_hz=10.0, probes=4
    )


def test_auto_parameters_scale_with_the_section() -> None:
    pipe, tunnel = derive(_probe(0.3, 0.2, 0.4)), derive(_probe(3.0, 2.0, 0.4))
    for section, key in [
        ("submap", "voxel_m"),
        ("contour", "inlier_distance_m"),
        ("boundary", "dog_sigma_small_m"),
        ("boundary", "dog_sigma_large_m"),
        ("descriptor", "half_length_m"),
    ]:
        assert tunnel[section][key] == pytest.approx(10 * pipe[section][key]), key
    # The tunnel preset's measured values are the reference at r = 3 m.
    assert tunnel["submap"]["voxel_m"] == pytest.approx(0.055)
    assert tunnel["descriptor"]["half_length_m"] == pytest.approx(2.4)


def test_auto_range_follows_where_the_sensor_sees_the_whole_ring() -> None:
    near, late = derive(_probe(3.0, 2.0, 1.3)), derive(_probe(3.0, 7.0, 1.3))
    assert late["submap"]["max_range_m"] > near["submap"]["max_range_m"]
    assert late["submap"]["max_range_m"] >= 7.0 + 2 * 2.4
    grazing = 3.0 / math.tan(math.radians(12.0))
    assert near["submap"]["max_range_m"] == pytest.approx(grazing, rel=1e-3)


def test_auto_schedule_follows_the_speed() -> None:
    slow, fast = derive(_probe(0.3, 0.2, 0.2)), derive(_probe(0.3, 0.2, 0.5))
    assert slow["submap"]["interval_s"] == pytest.approx(
        2.5 * fast["submap"]["interval_s"], rel=0.01
    )
    assert slow["matching"]["min_time_separation_s"] > fast["matching"]["min_time_separation_s"]


def test_auto_schedule_fills_the_descriptor_of_a_sparse_sensor() -> None:
    from decod_rs.autoscale import DESCRIPTOR_CELLS, DESCRIPTOR_FILL

    # A sensor that puts few points into a descriptor-long stretch of wall per scan gets
    # windows long enough that the points of a submap fill DESCRIPTOR_FILL of the cells
    # (Poisson: n = -ln(1 - f) cells); a dense one keeps the visible-window schedule.
    dense = derive(replace(_probe(0.2, 0.55, 0.4), descriptor_points=5000.0))
    sparse = derive(replace(_probe(0.2, 0.55, 0.4), descriptor_points=350.0))
    assert dense["submap"] == derive(_probe(0.2, 0.55, 0.4))["submap"]
    needed = -math.log(1.0 - DESCRIPTOR_FILL) * DESCRIPTOR_CELLS / 350.0
    assert sparse["submap"]["scans_per_submap"] == round(needed)
    assert sparse["submap"]["interval_s"] == pytest.approx(needed / 10.0, rel=1e-3)
    assert sparse["submap"]["interval_s"] > dense["submap"]["interval_s"]
    # Two views then share about half of their cells: twice the matcher's overlap floor.
    assert DESCRIPTOR_FILL**2 == pytest.approx(2 * 0.25)


def test_auto_schedule_fills_only_the_part_of_the_section_the_sensor_sees() -> None:
    from types import SimpleNamespace

    from decod_rs.autoscale import DESCRIPTOR_CELLS, DESCRIPTOR_FILL, _descriptor_points

    # Water fills the bottom of a 0.4 m pipe to 30 % of its diameter and mirrors the beam
    # away: the sensor sees the wall above it, 73 % of the section outside the bottom mask
    # (+-66 deg of 180 about the bottom are under water; the mask is +-30 deg). Scans of the
    # wall as sparse as a 16-beam sensor's there, a ring of points every 5 cm along the range
    # window, each point 3 deg apart round the section, and under the water one ray in 33
    # returns from its surface.
    rng = np.random.default_rng(0)
    radius, level = 0.2, -0.2 + 0.12

    def scan(water: bool) -> SimpleNamespace:
        x = np.repeat(np.arange(0.4, 1.3, 0.05), 120)
        ang = np.tile(np.radians(np.arange(0.0, 360.0, 3.0)), x.size // 120)
        y, z = radius * np.sin(ang), -radius * np.cos(ang)
        hidden = water & (z < level)
        kept = ~hidden | (rng.random(x.size) < 0.03)
        z = np.where(hidden, level, z)
        return SimpleNamespace(points=np.stack([x, y, z], axis=1)[kept])

    submap = SimpleNamespace(forward=np.array([1.0, 0.0, 0.0]), gravity=np.array([0, 0, -1.0]))
    probed = [(submap, np.array([1.0, 0.0, 0.0]))]
    probe = _probe(radius, 0.55, 0.4)
    dry_points, dry_share = _descriptor_points([[scan(False)] * 3], probed, probe)
    wet_points, wet_share = _descriptor_points([[scan(True)] * 3], probed, probe)
    assert dry_share == 1.0
    seen = (180.0 - np.degrees(np.arccos(0.08 / radius))) / 150.0  # 0.73: crown side of the line
    assert wet_share == pytest.approx(seen, abs=2.0 / 30)  # 10 deg sectors, one each side
    assert wet_points == pytest.approx(dry_points * seen, rel=0.05)
    # The points fall on the cells of the wall the sensor sees: the fill rule asks for as
    # many scans as fill DESCRIPTOR_FILL of those, not of the whole section (a longer window
    # only smears the boundaries under drift).
    wet = derive(replace(probe, descriptor_points=wet_points, wall_share=wet_share))
    needed = -math.log(1.0 - DESCRIPTOR_FILL) * DESCRIPTOR_CELLS * wet_share / wet_points
    assert wet["submap"]["scans_per_submap"] == round(needed)
    unseen = derive(replace(probe, descriptor_points=wet_points))  # as if the water were wall
    ratio = unseen["submap"]["interval_s"] / wet["submap"]["interval_s"]
    assert ratio == pytest.approx(1.0 / wet_share, rel=0.1)


def test_auto_schedule_keeps_a_window_shorter_than_the_drift_smears() -> None:
    from decod_rs.autoscale import DRIFT_FRACTION, auto_config

    # The fresh tier's hume pipe with 16 beams rolled 30 deg and pitched 10 deg: one probe of
    # four saw the whole ring from 2.7 m, and a scan put 35 points into a descriptor-long
    # stretch there, so filling a descriptor asked for 12 s windows (4.7 m of travel). Odometry
    # drifting by DRIFT_FRACTION smears a boundary over such a window by 0.7 m, three times the
    # descriptor's half length: no loop under either drift. The window stays short enough
    # that the smear is at most half of the half length.
    probe = replace(_probe(0.3, 2.67, 0.39), descriptor_points=35.0)
    derived = derive(probe)
    half = derived["descriptor"]["half_length_m"]
    window = derived["submap"]["scans_per_submap"] / probe.scan_rate_hz
    assert DRIFT_FRACTION * probe.speed_mps * window <= 0.5 * half * 1.05
    assert derived["submap"]["interval_s"] == pytest.approx(window, rel=0.05)
    # Where the descriptor fills within that time, the fill rule alone sets the window.
    level = replace(_probe(0.3, 0.9, 0.39), descriptor_points=430.0)
    assert DRIFT_FRACTION * 0.39 * derive(level)["submap"]["interval_s"] < 0.5 * half
    # report.json says which rule set the interval.
    assert auto_config(probe, None)[1]["schedule"]["rule"] == "drift_cap"
    assert auto_config(level, None)[1]["schedule"]["rule"] == "descriptor_fill"
    fast = replace(_probe(0.2, 0.55, 2.0), descriptor_points=5000.0)  # 0.1 s would do
    assert auto_config(fast, None)[1]["schedule"]["rule"] == "minimum"
    assert derive(fast)["submap"]["interval_s"] == 0.5


def test_auto_report_is_strict_json_when_a_distance_was_never_sampled() -> None:
    from decod_rs.autoscale import auto_config

    # A sensor that never saw the whole ring ahead: z_near is infinite and taken at the
    # grazing limit (range: a descriptor length and a radius beyond it), and report.json
    # says null rather than the non-JSON `Infinity`.
    cfg, report = auto_config(_probe(0.3, math.inf, 0.4), None)
    assert report["measured"]["z_near_m"] is None
    assert report["measured"]["radius_m"] == pytest.approx(0.3)
    json.dumps(report, allow_nan=False)
    grazing = 0.3 / math.tan(math.radians(12.0))
    assert cfg.submap.max_range_m == pytest.approx(grazing + 2 * 0.24 + 0.3, rel=1e-3)


def _out_and_back_tracks() -> tuple[Any, Any, Any, Any, Any, list[Any]]:
    """A 20 m out-and-back at 0.5 m/s whose odometry reports 90 % of the outbound distance
    and 80 % on the way back; boundaries every 2.5 m are seen from the two anchors before
    them: stamps, true and odometry poses, anchor stamps and odometry, sequential pairs."""
    from decod_rs.graph import LoopConstraint

    t = np.arange(0.0, 80.0, 0.1)
    x = np.where(t <= 40.0, 0.5 * t, 40.0 - 0.5 * t)
    scale = np.where(t <= 40.0, 0.9, 0.8)
    odo_x = np.concatenate([[0.0], np.cumsum(np.diff(x) * scale[1:])])

    def poses(xs: np.ndarray) -> np.ndarray:
        p = np.tile(np.eye(4), (xs.size, 1, 1))
        p[:, 0, 3] = xs
        return p

    anchors = t[::10]  # one every second
    a_odom = poses(np.interp(anchors, t, odo_x))
    a_true = np.interp(anchors, t, x)
    seq = []
    for k in range(anchors.size - 1):
        if anchors[k] in (40.0,):
            continue
        joint = a_true[k] + (1.2 if anchors[k] < 40.0 else -1.2)  # ahead of the motion
        seq.append(
            LoopConstraint(
                query_index=k + 1,
                db_index=k,
                query_origin=np.array([joint - a_true[k + 1], 0.0, 0.0]),
                query_axis=np.array([1.0, 0.0, 0.0]),
                db_origin=np.array([joint - a_true[k], 0.0, 0.0]),
                db_axis=np.array([1.0, 0.0, 0.0]),
                kind="sequential",
                sigma_m=0.01,
            )
        )
    return t, poses(x), poses(odo_x), anchors, a_odom, seq


def test_tracked_boundaries_recover_each_pass_scale() -> None:
    from decod_rs.odometry_scale import rescale_odometry

    t, truth, odom, anchors, a_odom, seq = _out_and_back_tracks()
    x = truth[:, 0, 3]
    fixed, est = rescale_odometry(t, odom, anchors, a_odom, seq, 0.01, 40.0)
    # One pair measures the outbound scale to sqrt(2) 1 cm / 0.45 m = 3 %: with a loop tying
    # the return to it, the outbound is rescaled, the return (unmeasured) is not.
    one, est_one = rescale_odometry(t, odom, anchors, a_odom, seq[:1], 0.01, 40.0)
    assert [p["rescaled"] for p in est_one.passes] == [True, False]
    assert est_one.passes[0]["measured_scale"] == pytest.approx(1 / 0.9, rel=1e-6)
    # The prior s = 1 is sigma 1 on the pass, not on each interval: it does not pull the one
    # measured window's 3 % scale towards 1 (it did by 0.4 % here, 1.3 % on a pe return).
    assert est_one.passes[0]["mean_scale"] == pytest.approx(1 / 0.9, rel=0.002)
    # (one window, no spread chosen: its scale holds for the whole pass to within 0.5 %)
    out = t <= 40.0
    assert np.abs(one[out, 0, 3] - x[out]).max() < 0.05 * np.abs(odom[out, 0, 3] - x[out]).max()
    # Without a loop, rescaling the outbound alone would move the unmeasured return, whose
    # own error (-20 %) had partly cancelled the outbound's: the odometry stands.
    same, untied = rescale_odometry(t, odom, anchors, a_odom, seq[:1], 0.01, 40.0, tied=False)
    np.testing.assert_allclose(same, odom)
    assert [p["rescaled"] for p in untied.passes] == [False, False]
    # The return measured alone, without a loop: the odometry stands. Rescaled (as it is with
    # a loop, which lets the graph place the far end), the return would start from the
    # outbound's -2 m at the far end and keep it all the way back (RMS 2 m), where the
    # odometry's errors go from -2 m to +2 m (RMS 1.15 m).
    back = [c for c in seq if anchors[c.db_index] > 40.0][:1]
    alone, est_back = rescale_odometry(t, odom, anchors, a_odom, back, 0.01, 40.0, tied=False)
    np.testing.assert_allclose(alone, odom)
    assert [p["rescaled"] for p in est_back.passes] == [False, False]
    moved, est_back = rescale_odometry(t, odom, anchors, a_odom, back, 0.01, 40.0)
    assert [p["rescaled"] for p in est_back.passes] == [False, True]
    ret = t > 40.0

    def rms(p: np.ndarray) -> float:
        return float(np.sqrt(np.mean((p[ret, 0, 3] - x[ret]) ** 2)))

    assert rms(odom) == pytest.approx(1.15, abs=0.05)
    assert rms(moved) == pytest.approx(2.0, abs=0.1)
    # A pair whose baseline measures less than 5 % is not used.
    wide = rescale_odometry(t, odom, anchors, a_odom, seq[:1], 0.03, 40.0)[1]
    assert [p["rescaled"] for p in wide.passes] == [False, False]
    before = np.abs(odom[:, 0, 3] - truth[:, 0, 3]).max()
    after = np.abs(fixed[:, 0, 3] - truth[:, 0, 3]).max()
    assert before > 1.9  # -2 m at the far end, +2 m at the end
    assert after < 0.05 * before, (after, est.passes)
    assert [p["mean_scale"] for p in est.passes] == pytest.approx([1 / 0.9, 1 / 0.8], rel=0.01)


def test_a_pass_measured_alone_is_stitched_on_but_not_output() -> None:
    """No loop, only the return's scale measured: the output is the odometry (rescaling the
    return alone would keep the outbound's far-end error all the way back), but rebuilt
    submaps are stitched on the return rescaled, where only its own geometry counts (a 10 m
    shield with the forward sensor then closes its loops in the rebuilt round)."""
    from decod_rs.config import load_config
    from decod_rs.sequential import SequentialFactors
    from decod_rs.stages.solve import optimise

    t, truth, odom, anchors, _, seq = _out_and_back_tracks()
    back = [c for c in seq if anchors[c.db_index] > 40.0][:3]
    factors = SequentialFactors(back, 0.01, len(back), {})
    ex = SimpleNamespace(anchor_stamps=list(anchors))
    cfg = load_config(preset="pipe")
    correction, scale, _, stitch = optimise((t, odom), ex, 40.0, list(back), factors, cfg)  # type: ignore[arg-type]
    assert scale is not None and [p["rescaled"] for p in scale.passes] == [False, False]
    np.testing.assert_allclose(correction.poses[:, :3, 3], odom[:, :3, 3], atol=1e-6)
    assert stitch is not None
    ret = t > 40.0
    # The return as stitched: its true 20 m to within 2 % (the odometry's reads 16 m).
    travel = float(np.abs(np.diff(stitch[ret, 0, 3])).sum())
    assert travel == pytest.approx(float(np.abs(np.diff(truth[ret, 0, 3])).sum()), rel=0.02)
    assert float(np.abs(np.diff(odom[ret, 0, 3])).sum()) < 0.85 * travel
    # With a loop the passes are tied: no separate stitching.
    loop = replace(back[0], kind="loop")
    *_, tied_stitch = optimise((t, odom), ex, 40.0, [*back, loop], factors, cfg)  # type: ignore[arg-type]
    assert tied_stitch is None


def test_the_less_well_measured_pass_gets_the_larger_odometry_sigmas() -> None:
    from decod_rs.odometry_scale import (
        UNMEASURED_SIGMA_FACTOR,
        odometry_sigma_factors,
        rescale_odometry,
    )

    t, _, odom, anchors, a_odom, seq = _out_and_back_tracks()
    outbound = [c for c in seq if anchors[c.db_index] < 40.0]
    back = [c for c in seq if anchors[c.db_index] > 40.0]
    out = t <= 40.0

    def factors(pairs: list[Any]) -> tuple[np.ndarray, list[float]]:
        est = rescale_odometry(t, odom, anchors, a_odom, pairs, 0.01, 40.0)[1]
        sigmas = [float(p["measured_scale_sigma"]) for p in est.passes]
        return odometry_sigma_factors(t, est, 40.0), sigmas

    # Both passes measured, the return by fewer pairs: its sigmas grow by the ratio of the
    # scale errors, the outbound's stay.
    f, sig = factors(outbound + back[:6])
    assert 1.0 < sig[1] / sig[0] < UNMEASURED_SIGMA_FACTOR
    np.testing.assert_allclose(f[out], 1.0)
    np.testing.assert_allclose(f[~out], sig[1] / sig[0])
    # The other way round, the outbound is the less well known.
    f, sig = factors(outbound[:6] + back)
    np.testing.assert_allclose(f[~out], 1.0)
    np.testing.assert_allclose(f[out], sig[0] / sig[1])
    # One pair against the outbound's forty: capped (the ratio is 7.1).
    f, sig = factors(outbound + back[:1])
    assert sig[1] / sig[0] > UNMEASURED_SIGMA_FACTOR
    np.testing.assert_allclose(f[~out], UNMEASURED_SIGMA_FACTOR)
    # A pass left at the odometry's scale counts as unmeasured; neither measured: all 1.
    np.testing.assert_allclose(factors(outbound)[0][~out], UNMEASURED_SIGMA_FACTOR)
    np.testing.assert_allclose(factors([])[0], 1.0)
    # Without a split there is one pass and nothing to weigh.
    est = rescale_odometry(t, odom, anchors, a_odom, seq, 0.01, None)[1]
    np.testing.assert_allclose(odometry_sigma_factors(t, est, None), 1.0)


def _one_pass_pairs(scale_of_x: Any, sigma: float, seed: int) -> tuple[Any, list[Any]]:
    """A 60 m pass, anchors every 1 m of true travel, each boundary (every 1.5 m) seen from the
    two anchors before it with ``sigma`` of detection noise; the odometry reads each metre
    ``scale_of_x(x)`` long. Odometry anchor positions and the (a, b, D_ab) pairs."""
    rng = np.random.default_rng(seed)
    x = np.arange(0.0, 60.0 + 1e-9, 1.0)
    u = np.concatenate([[0.0], np.cumsum(np.diff(x) * scale_of_x(x[:-1] + 0.5))])
    pairs = []
    for joint in np.arange(1.25, 59.0, 1.5):
        k = int(np.searchsorted(x, joint)) - 1  # the anchor at or before it
        if k < 1:
            continue
        seen = [(a, joint - x[a] + rng.normal(0.0, sigma)) for a in (k - 1, k)]
        (a, da), (b, db) = seen
        pairs.append((a, b, da - db))
    return u, pairs


def test_the_scale_follows_sections_only_where_the_pairs_say_it_changes() -> None:
    from decod_rs.odometry_scale import _pass_scales

    # Constant scale: one scale for the pass (no spread chosen), within 0.5 %.
    u, pairs = _one_pass_pairs(lambda x: np.full_like(x, 0.9), 0.01, 0)
    scales, share, (tau, _) = _pass_scales(u, pairs, 0.01)
    assert tau == 0.0 and share > 0.6
    assert np.allclose(scales, 1 / 0.9, rtol=0.005)
    # Odometry that reads 95 % of the first 30 m and 85 % of the rest (sections, as wheels
    # slip more on one stretch): a spread is chosen, and the scales follow each section
    # to within 1.5 % away from the change (one scale for the pass is 5 % off on each).
    u, pairs = _one_pass_pairs(lambda x: np.where(x < 30.0, 0.95, 0.85), 0.01, 1)
    scales, _, (tau, length) = _pass_scales(u, pairs, 0.01)
    assert tau > 0.0 and length > 0.0
    assert np.allclose(scales[:25], 1 / 0.95, rtol=0.015), scales[:25]
    assert np.allclose(scales[35:], 1 / 0.85, rtol=0.015), scales[35:]


def test_a_run_that_does_not_come_back_says_when_its_odometry_wanders() -> None:
    from decod_rs.selection import why_no_loop

    t = np.linspace(0.0, 160.0, 1601)
    one_way = np.stack([0.4 * t, np.zeros_like(t), np.zeros_like(t)], axis=1)
    # Like KISS-ICP in the 0.3 m pipe (12.9 m of path within 3.2 m of its start): back and
    # forth within 3.6 m of the start.
    wander = np.stack([1.8 - 1.8 * np.cos(2 * np.pi * t / 80.0), 0 * t, 0 * t], axis=1)
    args = ((3, 0), 3, {}, {}, None)
    plain = why_no_loop(*args)
    assert plain.startswith("no return pass found")
    assert why_no_loop(*args, one_way) == plain
    hint = why_no_loop(*args, wander)
    assert hint.startswith(plain) and "14.4 m stays within 3.6 m of its start" in hint


def test_a_stretch_with_its_own_scale_does_not_measure_the_pass() -> None:
    """Pairs that all lie in one stretch measure that stretch; where the evidence chose a
    spread of scales, the pass's mean scale is known only to about that spread, and a pass
    known to worse than ``MAX_SCALE_SIGMA`` keeps its odometry (seed 251's pitched 16 beams
    in the horseshoe: a return within 0.2 % overall, measured on 5 m that read 8-11 % short,
    was stretched 8.7 % and ended 3.35 m from the start instead of 1.20 m: its pairs read
    1.14 and 1.06)."""
    from decod_rs.odometry_scale import (
        MAX_SCALE_SIGMA,
        _measured_scale,
        _pass_scale_sigma,
        _pass_scales,
    )

    rng = np.random.default_rng(3)
    true = np.full(13, 3.0)  # anchors 3 m apart
    reads = np.ones(13)
    reads[2], reads[3] = 1 / 1.14, 1 / 1.06  # the stretch the pairs see (as measured there)
    u = np.concatenate([[0.0], np.cumsum(true * reads)])
    sigma = 0.04
    pairs = [(2, 3, 3.0 + rng.normal(0.0, sigma)) for _ in range(4)]
    pairs += [(3, 4, 3.0 + rng.normal(0.0, sigma)) for _ in range(6)]
    _, _, slip = _pass_scales(u, pairs, sigma)
    ratio, error = _measured_scale(u, pairs, sigma)
    assert slip[0] > 0.0 and ratio > 1.07  # the stretch's own scale, not the pass's 1.0
    assert error < 0.01  # as a standard error the pairs look decisive...
    spread = _pass_scale_sigma(u, pairs, sigma, slip)
    assert spread > MAX_SCALE_SIGMA and spread > 0.5 * slip[0]  # ...the model says not
    # The same pairs spread along the pass (one scale, no spread chosen): the pass's sigma is
    # the standard error.
    even = np.concatenate([[0.0], np.cumsum(true * 0.95)])
    along = [(k, k + 1, 3.0 + rng.normal(0.0, sigma)) for k in range(13)]
    _, _, slip = _pass_scales(even, along, sigma)
    assert slip[0] == 0.0
    error = _measured_scale(even, along, sigma)[1]
    assert _pass_scale_sigma(even, along, sigma, slip) == pytest.approx(error, rel=1e-3)
    # A scale that changes along the pass, measured all along it (a spread chosen): every
    # stretch is measured, so the mean scale is known to about the standard error, not tau.
    varying = 0.9 + 0.08 * (np.arange(13) % 2)
    u = np.concatenate([[0.0], np.cumsum(true * varying)])
    along = [(k, k + 1, 3.0 + rng.normal(0.0, sigma)) for k in range(13) for _ in range(3)]
    _, _, slip = _pass_scales(u, along, sigma)
    assert slip[0] > 0.0
    assert _pass_scale_sigma(u, along, sigma, slip) < min(0.2 * slip[0], MAX_SCALE_SIGMA)


def test_the_slip_model_takes_pairs_of_the_same_anchors_together_exactly() -> None:
    """Pairs between the same two anchors enter the slip model as their mean (a sufficient
    statistic): the scales and the chosen spread are those of the pairs one by one (the
    model written out below, as it was before), with solves of the anchor pairs' size."""
    from decod_rs.odometry_scale import (
        SLIP_EVIDENCE_MARGIN,
        SLIP_LENGTHS_M,
        SLIP_SPREADS,
        _pass_scales,
    )

    def one_by_one(u: Any, pairs: Any, sigma: float) -> tuple[Any, tuple[float, float]]:
        du = np.diff(u)
        a_mat = np.zeros((len(pairs), du.size))
        for i, (a, b, _) in enumerate(pairs):
            a_mat[i, a:b] = du[a:b]
        residual = np.array([d for *_, d in pairs]) - a_mat.sum(axis=1)
        path = np.cumsum(np.abs(du)) - 0.5 * np.abs(du)
        gap = np.abs(path[:, None] - path[None, :])
        best: Any = None
        for tau in SLIP_SPREADS:
            for length in SLIP_LENGTHS_M if tau > 0 else SLIP_LENGTHS_M[:1]:
                prior = 1.0 + tau**2 * np.exp(-gap / length)
                c = a_mat @ prior @ a_mat.T + np.eye(len(pairs)) * 2.0 * sigma**2
                solved = np.linalg.solve(c, residual)
                evidence = -0.5 * (residual @ solved + np.linalg.slogdet(c)[1])
                evidence -= SLIP_EVIDENCE_MARGIN if tau > 0 else 0.0
                if best is None or evidence > best[0]:
                    scales = 1.0 + prior @ a_mat.T @ solved
                    best = (evidence, scales, (tau, length if tau else 0.0))
        return best[1], best[2]

    rng = np.random.default_rng(11)
    for trial in range(40):
        n = int(rng.integers(3, 25))
        u = np.concatenate([[0.0], np.cumsum(rng.uniform(1.0, 3.0, n))])
        local = 1.0 + (0.1 * rng.normal(size=n) if trial % 2 else np.zeros(n))
        pairs = []
        for _ in range(int(rng.integers(1, 50))):
            a = int(rng.integers(0, n))
            b = min(n, a + int(rng.integers(1, 3)))
            true = float(np.sum(np.diff(u)[a:b] * local[a:b]))
            pairs.append((a, b, true + rng.normal(0.0, 0.03)))
        scales, _, slip = _pass_scales(u, pairs, 0.03)
        expected, expected_slip = one_by_one(u, pairs, 0.03)
        assert slip == expected_slip, trial
        np.testing.assert_allclose(scales, np.clip(expected, 0.5, 2.0), atol=1e-9)
