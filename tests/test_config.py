import subprocess
import sys

import pytest

import decod_rs


def test_presets_resolve_with_paper_defaults():
    tunnel = decod_rs.load_config(preset="tunnel")
    assert tunnel.submap.scans_per_submap == 20
    assert tunnel.submap.voxel_m == pytest.approx(0.055)
    assert tunnel.boundary.dog_sigma_small_m == pytest.approx(0.025)
    assert tunnel.matching.patch_rows == 9 and tunnel.matching.patch_cols == 33
    pipe = decod_rs.load_config(preset="pipe")
    # Spatial sampling ten times finer, grid unchanged (paper section IV-E).
    assert pipe.submap.voxel_m == pytest.approx(tunnel.submap.voxel_m / 10)
    assert (pipe.descriptor.rows, pipe.descriptor.cols) == (16, 256)


def test_toml_overrides_and_errors_name_the_parameter(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text("[matching]\nmin_inliers = 15\n")
    assert decod_rs.load_config(good, preset="pipe").matching.min_inliers == 15
    # The rule on single detections is on unless a config turns it off (ablation).
    assert decod_rs.load_config(preset="tunnel").matching.require_tracked_loop is True
    off = tmp_path / "off.toml"
    off.write_text("[matching]\nrequire_tracked_loop = false\n")
    assert decod_rs.load_config(off).matching.require_tracked_loop is False
    bad = tmp_path / "bad.toml"
    bad.write_text("[matching]\nmin_inlier = 15\n")
    with pytest.raises(decod_rs.ConfigError, match=r"matching\.min_inlier"):
        decod_rs.load_config(bad)
    with pytest.raises(decod_rs.ConfigError, match="preset"):
        decod_rs.load_config(preset="sewer")


def test_dump_config_command_prints_loadable_toml(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "decod_rs.cli", "dump-config", "--preset", "pipe"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    path = tmp_path / "dumped.toml"
    path.write_text(out)
    assert decod_rs.load_config(path).to_dict() == decod_rs.load_config(preset="pipe").to_dict()
