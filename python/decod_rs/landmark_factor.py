"""The 5-DoF landmark factor of the paper (§III-C, Eq. ``residual``) for GTSAM.

For a verified boundary pair, query landmark ``i`` (origin ``c_i``, unit axis ``a_i`` in the
body frame of pose ``T_i``) and database landmark ``j`` (``c_j``, ``a_j`` in that of ``T_j``),
with ``T_ij = T_i^-1 T_j = (R_ij, t_ij)``:

    r = T_ij * c_j - c_i                  (3,, metres, frame k_i: the origins coincide)
    delta = 1 - (a_i^T R_ij a_j)^2        (the axes are parallel, in either direction)

Rotating either pose about the shared axis through the landmark origin changes neither term:
the roll about the degenerate axis stays free, the point of the factor. The residual and its
analytic Jacobians (GTSAM's Pose3 chart, ``[w, v]``) are computed in Rust
(``src/landmark_factor.rs``, where the derivation is; 25 us per linearisation in numpy, GTSAM
asks tens of thousands of times per run) and checked against central finite differences
through ``gtsam.Pose3.retract`` in ``tests/test_graph.py``.

The graph adds the factors between nearby poses as one ``gtsam.CustomFactor``
(:func:`landmark_factor_group`, :data:`decod_rs.graph.LOOP_GROUP_KEYS`): inside GTSAM's
optimisers a Python factor is handed a copy of every variable at each call (the Values the
optimiser owns are not Python objects), so a call costs in proportion to the graph and an
iteration in proportion to the graph times its Python factors. A kilometre of tunnel (539
anchors, 2,805 landmark factors) took 78 ms an LM iteration, 12.5 s of a 41 s run, and 400 m
of pipe (1,711 anchors, 2,784 factors) 1.5 s an iteration, 17.8 s of 75 s; grouped, 4.3 s
and 7.0 s (``docs/measurements.md``, "Long logs").
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from decod_rs import _core

FloatArray = NDArray[np.float64]

#: Residual layout: 3 position components (metres, frame k_i), then the axis term.
RESIDUAL_DIM = 4

__all__ = [
    "RESIDUAL_DIM",
    "LandmarkTerm",
    "axis_frame",
    "landmark_factor",
    "landmark_factor_group",
    "landmark_residual",
]


def _f64(a: ArrayLike) -> FloatArray:
    return np.ascontiguousarray(a, dtype=np.float64)


#: No rotation of the position rows.
_IDENTITY = np.eye(3)


def axis_frame(axis: ArrayLike) -> FloatArray:
    """(3, 3) rotation whose first row is the unit ``axis`` and whose other two rows span
    the plane across it: a position residual ``r`` becomes ``[along, across, across]``. For
    an axis within 64 deg of level the second row is horizontal (lateral) and the third lies
    in the vertical plane through the axis (:mod:`decod_rs.cross_axis` weighs them apart),
    vertical as the frame's +z has it (a sensor mounted rolled by theta tilts both rows by
    theta; ``decisions.md``, "What the graph keeps from the odometry")."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = (0.0, 0.0, 1.0) if abs(a[2]) < 0.9 else (1.0, 0.0, 0.0)
    e1 = np.array(_cross(a, helper))
    e1 /= np.linalg.norm(e1)
    return np.array([a, e1, _cross(a, e1)])


def _cross(a: FloatArray, b: Any) -> tuple[float, float, float]:
    """``np.cross`` of two 3-vectors with the same products and differences (same bits), at
    a tenth of its cost: the graph builds one frame per loop and sequential factor."""
    a0, a1, a2 = float(a[0]), float(a[1]), float(a[2])
    b0, b1, b2 = float(b[0]), float(b[1]), float(b[2])
    return (a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0)


