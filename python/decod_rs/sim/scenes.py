"""Scene registry: each scene's builder, its parameters and its defaults (sensor, speed,
length, return mode, sensor mount, wobble).

Geometry overrides (``scene_overrides``) change the builder's parameter dict; the sensor mount
follows the section (:func:`defaults_for`): in a pipe the crawler's sensor height and its
lateral/vertical wobble scale with the radius; in a tunnel the vehicle keeps its sensor height
above the floor (1.6 m), capped at half the floor-to-crown height of a small section.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from decod_rs.sim.pipes import HUME_PARAMS, PE_PARAMS, build_hume, build_pe, hume_params, pe_params
from decod_rs.sim.surface import Scene
from decod_rs.sim.tunnels import (
    HORSESHOE_PARAMS,
    SHIELD_PARAMS,
    build_horseshoe,
    build_shield,
    horseshoe_params,
    shield_params,
)

Builder = Callable[[np.random.Generator, float, float, bool, dict[str, Any] | None], Scene]
ParamsFn = Callable[[dict[str, Any] | None], dict[str, Any]]

#: Per scene: the builder's default parameters and the function applying overrides to them.
PARAMS: dict[str, tuple[dict[str, Any], ParamsFn]] = {
    "hume": (HUME_PARAMS, hume_params),
    "pe": (PE_PARAMS, pe_params),
    "shield": (SHIELD_PARAMS, shield_params),
    "horseshoe": (HORSESHOE_PARAMS, horseshoe_params),
}


@dataclass(frozen=True)
class SceneDefaults:
    """Defaults of one scene. ``z0_m`` is the sensor's nominal height in the world (the
    section centre is at z = 0); the run starts at ``x_start_m`` and the corridor extends
    ``beyond_m`` past the far end of the run (then a cap)."""

    builder: Builder
    sensor: str
    speed_mps: float
    length_m: float
    return_mode: str
    x_start_m: float
    z0_m: float
    beyond_m: float
    lateral_m: float
    vertical_m: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    wobble_wavelength_m: float


SCENES: dict[str, SceneDefaults] = {
    "hume": SceneDefaults(
        build_hume,
        "avia",
        0.4,
        60.0,
        "reverse",
        0.5,
        -0.03,
        15.0,
        0.01,
        0.005,
        0.03,
        0.008,
        0.01,
        3.0,
    ),
    "pe": SceneDefaults(
        build_pe,
        "avia",
        0.4,
        60.0,
        "reverse",
        0.5,
        -0.02,
        15.0,
        0.008,
        0.004,
        0.03,
        0.008,
        0.01,
        3.0,
    ),
    "shield": SceneDefaults(
        build_shield,
        "spin16",
        1.5,
        120.0,
        "turn",
        2.0,
        -0.4,
        40.0,
        0.05,
        0.02,
        0.01,
        0.01,
        0.02,
        10.0,
    ),
    "horseshoe": SceneDefaults(
        build_horseshoe,
        "spin16",
        1.2,
        100.0,
        "turn",
        2.0,
        0.1,
        40.0,
        0.05,
        0.02,
        0.01,
        0.01,
        0.02,
        10.0,
    ),
}


def scene_defaults(name: str) -> SceneDefaults:
    if name not in SCENES:
        raise ValueError(f"unknown scene {name!r}; choose one of {sorted(SCENES)}")
    return SCENES[name]


def scene_params(name: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """The builder's parameters of scene ``name`` with ``overrides`` applied (``ValueError``
    naming an unknown key and listing the valid ones)."""
    scene_defaults(name)
    return PARAMS[name][1](overrides)


def defaults_for(name: str, params: dict[str, Any]) -> SceneDefaults:
    """``name``'s defaults with the sensor mount adapted to the section in ``params`` (module
    doc): pipes scale ``z0_m``, ``lateral_m`` and ``vertical_m`` with the radius; tunnels keep
    the sensor's height above the floor, at most half the floor-to-crown height."""
    base = scene_defaults(name)
    nominal = PARAMS[name][0]
    radius = float(params["radius_m"])
    if all(params.get(k) == nominal[k] for k in ("radius_m", "floor_z_m") if k in nominal):
        return base  # the nominal section: the defaults exactly
    if "floor_z_m" not in nominal:
        ratio = radius / float(nominal["radius_m"])
        return replace(
            base,
            z0_m=base.z0_m * ratio,
            lateral_m=base.lateral_m * ratio,
            vertical_m=base.vertical_m * ratio,
        )
    floor = float(params["floor_z_m"])
    height = min(base.z0_m - float(nominal["floor_z_m"]), 0.5 * (radius - floor))
    return replace(base, z0_m=floor + height)


def build_scene(
    name: str,
    seed: int,
    x_max_m: float,
    distinctiveness: float = 1.0,
    identical_joints: bool = False,
    overrides: dict[str, Any] | None = None,
) -> Scene:
    """Build scene ``name`` out to ``x_max_m`` (world x) with its own seeded generator;
    ``overrides`` change the builder's parameters (:func:`scene_params`)."""
    if not np.isfinite(distinctiveness) or distinctiveness < 0.0:
        raise ValueError(f"distinctiveness must be >= 0, got {distinctiveness}")
    scene_params(name, overrides)  # validate before drawing anything
    rng = np.random.default_rng([seed, 1])
    builder = scene_defaults(name).builder
    return builder(rng, x_max_m, distinctiveness, identical_joints, overrides)
