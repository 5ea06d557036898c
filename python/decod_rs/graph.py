"""The pose graph (paper §III-C, Eq. ``pgo_objective``): relative odometry between
consecutive poses plus one landmark factor per verified loop, Huber-robust, solved with
Levenberg-Marquardt by GTSAM.

Typical use, from a run (``decod run`` wires exactly this)::

    cfg = decod_rs.load_config(preset="pipe").graph
    loops = [LoopConstraint(query_index=qi, db_index=di, query_origin=..., ...)]
    out = correct_trajectory(scan_stamps, scan_odom, anchor_stamps, loops, cfg)
    write_tum("corrected.tum", scan_stamps, out.poses)

``optimize`` is the bare graph on whatever poses it is given; ``propagate_to_scans`` carries
a node-level correction to every scan; ``correct_trajectory`` does both, at the granularity
``cfg.granularity`` (``"submap"``: one node per submap anchor, ``"scan"``: one per scan).

Odometry noise (the paper gives the cost but not the weights): an edge of length ``d`` metres
gets sigmas ``sigma_per_m * sqrt(max(d, MIN_EDGE_LENGTH_M) / 1 m)``: variances add along the
chain (a random walk), so a 1 m stretch has the configured sigma whether it is cut into 1 or
100 edges, and the optimiser spreads a correction in proportion to the distance travelled,
which is how scale drift along the corridor accumulates. (Sigma proportional to ``d`` would
make a scan-granularity chain 10x stiffer than a submap one with 100 scans per metre, and
would bend long edges more than short ones.) Across its direction of travel an edge's
translation sigma is ``graph.odom_across_sigma_ratio`` (0.1) times that
(:func:`odometry_covariances`): the walls constrain a corridor odometry sideways, and with
one isotropic sigma the landmark factors were free to tilt the whole trajectory (0.5 deg
in the simulated shield tunnel: 0.19 m vertical RMS after correction, 2 mm before).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from decod_rs.config import Config
from decod_rs.landmark_factor import (
    LandmarkTerm,
    axis_frame,
    landmark_factor_group,
    landmark_residual,
)
from decod_rs.tum import blend_poses, check_poses, interpolate_poses

FloatArray = NDArray[np.float64]

#: Edges shorter than this (a robot standing still) are weighted as if this long, so no
#: sigma is zero. 1 mm: well below a pipe crawler's 1 cm per 10 Hz scan.
MIN_EDGE_LENGTH_M = 1e-3

#: Sigma of the prior that anchors the first pose (rad and m): the gauge freedom of the graph,
#: fixed at the odometry's start.
PRIOR_SIGMA = 1e-6

LOOP_FACTORS = ("five_dof", "pose3")

GRANULARITIES = ("submap", "scan")

#: Landmark factors whose poses lie in the same two blocks of this many consecutive keys go
#: into one GTSAM factor (:func:`add_landmark_factors`). Inside GTSAM's optimisers each call
#: of a Python factor copies every pose of the graph, so an iteration costs the graph's size
#: times its Python factors: 400 m of pipe (1,711 poses, 2,784 factors) took 1.5 s an LM
#: iteration. A factor on up to 16 poses joins them in one clique of the elimination
#: (96 unknowns), still small beside the calls it saves.
LOOP_GROUP_KEYS = 8

__all__ = [
    "GRANULARITIES",
    "LOOP_FACTORS",
    "CorrectionResult",
    "GraphResult",
    "LoopConstraint",
    "add_landmark_factors",
    "blend_fractions",
    "build_graph",
    "correct_trajectory",
    "loop_noise_sigmas",
    "odometry_sigmas",
    "optimize",
    "propagate_to_scans",
]


@dataclass(frozen=True, eq=False)
class LoopConstraint:
    """One verified landmark pair: indices into the pose list given to ``optimize`` and the
    boundary geometry each pose observed, in that pose's body frame.

    ``query_origin``/``db_origin``: (3,) contour centres at the boundary, metres;
    ``query_axis``/``db_axis``: (3,) unit corridor axes (their signs need not agree);
    ``inliers``/``score``: the verification result (kept for reports and exports);
    ``kind``: ``"loop"`` (between passes) or ``"sequential"`` (two views of one boundary
    within a pass, :mod:`decod_rs.sequential`); ``sigma_m``: the position sigma of this
    factor along the corridor axis, metres (None: ``graph.landmark_position_sigma_m``);
    ``sigma_transverse_m``: across it (None: the same as along); ``sigma_vertical_m``: across
    it vertically, over ``sigma_transverse_m`` (None: that; :mod:`decod_rs.cross_axis`). The
    five-DoF factor applies them in the query landmark's axis frame
    (:func:`decod_rs.landmark_factor.axis_frame`).
    """

    query_index: int
    db_index: int
    query_origin: FloatArray
    query_axis: FloatArray
    db_origin: FloatArray
    db_axis: FloatArray
    inliers: int = 0
    score: float = 0.0
    kind: str = "loop"
    sigma_m: float | None = None
    sigma_transverse_m: float | None = None
    sigma_vertical_m: float | None = None

    def __post_init__(self) -> None:
        for name in ("query_origin", "query_axis", "db_origin", "db_axis"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"LoopConstraint.{name}: expected a finite (3,) vector, got {v}")
            if name.endswith("axis"):
                n = float(np.linalg.norm(v))
                if n < 1e-9:
                    raise ValueError(f"LoopConstraint.{name}: zero axis")
                v = v / n
            object.__setattr__(self, name, v)
        if self.query_index == self.db_index:
            raise ValueError(f"LoopConstraint: query and db are both pose {self.query_index}")
        for name in ("sigma_m", "sigma_transverse_m", "sigma_vertical_m"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"LoopConstraint.{name}: expected > 0 metres, got {v}")

    def sigmas(self, cfg: Config) -> FloatArray:
        """This factor's noise sigmas (:func:`loop_noise_sigmas` with ``sigma_m`` and, for
        the five-DoF factor, ``sigma_transverse_m`` and ``sigma_vertical_m``: ``[along,
        lateral, vertical, axis]``)."""
        out = loop_noise_sigmas(cfg).copy()
        if self.sigma_m is not None:
            # five_dof: [pos x3, axis]; pose3: [rot x3, pos x3].
            position = slice(3, 6) if cfg.loop_factor == "pose3" else slice(0, 3)
            out[position] = self.sigma_m
        if self.sigma_transverse_m is not None and cfg.loop_factor != "pose3":
            out[1:3] = self.sigma_transverse_m
        if self.sigma_vertical_m is not None and cfg.loop_factor != "pose3":
            out[2] = self.sigma_vertical_m  # axis_frame's rows: along, lateral, vertical
        return out


@dataclass
class GraphResult:
    """What ``optimize`` returns.

    ``poses`` (N, 4, 4) optimised ``world_from_body`` (the input itself, copied bit for bit,
    when there is no loop); ``iterations`` of LM; ``initial_error``/``final_error`` the
    graph's cost (0.5 * sum of squared whitened, robustified residuals); ``time_s`` wall time
    of building and solving; ``loop_residuals`` (L, 4) the 5-DoF residual
    ``[r (m), delta]`` of every loop at the optimised poses; ``loop_weights`` (L,) the Huber
    weight each loop factor ended with (1 = inlier, ``k / e`` beyond the threshold).
    """

    poses: FloatArray
    iterations: int = 0
    initial_error: float = 0.0
    final_error: float = 0.0
    time_s: float = 0.0
    loop_factor: str = "five_dof"
    loop_residuals: FloatArray = field(default_factory=lambda: np.zeros((0, 4)))
    loop_weights: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass
class CorrectionResult:
    """What ``correct_trajectory`` returns: ``poses`` (M, 4, 4) corrected scan poses,
    ``node_stamps`` (N,) the stamps of the graph's nodes, and the ``graph`` result on them."""

    poses: FloatArray
    node_stamps: FloatArray
    graph: GraphResult


