"""The Zenoh transport every service shares, one module per concern:

- `session`: where a session listens and connects (BusConfig), opening it, its real endpoints;
- `flags`: the command-line flags every service takes;
- `keys`: the key space bagit/<rig>/... and the QoS of each key (KEY_TABLE);
- `drops`: the per-key count of payloads that did not decode;
- `pubsub`: typed publishers, subscribers and latest-wins caches;
- `query`: typed queryables and requests, and the rig's run control on top;
- `liveliness`: a token per running service and a watcher of them;
- `sim_time`: the rig's clock as a service reads it (wall, or the simulator's sim/clock).

Zenoh is imported here and in the service nodes only; the pure algorithm modules never see it.
Payloads are `bagit.common.wire` bytes (a JSON header plus raw little-endian arrays, no pickle).

    cfg = BusConfig(rig="lab", connect=["tcp/127.0.0.1:7447"])
    with open_session(cfg) as s:
        keys = Keys(cfg.rig)
        pub = Publisher(s, keys.perception_soi, SoiState)
        cache = LatestCache(s, keys.perception_soi, SoiState)
        token = declare_alive(s, keys, "perception")

This package's namespace is the public API (`from bagit.common.bus import Keys, Publisher`); the
modules say where each part lives.
"""

from bagit.common.bus.drops import DROPS, DropCounters
from bagit.common.bus.flags import add_bus_arguments, bus_config_from_args
from bagit.common.bus.keys import (
    COMMAND,
    CONTROL,
    DISPLAY,
    ESTOP,
    KEY_TABLE,
    RESULT,
    STATE,
    STATE_HIGH,
    Keys,
    KeySpec,
    QoS,
    key_table_markdown,
)
from bagit.common.bus.liveliness import LivelinessWatcher, declare_alive
from bagit.common.bus.pubsub import LatestCache, Polled, Publisher, Subscriber, encoding_for
from bagit.common.bus.query import Server, request, request_run_control, serve_run_control
from bagit.common.bus.session import DEFAULT_ROUTER_PORT, BusConfig, config_value, locators, open_session, parse_bus_config
from bagit.common.bus.sim_time import rig_clock
from bagit.common.errors import BusError

__all__ = [
    "COMMAND",
    "CONTROL",
    "DEFAULT_ROUTER_PORT",
    "DISPLAY",
    "DROPS",
    "ESTOP",
    "KEY_TABLE",
    "RESULT",
    "STATE",
    "STATE_HIGH",
    "BusConfig",
    "BusError",
    "DropCounters",
    "KeySpec",
    "Keys",
    "LatestCache",
    "LivelinessWatcher",
    "Polled",
    "Publisher",
    "QoS",
    "Server",
    "Subscriber",
    "add_bus_arguments",
    "bus_config_from_args",
    "config_value",
    "declare_alive",
    "encoding_for",
    "key_table_markdown",
    "locators",
    "open_session",
    "parse_bus_config",
    "request",
    "request_run_control",
    "rig_clock",
    "serve_run_control",
]
