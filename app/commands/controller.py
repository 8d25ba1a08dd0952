"""`bagit controller`: shape servoing of the current run on the rig's bus.

Follows run/state; when planner/path for the run arrives it servos at the control rate on the
newest perception/soi and the arms' states, publishing controller/cmd and controller/status. A
missing, stale or implausible SOI, stale arm states, an e-stop or the run's end: hold (u = 0) with
the reason. Ctrl-C or SIGTERM: one last hold, then exit.
"""

from __future__ import annotations

import argparse
from typing import Any

from bagit.commands import _args

NAME = "controller"
HELP = "servo the current run: SOI and arm states in, arm increments out (mpc, ibvs, ssvs, autobag, shakingbot, bimamanip)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--config", metavar="YAML", help="service config (rig_config, soi_max_age_s, arm_max_age_s, bus); the controller, "
                   "its parameters and the control rate are the run's")
    p.add_argument("--rig-config", metavar="YAML", help="rig config: the arm driver's watchdog, safety.watchdog_s (default: built-in rig)")
    p.add_argument("--soi-max-age", type=_args.positive_seconds, metavar="S", help="hold on a SOI older than this (default: the config's soi_max_age_s)")
    p.add_argument("--arm-max-age", type=_args.positive_seconds, metavar="S", help="hold on arm states older than this (default: the config's arm_max_age_s)")
    # flags that once set the run's settings here: refused, naming where they are (the service's MOVED_SETTINGS)
    p.add_argument("--controller", type=_args.moved("the run's choice (bagit run/up --controller, the dashboard)"), help=argparse.SUPPRESS)
    p.add_argument("--rate", type=_args.moved("the run's parameter control_rate_hz (a scenario's params:, bagit run --params)"), help=argparse.SUPPRESS)
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.commands._service import load_service_config, run_service, service_rig
    from bagit.services.controller.node import ControllerNode, ControllerServiceConfig

    overrides = {"rig_config": args.rig_config, "soi_max_age_s": args.soi_max_age, "arm_max_age_s": args.arm_max_age}
    cfg, bus = load_service_config(ControllerServiceConfig, args.config, overrides, args)
    rig = service_rig(cfg.rig_config, args.rig_config, args.config)
    return run_service("controller", bus, lambda session, keys: ControllerNode(session, keys, cfg, clock=bus.clock, rig=rig), duration=args.duration,
                       banner=lambda node: f"following {node.keys.run_state}, commanding on {node.keys.controller_cmd}")


def human(r: dict[str, Any]) -> str:
    c = r["counters"]
    return (f"controller stopped after {r['uptime_s']:.1f} s: {c['runs']} runs, {c['servo']} servo and {c['hold']} hold commands, "
            f"{c['errors']} errors")