def landmark_residual(
    world_from_i: ArrayLike,
    world_from_j: ArrayLike,
    c_i: ArrayLike,
    a_i: ArrayLike,
    c_j: ArrayLike,
    a_j: ArrayLike,
    jacobians: bool = False,
    frame: ArrayLike | None = None,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """The unwhitened 5-DoF residual ``[r (3), delta]`` and, if asked, its (4, 6) Jacobians
    with respect to the tangent spaces of ``T_i`` and ``T_j`` (GTSAM order ``[w, v]``).

    ``world_from_i``/``world_from_j``: (4, 4); ``c_*``: (3,) origins in metres and ``a_*``:
    (3,) unit axes, each in its own pose's body frame; ``frame`` (3, 3): the rotation of the
    position rows, as in :func:`landmark_factor` (default none).
    """
    return _core.landmark_residual(
        _f64(world_from_i),
        _f64(world_from_j),
        _f64(c_i),
        _f64(a_i),
        _f64(c_j),
        _f64(a_j),
        _IDENTITY if frame is None else _f64(frame),
        jacobians,
    )


def landmark_factor(
    key_i: int,
    key_j: int,
    c_i: ArrayLike,
    a_i: ArrayLike,
    c_j: ArrayLike,
    a_j: ArrayLike,
    noise: gtsam.noiseModel.Base,
    frame: ArrayLike | None = None,
) -> gtsam.CustomFactor:
    """A ``gtsam.CustomFactor`` on the Pose3 variables ``key_i`` (query) and ``key_j``
    (database) with the residual of ``landmark_residual`` and a 4-dimensional ``noise``
    model (the graph uses a Huber-robust diagonal one). ``frame`` (3, 3): a rotation applied
    to the position residual and its Jacobian rows before the noise model (the graph passes
    :func:`axis_frame` of ``a_i``, so the sigmas are along the corridor and across it)."""
    rot = _IDENTITY if frame is None else _f64(frame).copy()
    ci, ai, cj, aj = (_f64(v).copy() for v in (c_i, a_i, c_j, a_j))
    residual = _core.landmark_residual

    def error(this: gtsam.CustomFactor, values: gtsam.Values, h: Any) -> FloatArray:
        keys = this.keys()
        ti = values.atPose3(keys[0]).matrix()
        tj = values.atPose3(keys[1]).matrix()
        res, hi, hj = residual(ti, tj, ci, ai, cj, aj, rot, h is not None)
        if h is not None and hi is not None and hj is not None:
            h[0] = hi
            h[1] = hj
        return res

    return gtsam.CustomFactor(noise, [key_i, key_j], error)


@dataclass(frozen=True)
class LandmarkTerm:
    """One landmark factor's data for :func:`landmark_factor_group`: its query's and its
    database's pose keys, origins and axes (each in its own pose's body frame), the rotation
    of the position rows (:func:`axis_frame`) and the four sigmas of its diagonal noise."""

    key_i: int
    key_j: int
    c_i: FloatArray
    a_i: FloatArray
    c_j: FloatArray
    a_j: FloatArray
    frame: FloatArray
    sigmas: FloatArray


def landmark_factor_group(terms: Sequence[LandmarkTerm], huber_k: float) -> gtsam.CustomFactor:
    """The landmark factors ``terms`` as one ``gtsam.CustomFactor`` on the poses they tie
    (module docs), each term robust on its own exactly as :func:`landmark_factor` with
    ``Robust(Huber(huber_k), Diagonal(sigmas))`` is in GTSAM: linearised, a term's whitened
    residual ``w`` and Jacobian are scaled by ``sqrt(k / |w|)`` beyond ``k`` (GTSAM's block
    reweighting); evaluated, its rows carry the Huber loss, ``0.5 |row|^2 = rho(|w|)``. The
    factor's own noise model is the unit one, so the graph's error, its linearisation and the
    optimiser's steps are those of the separate factors (the Jacobian blocks of the poses a
    term does not tie are zero)."""
    if not terms:
        raise ValueError("landmark_factor_group: no terms")
    keys = sorted({int(t.key_i) for t in terms} | {int(t.key_j) for t in terms})
    where = {key: n for n, key in enumerate(keys)}
    for t in terms:
        if t.key_i == t.key_j:
            raise ValueError(f"landmark_factor_group: a term ties pose {t.key_i} to itself")
    k = float(huber_k)
    data = [
        (
            where[int(t.key_i)],
            where[int(t.key_j)],
            _f64(t.c_i).copy(),
            _f64(t.a_i).copy(),
            _f64(t.c_j).copy(),
            _f64(t.a_j).copy(),
            _f64(t.frame).copy(),
            1.0 / _f64(t.sigmas),
        )
        for t in terms
    ]
    size = RESIDUAL_DIM * len(data)
    residual = _core.landmark_residual

    def error(this: gtsam.CustomFactor, values: gtsam.Values, h: Any) -> FloatArray:
        poses = [values.atPose3(key).matrix() for key in this.keys()]
        jac = h is not None
        out = np.empty(size)
        blocks = [np.zeros((size, 6)) for _ in poses] if jac else []
        for n, (i, j, ci, ai, cj, aj, rot, inv) in enumerate(data):
            res, hi, hj = residual(poses[i], poses[j], ci, ai, cj, aj, rot, jac)
            w = res * inv
            norm = float(np.sqrt(w @ w))
            rows = slice(RESIDUAL_DIM * n, RESIDUAL_DIM * (n + 1))
            if norm <= k:
                scale = 1.0
            elif jac:
                scale = float(np.sqrt(k / norm))
            else:
                scale = float(np.sqrt(2.0 * k * norm - k * k)) / norm
            out[rows] = w * scale
            if blocks and hi is not None and hj is not None:
                blocks[i][rows] = hi * (inv * scale)[:, None]
                blocks[j][rows] = hj * (inv * scale)[:, None]
        if h is not None:
            for n, block in enumerate(blocks):
                h[n] = block
        return out

    return gtsam.CustomFactor(gtsam.noiseModel.Unit.Create(size), keys, error)
