"""Export the pose graph for users who optimise elsewhere: g2o text and JSON.

g2o (``write_g2o``): standard ``VERTEX_SE3:QUAT id x y z qx qy qz qw`` per pose,
``FIX 0`` for the prior, ``EDGE_SE3:QUAT i j x y z qx qy qz qw I(21)`` per odometry edge
(information upper triangle, g2o's translation-then-rotation order) and, for the Pose3
ablation, per loop. 5-DoF landmark factors have no g2o type; they are written as one custom
line each, which g2o itself skips with a warning and other readers can parse::

    EDGE_DECOD_LANDMARK5 i j cix ciy ciz aix aiy aiz cjx cjy cjz ajx ajy ajz
        sigma_pos_m sigma_axis huber_k

(one line): pose ``i`` is the query, ``j`` the database pose, ``c``/``a`` the boundary origin
(m) and unit axis in each pose's body frame; the residual is ``[T_i^-1 T_j c_j - c_i,
1 - (a_i^T R_ij a_j)^2]`` (see ``decod_rs.landmark_factor``) under a Huber loss.

JSON (``write_graph_json``): ``{"format": "decod-graph-1", "loop_factor", "poses": [[x y z
qx qy qz qw], ...], "odometry": [{"from", "to", "measurement": [x y z qx qy qz qw],
"sigmas": [rx ry rz tx ty tz]}], "loops": [{"query_index", "db_index", "query_origin",
"query_axis", "db_origin", "db_axis", "inliers", "score", "kind", "sigmas", "huber_k"}]}``
(``kind``: ``loop`` or ``sequential``; each factor carries its own sigmas), sigmas
in GTSAM's rotation-first order. A landmark factor's position sigmas are along the query's
axis, then across it twice (the graph rotates its position residual into that frame,
:func:`decod_rs.landmark_factor.axis_frame`); the g2o line gives the one along the axis. The
odometry sigmas are the ones along each edge's direction of travel: the graph's edges are
``graph.odom_across_sigma_ratio`` times tighter across it, and its per-pose roll/pitch
attitude factors (``graph.odom_attitude_sigma_rad``) are not exported.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from decod_rs.config import Config
from decod_rs.graph import (
    LoopConstraint,
    _check_cfg,
    _check_loops,
    _inverse,
    _pose3_measurement,
    odometry_sigmas,
)
from decod_rs.tum import check_poses, rotation_to_quaternion

__all__ = ["G2O_LANDMARK_TAG", "write_g2o", "write_graph_json"]

#: The custom g2o line type of the 5-DoF landmark factor.
G2O_LANDMARK_TAG = "EDGE_DECOD_LANDMARK5"


def _tq(t: np.ndarray) -> list[float]:
    q = rotation_to_quaternion(t[:3, :3])
    return [float(v) for v in (*t[:3, 3], *q)]


def _g2o_information(sigmas_rot_first: np.ndarray) -> list[float]:
    """Upper triangle (21,) of the diagonal information in g2o's ``[t, r]`` order."""
    g2o_order = np.concatenate([sigmas_rot_first[3:], sigmas_rot_first[:3]])
    info = np.diag(1.0 / g2o_order**2)
    return [float(info[r, c]) for r in range(6) for c in range(r, 6)]


def _fmt(values: Sequence[float]) -> str:
    return " ".join(f"{v:.12g}" for v in values)


def write_g2o(
    path: str | Path, poses: ArrayLike, loops: Sequence[LoopConstraint], cfg: Config
) -> None:
    """Write the graph on ``poses`` (N, 4, 4) ``world_from_body`` with ``loops`` as g2o."""
    _check_cfg(cfg)
    p = check_poses(poses)
    _check_loops(loops, p.shape[0])
    lines = [f"VERTEX_SE3:QUAT {k} {_fmt(_tq(t))}" for k, t in enumerate(p)]
    lines.append("FIX 0")
    sig = odometry_sigmas(p, cfg)
    for k in range(p.shape[0] - 1):
        rel = _inverse(p[k]) @ p[k + 1]
        lines.append(f"EDGE_SE3:QUAT {k} {k + 1} {_fmt(_tq(rel))} {_fmt(_g2o_information(sig[k]))}")
    for lc in loops:
        loop_sig = lc.sigmas(cfg)
        if cfg.loop_factor == "pose3":
            meas = _pose3_measurement(p, lc).matrix()
            lines.append(
                f"EDGE_SE3:QUAT {lc.query_index} {lc.db_index} {_fmt(_tq(meas))} "
                f"{_fmt(_g2o_information(loop_sig))}"
            )
        else:
            geo = [*lc.query_origin, *lc.query_axis, *lc.db_origin, *lc.db_axis]
            lines.append(
                f"{G2O_LANDMARK_TAG} {lc.query_index} {lc.db_index} {_fmt(geo)} "
                f"{_fmt([loop_sig[0], loop_sig[3], cfg.huber_k])}"
            )
    Path(path).write_text("\n".join(lines) + "\n", encoding="utf-8")


def write_graph_json(
    path: str | Path, poses: ArrayLike, loops: Sequence[LoopConstraint], cfg: Config
) -> None:
    """Write the graph on ``poses`` (N, 4, 4) with ``loops`` as JSON (format in the module
    doc)."""
    _check_cfg(cfg)
    p = check_poses(poses)
    _check_loops(loops, p.shape[0])
    sig = odometry_sigmas(p, cfg)
    doc: dict[str, Any] = {
        "format": "decod-graph-1",
        "loop_factor": cfg.loop_factor,
        "poses": [_tq(t) for t in p],
        "odometry": [
            {
                "from": k,
                "to": k + 1,
                "measurement": _tq(_inverse(p[k]) @ p[k + 1]),
                "sigmas": [float(v) for v in sig[k]],
            }
            for k in range(p.shape[0] - 1)
        ],
        "loops": [
            {
                "query_index": lc.query_index,
                "db_index": lc.db_index,
                "query_origin": lc.query_origin.tolist(),
                "query_axis": lc.query_axis.tolist(),
                "db_origin": lc.db_origin.tolist(),
                "db_axis": lc.db_axis.tolist(),
                "inliers": int(lc.inliers),
                "score": float(lc.score),
                "kind": lc.kind,
                "sigmas": [float(v) for v in lc.sigmas(cfg)],
                "huber_k": float(cfg.huber_k),
            }
            for lc in loops
        ],
    }
    Path(path).write_text(json.dumps(doc), encoding="utf-8")
