"""Extraction on analytic scenes with known answers (issue 2): seeded, tolerances justified."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import decod_rs

import scenes_analytic as sa

GRAVITY = np.array([0.0, 0.0, -1.0])


def axis_error_deg(a, b):
    return float(np.degrees(np.arccos(min(1.0, abs(float(a @ b))))))


def oracle_descriptor(points, true_offset, lm):
    """Cell means of the TRUE offsets, binned in the landmark's own (z, p) chart with the
    paper's conventions (p from e1 towards e2 = axis x e1, circle: p = theta / 2 pi)."""
    rows, cols = lm.descriptor.shape
    rel = points - lm.origin
    z = rel @ lm.axis
    theta = np.arctan2(rel @ lm.e2, rel @ lm.e1) % (2 * np.pi)
    half = rows * lm.cell_z_m / 2
    keep = np.abs(z) < half
    r = np.minimum(((z[keep] + half) / lm.cell_z_m).astype(int), rows - 1)
    c = np.minimum((theta[keep] / (2 * np.pi) * cols).astype(int), cols - 1)
    total = np.zeros((rows, cols))
    count = np.zeros((rows, cols))
    np.add.at(total, (r, c), true_offset[keep])
    np.add.at(count, (r, c), 1)
    return np.divide(total, count, out=np.zeros_like(total), where=count > 0), count


