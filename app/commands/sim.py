"""`bagit sim SCENARIO`: the simulated rig with its two CR5 controllers on TCP and its camera.

The controllers listen on the rig config's ports (defaults: left 29999/30004, right 29989/30014,
loopback) and speak Dobot's TCP/IP protocol V4, so an arm driver connects to them as to real
CR5s. Simulated time runs `--speed` times the wall clock (as fast as the machine allows). Camera
frames are rendered at `--fps` per simulated second; publishing them over Zenoh comes with the
services.
Ctrl-C stops cleanly.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from typing import Any

NAME = "sim"
HELP = "run the simulated rig: bag, object, camera and two CR5 controllers speaking Dobot's protocol"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario")
    p.add_argument("--rig", help="rig config YAML (arm bases, controller ports, camera); default: the paper's set-up")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second (default 1)")
    p.add_argument("--duration", type=float, default=None, help="stop after this many simulated seconds (default: run until Ctrl-C)")
    p.add_argument("--no-camera", action="store_true", help="no camera frames (faster)")
    p.add_argument("--fps", type=float, default=15.0, help="camera frames per simulated second (default 15, at most the camera's rate)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--ephemeral-ports", action="store_true", help="listen on free ports instead of the rig config's")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.common.errors import BadScenario
    from bagit.common.rig import RigConfig
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.sim.rig_sim import RealtimeStats, SimRig

    if not args.speed > 0 or args.speed > 1000:
        raise BadScenario(f"--speed must be in (0, 1000], got {args.speed}")
    if not 0 < args.fps <= 120:
        raise BadScenario(f"--fps must be in (0, 120], got {args.fps}")
    if args.duration is not None and not args.duration > 0:
        raise BadScenario(f"--duration must be > 0, got {args.duration}")
    scenario = Scenario.from_file(find_scenario(args.scenario))
    rig_cfg = RigConfig.from_file(args.rig) if args.rig else RigConfig()
    out = sys.stderr if args.json else sys.stdout

    def say(msg: str) -> None:
        print(f"[sim] {msg}", file=out, flush=True)

    stop = threading.Event()
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, lambda *_: stop.set())
    frames = {"n": 0}

    def on_frame(_frame: object) -> None:
        frames["n"] += 1

    def on_progress(s: RealtimeStats) -> None:
        say(f"t = {s.sim_s:6.1f} s simulated in {s.wall_s:6.1f} s (x{s.realtime_factor:.2f}), {s.frames} frames")

    try:
        with SimRig(scenario, rig_cfg, args.seed, camera=not args.no_camera) as rig:
            ports = rig.start_servers(ephemeral_ports=args.ephemeral_ports)
            for name, (dash, fb) in ports.items():
                say(f"{name} CR5: dashboard {rig_cfg.arms[name].host}:{dash}, feedback {rig_cfg.arms[name].host}:{fb}")
            say(f"scenario {scenario.name}, seed {args.seed}, speed x{args.speed:g}" + (", no camera" if args.no_camera else ""))
            stats = rig.run_realtime(
                args.speed,
                args.duration,
                stop,
                on_frame=None if args.no_camera else on_frame,
                on_progress=on_progress,
                fps=min(args.fps, rig_cfg.camera.fps),
            )
            gt = rig.ground_truth()
            modes = {name: arm.robot_mode() for name, arm in rig.arms.items()}
    finally:
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGINT, previous)
    return {
        "success": True,
        "scenario": scenario.name,
        "seed": args.seed,
        "ports": {name: {"dashboard": d, "feedback": f} for name, (d, f) in ports.items()},
        "sim_s": stats.sim_s,
        "wall_s": stats.wall_s,
        "realtime_factor": stats.realtime_factor,
        "frames": stats.frames,
        "robot_modes": modes,
        "interrupted": stop.is_set(),
        "rim_perimeter": gt.rim_perimeter,
        "passed_through": gt.passed_through,
    }


def human(r: dict[str, Any]) -> str:
    how = "interrupted" if r["interrupted"] else "done"
    return (
        f"{r['scenario']} (seed {r['seed']}): {how} after {r['sim_s']:.1f} s simulated in {r['wall_s']:.1f} s "
        f"(x{r['realtime_factor']:.2f}), {r['frames']} camera frames; arms in modes "
        + ", ".join(f"{k} {v}" for k, v in r["robot_modes"].items())
    )
