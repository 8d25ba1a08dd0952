"""`bagit router`: the rig's Zenoh router, from zenoh-python (no zenohd binary needed).

Runs in router mode with the committed deploy/zenoh-router.json5 (loopback unless told
otherwise: `--listen tcp/0.0.0.0:7447` for a multi-host rig), or any other config through
`--zenoh-config` (e.g. deploy/secure/zenoh-router-secure.json5). Stops on Ctrl-C or SIGTERM.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.router")

NAME = "router"
HELP = "run the Zenoh router of a multi-host rig (zenoh-python in router mode)"


def default_config_path() -> str:
    """The committed router config, wherever the package is installed."""
    from importlib.resources import files

    return str(files("bagit.deploy") / "zenoh-router.json5")


def add_arguments(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("zenoh")
    g.add_argument("--zenoh-config", metavar="FILE", help="router json5 config (default: the committed deploy/zenoh-router.json5)")
    g.add_argument("-l", "--listen", action="append", metavar="ENDPOINT", help="listen endpoint, overriding the config (repeatable)")
    g.add_argument("-e", "--connect", action="append", metavar="ENDPOINT", help="another router to connect to (repeatable)")
    g.add_argument("--tls-ca", metavar="PEM", help="CA certificate of the rig")
    g.add_argument("--tls-cert", metavar="PEM", help="the router's certificate")
    g.add_argument("--tls-key", metavar="PEM", help="the router's private key")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: run until stopped)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    import threading
    import time

    import zenoh

    from bagit.common.bus import config_value, open_session, parse_bus_config

    data: dict[str, Any] = {"mode": "router", "config_file": args.zenoh_config or default_config_path()}
    for flag, field in (("listen", "listen"), ("connect", "connect"), ("tls_ca", "tls_ca"), ("tls_cert", "tls_cert"), ("tls_key", "tls_key")):
        if getattr(args, flag, None) is not None:
            data[field] = getattr(args, flag)
    cfg = parse_bus_config(data)
    listen = config_value(cfg.to_zenoh(), "listen/endpoints")
    from bagit.commands._service import stop_on_signals, wait_stop

    stop = threading.Event()
    restore = stop_on_signals(stop)
    t0 = time.monotonic()
    try:
        session = open_session(cfg)
        joined: list[str] = []

        def on_transport(ev: Any) -> None:
            up = ev.kind == zenoh.SampleKind.PUT
            if up:
                joined.append(str(ev.transport.zid))
            log.info("%s %s %s", ev.transport.whatami, ev.transport.zid, "joined" if up else "left")

        try:
            listener = session.info.declare_transport_events_listener(on_transport)
        except Exception:  # noqa: BLE001 - an optional, unstable zenoh-python API: the router works without it
            listener = None
        log.info("%s listening on %s; Ctrl-C to stop", session.zid(), ", ".join(listen) if listen else "(nothing)")
        try:
            wait_stop(stop, args.duration)
        finally:
            if listener is not None:
                try:
                    listener.undeclare()
                except Exception:  # noqa: BLE001
                    pass
            zid = str(session.zid())
            session.close()
    finally:
        restore()
    return {
        "success": True,
        "zid": zid,
        "config": str(cfg.config_file),
        "listen": listen,
        "sessions_seen": len(set(joined)),
        "uptime_s": time.monotonic() - t0,
    }


def human(r: dict[str, Any]) -> str:
    return f"router {r['zid']} stopped after {r['uptime_s']:.1f} s ({r['sessions_seen']} sessions seen)"
