"""``decod_rs.changes.residual_difference``: what is left of two views of one boundary once
their alignment and what two contour fits of one unchanged surface can differ by are taken
out (a column offset and a tilt of the section). A re-inspection's ``changes.csv`` ranks
joints by it, so a user relies on unchanged walls giving ~0 and a local change staying."""

from __future__ import annotations

import numpy as np

from decod_rs._core import Landmark
from decod_rs.changes import residual_difference

ROWS, COLS, CELL_Z, RADIUS = 16, 256, 0.03, 0.3
THETA = 2.0 * np.pi * (np.arange(COLS) + 0.5) / COLS


def _landmark(offsets: np.ndarray, normal_e2: np.ndarray | None = None) -> Landmark:
    return Landmark(
        0.0,
        np.zeros(3),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.0, -1.0]),
        offsets,
        np.ones(offsets.shape, dtype=bool),
        cell_z_m=CELL_Z,
        perimeter_m=2.0 * np.pi * RADIUS,
        normal_e1=np.cos(THETA),
        normal_e2=np.sin(THETA) if normal_e2 is None else normal_e2,
        radius_m=RADIUS,
    )


def _views(beta2: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A survey surface, the same surface seen again 2 rows and 5 columns further with a
    column offset, a tilt ``(0.0004, beta2)`` m per row and a 5 mm bump, and the bump's cells."""
    rng = np.random.default_rng(3)
    wide = rng.normal(0.0, 0.002, (ROWS + 2, COLS))
    survey = wide[:ROWS]
    shifted = np.roll(wide[2 : ROWS + 2], -5, axis=1)  # query row r = survey row r + 2
    z = (np.arange(ROWS) - 0.5 * (ROWS - 1))[:, None]
    offset = 0.003 * np.sin(3.0 * THETA)[None, :]
    tilt = z * (0.0004 * np.cos(THETA) + beta2 * np.sin(THETA))[None, :]
    bump = np.zeros((ROWS, COLS), dtype=bool)
    bump[6:10, 100:111] = True
    query = shifted + offset + tilt + np.where(bump, 0.005, 0.0)
    return survey, query, bump


def test_the_fit_takes_out_alignment_offset_and_tilt_and_leaves_a_local_change() -> None:
    survey, query, bump = _views(beta2=-0.0002)
    residual = residual_difference(_landmark(query), _landmark(survey), 0.0, 2 * CELL_Z, 5 / COLS)
    # The last two query rows have no survey row to compare with.
    assert np.isnan(residual[ROWS - 2 :]).all()
    compared = np.isfinite(residual)
    assert compared[: ROWS - 2].all()
    # Away from the bump's columns nothing is left (the surfaces are the same there).
    columns = np.zeros(COLS, dtype=bool)
    columns[100:111] = True
    assert np.abs(residual[:, ~columns][compared[:, ~columns]]).max() < 1e-4
    # The bump stays, less the share of it its columns' offset absorbs (4 of 14 rows).
    inside = residual[bump]
    # (within 10 %: four alternating rounds of offset and tilt leave up to 0.25 mm of it.)
    assert np.allclose(inside, 0.005 * (1.0 - 4.0 / 14.0), rtol=0.1), (inside.min(), inside.max())


def test_a_tilt_the_contour_cannot_show_is_left_at_zero_not_an_error() -> None:
    # Normals without an e2 component: the second tilt regressor is all zero, so the least
    # squares are rank deficient; the first tilt and the offset are still taken out.
    survey, query, bump = _views(beta2=0.0)
    residual = residual_difference(
        _landmark(query, np.zeros(COLS)),
        _landmark(survey, np.zeros(COLS)),
        0.0,
        2 * CELL_Z,
        5 / COLS,
    )
    columns = np.zeros(COLS, dtype=bool)
    columns[100:111] = True
    finite = np.isfinite(residual[:, ~columns])
    assert np.abs(residual[:, ~columns][finite]).max() < 1e-4
    assert np.allclose(residual[bump], 0.005 * (1.0 - 4.0 / 14.0), rtol=0.1)