def _check_cfg(cfg: Config) -> None:
    if cfg.loop_factor not in LOOP_FACTORS:
        raise ValueError(f"graph.loop_factor: {cfg.loop_factor!r} is not one of {LOOP_FACTORS}")
    if cfg.granularity not in GRANULARITIES:
        raise ValueError(f"graph.granularity: {cfg.granularity!r} is not one of {GRANULARITIES}")


def odometry_sigmas(
    poses: FloatArray, cfg: Config, factors: FloatArray | None = None
) -> FloatArray:
    """(N-1, 6) GTSAM-ordered sigmas ``[rot (rad) x3, trans (m) x3]`` of the odometry edges
    between consecutive ``poses`` (N, 4, 4) (random-walk model, see the module doc)."""
    d = np.linalg.norm(np.diff(poses[:, :3, 3], axis=0), axis=1)
    root = np.sqrt(np.maximum(d, MIN_EDGE_LENGTH_M))
    rot = cfg.odom_rotation_sigma_per_m * root
    trans = cfg.odom_translation_sigma_per_m * root
    sig = np.column_stack([rot, rot, rot, trans, trans, trans])
    return sig if factors is None else sig * np.asarray(factors, dtype=np.float64)[:, None]


def odometry_covariances(
    poses: FloatArray, cfg: Config, factors: FloatArray | None = None
) -> FloatArray:
    """(N-1, 6, 6) GTSAM-ordered covariances of the odometry edges: the rotation as in
    :func:`odometry_sigmas`; the translation's sigma along the edge's own direction of travel
    (in the body frame of its first pose) as there, and ``graph.odom_across_sigma_ratio``
    times it across (module docs). An edge shorter than ``MIN_EDGE_LENGTH_M`` has no
    direction: isotropic."""
    sig = odometry_sigmas(poses, cfg, factors)
    rel = _inverse(poses[:-1]) @ poses[1:]
    t = rel[:, :3, 3]
    d = np.linalg.norm(t, axis=1)
    cov = np.zeros((sig.shape[0], 6, 6))
    cov[:, [0, 1, 2], [0, 1, 2]] = sig[:, :3] ** 2
    along = sig[:, 3] ** 2
    across = (float(cfg.odom_across_sigma_ratio) * sig[:, 3]) ** 2
    u = np.where((d > MIN_EDGE_LENGTH_M)[:, None], t / np.maximum(d, 1e-12)[:, None], 0.0)
    outer = np.einsum("ni,nj->nij", u, u)
    cov[:, 3:, 3:] = across[:, None, None] * np.eye(3) + (along - across)[:, None, None] * outer
    short = d <= MIN_EDGE_LENGTH_M
    cov[short, 3:, 3:] = along[short, None, None] * np.eye(3)
    return cov


