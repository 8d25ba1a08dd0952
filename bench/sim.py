"""Simulator speed: simulated seconds per wall second for the default bag (R = 0.68 m) lifted round
the canned pineapple off-centre, so that its fabric is pressed against the can for most of the run;
physics alone and with the camera rendering 640x480 RGB-D at 15 frames per simulated second.

    python -m bagit.bench.sim [--quick] [--jsonl PATH]

Prints the real-time factors (the target is >= 2 with the object in contact, and >= 1 with the
camera at 15 Hz), the wall time per 1/30 s control tick and per frame (min / median / p95), a
frame's stages apart (the render, the depth noise, the conversion to uint16 units; wall and CPU,
the CPU counting the noise's worker thread, which makes the next frame's draws while the units are
converted and the world steps), and how much of the run the fabric was touching the object.
A full run appends a record (commit, host, load, parameters) to bench/results/sim.jsonl; a --quick
run writes one only where --jsonl says.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.common import RESULTS_DIR, machine, stats_ms
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim import camera
from bagit.services.sim.camera import depth_units
from bagit.services.sim.world import SimWorld

RESULTS = RESULTS_DIR / "sim.jsonl"

TICK_S = 1 / 30
TOUCH_M = 0.006  # fabric mid-surface this close to the object: touching (half-thickness + contact gap)


def _targets(start: dict, offset: np.ndarray) -> dict:
    out = {}
    for name, T in start.items():
        T2 = T.copy()
        T2[:3, 3] += offset
        out[name] = T2
    return out


def lift_run(camera: bool, seconds: float, fps: float = 15.0) -> dict:
    """Settle, bring the bag under the can 5 cm off its axis, lift the rim 8 cm past the can's bottom
    (its wall drags along the can), then hold it there for the rest of the run."""
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    w = SimWorld(s, seed=0, camera=camera)
    w.step(0.3)
    start, c = w.mount_poses(), w.true_rim().mean(axis=0)
    V = s.object.bottom_vertices()
    bottom = V[:, 2].min()
    under = np.array([V[:, 0].mean() + 0.05 - c[0], V[:, 1].mean() - c[1], min(0.0, bottom - 0.05 - w.true_rim()[:, 2].max())])
    up = bottom + 0.08 - (c[2] + under[2])
    n = int(round(seconds / TICK_S))
    tick_ms, tick_cpu_ms, frame_ms, touching = [], [], [], 0
    stage_ms: dict[str, list[float]] = {f"{st}{kind}": [] for st in ("render", "noise", "units") for kind in ("", "_cpu")}
    frames, next_frame = 0, 0.0
    depth_scale = w.rig.camera.info().depth_scale
    t0 = time.perf_counter()
    for k in range(n):
        f = min(1.0, (k + 1) / (0.3 * n))  # 30 % of the run to get under the can ...
        g = float(np.clip(((k + 1) / n - 0.3) / 0.4, 0.0, 1.0))  # ... 40 % to lift (about 0.1 m/s), 30 % held
        tt, tc = time.perf_counter(), time.process_time()
        w.set_mount_targets(_targets(start, under * f + np.array([0.0, 0.0, up * g])))
        w.step(TICK_S)
        tick_ms.append((time.perf_counter() - tt) * 1e3)
        tick_cpu_ms.append((time.process_time() - tc) * 1e3)
        if camera and w.time >= next_frame - 1e-9:
            # render_rgbd's stages, one by one
            marks = [(time.perf_counter(), time.process_time())]
            _, z = w.render_true()
            marks.append((time.perf_counter(), time.process_time()))
            z = w.noisy_depth(z, frames)
            marks.append((time.perf_counter(), time.process_time()))
            depth_units(z, depth_scale)
            marks.append((time.perf_counter(), time.process_time()))
            for st, (a, b) in zip(("render", "noise", "units"), zip(marks, marks[1:], strict=False), strict=True):
                stage_ms[st].append((b[0] - a[0]) * 1e3)
                stage_ms[f"{st}_cpu"].append((b[1] - a[1]) * 1e3)
            frame_ms.append((marks[-1][0] - marks[0][0]) * 1e3)
            frames += 1
            next_frame += 1.0 / fps
        touching += w.ground_truth().clearance_m < TOUCH_M
    wall = time.perf_counter() - t0
    gt = w.ground_truth()
    w.close()
    return {
        "sim_s": n * TICK_S,
        "wall_s": wall,
        "realtime_factor": n * TICK_S / wall,
        "tick": stats_ms(tick_ms),
        "tick_cpu": stats_ms(tick_cpu_ms),
        "frames": frames,
        "frame": stats_ms(frame_ms),
        "frame_stages": {k: stats_ms(v) for k, v in stage_ms.items()},
        "touching_share": touching / n,
        "max_penetration_mm": gt.max_penetration_m * 1e3,
        "passed_through": gt.passed_through,
    }


def run(quick: bool = False) -> dict:
    seconds = 3.0 if quick else 10.0
    return {"physics_only": lift_run(False, seconds), "with_camera_15hz": lift_run(True, seconds)}


def _ms(st: dict) -> str:
    return f"{st['min_ms']:.1f} / {st['median_ms']:.1f} / {st['p95_ms']:.1f} ms" if st.get("n") else "-"


def _stages(v: dict) -> str:
    st = v["frame_stages"]
    return "; per frame median wall (CPU): " + ", ".join(
        f"{name} {st[name]['median_ms']:.1f} ({st[name + '_cpu']['median_ms']:.1f}) ms" for name in ("render", "noise", "units")
    )


def record(r: dict, quick: bool, load_before: float) -> dict[str, Any]:
    """The run's record: the machine (commit, host, ...), the load around it and the effective parameters."""
    return {
        **machine(),
        "load_1min_before": round(load_before, 2),
        "load_1min_after": round(os.getloadavg()[0], 2),
        "params": {"scenario": "exp02-canned-pineapple", "seconds": 3.0 if quick else 10.0, "tick_s": TICK_S, "fps": 15.0,
                   "noise_bands": camera.NOISE_BANDS, "mujoco_gl": os.environ.get("MUJOCO_GL", "")},
        "results": r,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3 s of simulated time instead of 10")
    ap.add_argument("--jsonl", type=Path, default=None, help=f"append the record here (default for a full run: {RESULTS})")
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    r = run(args.quick)
    for name, v in r.items():
        print(
            f"{name}: {v['realtime_factor']:.2f}x real time ({v['sim_s']:.1f} s simulated in {v['wall_s']:.1f} s); "
            f"tick min/median/p95 {_ms(v['tick'])} (CPU median {v['tick_cpu']['median_ms']:.1f} ms); "
            f"fabric touching the can {v['touching_share'] * 100:.0f} % of ticks; "
            f"max penetration {v['max_penetration_mm']:.1f} mm"
            + (f"; {v['frames']} frames, min/median/p95 {_ms(v['frame'])}" + _stages(v) if v["frames"] else "")
        )
    rec = record(r, args.quick, load_before)
    print(f"commit {rec['commit']}, host {rec['host']}, load {rec['load_1min_before']:.1f} -> {rec['load_1min_after']:.1f}")
    out = args.jsonl or (None if args.quick else RESULTS)
    if out is not None:
        with out.open("a") as f:
            f.write(json.dumps(rec, default=str) + "\n")
        print(f"record appended to {out}")


if __name__ == "__main__":
    main()
