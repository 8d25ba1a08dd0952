"""`bagit arm-driver`: both CR5s on the rig's bus: controller/cmd in, arm/<side>/state out, e-stop.

Brings both controllers up (ClearError, EnableRobot, SpeedFactor) before it listens, streams the
controller's increments through Ruckig and the safety gate, holds the arms when commands stop
(watchdog), latches the e-stop on `estop`. Ctrl-C or SIGTERM: smooth stop, hold, DisableRobot.
An unreachable controller is a one-line error (exit 2).
"""

from __future__ import annotations

import argparse
from typing import Any

from bagit.commands import _args

NAME = "arm-driver"
HELP = "drive both CR5s from controller/cmd, publish their state, latch the e-stop"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--config", metavar="YAML", help="service config (rig_config, driver, state_rate_hz, bus); flags override it")
    p.add_argument("--rig-config", metavar="YAML", help="rig config: the CR5s' addresses and ports, bases, safety limits (default: built-in)")
    p.add_argument("--state-rate", type=_args.positive_number, metavar="HZ", help="publish arm states at most this often (default: every feedback packet)")
    p.add_argument("--servo-command", choices=["servop", "servoj"], help="ServoP (default) or ServoJ")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.commands._service import load_service_config, run_service, service_rig
    from bagit.common.rig import RigConfig
    from bagit.services.arm_driver.config import ArmDriverServiceConfig
    from bagit.services.arm_driver.driver import ArmDriver
    from bagit.services.arm_driver.node import ArmDriverNode

    overrides = {"rig_config": args.rig_config, "state_rate_hz": args.state_rate, "driver": {"servo_command": args.servo_command}}
    rigs: list[RigConfig] = []

    def load_rig(cfg: ArmDriverServiceConfig) -> str:
        rigs.append(service_rig(cfg.rig_config, args.rig_config, args.config))
        return rigs[0].name

    cfg, bus = load_service_config(ArmDriverServiceConfig, args.config, overrides, args, default_rig=load_rig)
    rig = rigs[0]

    def start(session, keys):
        return ArmDriverNode(session, keys, ArmDriver(rig, cfg.driver), state_rate_hz=cfg.state_rate_hz, notice_s=cfg.notice_s,
                             clock=bus.clock)

    def banner(node) -> str:
        ports = ", ".join(f"{a} {c.host}:{c.dashboard_port}/{c.feedback_port}" for a, c in rig.arms.items())
        return f"both arms enabled ({ports}); listening on {node.keys.controller_cmd}"

    return run_service("arm-driver", bus, start, duration=args.duration, banner=banner)


def human(r: dict[str, Any]) -> str:
    return (f"arm driver stopped after {r['uptime_s']:.1f} s: {r['commands']} commands ({r['refused']} refused), "
            f"{sum(r['states_published'].values())} states published, e-stop {'latched' if r['estop']['latched'] else 'clear'}")