def loop_noise_sigmas(cfg: Config) -> FloatArray:
    """Sigmas of a loop factor: (4,) ``[pos x3 (m), axis]`` for ``five_dof``; (6,)
    ``[rot x3 (rad), pos x3 (m)]`` for ``pose3``, where the rotation sigma is
    ``sqrt(landmark_axis_sigma)``, the angle at which the 5-DoF axis term (``sin^2 theta``)
    reaches one sigma, so both factor types weigh a tilt alike (paper §IV-D keeps the
    weights unchanged across the ablation)."""
    pos = cfg.landmark_position_sigma_m
    if cfg.loop_factor == "pose3":
        rot = float(np.sqrt(cfg.landmark_axis_sigma))
        return np.array([rot, rot, rot, pos, pos, pos])
    return np.array([pos, pos, pos, cfg.landmark_axis_sigma])


def _robust(sigmas: FloatArray, k: float) -> gtsam.noiseModel.Base:
    return gtsam.noiseModel.Robust.Create(
        gtsam.noiseModel.mEstimator.Huber.Create(k), gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    )


def _check_loops(loops: Sequence[LoopConstraint], n: int) -> None:
    for k, lc in enumerate(loops):
        for name in ("query_index", "db_index"):
            idx = getattr(lc, name)
            if not 0 <= idx < n:
                raise ValueError(f"loop {k}: {name} {idx} outside the {n} poses")


def _pose3_measurement(poses: FloatArray, lc: LoopConstraint) -> gtsam.Pose3:
    """The Pose3 ablation's relative pose (§IV-D): rotation from odometry, translation
    chosen so that the landmark origins coincide, ``t = c_i - R_ij c_j`` (r = 0)."""
    ti, tj = poses[lc.query_index], poses[lc.db_index]
    r_ij = ti[:3, :3].T @ tj[:3, :3]
    m = np.eye(4)
    m[:3, :3] = r_ij
    m[:3, 3] = lc.query_origin - r_ij @ lc.db_origin
    return gtsam.Pose3(m)


def _add_odometry(
    graph: gtsam.NonlinearFactorGraph,
    p: FloatArray,
    cfg: Config,
    factors: FloatArray | None = None,
) -> None:
    cov = odometry_covariances(p, cfg, factors)
    rel = _inverse(p[:-1]) @ p[1:]
    for k in range(p.shape[0] - 1):
        graph.add(
            gtsam.BetweenFactorPose3(
                k, k + 1, gtsam.Pose3(rel[k]), gtsam.noiseModel.Gaussian.Covariance(cov[k])
            )
        )


