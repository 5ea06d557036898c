"""The path's curvature that switches on the curved centre lines (decod_rs.path_curve)."""

from __future__ import annotations

import numpy as np
import pytest

from decod_rs.autoscale import CorridorProbe, derive
from decod_rs.path_curve import path_curvature


def _out_and_back(radius_m: float | None, length_m: float, wobble_m: float) -> np.ndarray:
    """A path out along a corridor and back (the direction reverses at the far end), every
    5 cm, with a lateral wobble of ``wobble_m`` (1.7 m wavelength, as a crawler steers)."""
    s = np.arange(0.0, length_m, 0.05)
    y = wobble_m * np.sin(2 * np.pi * s / 1.7)
    if radius_m is None:
        out = np.column_stack([s, y, np.zeros_like(s)])
    else:
        phi = s / radius_m
        out = np.column_stack(
            [
                (radius_m - y) * np.sin(phi),
                radius_m - (radius_m - y) * np.cos(phi),
                np.zeros_like(s),
            ]
        )
    return np.concatenate([out, out[::-1]])


def test_a_curve_is_measured_and_a_straight_wobbling_path_is_not() -> None:
    for radius in (300.0, -120.0, 20.0):
        k = path_curvature(_out_and_back(radius, 40.0, 0.05), 30.0 if abs(radius) > 50 else 8.0)
        assert k == pytest.approx(1.0 / abs(radius), rel=0.1), radius
    # Straight: the wobble (5 cm, 0.18 rad of heading) averages out over the window to a
    # tenth of a 300 m curve, and the turnaround, where the direction reverses, is no curve.
    assert path_curvature(_out_and_back(None, 40.0, 0.05), 30.0) < 0.12 / 300.0
    assert path_curvature(_out_and_back(None, 40.0, 0.0), 30.0) < 1e-9
    # Too short a path for one window: no figure.
    assert path_curvature(_out_and_back(300.0, 10.0, 0.0), 30.0) == 0.0


def test_auto_fits_curved_centre_lines_only_where_the_curve_matters() -> None:
    # A 6 m tunnel seen to ~15 m: a 300 m curve puts the centre line 0.37 m off the chord
    # there (12 % of the radius), a 3 km one 3.7 cm (1 %).
    tunnel = CorridorProbe(radius_m=3.0, z_near_m=5.0, speed_mps=1.2, scan_rate_hz=10.0, probes=4)
    for curvature, curved in ((1 / 300, True), (1 / 3000, False), (0.0, False)):
        probe = CorridorProbe(**{**tunnel.__dict__, "curvature_per_m": curvature})
        assert derive(probe)["axis"]["curved"] is curved, curvature
