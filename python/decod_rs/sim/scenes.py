"""Scene registry: each scene's builder and its defaults (sensor, speed, length, return mode,
sensor mount, wobble)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from decod_rs.sim.pipes import build_hume, build_pe
from decod_rs.sim.surface import Scene
from decod_rs.sim.tunnels import build_horseshoe, build_shield

Builder = Callable[[np.random.Generator, float, float, bool], Scene]


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


def build_scene(
    name: str,
    seed: int,
    x_max_m: float,
    distinctiveness: float = 1.0,
    identical_joints: bool = False,
) -> Scene:
    """Build scene ``name`` out to ``x_max_m`` (world x) with its own seeded generator."""
    if not np.isfinite(distinctiveness) or distinctiveness < 0.0:
        raise ValueError(f"distinctiveness must be >= 0, got {distinctiveness}")
    rng = np.random.default_rng([seed, 1])
    return scene_defaults(name).builder(rng, x_max_m, distinctiveness, identical_joints)