def _add_attitude(
    graph: gtsam.NonlinearFactorGraph,
    p: FloatArray,
    keys: Sequence[int],
    cfg: Config,
) -> None:
    """Per pose, its gravity direction as the odometry has it (module docs): an
    ``AttitudeFactorPose3`` on roll and pitch, yaw and position free."""
    down = np.array([0.0, 0.0, -1.0])
    model = gtsam.noiseModel.Isotropic.Sigma(2, float(cfg.odom_attitude_sigma_rad))
    for key, pose in zip(keys, p, strict=True):
        body = pose[:3, :3].T @ down
        graph.add(gtsam.AttitudeFactorPose3(int(key), gtsam.Unit3(down), model, gtsam.Unit3(body)))


def _add_loops(
    graph: gtsam.NonlinearFactorGraph,
    p: FloatArray,
    loops: Sequence[LoopConstraint],
    cfg: Config,
    index: dict[int, int] | None = None,
) -> None:
    """The robust loop factors, on keys ``index[pose index]`` (identity if None): one
    ``BetweenFactorPose3`` per loop for ``pose3``, grouped 5-DoF ones for ``five_dof``
    (:func:`add_landmark_factors`)."""
    terms: list[LandmarkTerm] = []
    for lc in loops:
        qi, di = lc.query_index, lc.db_index
        ki, kj = (qi, di) if index is None else (index[qi], index[di])
        if cfg.loop_factor == "pose3":
            noise = _robust(lc.sigmas(cfg), cfg.huber_k)
            graph.add(gtsam.BetweenFactorPose3(ki, kj, _pose3_measurement(p, lc), noise))
            continue
        term = LandmarkTerm(
            ki,
            kj,
            np.asarray(lc.query_origin, dtype=np.float64),
            np.asarray(lc.query_axis, dtype=np.float64),
            np.asarray(lc.db_origin, dtype=np.float64),
            np.asarray(lc.db_axis, dtype=np.float64),
            axis_frame(lc.query_axis),
            lc.sigmas(cfg),
        )
        terms.append(term)
    add_landmark_factors(graph, terms, float(cfg.huber_k))


