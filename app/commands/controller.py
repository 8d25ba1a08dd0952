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
from bagit.common.names import CONTROLLER_NAMES

NAME = "controller"
HELP = "servo the current run: SOI and arm states in, arm increments out (mpc, ibvs, ssvs)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--config", metavar="YAML", help="service config (controller, control_rate_hz, soi_max_age_s, arm_max_age_s, params, bus)")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, help="force this controller (default: the run's, else mpc)")
    p.add_argument("--rate", type=_args.positive_number, metavar="HZ", help="control rate (default: the run's params.control_rate_hz)")
    p.add_argument("--soi-max-age", type=_args.positive_seconds, metavar="S", help="hold on a SOI older than this (default 0.5 s)")
    p.add_argument("--arm-max-age", type=_args.positive_seconds, metavar="S", help="hold on arm states older than this (default 0.3 s)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.commands._service import load_service_config, run_service
    from bagit.services.controller.node import ControllerNode, ControllerServiceConfig

    overrides = {"controller": args.controller, "control_rate_hz": args.rate, "soi_max_age_s": args.soi_max_age,
                 "arm_max_age_s": args.arm_max_age}
    cfg, bus = load_service_config(ControllerServiceConfig, args.config, overrides, args)
    return run_service("controller", bus, lambda session, keys: ControllerNode(session, keys, cfg, clock=bus.clock), duration=args.duration,
                       banner=lambda node: f"following {node.keys.run_state}, commanding on {node.keys.controller_cmd}")


def human(r: dict[str, Any]) -> str:
    c = r["counters"]
    return (f"controller stopped after {r['uptime_s']:.1f} s: {c['runs']} runs, {c['servo']} servo and {c['hold']} hold commands, "
            f"{c['errors']} errors")
