"""`bagit dashboard`: the web dashboard of a rig (viser), on the rig's Zenoh bus.

Serves http://127.0.0.1:8080 by default: loopback only, so nobody else on the network can press
its buttons; `--host 0.0.0.0` (or an interface address) widens it explicitly. The bus flags are
those of every service (`--rig`, `--connect`, ...). Stops on Ctrl-C or SIGTERM, or after
`--duration` seconds.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.dashboard")

NAME = "dashboard"
HELP = "serve the web dashboard: live scene, plots and health; start, stop and E-STOP the rig"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--host", default="127.0.0.1", help="address to serve on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=_args.port, default=8080, help="HTTP/websocket port (default 8080; 0 = any free port)")
    p.add_argument("--rig-config", metavar="YAML", help="rig config (arm bases, camera) used to draw the arms; default: the paper's set-up")
    p.add_argument("--scenario", metavar="NAME", help="bundled scenario the picker starts on (name or unique prefix); default the first")
    p.add_argument("--max-cloud-points", type=_args.positive_int, default=20000, help="points of a cloud drawn at most (default 20000)")
    p.add_argument("--query-timeout", type=_args.positive_seconds, default=5.0, help="seconds to wait for run/control answers (default 5)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    import threading
    import time

    from pydantic import ValidationError

    from bagit.common.bus import bus_config_from_args
    from bagit.common.errors import BadScenario, BusError
    from bagit.common.rig import RigConfig
    from bagit.dashboard.node import DashboardNode
    from bagit.dashboard.server import DashboardConfig

    if not 0 < args.query_timeout <= 120:
        raise BusError(f"--query-timeout must be in (0, 120] s, got {args.query_timeout}")
    try:
        cfg = DashboardConfig(host=args.host, port=args.port, max_cloud_points=args.max_cloud_points, scenario=args.scenario)
    except ValidationError as e:
        first = e.errors()[0]
        raise BadScenario(f"--{str(first['loc'][0]).replace('_', '-')}: {first['msg']}") from None
    rig = RigConfig.from_file(args.rig_config) if args.rig_config else RigConfig()
    bus = bus_config_from_args(args)
    from bagit.commands._service import stop_on_signals, wait_stop

    stop = threading.Event()
    restore = stop_on_signals(stop)
    t0 = time.monotonic()
    try:
        try:
            node = DashboardNode(bus, cfg, rig, query_timeout_s=args.query_timeout)
        except OSError as e:
            raise BusError(f"cannot serve on {args.host}:{args.port}: {e}") from None
        with node:
            url = node.url
            log.info("%s (rig %s); Ctrl-C to stop", url, bus.rig)
            wait_stop(stop, args.duration)
            stats = node.dashboard.stats()
            runs = [r.run_id for r in node.dashboard.history.records()]
    finally:
        restore()
    return {
        "success": True,
        "url": url,
        "rig": bus.rig,
        "uptime_s": time.monotonic() - t0,
        "runs": runs,
        "received": {k: v["received"] for k, v in stats["slots"].items()},
        "render_errors": stats["render_errors"],
    }


def human(r: dict[str, Any]) -> str:
    return f"dashboard {r['url']} stopped after {r['uptime_s']:.1f} s ({len(r['runs'])} runs this session)"