@pytest.mark.parametrize(
    ("yaw", "pitch", "offset"),
    [(20.0, 10.0, (0.5, -0.3, 0.2)), (-35.0, -25.0, (-1.0, 0.4, -0.6))],
)
def test_tilted_offcentre_pipe(yaw, pitch, offset):
    rng = np.random.default_rng(7)
    scene = sa.pipe(rng, joints_x_m=(0.37,))
    rot = sa.rotation(np.radians(yaw), np.radians(pitch), np.radians(5.0))
    pts = sa.rigid(scene.points, rot, offset)
    result = decod_rs.extract_landmarks(pts, config="pipe", stamp=3.0)
    assert result.rejections == []
    assert len(result.landmarks) == 1
    lm = result.landmarks[0]
    assert lm.submap_stamp == 3.0
    # Axis within 0.5 deg (issue 2); oriented with forward = +x of the submap frame.
    assert axis_error_deg(lm.axis, rot[:, 0]) < 0.5
    assert lm.axis @ np.array([1.0, 0.0, 0.0]) > 0
    # Boundary within 1 cm of the groove along the axis (issue 2, pipe preset).
    local = rot.T @ (lm.origin - np.asarray(offset))
    assert abs(local[0] - 0.37) < 0.01
    assert np.hypot(local[1], local[2]) < 1e-3  # origin on the centre line
    assert lm.radius_m == pytest.approx(0.3, abs=2e-4)
    # e1 is gravity projected off the axis.
    g_perp = GRAVITY - (GRAVITY @ lm.axis) * lm.axis
    assert np.allclose(lm.e1, g_perp / np.linalg.norm(g_perp), atol=1e-9)
    # Descriptor against the oracle built from the true offsets: ~3 points per cell, cells
    # may differ only through the contour fit (< 0.05 mm here), so 0.05 mm median.
    expected, count = oracle_descriptor(pts, scene.true_offset_m, lm)
    both = lm.mask & (count > 0)
    assert both.sum() > 0.7 * lm.mask.size
    diff = np.abs(lm.descriptor - expected)[both]
    assert np.median(diff) < 5e-5
    # The two rows sharing the 12 mm groove (6 mm each in 30 mm cells) hold on average
    # 0.2 * depth; with ~3 points per cell the groove occupancy of a cell is binomial
    # (0.7 mm per cell, 0.035 mm over ~400 cells): tolerance 0.12 mm.
    groove = lm.descriptor[7:9][lm.mask[7:9]]
    assert groove.mean() == pytest.approx(0.2 * 0.003, abs=1.2e-4)
    assert np.abs(lm.descriptor[[0, 1, 14, 15]][lm.mask[[0, 1, 14, 15]]]).mean() < 3e-4
    # The bottom +-30 deg sector is masked.
    assert not lm.mask[:, 0].any() and not lm.mask[:, -1].any()
    assert lm.mask[:, lm.mask.shape[1] // 2].all()


def test_wide_groove_offsets_equal_its_depth_around_the_circumference():
    # A 60 mm groove holds at least one full 30 mm row whatever edge the boundary lands on;
    # there every cell is depth(theta) + noise (0.3 mm / sqrt(~4) per cell, 0.04 mm over a
    # block of 16 cells): tolerance 0.15 mm. Checks p = 0 at gravity and p running towards e2.
    rng = np.random.default_rng(8)
    scene = sa.pipe(rng, joints_x_m=(0.4,), groove_width_m=0.06)
    rot = sa.rotation(np.radians(15.0), np.radians(-8.0), np.radians(10.0))
    pts = sa.rigid(scene.points, rot, (0.3, 0.2, -0.1))
    # Box binning along z (the pipe preset's tent binning mixes each row with its
    # neighbours, so no 30 mm row would hold the groove depth alone).
    values = decod_rs.load_config(None, preset="pipe").to_dict()
    values["descriptor"]["axial_interpolation"] = False
    cfg = decod_rs.config.Config(values)
    lm = decod_rs.extract_landmarks(pts, config=cfg).landmarks[0]
    edge = (rot.T @ (lm.origin - np.array([0.3, 0.2, -0.1])))[0]
    assert min(abs(edge - 0.37), abs(edge - 0.43)) < 0.01  # a groove edge, within 1 cm
    # Rows entirely inside the groove, from the groove's z-range relative to the origin.
    sign = np.sign(lm.axis @ rot[:, 0])
    z_lo, z_hi = sorted([sign * (0.37 - edge), sign * (0.43 - edge)])
    lower = -0.24 + lm.cell_z_m * np.arange(16)
    inside = np.flatnonzero((lower >= z_lo) & (lower + lm.cell_z_m <= z_hi))
    assert len(inside) >= 1
    cols = lm.descriptor.shape[1]
    theta = 2 * np.pi * (np.arange(cols) + 0.5) / cols
    direction = np.outer(np.cos(theta), lm.e1) + np.outer(np.sin(theta), lm.e2)
    local_dir = direction @ rot  # column directions in the pipe's own frame
    want = sa.groove_depth(np.arctan2(local_dir[:, 1], -local_dir[:, 2]), 0.003)
    rows, mask = lm.descriptor[inside], lm.mask[inside]
    checked = 0
    for block in range(0, cols, 16):
        m = mask[:, block : block + 16]
        if m.sum() < 8:
            continue  # the masked bottom sector
        got = rows[:, block : block + 16][m].mean()
        expected = np.broadcast_to(want[block : block + 16], m.shape)[m].mean()
        assert got == pytest.approx(expected, abs=1.5e-4), block
        checked += 1
    assert checked >= 12


def test_horseshoe_flat_floor_contour_and_boundaries():
    rng = np.random.default_rng(3)
    scene = sa.horseshoe(rng)
    result = decod_rs.extract_landmarks(scene.points, config="tunnel")
    d = result.diagnostics
    assert d.contour_model == "polar"
    assert d.contour_inlier_fraction >= 0.9
    found = np.array(sorted(lm.origin[0] for lm in result.landmarks))
    joints = np.array(scene.joints_x_m)
    # Every arch away from the ends (the DoG needs 3 large sigmas = 0.3 m of data each side)
    # is found within 5 cm (arches are 15 cm wide; 1 cm noise), and nothing else is found.
    inner = joints[np.abs(joints) < 9.5]
    assert all(np.min(np.abs(found - j)) < 0.05 for j in inner)
    assert all(np.min(np.abs(joints - f)) < 0.05 for f in found)
    # The floor is flat: the contour around p = 0 (gravity) lies on z = -2 m, normals down.
    lm = result.landmarks[0]
    contour = lm.origin + np.outer(lm.contour[:, 0], lm.e1) + np.outer(lm.contour[:, 1], lm.e2)
    floor = np.r_[0:20, 236:256]  # +-28 deg about the bottom; the floor spans +-48 deg
    assert np.abs(contour[floor, 2] + 2.0).max() < 0.03  # 1 cm noise, 15 cm arches
    assert np.all(lm.normal_e1[floor] > 0.99)


def test_heading_reversal_gives_the_flipped_descriptor():
    rng = np.random.default_rng(11)
    scene = sa.pipe(rng, n_points=60_000)
    rot = sa.rotation(np.radians(5.0), np.radians(3.0), 0.0)
    pts = sa.rigid(scene.points, rot, (0.2, 0.1, 0.0))
    a = decod_rs.extract_landmarks(pts, config="pipe").landmarks[0]
    # The sensor turned round: the same cloud seen from a frame yawed by 180 deg.
    turn = sa.rotation(np.pi, 0.0, 0.0)
    b = decod_rs.extract_landmarks(sa.rigid(pts, turn.T, (0.0, 0.0, 0.0)), config="pipe")
    b = b.landmarks[0]
    assert np.allclose(turn @ b.axis, -a.axis, atol=1e-9)
    assert np.linalg.norm(turn @ b.origin - a.origin) < 1e-3
    flipped = b.descriptor[::-1, ::-1]
    both = a.mask & b.mask[::-1, ::-1]
    assert (a.mask == b.mask[::-1, ::-1]).mean() > 0.97
    # Same points in the same cells up to bin-edge ties: 97 % of cells within 0.1 mm.
    assert (np.abs(a.descriptor - flipped)[both] < 1e-4).mean() > 0.97
    # Unflipped, they do not match: the test can fail.
    assert (np.abs(a.descriptor - b.descriptor)[a.mask & b.mask] < 1e-4).mean() < 0.9


def test_open_box_room_is_rejected_as_not_a_corridor():
    scene = sa.box_room(np.random.default_rng(5))
    result = decod_rs.extract_landmarks(scene.points)
    assert result.landmarks == []
    [rejection] = result.rejections
    assert rejection.kind == "not_elongated"
    assert "axis.min_elongation" in rejection.message
    assert result.diagnostics.elongation < 2.0


def test_featureless_pipe_and_too_few_points_are_rejected_with_reasons():
    rng = np.random.default_rng(2)
    plain = sa.pipe(rng, joints_x_m=(), n_points=50_000)
    [r] = decod_rs.extract_landmarks(plain.points, config="pipe").rejections
    assert r.kind == "no_boundary"
    [r] = decod_rs.extract_landmarks(plain.points[:100], config="pipe").rejections
    assert r.kind == "too_few_points"
    # A pipe cloud with 30 % of the points scattered 5 cm inside: the contour does not fit.
    noisy = plain.points.copy()
    noisy[::3, 1:] *= 0.8
    [r] = decod_rs.extract_landmarks(noisy, config="pipe").rejections
    assert r.kind == "contour_misfit"


def test_bad_input_raises_value_errors_naming_the_argument():
    pts = sa.pipe(np.random.default_rng(0), n_points=2000).points
    for bad_value in (np.nan, np.inf):
        bad = pts.copy()
        bad[17, 1] = bad_value
        with pytest.raises(ValueError, match=r"`points` row 17"):
            decod_rs.extract_landmarks(bad)
    with pytest.raises(ValueError, match=r"`points`.*\(N, 3\)"):
        decod_rs.extract_landmarks(pts[:, :2])
    with pytest.raises(ValueError, match="`points` is empty"):
        decod_rs.extract_landmarks(np.zeros((0, 3)))
    with pytest.raises(ValueError, match="`gravity`"):
        decod_rs.extract_landmarks(pts, gravity=(0.0, 0.0, 0.0))
    stamps = np.arange(3.0)
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    clouds = [pts[:500], pts[500:1000], pts[1000:1500]]
    with pytest.raises(ValueError, match=r"`poses` must have shape \(3, 4, 4\)"):
        decod_rs.build_submap(stamps, clouds, poses[:2])
    with pytest.raises(ValueError, match="`points` must hold K"):
        decod_rs.build_submap(stamps, clouds[:2], poses)
    with pytest.raises(ValueError, match=r"`points\[1\]` is empty"):
        decod_rs.build_submap(stamps, [clouds[0], np.zeros((0, 3)), clouds[2]], poses)
    nan_cloud = clouds[2].copy()
    nan_cloud[3, 0] = np.nan
    with pytest.raises(ValueError, match=r"`points\[2\]` row 3"):
        decod_rs.build_submap(stamps, [clouds[0], clouds[1], nan_cloud], poses)
    skewed = poses.copy()
    skewed[1, 0, 0] = 2.0
    with pytest.raises(ValueError, match=r"poses\[1\]"):
        decod_rs.build_submap(stamps, clouds, skewed)
    with pytest.raises(ValueError, match=r"`specific_force` must have shape \(3, 3\)"):
        decod_rs.build_submap(stamps, clouds, poses, specific_force=np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"scans\[2\]\.stamp"):
        decod_rs.build_submap(np.array([0.0, 2.0, 1.0]), clouds, poses)
    with pytest.raises(decod_rs.ConfigError):
        decod_rs.extract_landmarks(pts, config="sewer")


def test_build_submap_motion_compensates_a_drive_and_finds_the_joint():
    rng = np.random.default_rng(4)
    log = sa.pipe_drive(rng, n_scans=40)
    cfg = decod_rs.load_config(preset="pipe")
    force = np.tile([0.0, 0.0, 9.81], (20, 1))
    submap = decod_rs.build_submap(
        log.stamps[:20], log.points[:20], log.poses[:20], specific_force=force, config=cfg
    )
    assert submap.anchor_stamp == log.stamps[10]
    assert np.allclose(submap.world_from_anchor, log.poses[10])
    assert len(submap) == submap.points.shape[0] > 10_000
    # Gravity: the mean over scans of R_anchor_body @ (-z), i.e. mostly -z of the anchor.
    assert submap.gravity @ (log.poses[10][:3, :3].T @ GRAVITY) > 0.999
    # Points land on the pipe wall in the world frame (within 4 noise sigmas + the voxel).
    world = submap.points @ submap.world_from_anchor[:3, :3].T + submap.world_from_anchor[:3, 3]
    radial = np.hypot(world[:, 1], world[:, 2])
    assert np.median(np.abs(radial - 0.3)) < 1e-3
    result = decod_rs.extract_submap(submap, config=cfg)
    assert len(result.landmarks) == 1, result.rejections
    origin_world = submap.world_from_anchor @ np.append(result.landmarks[0].origin, 1.0)
    assert abs(origin_world[0] - log.joints_x_m[0]) < 0.01
    # Batch extraction gives the same answer.
    [again] = decod_rs.extract_submaps([submap], config=cfg)
    assert np.allclose(again.landmarks[0].descriptor, result.landmarks[0].descriptor)


def test_submap_builder_streams_on_schedule():
    rng = np.random.default_rng(6)
    log = sa.pipe_drive(rng, n_scans=105, points_per_scan=500)
    builder = decod_rs.submap_builder("pipe")  # 20 scans every 2 s; 10 Hz scans
    out = [
        builder.push(t, p, pose)
        for t, p, pose in zip(log.stamps, log.points, log.poses, strict=True)
    ]
    submaps = [m for m in out if m is not None]
    last = builder.finish()
    # Windows never overlap: a 20-scan window (1.9 s) starts every 2 s, anchor in the middle.
    assert [m.anchor_stamp for m in submaps] == pytest.approx([1.0, 3.0, 5.0, 7.0, 9.0])
    assert all(len(m.scan_stamps) == 20 for m in submaps)
    # The log ends (10.4 s) inside the sixth window: finish() emits it, short.
    assert last is not None and len(last.scan_stamps) == 5
    with pytest.raises(ValueError, match="earlier than the previous scan"):
        builder.push(0.0, log.points[0], log.poses[0])
    bad = log.points[0].copy()
    bad[5, 2] = np.inf
    with pytest.raises(ValueError, match=r"points\[5\]"):
        builder.push(20.0, bad, log.poses[0])
    # IMU: the specific force of a pitched body gives a pitched gravity in the anchor frame.
    tilted = decod_rs.submap_builder("pipe")
    force = np.array([-9.81 * np.sin(0.1), 0.0, 9.81 * np.cos(0.1)])
    emitted = [tilted.push(t, p, pose, force) for t, p, pose in zip(*_window(log), strict=True)]
    m = emitted[-1]
    assert m is not None
    # Expected: -normalize(sum_k R_anchor^T R_k f) over the 20 scans (anchor = scan 10).
    anchor_rot = log.poses[10][:3, :3]
    total = sum(anchor_rot.T @ log.poses[k][:3, :3] @ force for k in range(20))
    assert np.allclose(m.gravity, -total / np.linalg.norm(total), atol=1e-6)
    assert m.gravity @ np.array([np.sin(0.1), 0.0, -np.cos(0.1)]) > 0.998  # wobble < 0.05 rad


def _window(log):
    return log.stamps[:20], log.points[:20], log.poses[:20]


@settings(max_examples=5, deadline=None)
@given(
    angles=st.tuples(*[st.floats(-3.0, 3.0)] * 3),
    shift=st.tuples(*[st.floats(-10.0, 10.0)] * 3),
)
def test_descriptor_is_invariant_to_rigid_motion(angles, shift):
    rng = np.random.default_rng(9)
    pts = sa.rigid(sa.pipe(rng, n_points=40_000).points, sa.rotation(0.2, 0.1, 0.0), (0, 0, 0))
    a = decod_rs.extract_landmarks(pts, config="pipe").landmarks[0]
    rot = sa.rotation(*angles)
    b = decod_rs.extract_landmarks(
        sa.rigid(pts, rot, shift), gravity=rot @ GRAVITY, forward=rot[:, 0], config="pipe"
    ).landmarks[0]
    assert np.linalg.norm(rot @ a.origin + np.asarray(shift) - b.origin) < 1e-3
    assert (a.mask == b.mask).mean() > 0.97
    assert (np.abs(a.descriptor - b.descriptor)[a.mask & b.mask] < 1e-4).mean() > 0.97


def test_heading_reversal_on_a_horseshoe_reverses_the_polar_contour():
    # Non-circular section: p -> 1 - p must hold for the arclength of the polar contour too.
    scene = sa.horseshoe(np.random.default_rng(12), n_points=60_000)
    a = decod_rs.extract_landmarks(scene.points, config="tunnel")
    b = decod_rs.extract_landmarks(scene.points, forward=(-1.0, 0.0, 0.0), config="tunnel")
    pairs = [
        (la, min(b.landmarks, key=lambda lb, la=la: np.linalg.norm(lb.origin - la.origin)))
        for la in a.landmarks
    ]
    assert len(pairs) >= 4
    for la, lb in pairs:
        assert np.linalg.norm(la.origin - lb.origin) < 0.02
        assert np.allclose(la.contour, lb.contour[::-1] * [1.0, -1.0], atol=1e-9)
        both = la.mask & lb.mask[::-1, ::-1]
        assert both.sum() > 0.5 * la.mask.size
        # The same points land in the mirrored cells; only those within the sub-mm origin
        # difference of a row edge move (measured: >= 97 % of cells identical).
        same = np.abs(la.descriptor - lb.descriptor[::-1, ::-1])[both] < 1e-9
        assert same.mean() > 0.95


def test_protruding_arches_are_located_at_the_arch_not_in_their_shadow():
    """Steel arches (0.2 m proud) seen from afar hide the rock behind them; the boundary must
    still be placed at the arch, whatever the view distance. Before the side-lobe rule
    (boundary.rs step 5) views from 3-10 m put it 0.14 m beyond the arch, on the side away
    from the sensor: a 1.5 % stretch that the sequential factors took for odometry scale.

    Horseshoe scene, spinning 64-beam sensor, exact poses, submaps of 20 scans at 1.3 m/s.
    Tolerances: the arch is 0.15 m wide, so a detection on the arch is within 5 cm of its
    centre (before the rule, about half of the views from 3 m on were 0.14-0.17 m off); a
    stretch below 0.5 % of the view distance is a third of the one measured before.
    """
    from decod_rs.config import Config, load_config
    from decod_rs.sim.raycast import cast
    from decod_rs.sim.scenes import build_scene
    from decod_rs.sim.sensors import measure, ray_directions, sensor_spec

    scene = build_scene("horseshoe", 0, 40.0)
    spec = sensor_spec("spin64")
    rng = np.random.default_rng(3)
    config = Config(load_config(preset="tunnel").to_dict())
    k = int(config.submap.scans_per_submap)
    joints = np.asarray(scene.joints_x_m)
    dist, err = [], []
    for anchor_x in (9.0, 14.3, 19.7, 25.1):
        stamps, clouds, poses = [], [], []
        for i in range(k):
            x = anchor_x + 1.3 * 0.1 * (i - k // 2)
            origin = np.array([x, 0.0, 0.0])
            hits = cast(scene, origin, ray_directions(spec, i))
            pts, _, _ = measure(spec, hits, origin, np.ones(8), 0.01, rng)
            pose = np.eye(4)
            pose[0, 3] = x
            stamps.append(0.1 * i)
            clouds.append(pts - origin)
            poses.append(pose)
        submap = decod_rs.extraction.build_submap(
            np.array(stamps), clouds, np.array(poses), anchor_index=k // 2, config=config
        )
        for lm in decod_rs.extraction.extract_submap(submap, config=config).landmarks:
            x = anchor_x + lm.origin[0]
            dist.append(lm.origin[0])
            err.append(x - joints[np.argmin(np.abs(joints - x))])
    dist_a, err_a = np.array(dist), np.array(err)
    far = np.abs(dist_a) >= 3.0
    assert far.sum() >= 10 and (~far).sum() >= 5, dist_a
    # Rock features are detected too (a few per cent): the arches' share, not every one.
    on_arch = np.abs(err_a) < 0.05
    assert on_arch.mean() >= 0.9, np.round(np.c_[dist_a, err_a], 3)
    assert np.median(np.abs(err_a[far])) < 0.03, np.round(np.c_[dist_a, err_a], 3)
    near_arch = np.abs(err_a) < 0.3
    slope = np.polyfit(dist_a[near_arch], err_a[near_arch], 1)[0]
    assert abs(slope) < 0.005, slope
