"""The Zenoh command-line flags every service takes, and their overlay on a bus config."""

from __future__ import annotations

import argparse

from bagit.common.bus.session import BusConfig, parse_bus_config
from bagit.common.clock import CLOCK_KINDS


def add_bus_arguments(p: argparse.ArgumentParser) -> None:
    """The Zenoh flags every service takes, named as in zenoh-python's examples."""
    g = p.add_argument_group("zenoh")
    g.add_argument("--rig", help="rig name (key prefix bagit/<rig>/...)")
    g.add_argument("-m", "--mode", choices=["peer", "client", "router"], help="zenoh session mode")
    g.add_argument("-e", "--connect", action="append", metavar="ENDPOINT", help="endpoint to connect to (repeatable)")
    g.add_argument("-l", "--listen", action="append", metavar="ENDPOINT", help="endpoint to listen on (repeatable)")
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh json5 config file (base; the flags override it)")
    g.add_argument("--multicast-scouting", action="store_true", default=None, help="discover peers by UDP multicast")
    g.add_argument("--tls-ca", metavar="PEM", help="CA certificate of the rig (TLS endpoints)")
    g.add_argument("--tls-cert", metavar="PEM", help="this service's certificate (mutual TLS identity)")
    g.add_argument("--tls-key", metavar="PEM", help="this service's private key")
    g.add_argument("--clock", choices=list(CLOCK_KINDS), help="the rig's clock: wall (real rig) or sim (the simulator's sim/clock, lockstep)")


def bus_config_from_args(args: argparse.Namespace, base: BusConfig | None = None) -> BusConfig:
    """Overlay the flags of `add_bus_arguments` on `base` (e.g. the `bus:` section of a service config)."""
    data = base.model_dump(exclude_unset=True) if base is not None else {}
    for flag, field in (("rig", "rig"), ("mode", "mode"), ("connect", "connect"), ("listen", "listen"),
                        ("zenoh_config", "config_file"), ("multicast_scouting", "multicast_scouting"),
                        ("tls_ca", "tls_ca"), ("tls_cert", "tls_cert"), ("tls_key", "tls_key"), ("clock", "clock")):
        v = getattr(args, flag, None)
        if v is not None:
            data[field] = v
    return parse_bus_config(data)


