"""`bagit planner`: the planner service and the rig's run coordinator.

Answers run/control (start a scenario, stop, reset; one run at a time), takes g0 from perception,
computes the bagging goal and the SOI path, publishes them on planner/goal and planner/path, and
publishes run/state (on every change and at --publish-hz) while following the controller's
status and the services' liveliness. Config: `--config FILE` (YAML, PlannerServiceConfig:
`coordinator:` timing rules, `publish_hz`, `bus:`); the bus flags override its `bus:` section.
Stops on Ctrl-C or SIGTERM, or after --duration seconds.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.planner")

NAME = "planner"
HELP = "run the planner service: the run coordinator (run/control, run/state), goal and SOI path"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--config", type=Path, metavar="YAML", help="service config (coordinator timing, publish_hz, bus)")
    p.add_argument("--publish-hz", type=_args.positive_number, default=None, help="run/state republish rate (default 2)")
    p.add_argument("--run-time-limit", type=_args.positive_seconds, default=None, metavar="S",
                   help="a run still servoing after S seconds of wall time fails (default 180)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until stopped)")
    add_bus_arguments(p)


def load_config(path: Path | None, model: Any) -> Any:
    """A service config from YAML (empty when no file); one-line BadScenario naming the bad field."""
    import yaml
    from pydantic import ValidationError

    from bagit.common.errors import BadScenario

    if path is None:
        return model()
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8")) or {}
    except (OSError, yaml.YAMLError) as e:
        raise BadScenario(f"cannot read config {path}: {str(e).splitlines()[0]}") from None
    try:
        return model.model_validate(data)
    except ValidationError as e:
        first = e.errors()[0]
        raise BadScenario(f"{path}: {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def run(args: argparse.Namespace) -> dict[str, Any]:

    from pydantic import ValidationError

    from bagit.commands._service import run_service
    from bagit.common.bus import bus_config_from_args, parse_bus_config
    from bagit.common.errors import BusError
    from bagit.services.planner.node import PlannerNode, PlannerServiceConfig

    cfg = load_config(args.config, PlannerServiceConfig)
    if args.publish_hz is not None:
        try:
            cfg = cfg.model_copy(update={"publish_hz": PlannerServiceConfig(publish_hz=args.publish_hz).publish_hz})
        except ValidationError as e:
            raise BusError(f"--publish-hz: {e.errors()[0]['msg']}") from None
    if args.run_time_limit is not None:
        try:
            coord = cfg.coordinator.model_validate({**cfg.coordinator.model_dump(), "run_time_limit_s": args.run_time_limit})
        except ValidationError as e:
            raise BusError(f"--run-time-limit: {e.errors()[0]['msg']}") from None
        cfg = cfg.model_copy(update={"coordinator": coord})
    bus = bus_config_from_args(args, parse_bus_config(cfg.bus))
    # The node declares its own liveliness token: alive as soon as it answers run/control.
    return run_service("planner", bus, lambda session, keys: PlannerNode(session, keys, cfg, clock=bus.clock), duration=args.duration,
                       banner=lambda node: "coordinating (run/control, run/state)", alive=False)


def human(r: dict[str, Any]) -> str:
    return f"planner stopped after {r['uptime_s']:.1f} s; {len(r['runs'])} run(s): " + ", ".join(f"{k} {v}" for k, v in r["runs"].items())
