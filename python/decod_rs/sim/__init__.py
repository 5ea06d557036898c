"""Synthetic corridors: a simulator that writes real ROS 2 MCAP logs with ground truth.

Scenes ``hume``, ``pe`` (pipes, Livox Avia-like sensor by default, crawler reversing back)
and ``shield``, ``horseshoe`` (tunnels, spinning sensor, turning back). See
:func:`simulate` (files on disk) and :func:`generate` (in memory).
"""

from decod_rs.sim.api import SimData, SimResult, Simulation, generate, simulate
from decod_rs.sim.drift import DRIFT_PRESETS, drift_odometry, resolve_drift
from decod_rs.sim.scenes import SCENES, build_scene
from decod_rs.sim.sensors import SENSORS, SensorSpec, sensor_spec

__all__ = [
    "DRIFT_PRESETS",
    "SCENES",
    "SENSORS",
    "SensorSpec",
    "SimData",
    "SimResult",
    "Simulation",
    "build_scene",
    "drift_odometry",
    "generate",
    "resolve_drift",
    "sensor_spec",
    "simulate",
]
