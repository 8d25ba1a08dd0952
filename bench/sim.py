"""Simulator speed: simulated seconds per wall second, with and without the camera (15 frames per
simulated second), while the mounts lift the bag round the object.

    python -m bagit.bench.sim [--quick]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.world import SimWorld

DT = 1 / 30


def _lift_run(camera: bool, seconds: float, fps: float = 15.0) -> dict:
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    w = SimWorld(s, seed=0, camera=camera)
    w.step(0.5)
    start = w.mount_poses()
    c = w.true_rim().mean(axis=0)
    bottom = s.object.bottom_vertices()[:, 2].min()
    goal = np.array([-c[0], -c[1], bottom + 0.05 - c[2]])  # under and then round the object
    n = int(seconds / DT)
    frames, render_s = 0, 0.0
    t0 = time.perf_counter()
    for k in range(n):
        f = min(1.0, (k + 1) / (0.8 * n))
        offs = goal * np.array([min(1.0, 2 * f), min(1.0, 2 * f), max(0.0, 2 * f - 1)])
        w.set_mount_targets({name: _moved(T, offs) for name, T in start.items()})
        w.step(DT)
        if camera and (k * DT * fps) % 1 < DT * fps:
            tr = time.perf_counter()
            w.render_rgbd(frames)
            render_s += time.perf_counter() - tr
            frames += 1
    wall = time.perf_counter() - t0
    gt = w.ground_truth()
    w.close()
    return {
        "sim_s": n * DT,
        "wall_s": wall,
        "realtime_factor": n * DT / wall,
        "frames": frames,
        "render_ms_mean": render_s / frames * 1e3 if frames else 0.0,
        "max_penetration_mm": gt.max_penetration_m * 1e3,
    }


def _moved(T: np.ndarray, off: np.ndarray) -> np.ndarray:
    T2 = T.copy()
    T2[:3, 3] += off
    return T2


def run(quick: bool = False) -> dict:
    seconds = 3.0 if quick else 10.0
    return {"physics_only": _lift_run(False, seconds), "with_camera_15hz": _lift_run(True, seconds)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    r = run(ap.parse_args().quick)
    for k, v in r.items():
        print(f"{k}: {v['realtime_factor']:.2f}x real time ({v['sim_s']:.0f} s simulated in {v['wall_s']:.1f} s)"
              + (f", {v['frames']} frames at {v['render_ms_mean']:.0f} ms each" if v["frames"] else ""))


if __name__ == "__main__":
    main()