def add_landmark_factors(
    graph: gtsam.NonlinearFactorGraph, terms: Sequence[LandmarkTerm], huber_k: float
) -> None:
    """Landmark factors, Huber-robust each, those whose two keys fall in the same two blocks
    of ``LOOP_GROUP_KEYS`` consecutive keys as one GTSAM factor
    (:func:`~decod_rs.landmark_factor.landmark_factor_group`: the same error and steps as
    one factor each, at a fraction of the calls): the run's graph and a re-inspection's."""
    groups: dict[tuple[int, int], list[LandmarkTerm]] = {}
    for t in terms:
        blocks = sorted((t.key_i // LOOP_GROUP_KEYS, t.key_j // LOOP_GROUP_KEYS))
        groups.setdefault((blocks[0], blocks[1]), []).append(t)
    for group in groups.values():
        graph.add(landmark_factor_group(group, huber_k))


def build_graph(
    poses: ArrayLike,
    loops: Sequence[LoopConstraint],
    cfg: Config,
    sigma_factors: FloatArray | None = None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The full factor graph and initial values (keys ``0..N-1`` = pose indices): a prior on
    pose 0, ``BetweenFactorPose3`` odometry edges, then one robust loop factor per loop (in
    order), five-DoF or Pose3 according to ``cfg.loop_factor``."""
    _check_cfg(cfg)
    p = check_poses(poses)
    _check_loops(loops, p.shape[0])
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(p.shape[0]):
        values.insert(k, gtsam.Pose3(p[k]))
    graph.add(
        gtsam.PriorFactorPose3(
            0, gtsam.Pose3(p[0]), gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
        )
    )
    _add_odometry(graph, p, cfg, sigma_factors)
    _add_attitude(graph, p, range(p.shape[0]), cfg)
    _add_loops(graph, p, loops, cfg)
    return graph, values


def _lm(
    graph: gtsam.NonlinearFactorGraph, initial: gtsam.Values, cfg: Config
) -> tuple[gtsam.Values, int]:
    params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(int(cfg.max_iterations))
    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    values = optimizer.optimize()
    return values, int(optimizer.iterations())


def _adjoint(t: FloatArray) -> FloatArray:
    """(..., 6, 6) adjoints of (..., 4, 4) poses in GTSAM's ``[w, v]`` order."""
    r = t[..., :3, :3]
    out = np.zeros((*t.shape[:-2], 6, 6))
    out[..., :3, :3] = r
    out[..., 3:, 3:] = r
    p = t[..., :3, 3]
    skew = np.zeros((*t.shape[:-2], 3, 3))
    skew[..., 0, 1], skew[..., 0, 2] = -p[..., 2], p[..., 1]
    skew[..., 1, 0], skew[..., 1, 2] = p[..., 2], -p[..., 0]
    skew[..., 2, 0], skew[..., 2, 1] = -p[..., 1], p[..., 0]
    out[..., 3:, :3] = skew @ r
    return out


def _reduced_graph(
    p: FloatArray,
    kept: NDArray[np.int64],
    loops: Sequence[LoopConstraint],
    cfg: Config,
    sigma_factors: FloatArray | None = None,
) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    """The graph on the ``kept`` poses only: the odometry between consecutive kept poses
    compounded into one edge whose covariance is the first-order sum of the edge covariances
    carried to the segment's end, ``sum_k Ad(X_k) S_k Ad(X_k)^T`` with ``X_k = T_end^-1
    T_{k+1}`` (noise is a right perturbation ``Z Exp(eps)``, as in GTSAM's between error):
    the exact marginal of the linearised chain, because no loop touches a dropped pose."""
    edge_cov = odometry_covariances(p, cfg, sigma_factors)
    edges = np.arange(p.shape[0] - 1)
    seg_end = kept[np.searchsorted(kept, edges, side="right")]
    x = _inverse(p[seg_end]) @ p[edges + 1]
    ad = _adjoint(x)
    contrib = np.einsum("nij,njl,nkl->nik", ad, edge_cov, ad)
    cov = np.add.reduceat(contrib, kept[:-1], axis=0)
    index = {int(k): n for n, k in enumerate(kept)}
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    pose3s = [gtsam.Pose3(p[k]) for k in kept]
    for n, pk in enumerate(pose3s):
        values.insert(n, pk)
    graph.add(
        gtsam.PriorFactorPose3(0, pose3s[0], gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA))
    )
    for n in range(len(kept) - 1):
        graph.add(
            gtsam.BetweenFactorPose3(
                n,
                n + 1,
                pose3s[n].between(pose3s[n + 1]),
                gtsam.noiseModel.Gaussian.Covariance(cov[n]),
            )
        )
    _add_attitude(graph, p[kept], range(len(kept)), cfg)
    _add_loops(graph, p, loops, cfg, index)
    return graph, values


def _fill_chain(
    p: FloatArray,
    kept: NDArray[np.int64],
    kept_opt: FloatArray,
    cfg: Config,
    sigma_factors: FloatArray | None = None,
) -> tuple[gtsam.Values, int]:
    """Every pose given the optimised ``kept`` ones: the odometry chain with the kept poses
    pinned (the dropped poses' exact conditional optimum; only C++ factors, so fast),
    started from the stamp-wise propagation of the kept corrections."""
    idx = np.arange(p.shape[0], dtype=np.float64)
    start = propagate_to_scans(idx, p, kept.astype(np.float64), p[kept], kept_opt)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    for k in range(p.shape[0]):
        values.insert(k, gtsam.Pose3(start[k]))
    pin = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    for n, k in enumerate(kept):
        graph.add(gtsam.PriorFactorPose3(int(k), gtsam.Pose3(kept_opt[n]), pin))
    _add_odometry(graph, p, cfg, sigma_factors)
    return _lm(graph, values, cfg)


def _edge_factors(sigma_factors: ArrayLike | None, n: int) -> FloatArray | None:
    """Per odometry edge (N-1,), the factor on its sigmas from per-pose factors (N,): the
    larger of its two ends; None stays None."""
    if sigma_factors is None:
        return None
    f = np.asarray(sigma_factors, dtype=np.float64)
    if f.shape != (n,) or not np.all(np.isfinite(f) & (f > 0)):
        raise ValueError(f"sigma_factors: expected ({n},) positive factors, got {f.shape}")
    return np.maximum(f[:-1], f[1:])


def optimize(
    poses: ArrayLike,
    loops: Sequence[LoopConstraint],
    cfg: Config,
    reduce: bool = True,
    sigma_factors: ArrayLike | None = None,
) -> GraphResult:
    """Optimise ``poses`` (N, 4, 4) ``world_from_body`` odometry with ``loops`` (indices
    into ``poses``) under ``cfg`` (``load_config(...).graph``).

    No loop: the odometry comes back unchanged, bit for bit (paper Alg. 1, line "keep
    X* = X_odom if L is empty"), with zero iterations.

    ``reduce`` (default): GTSAM hands a Python factor a *copy* of all the Values at every
    call, so a CustomFactor costs O(N): a 10,000-pose graph with 500 of them took 46.5 s
    (11 LM iterations, ``tests/benchmarks`` corridor, 2 cores) against 2.1 s reduced.
    Instead, LM first solves the graph on the poses the loops touch (plus the first and
    last), with the odometry between them compounded (``_reduced_graph``), then fills in
    the other poses with the pinned odometry chain (``_fill_chain``, C++ factors only). The
    result matches the full graph to first order (same marginal); ``tests/test_graph.py``
    checks the two agree within 1 mm on the corridor. ``reduce=False`` runs LM on the full
    graph.
    """
    _check_cfg(cfg)
    p = check_poses(poses)
    _check_loops(loops, p.shape[0])
    if not loops:
        return GraphResult(poses=p.copy(), loop_factor=cfg.loop_factor)
    start = time.perf_counter()
    factors = _edge_factors(sigma_factors, p.shape[0])
    graph, initial = build_graph(p, loops, cfg, factors)
    kept = np.unique(
        np.array(
            [0, p.shape[0] - 1] + [lc.query_index for lc in loops] + [lc.db_index for lc in loops],
            dtype=np.int64,
        )
    )
    if reduce and kept.size < p.shape[0]:
        small, small_init = _reduced_graph(p, kept, loops, cfg, factors)
        small_values, iterations = _lm(small, small_init, cfg)
        kept_opt = np.stack([small_values.atPose3(n).matrix() for n in range(kept.size)])
        values, _ = _fill_chain(p, kept, kept_opt, cfg, factors)
    else:
        values, iterations = _lm(graph, initial, cfg)
    out = np.stack([values.atPose3(k).matrix() for k in range(p.shape[0])])
    elapsed = time.perf_counter() - start

    residuals = np.zeros((len(loops), 4))
    weights = np.ones(len(loops))
    for n, lc in enumerate(loops):
        sigmas = lc.sigmas(cfg)
        residuals[n], _, _ = landmark_residual(
            out[lc.query_index],
            out[lc.db_index],
            lc.query_origin,
            lc.query_axis,
            lc.db_origin,
            lc.db_axis,
        )
        e = float(np.linalg.norm(_factor_residual(out, p, lc, cfg) / sigmas))
        weights[n] = 1.0 if e <= cfg.huber_k else cfg.huber_k / e
    return GraphResult(
        poses=out,
        iterations=iterations,
        initial_error=float(graph.error(initial)),
        final_error=float(graph.error(values)),
        time_s=elapsed,
        loop_factor=cfg.loop_factor,
        loop_residuals=residuals,
        loop_weights=weights,
    )


def _factor_residual(
    poses: FloatArray, odometry: FloatArray, lc: LoopConstraint, cfg: Config
) -> FloatArray:
    """The unwhitenedError of ``lc``'s factor at ``poses`` (its Huber weight follows from its
    norm once whitened by its sigmas): the 5-DoF residual with its position rows along and
    across the axis, or the ``pose3`` between error against the measurement the graph made
    from the ``odometry``."""
    ti, tj = poses[lc.query_index], poses[lc.db_index]
    if cfg.loop_factor == "pose3":
        factor = gtsam.BetweenFactorPose3(
            0, 1, _pose3_measurement(odometry, lc), gtsam.noiseModel.Unit.Create(6)
        )
        values = gtsam.Values()
        values.insert(0, gtsam.Pose3(ti))
        values.insert(1, gtsam.Pose3(tj))
        return np.asarray(factor.unwhitenedError(values), dtype=np.float64)
    res, _, _ = landmark_residual(
        ti,
        tj,
        lc.query_origin,
        lc.query_axis,
        lc.db_origin,
        lc.db_axis,
        frame=axis_frame(lc.query_axis),
    )
    return res


def _inverse(t: FloatArray) -> FloatArray:
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def _fraction(value: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    span = hi - lo
    out = np.where(span > 0.0, (value - lo) / np.where(span > 0.0, span, 1.0), 0.0)
    return np.clip(out, 0.0, 1.0)


def blend_fractions(
    scan_stamps: FloatArray,
    scan_odom: FloatArray,
    node_stamps: FloatArray,
    node_optimised: FloatArray,
    k: NDArray[np.int64],
    k1: NDArray[np.int64],
) -> FloatArray:
    """How far each scan lies from node ``k`` towards node ``k1`` (0-1), for
    :func:`propagate_to_scans`: the fraction of the odometry's travel between the two nodes.

    A correction is mostly a scale or heading error of the odometry, and that accrues with
    the distance driven, not with time: blended by stamp, the correction between an anchor at
    rest and the next one leaked into the rest, and a robot standing still at the start of the
    simulated horseshoe crept 1.3 cm forward in its corrected trajectory (m95,
    horseshoe-spin64-reverse-s0 under uneven drift), and the corrected path 6 m in was up to
    2.1 cm longer than its straight extent (median 0.1 cm over the matrix's 100 runs; now at
    most 0.17 cm), which the joint registry's chainage counts. Matrix m99 against m95 (the
    same logs): corrected RMSE geometric mean x0.971, far end within 1 % in 97 of 98 rows
    instead of 96, loops unchanged (11,337, none wrong). Where the odometry saw less than half
    the corrected motion between the two nodes (a frontend stalling along the axis), its
    travel says nothing of where the motion happened and the stamp fraction is used."""
    # The odometry's path length in time order (the scans need not be given sorted).
    order = np.argsort(scan_stamps, kind="stable")
    steps = np.linalg.norm(np.diff(scan_odom[order, :3, 3], axis=0), axis=1)
    travel_sorted = np.concatenate([[0.0], np.cumsum(steps)])
    travel = np.empty_like(travel_sorted)
    travel[order] = travel_sorted
    node_travel = np.interp(node_stamps, scan_stamps[order], travel_sorted)
    odom_span = node_travel[k1] - node_travel[k]
    corrected_span = np.linalg.norm(node_optimised[k1, :3, 3] - node_optimised[k, :3, 3], axis=1)
    by_time = _fraction(scan_stamps, node_stamps[k], node_stamps[k1])
    by_travel = _fraction(travel, node_travel[k], node_travel[k1])
    seen = (odom_span > 0.0) & (odom_span >= 0.5 * corrected_span)
    return np.where(seen, by_travel, by_time)


def propagate_to_scans(
    scan_stamps: ArrayLike,
    scan_odom_poses: ArrayLike,
    node_stamps: ArrayLike,
    node_odom: ArrayLike,
    node_optimised: ArrayLike,
) -> FloatArray:
    """Corrected poses (M, 4, 4) for every scan from a graph solved on fewer nodes.

    A scan between nodes ``k`` and ``k+1`` (by stamp) gets two estimates that each keep its
    odometry relative to one node, ``A = T*_k (T_k)^-1 T_s`` and ``B = T*_{k+1} (T_{k+1})^-1
    T_s``, blended in SE(3) with the fraction of the way between the nodes
    (:func:`blend_fractions`: by the odometry's travel, or by stamp where the odometry did
    not see the motion): at a node the scan sits exactly on the node's correction, and the
    trajectory is continuous in between. Scans before the first or after the last node keep
    their odometry relative to that node. If the optimised nodes equal the odometry nodes,
    the scan odometry comes back unchanged, bit for bit.
    """
    s_odom = check_poses(scan_odom_poses, "scan_odom_poses")
    n_odom = check_poses(node_odom, "node_odom")
    n_opt = check_poses(node_optimised, "node_optimised")
    s_st = np.asarray(scan_stamps, dtype=np.float64)
    n_st = np.asarray(node_stamps, dtype=np.float64)
    if s_st.shape != (s_odom.shape[0],):
        raise ValueError(f"scan_stamps: expected ({s_odom.shape[0]},), got {s_st.shape}")
    if n_st.shape != (n_odom.shape[0],) or n_opt.shape != n_odom.shape or n_st.size == 0:
        raise ValueError(
            f"node_stamps {n_st.shape}, node_odom {n_odom.shape} and node_optimised "
            f"{n_opt.shape} must describe the same N >= 1 nodes"
        )
    if n_st.size > 1 and np.any(np.diff(n_st) <= 0.0):
        raise ValueError("node_stamps must be strictly increasing")
    if np.array_equal(n_odom, n_opt):
        return s_odom.copy()
    correction = n_opt @ _inverse(n_odom)  # (N, 4, 4) world-from-world per node
    k = np.clip(np.searchsorted(n_st, s_st, side="right") - 1, 0, n_st.size - 1)
    k1 = np.minimum(k + 1, n_st.size - 1)
    alpha = blend_fractions(s_st, s_odom, n_st, n_opt, k, k1)
    a = correction[k] @ s_odom
    b = correction[k1] @ s_odom
    return blend_poses(a, b, alpha)


def _remap_loops(
    loops: Sequence[LoopConstraint],
    anchor_stamps: FloatArray,
    anchor_odom: FloatArray,
    node_stamps: FloatArray,
    node_odom: FloatArray,
) -> list[LoopConstraint]:
    """Loops indexed by anchors -> loops indexed by the nearest node, with the landmark
    geometry moved from the anchor's body frame into the node's through the odometry."""
    out = []
    for lc in loops:
        idx = []
        geo = []
        for a_idx, origin, axis in (
            (lc.query_index, lc.query_origin, lc.query_axis),
            (lc.db_index, lc.db_origin, lc.db_axis),
        ):
            n = int(np.argmin(np.abs(node_stamps - anchor_stamps[a_idx])))
            node_from_anchor = _inverse(node_odom[n]) @ anchor_odom[a_idx]
            idx.append(n)
            geo.append(
                (
                    node_from_anchor[:3, :3] @ origin + node_from_anchor[:3, 3],
                    node_from_anchor[:3, :3] @ axis,
                )
            )
        out.append(
            LoopConstraint(
                query_index=idx[0],
                db_index=idx[1],
                query_origin=geo[0][0],
                query_axis=geo[0][1],
                db_origin=geo[1][0],
                db_axis=geo[1][1],
                inliers=lc.inliers,
                score=lc.score,
                kind=lc.kind,
                sigma_m=lc.sigma_m,
                sigma_transverse_m=lc.sigma_transverse_m,
                sigma_vertical_m=lc.sigma_vertical_m,
            )
        )
    return out


def correct_trajectory(
    scan_stamps: ArrayLike,
    scan_odom: ArrayLike,
    anchor_stamps: ArrayLike,
    loops: Sequence[LoopConstraint],
    cfg: Config,
    sigma_factors: ArrayLike | None = None,
) -> CorrectionResult:
    """Optimise at ``cfg.granularity`` and give every scan a corrected pose.

    ``scan_stamps`` (M,), ``scan_odom`` (M, 4, 4): the odometry at every scan;
    ``anchor_stamps`` (A,): the submap anchor stamps, inside the scan time span; ``loops``
    index into ``anchor_stamps`` with landmark geometry in the anchors' body frames.
    ``"submap"``: one node per anchor (odometry interpolated at the anchor stamps);
    ``"scan"``: one node per scan (each loop moved to the scan nearest its anchor).
    ``sigma_factors`` (M,): a factor per scan on the odometry sigmas (an edge takes the
    larger of its ends'), e.g. to trust a pass whose scale was not measured less.
    No loop: ``poses`` is ``scan_odom``, bit for bit.
    """
    _check_cfg(cfg)
    s_odom = check_poses(scan_odom, "scan_odom")
    s_st = np.asarray(scan_stamps, dtype=np.float64)
    a_st = np.asarray(anchor_stamps, dtype=np.float64)
    if a_st.ndim != 1:
        raise ValueError(f"anchor_stamps: expected (A,), got {a_st.shape}")
    _check_loops(loops, a_st.size)
    if not loops:
        return CorrectionResult(
            poses=s_odom.copy(),
            node_stamps=a_st.copy() if cfg.granularity == "submap" else s_st.copy(),
            graph=GraphResult(poses=s_odom.copy(), loop_factor=cfg.loop_factor),
        )
    a_odom = interpolate_poses(s_st, s_odom, a_st)
    if cfg.granularity == "scan":
        node_st, node_odom = s_st, s_odom
        node_loops = _remap_loops(loops, a_st, a_odom, s_st, s_odom)
    else:
        node_st, node_odom, node_loops = a_st, a_odom, list(loops)
    node_factors = None
    if sigma_factors is not None:
        f = np.asarray(sigma_factors, dtype=np.float64)
        if f.shape != s_st.shape:
            raise ValueError(f"sigma_factors: expected one per scan {s_st.shape}, got {f.shape}")
        nearest = np.clip(np.searchsorted(s_st, node_st), 0, s_st.size - 1)
        node_factors = f[nearest]
    result = optimize(node_odom, node_loops, cfg, sigma_factors=node_factors)
    poses = propagate_to_scans(s_st, s_odom, node_st, node_odom, result.poses)
    return CorrectionResult(poses=poses, node_stamps=node_st.copy(), graph=result)
