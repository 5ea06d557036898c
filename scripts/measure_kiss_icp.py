"""Run KISS-ICP (a real LiDAR odometry, ``pip install kiss-icp``) on simulated scans and
measure how much it drifts along the corridor axis in each scene.

    python scripts/measure_kiss_icp.py [--scenes hume pe shield horseshoe] [--length 20]

Prints, per scene: scans, KISS-ICP time per scan, the axial / lateral / vertical error at the
far end and at the end (metres), and the maximum axial error. The KISS-ICP trajectory is
anchored at the first ground-truth pose (both start there).
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
from kiss_icp.config import KISSConfig
from kiss_icp.kiss_icp import KissICP

from decod_rs.sim import Simulation

# Voxel sizes: KISS-ICP's default rule (max range / 100) with a range that suits the scale.
SETTINGS = {
    "hume": {"max_range": 10.0, "voxel": 0.02, "length": 20.0},
    "pe": {"max_range": 10.0, "voxel": 0.02, "length": 20.0},
    "shield": {"max_range": 60.0, "voxel": 0.5, "length": 60.0},
    "horseshoe": {"max_range": 60.0, "voxel": 0.5, "length": 60.0},
}


def run(
    scene: str, length: float | None, seed: int, voxel: float | None = None
) -> dict[str, float]:
    s = dict(SETTINGS[scene])
    if voxel is not None:
        s["voxel"] = voxel
    sim = Simulation(scene, seed=seed, length_m=length or s["length"], drift="none")
    cfg = KISSConfig()
    cfg.data.max_range = s["max_range"]
    cfg.data.min_range = 0.0
    cfg.data.deskew = False
    cfg.mapping.voxel_size = s["voxel"]
    cfg.registration.max_num_threads = 1
    odo = KissICP(cfg)
    poses = np.zeros((sim.n_scans, 4, 4))
    t_kiss = 0.0
    for k in range(sim.n_scans):
        pts, _ = sim.scan(k)
        frame = pts.astype(np.float64)
        t0 = time.perf_counter()
        odo.register_frame(frame, np.zeros(frame.shape[0]))
        t_kiss += time.perf_counter() - t0
        poses[k] = sim.gt_poses[0] @ odo.last_pose
    err = poses[:, :3, 3] - sim.gt_poses[:, :3, 3]
    k_far = sim.scan_index_at(sim.traj.t_far_arrive)
    return {
        "scans": sim.n_scans,
        "kiss_ms_per_scan": 1000 * t_kiss / sim.n_scans,
        "far_axial_m": float(err[k_far, 0]),
        "far_lateral_m": float(err[k_far, 1]),
        "far_vertical_m": float(err[k_far, 2]),
        "end_axial_m": float(err[-1, 0]),
        "end_lateral_m": float(err[-1, 1]),
        "end_vertical_m": float(err[-1, 2]),
        "max_abs_axial_m": float(np.max(np.abs(err[:, 0]))),
        "max_abs_lateral_m": float(np.max(np.hypot(err[:, 1], err[:, 2]))),
        "travelled_m": float(sim.traj.travelled(sim.t_s)[-1]),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenes", nargs="+", default=list(SETTINGS))
    ap.add_argument("--length", type=float, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--voxel", type=float, default=None, help="override the voxel size (m)")
    args = ap.parse_args()
    for scene in args.scenes:
        res = run(scene, args.length, args.seed, args.voxel)
        voxel = args.voxel or SETTINGS[scene]["voxel"]
        out = {"scene": scene, "voxel_m": voxel, **{k: round(v, 4) for k, v in res.items()}}
        print(json.dumps(out), flush=True)


if __name__ == "__main__":
    main()
