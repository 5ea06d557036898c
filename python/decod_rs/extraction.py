"""Descriptor extraction (paper section III-A): submaps, corridor axis, contour, boundaries
and DeCOD descriptors, computed in the Rust core with the GIL released.

Shapes: points are ``(N, 3)`` float64 metres; poses ``(K, 4, 4)`` homogeneous
``world_from_body`` matrices; vectors ``(3,)``. Every function takes ``config``: a
``decod_rs.Config`` (from ``load_config``) or a preset name (``"tunnel"``, ``"pipe"``).

Conventions (see ``decod::descriptor``): ``Landmark.descriptor`` is ``(rows, cols)``; row ``r``
covers ``z`` from ``-H + r * cell_z_m`` along the axis from the landmark origin; column ``c``
covers normalised arclength ``p`` in ``[c / cols, (c + 1) / cols)`` from ``e1`` (gravity, the
bottom of the section) towards ``e2 = axis x e1``.
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from decod_rs import _core
from decod_rs._core import ExtractionResult, Rejection, Submap, SubmapBuilder, SubmapDiagnostics
from decod_rs.config import PRESETS, Config
from decod_rs.io import ScanRecord

__all__ = [
    "ExtractionResult",
    "Rejection",
    "Submap",
    "SubmapBuilder",
    "SubmapDiagnostics",
    "build_submap",
    "extract_landmarks",
    "extract_submap",
    "extract_submaps",
    "submap_builder",
    "submap_from_points",
]


def config_json(config: Config | str) -> str:
    """The config as the JSON the core reads: a preset name or a resolved ``Config``."""
    if isinstance(config, str):
        if config not in PRESETS:
            raise _core.ConfigError(f"invalid config `preset`: {config!r} is not one of {PRESETS}")
        return _core.resolve_config_json(config)
    if isinstance(config, Config):
        return json.dumps(config.to_dict())
    raise TypeError(f"`config` must be a decod_rs.Config or a preset name, got {type(config)}")


def _array(value: ArrayLike, name: str, shape: tuple[int | None, ...]) -> NDArray[np.float64]:
    """``value`` as float64 with ``shape`` (None = any length); errors name the argument."""
    try:
        array = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"`{name}` must be a float array of shape {_fmt(shape)}: {exc}") from None
    if array.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(array.shape, shape, strict=True)
    ):
        raise ValueError(f"`{name}` must have shape {_fmt(shape)}, got {array.shape}")
    return array


def _fmt(shape: tuple[int | None, ...]) -> str:
    names = iter("NMK")
    return "(" + ", ".join(str(s) if s is not None else next(names) for s in shape) + ")"


def submap_from_points(
    points: ArrayLike,
    *,
    stamp: float = 0.0,
    gravity: ArrayLike | None = None,
    forward: ArrayLike = (1.0, 0.0, 0.0),
) -> Submap:
    """A submap from a cloud already in one frame (no odometry, no voxel filter).

    ``points`` ``(N, 3)``; ``gravity`` ``(3,)`` the downward direction in that frame (default
    ``-z``); ``forward`` ``(3,)`` orients the axis. Non-finite or empty input raises
    ``ValueError`` naming the argument.
    """
    g = (0.0, 0.0, -1.0) if gravity is None else gravity
    return _core.submap_from_points(
        _array(points, "points", (None, 3)),
        float(stamp),
        _array(g, "gravity", (3,)),
        _array(forward, "forward", (3,)),
    )


def extract_landmarks(
    points: ArrayLike,
    *,
    stamp: float = 0.0,
    gravity: ArrayLike | None = None,
    forward: ArrayLike = (1.0, 0.0, 0.0),
    config: Config | str = "tunnel",
) -> ExtractionResult:
    """Landmarks of one cloud given in the submap frame: ``points`` ``(N, 3)`` metres.

    Returns landmarks (strongest first), rejections with reasons, and diagnostics.
    """
    submap = submap_from_points(points, stamp=stamp, gravity=gravity, forward=forward)
    return _core.extract_submap(submap, config_json(config))


def build_submap(
    stamps: ArrayLike,
    points: Sequence[ArrayLike],
    poses: ArrayLike,
    *,
    anchor_index: int | None = None,
    specific_force: ArrayLike | None = None,
    config: Config | str = "tunnel",
) -> Submap:
    """Accumulates K scans into the body frame of the anchor scan (default: the middle one).

    ``stamps`` ``(K,)`` seconds, increasing; ``points`` K arrays ``(N_k, 3)`` in each scan's
    body frame; ``poses`` ``(K, 4, 4)`` odometry ``world_from_body``; ``specific_force``
    ``(K, 3)`` mean IMU specific force per scan in its body frame (gravity is its negation),
    or None (gravity = the anchor's ``-z``). Points are motion-compensated, range-filtered
    and voxel-filtered with the ``submap`` section of ``config``.
    """
    stamps_a = _array(stamps, "stamps", (None,))
    k = len(stamps_a)
    if k == 0:
        raise ValueError("`stamps` is empty: expected shape (K,) with K >= 1")
    poses_a = _array(poses, "poses", (k, 4, 4))
    if len(points) != k:
        raise ValueError(f"`points` must hold K = len(stamps) = {k} arrays, got {len(points)}")
    clouds = [_array(p, f"points[{i}]", (None, 3)) for i, p in enumerate(points)]
    force = None if specific_force is None else _array(specific_force, "specific_force", (k, 3))
    anchor = k // 2 if anchor_index is None else int(anchor_index)
    if not 0 <= anchor < k:
        raise ValueError(f"`anchor_index` {anchor} is out of range for K = {k} scans")
    return _core.build_submap(stamps_a, clouds, poses_a, anchor, force, config_json(config))


def scans_submap(
    window: Sequence[ScanRecord], config_json: str, poses: NDArray[np.float64] | None = None
) -> Submap:
    """The submap of the scans in ``window`` (:class:`~decod_rs.io.ScanRecord`, in time
    order) anchored at the middle one, stitched on their own poses or on ``poses``
    ``(K, 4, 4)``, under config JSON ``config_json``; gravity from their IMU specific force
    when every scan has one. ``auto``'s probe windows and the focus's windows
    (:mod:`decod_rs.focus`) are built so."""
    force = [w.specific_force for w in window]
    return _core.build_submap(
        np.array([w.stamp for w in window]),
        [w.points.astype(np.float64) for w in window],
        np.stack([w.pose for w in window]) if poses is None else poses,
        len(window) // 2,
        None if any(f is None for f in force) else np.stack(force),  # type: ignore[arg-type]
        config_json,
    )


def extract_submap(submap: Submap, *, config: Config | str = "tunnel") -> ExtractionResult:
    """Runs the extraction pipeline on one submap."""
    return _core.extract_submap(submap, config_json(config))


def extract_submaps(
    submaps: Sequence[Submap], *, config: Config | str = "tunnel"
) -> list[ExtractionResult]:
    """Runs the extraction pipeline on many submaps in parallel; results in input order."""
    return _core.extract_submaps(list(submaps), config_json(config))


def submap_builder(config: Config | str = "tunnel") -> SubmapBuilder:
    """A streaming builder: ``push(stamp, points (N, 3), pose (4, 4), specific_force=None)``
    returns a ``Submap`` whenever a window of ``submap.scans_per_submap`` scans completes
    (one window every ``submap.interval_s``); ``finish()`` emits the partial last window."""
    return SubmapBuilder(config_json(config))
