"""The 5-DoF landmark factor of the paper (§III-C, Eq. ``residual``) for GTSAM.

For a verified boundary pair, query landmark ``i`` observed from pose ``T_i`` (submap ``k_i``)
and database landmark ``j`` observed from pose ``T_j`` (``k_j``), both ``world_from_body``:

* ``c_i``, ``a_i``: contour centre (boundary origin, metres) and unit corridor axis of the
  query, in the body frame of ``T_i``; ``c_j``, ``a_j`` the same for the database landmark in
  the body frame of ``T_j``.
* ``T_ij = T_i^-1 T_j = (R_ij, t_ij)``.

Our reading of the paper's ``r_ij = t_ij - (c̄_i - c̄_j)`` with "these vectors expressed in
frame k_i under the current relative pose": ``c̄_j`` is ``c_j`` rotated into frame ``k_i``,
``R_ij c_j``, so

    r = t_ij - (c_i - R_ij c_j) = T_ij * c_j - c_i          (3,, metres, frame k_i)

i.e. the two observed boundary origins must coincide in the world; and

    delta = 1 - (a_i^T R_ij a_j)^2                          (scalar)

the two axes must be parallel, in either direction (a reversed traversal flips the sign of
an axis, which ``delta`` ignores). Rotating either pose about the shared axis through the
landmark origin changes neither term: the roll about the degenerate axis stays free, which is
the point of the factor (§III-C, §IV-D: a 6-DoF factor imposes the gravity-based roll).

``delta`` is quadratic in the axis misalignment angle ``theta`` (``delta = sin^2 theta``), so
``landmark_axis_sigma`` = 0.01 means "about 0.1 rad is one sigma", and near ``delta = 0`` the
term adds little curvature; the odometry chain carries the relative rotation there.

Jacobians are analytic, for GTSAM's Pose3 chart: right-multiplied tangent perturbations
``xi = [w, v]`` (rotation first), ``R -> R Exp(w)``, ``t -> t + R v``. With ``q = T_ij c_j``,
``b = R_ij a_j`` and ``s = a_i^T b``:

    dr/dw_i = [q]x          dr/dv_i = -I
    dr/dw_j = -R_ij [c_j]x  dr/dv_j = R_ij
    ddelta/dw_i = -2 s a_i^T [b]x      ddelta/dw_j = 2 s a_i^T R_ij [a_j]x
    ddelta/dv_i = ddelta/dv_j = 0

checked against central finite differences through ``gtsam.Pose3.retract`` in
``tests/test_graph.py``.
"""

from __future__ import annotations

from typing import Any

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

#: Residual layout: 3 position components (metres, frame k_i), then the axis term.
RESIDUAL_DIM = 4

__all__ = ["RESIDUAL_DIM", "axis_frame", "landmark_factor", "landmark_residual", "skew"]


def axis_frame(axis: ArrayLike) -> FloatArray:
    """(3, 3) rotation whose first row is the unit ``axis`` and whose other two rows span
    the plane across it: a position residual ``r`` becomes ``[along, across, across]``."""
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    helper = np.array([0.0, 0.0, 1.0]) if abs(a[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    return np.stack([a, e1, np.cross(a, e1)])


def skew(v: FloatArray) -> FloatArray:
    """The (3, 3) cross-product matrix ``[v]x`` of a (3,) vector."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def landmark_residual(
    world_from_i: ArrayLike,
    world_from_j: ArrayLike,
    c_i: ArrayLike,
    a_i: ArrayLike,
    c_j: ArrayLike,
    a_j: ArrayLike,
    jacobians: bool = False,
) -> tuple[FloatArray, FloatArray | None, FloatArray | None]:
    """The unwhitened 5-DoF residual ``[r (3), delta]`` and, if asked, its (4, 6) Jacobians
    with respect to the tangent spaces of ``T_i`` and ``T_j`` (GTSAM order ``[w, v]``).

    ``world_from_i``/``world_from_j``: (4, 4); ``c_*``: (3,) origins in metres and ``a_*``:
    (3,) unit axes, each in its own pose's body frame.
    """
    ti = np.asarray(world_from_i, dtype=np.float64)
    tj = np.asarray(world_from_j, dtype=np.float64)
    ci = np.asarray(c_i, dtype=np.float64)
    ai = np.asarray(a_i, dtype=np.float64)
    cj = np.asarray(c_j, dtype=np.float64)
    aj = np.asarray(a_j, dtype=np.float64)
    ri_t = ti[:3, :3].T
    r_ij = ri_t @ tj[:3, :3]
    t_ij = ri_t @ (tj[:3, 3] - ti[:3, 3])
    q = r_ij @ cj + t_ij
    b = r_ij @ aj
    s = float(ai @ b)
    res = np.empty(RESIDUAL_DIM)
    res[:3] = q - ci
    res[3] = 1.0 - s * s
    if not jacobians:
        return res, None, None
    hi = np.zeros((RESIDUAL_DIM, 6))
    hj = np.zeros((RESIDUAL_DIM, 6))
    hi[:3, :3] = skew(q)
    hi[:3, 3:] = -np.eye(3)
    hj[:3, :3] = -r_ij @ skew(cj)
    hj[:3, 3:] = r_ij
    hi[3, :3] = -2.0 * s * (ai @ skew(b))
    hj[3, :3] = 2.0 * s * (ai @ r_ij @ skew(aj))
    return res, hi, hj


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
    rot = np.eye(3) if frame is None else np.asarray(frame, dtype=np.float64).copy()
    ci = np.asarray(c_i, dtype=np.float64).copy()
    ai = np.asarray(a_i, dtype=np.float64).copy()
    cj = np.asarray(c_j, dtype=np.float64).copy()
    aj = np.asarray(a_j, dtype=np.float64).copy()

    def error(this: gtsam.CustomFactor, values: gtsam.Values, h: Any) -> FloatArray:
        keys = this.keys()
        ti = values.atPose3(keys[0]).matrix()
        tj = values.atPose3(keys[1]).matrix()
        res, hi, hj = landmark_residual(ti, tj, ci, ai, cj, aj, jacobians=h is not None)
        res[:3] = rot @ res[:3]
        if h is not None and hi is not None and hj is not None:
            hi[:3] = rot @ hi[:3]
            hj[:3] = rot @ hj[:3]
            h[0] = hi
            h[1] = hj
        return res

    return gtsam.CustomFactor(noise, [key_i, key_j], error)
