"""`bagit sim SCENARIO`: the simulated rig with its two CR5 controllers on TCP and its camera.

The controllers listen on the rig config's ports (defaults: left 29999/30004, right 29989/30014,
loopback) and speak Dobot's TCP/IP protocol V4, so an arm driver connects to them as to real
CR5s. Simulated time runs `--speed` times the wall clock (as fast as the machine allows; when it
cannot keep up it says its real-time factor). Camera frames are rendered at `--fps` per simulated
second and published on camera/rgbd (stamped with the wall clock), ground truth on sim/truth
(tests and benchmarks only), and the world is reset to each new run's scenario as run/state
announces it (bagit.services.sim.node). `--no-bus` runs without Zenoh.
Ctrl-C or SIGTERM stops cleanly.
"""

from __future__ import annotations

import argparse
import logging
import threading
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.sim")

NAME = "sim"
HELP = "run the simulated rig: bag, object, camera and two CR5 controllers speaking Dobot's protocol"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario (the world until a run says otherwise)")
    p.add_argument("--rig-config", metavar="YAML", help="rig config YAML (arm bases, controller ports, camera); default: the paper's set-up")
    p.add_argument("--speed", type=_args.positive_number, default=None,
                   help="simulated seconds per wall second at most (default: real time, and a lockstep run as fast as the rig answers)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, help="stop after this many simulated seconds (default: run until Ctrl-C)")
    p.add_argument("--no-camera", action="store_true", help="no camera frames (faster)")
    p.add_argument("--fps", type=_args.positive_number, default=None,
                   help="camera frames per simulated second, at most the camera's rate (default: the run's control rate in lockstep, else 10)")
    p.add_argument("--seed", type=_args.seed, default=0)
    p.add_argument("--ephemeral-ports", action="store_true", help="listen on free ports instead of the rig config's")
    p.add_argument("--no-bus", action="store_true", help="no Zenoh: frames are rendered but not published, no resets")
    p.add_argument("--cr5-netns", metavar="NAME",
                   help="listen for the simulated CR5s inside Linux network namespace NAME (`ip netns`; needs root): the robot LAN "
                        "of a rig split across namespaces (`bagit bench multihost`), while camera and Zenoh stay on this one")
    p.add_argument("--truth-hz", type=_args.positive_number, default=2.0, help="ground truth on sim/truth this often (default 2 Hz)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from pydantic import ValidationError

    from bagit.common.errors import BadScenario
    from bagit.common.rig import RigConfig
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.sim.node import SimNodeConfig
    from bagit.services.sim.rig_sim import WALL_FPS, RealtimeStats, SimRig

    try:  # the node's bounds on the flags, before the world is built
        SimNodeConfig(speed=args.speed, fps=args.fps, truth_hz=args.truth_hz)
    except ValidationError as e:
        first = e.errors()[0]
        raise BadScenario(f"--{str(first['loc'][0]).replace('_', '-')}: {first['msg']}") from None
    scenario = Scenario.from_file(find_scenario(args.scenario))
    rig_cfg = RigConfig.from_file(args.rig_config) if args.rig_config else RigConfig()
    fps = None if args.fps is None else min(args.fps, rig_cfg.camera.fps)  # None: the node's default (`camera_fps`)
    say = log.info

    stop = threading.Event()
    from bagit.commands._service import stop_on_signals

    restore = stop_on_signals(stop)
    frames = {"n": 0}

    def on_frame(_frame: object) -> None:
        frames["n"] += 1

    def on_progress(s: RealtimeStats) -> None:
        say(f"t = {s.sim_s:6.1f} s simulated in {s.wall_s:6.1f} s (x{s.realtime_factor:.2f}), {s.frames} frames")

    try:
        with SimRig(scenario, rig_cfg, args.seed, camera=not args.no_camera) as rig:
            if args.cr5_netns:
                from bagit.common.netns import entered_netns

                with entered_netns(args.cr5_netns):
                    ports = rig.start_servers(ephemeral_ports=args.ephemeral_ports)
            else:
                ports = rig.start_servers(ephemeral_ports=args.ephemeral_ports)
            for name, (dash, fb) in ports.items():
                say(f"{name} CR5: dashboard {rig_cfg.arms[name].host}:{dash}, feedback {rig_cfg.arms[name].host}:{fb}")
            speed = f"x{args.speed:g}" if args.speed else "default"
            say(f"scenario {scenario.name}, seed {args.seed}, speed {speed}" + (", no camera" if args.no_camera else f", camera {fps or 'default'} fps"))
            if not args.no_bus:
                stats = _run_on_bus(args, rig, scenario.name, fps, stop, say)
            else:
                stats = rig.run_realtime(
                    args.speed or 1.0,
                    args.duration,
                    stop,
                    on_frame=None if args.no_camera else on_frame,
                    on_progress=on_progress,
                    fps=fps or WALL_FPS,
                )
            gt = rig.ground_truth()
            modes = {name: arm.robot_mode() for name, arm in rig.arms.items()}
    finally:
        restore()
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


def _run_on_bus(args: argparse.Namespace, rig: Any, scenario_name: str, fps: float | None, stop: threading.Event, say: Any) -> Any:
    from bagit.common.bus import Keys, bus_config_from_args, open_session
    from bagit.services.sim.node import SimNode, SimNodeConfig
    from bagit.services.sim.rig_sim import RealtimeStats

    bus = bus_config_from_args(args)
    cfg = SimNodeConfig(speed=args.speed, fps=fps, camera=not args.no_camera, truth_hz=args.truth_hz)
    session = open_session(bus)
    try:
        node = SimNode(session, Keys(bus.rig), rig, cfg, scenario_name, say=say, clock=bus.clock)
        say(f"on the bus as rig {bus.rig}: camera/rgbd, sim/truth; following run/state")
        try:
            st = node.run(stop, args.duration)
        finally:
            node.close()
    finally:
        session.close()
    return RealtimeStats(st.sim_s, st.wall_s, st.realtime_factor, st.frames)


def human(r: dict[str, Any]) -> str:
    how = "interrupted" if r["interrupted"] else "done"
    return (
        f"{r['scenario']} (seed {r['seed']}): {how} after {r['sim_s']:.1f} s simulated in {r['wall_s']:.1f} s "
        f"(x{r['realtime_factor']:.2f}), {r['frames']} camera frames; arms in modes "
        + ", ".join(f"{k} {v}" for k, v in r["robot_modes"].items())
    )
