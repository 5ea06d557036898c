"""Synthetic corridors: a simulator that writes real ROS 2 MCAP logs with ground truth.

Scenes (defaults: sensor, speed, one-way length, return):

- ``hume``: precast concrete pipe, 0.6 m ID, 2.43 m segments, annular joint grooves whose
  depth/width/centre vary around the circumference, eccentric lips, chipped edges, lateral
  connections, 1 mm roughness, 1.5 mm range noise (``avia``, 0.4 m/s, 60 m, ``reverse``).
- ``pe``: ribbed polyethylene pipe, 0.4 m, ribs every 35 mm, couplers every 6 m
  (``avia``, 0.4 m/s, 60 m, ``reverse``).
- ``shield``: 6 m segmental tunnel, 1.5 m rings, ring seams with lipping, staggered
  longitudinal seams, bolt pockets beside the seams, flat invert, 1 cm range noise
  (``spin16``, 1.5 m/s, 120 m, ``turn``).
- ``horseshoe``: rough rock, steel arches every 1.2 m, flat floor, 1.5 cm range noise
  (``spin16``, 1.2 m/s, 100 m, ``turn``).

Geometry overrides: ``simulate(..., scene_overrides={"radius_m": 0.5})`` (``decod simulate
... --scene-param radius_m=0.5``) changes the builder's parameters (``radius_m``,
``segment_length_m`` / ``ring_width_m`` / ``arch_spacing_m`` = the boundary spacing, ...;
:func:`scene_params` lists them); the sensor mount and a tunnel's floor follow the radius.
A pipe's ``water_depth_m`` (below its radius, the sensor above it) fills its bottom with
water: a floor at ``-radius + depth`` that returns ``WATER_RETURN_FRACTION`` (3 %) of the
rays meeting it (calm water mirrors the beam away), recorded as ``axis.floor_z_m``.
``sensor_height_m`` (``--height``) puts the sensor that high above the section's lowest
point (a pipe's invert, a tunnel's floor) instead of near a pipe's centre or 1.6 m above a
tunnel's floor.

Drift profiles (:mod:`decod_rs.sim.drift`): an endpoint error in metres or a preset, or
per-leg scale errors ``"legs:-0.05,-0.15"``, or scale errors changing along the way
``"slip:-0.15,-0.01"``; :func:`odometry_for_profile` makes the odometry
of any profile from ground truth without re-simulating the scans.

Frames: world x = corridor axis from x = 0, z up, section centre at y = z = 0 (tunnel floors
at ``floor_z_m``: shield -2.0 m, horseshoe -1.5 m). Body = sensor frame, FLU. ``gt.tum`` is
``world_from_body``; ``/odom`` and ``odom.tum`` are the drifting ``odom_from_body`` (odom =
world at the first stamp). Scans at 10 Hz, IMU at 100 Hz, stamps from 1700000000 s.

Python::

    from decod_rs.sim import simulate, generate
    res = simulate("hume", "out/hume", seed=0, drift=2.0)   # -> SimResult (files on disk)
    data = generate("pe", length_m=5.0, scan_indices=[0, 10])  # -> SimData (in memory)

``out_dir`` layout: ``log/`` (rosbag2: ``metadata.yaml`` + ``log.mcap``), ``gt.tum``,
``odom.tum``, ``joints.json``. ``joints.json`` keys: ``format`` ("decod-sim"), ``version``
(1), ``scene``, ``seed``, ``distinctiveness``, ``identical_joints``, ``axis`` {frame,
origin_m, direction, centre_line_y_m, centre_line_z_m, radius_m, floor_z_m, x_min_m,
x_max_m}, ``joints_x_m`` (true boundary positions along the axis, m from x = 0),
``n_joints``, ``scene_params`` (every geometry parameter), ``scene_overrides``, ``sensor``
(SensorSpec fields + ``range_noise_m``), ``trajectory`` (TrajectorySpec fields), ``drift``
{profile, requested_endpoint_m (None for a leg profile), endpoint_error_m, endpoint_axial_m,
endpoint_lateral_m, max_axial_m, yaw_end_rad, pitch_end_rad, turnaround_axial_m, model},
``odometry`` {name: "drift-model" | "kiss-icp", endpoint_error_m, ...}, ``imu`` (ImuSpec
fields), ``time_split`` {start_stamp, far_end_arrival_stamp, return_start_stamp, end_stamp,
outbound_scans [first, last], return_scans [first, last], duration_s}, ``frames``,
``topics``, ``files`` {log, gt, odom}.
"""

import importlib
from typing import TYPE_CHECKING, Any

from decod_rs.sim.drift import (
    DRIFT_PRESETS,
    LegProfile,
    SlipProfile,
    drift_odometry,
    odometry_for_profile,
    parse_profile,
    resolve_drift,
    turnaround_index,
)
from decod_rs.sim.scenes import SCENES, build_scene, scene_params
from decod_rs.sim.sensors import SENSORS, SensorSpec, sensor_spec

if TYPE_CHECKING:
    from decod_rs.sim.api import SimData, SimResult, Simulation, generate, simulate

#: The simulator itself (its log writer imports rosbags) is imported when first used: the
#: scene, sensor and drift tables (``decod simulate --help``) do not wait for it.
_API = ("SimData", "SimResult", "Simulation", "generate", "simulate")


def __getattr__(name: str) -> Any:
    if name not in _API:
        raise AttributeError(f"module 'decod_rs.sim' has no attribute {name!r}")
    return getattr(importlib.import_module("decod_rs.sim.api"), name)


__all__ = [
    "DRIFT_PRESETS",
    "SCENES",
    "SENSORS",
    "LegProfile",
    "SensorSpec",
    "SimData",
    "SimResult",
    "Simulation",
    "SlipProfile",
    "build_scene",
    "drift_odometry",
    "generate",
    "odometry_for_profile",
    "parse_profile",
    "resolve_drift",
    "scene_params",
    "sensor_spec",
    "simulate",
    "turnaround_index",
]
