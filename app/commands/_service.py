"""What every long-running service command shares: its config file, and its life on the bus.

    cfg, bus = load_service_config(PerceptionConfig, args.config, overrides, args)
    result = run_service("perception", bus, lambda session, keys: PerceptionNode(session, keys, cfg),
                         duration=args.duration)

A service config is a YAML file: the service's own pydantic model, plus an optional `bus:`
section (a `BusConfig`: rig, mode, connect, listen, ...). Command-line flags override the file:
service flags through `overrides` (a nested mapping, None values ignored), the Zenoh flags of
`add_bus_arguments` over the `bus:` section.

`run_service` opens the session, starts the node, declares `bagit/<rig>/alive/<service>` once
the node is up (so liveliness means "ready"), and waits for SIGINT/SIGTERM, `--duration` or the
node's own `stopped` event; then it undeclares the token, closes the node and the session, in
that order, and returns the node's final status.
"""

from __future__ import annotations

import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

import yaml
from pydantic import BaseModel, ValidationError

from bagit.common.bus import BusConfig, Keys, bus_config_from_args, declare_alive, open_session, parse_bus_config
from bagit.common.errors import BadScenario, BusError

if TYPE_CHECKING:
    from bagit.common.rig import CameraConfig, RigConfig

C = TypeVar("C", bound=BaseModel)


class ServiceNode(Protocol):
    """What run_service needs of a node: a final status on close, and optionally a `stopped` event
    the node sets when it has nothing more to do (`stop_ok` True, e.g. the end of a recording) or
    cannot go on (`stop_ok` False: the command fails with `stop_reason`)."""

    def close(self) -> dict[str, Any]: ...


def deep_merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """`base` with `over` laid on top, recursively for mappings; None in `over` leaves base as is."""
    out = dict(base)
    for k, v in over.items():
        if v is None:
            continue
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_merge(out[k], v)
        elif isinstance(v, dict):
            out[k] = deep_merge({}, v)
        else:
            out[k] = v
    return out


def read_yaml(path: str | Path | None) -> dict[str, Any]:
    """A YAML mapping from `path` ({} for None); BadScenario naming the file otherwise."""
    if path is None:
        return {}
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as e:
        raise BadScenario(f"cannot read config {p}: {str(e).splitlines()[0]}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise BadScenario(f"config {p} must be a mapping of settings, not {type(data).__name__}")
    return data


def validate_config(model: type[C], data: dict[str, Any], where: str = "config") -> C:
    """`model` from `data`; BadScenario naming the first bad field otherwise."""
    try:
        return model.model_validate(data)
    except ValidationError as e:
        first = e.errors()[0]
        loc = ".".join(map(str, first["loc"])) or model.__name__
        raise BadScenario(f"{where}: {loc}: {first['msg'].removeprefix('Value error, ')}") from None


def load_service_config(
    model: type[C],
    path: str | Path | None,
    overrides: dict[str, Any],
    args: Any,
    default_rig: str | Callable[[C], str | None] | None = None,
) -> tuple[C, BusConfig]:
    """The service config (file, then flags) and the bus config (file's `bus:`, then the Zenoh flags).

    `default_rig`: the rig name when neither the file nor `--rig` gives one (e.g. the rig config's),
    or a function of the service config giving it.
    """
    data = read_yaml(path)
    bus_data = data.pop("bus", None) or {}
    if not isinstance(bus_data, dict):
        raise BadScenario(f"config {path}: bus: must be a mapping")
    where = f"config {path}" if path is not None else "settings"
    cfg = validate_config(model, deep_merge(data, overrides), where)
    if callable(default_rig):
        default_rig = default_rig(cfg)
    if default_rig is not None and "rig" not in bus_data:
        bus_data = {**bus_data, "rig": default_rig}
    base = parse_bus_config(bus_data)
    return cfg, bus_config_from_args(args, base)


def service_rig(rig_config: str | None, flag: str | None, config_path: str | None) -> RigConfig:
    """The rig config a service's `rig_config` names (the built-in rig when None): a path from the
    config file is relative to that file, one from `--rig-config` (`flag`) to the working directory."""
    from bagit.common.rig import RigConfig

    path = rig_config
    if path is not None and flag is None and config_path is not None and not Path(path).is_absolute():
        path = str(Path(config_path).parent / path)
    return RigConfig.from_file(path) if path else RigConfig()


def flagged_camera(camera: CameraConfig, **flags: Any) -> CameraConfig:
    """The rig's camera with a command's flags (those given: serial, width, height, fps) over it;
    CameraError naming the first bad one."""
    from bagit.common.errors import CameraError
    from bagit.common.rig import CameraConfig

    try:
        return CameraConfig.model_validate({**camera.model_dump(), **{k: v for k, v in flags.items() if v is not None}})
    except ValidationError as e:
        first = e.errors()[0]
        raise CameraError(f"bad camera settings: {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


ENDED_POLL_S = 0.1  # how often a waiting command looks at its node's own `stopped` event


def stop_on_signals(stop: threading.Event) -> Callable[[], None]:
    """SIGINT and SIGTERM set `stop`; returns what puts the previous handlers back. Every command's one way to
    be stopped (set up in the main thread only: elsewhere Python cannot take signals).

    No handler takes a lock. Python runs a handler in the main thread between two bytecodes; one that called
    `stop.set()` while the main thread was entering `stop.wait()`, holding `stop`'s own lock, deadlocked (the
    planner's rare hang on SIGTERM, caught by its stack dump). Here the C-level wake-up fd gets the signal's
    number whichever thread the kernel picked, the Python handler writes it too, and a relay thread reading
    that pipe sets `stop`, so a signal also wakes a main thread blocked in a wait of any length."""
    if threading.current_thread() is not threading.main_thread():
        return lambda: None
    r, w = os.pipe()
    os.set_blocking(w, False)
    stops = {int(signal.SIGINT), int(signal.SIGTERM)}

    def poke(signum: int, _frame: object) -> None:
        try:
            os.write(w, bytes([signum]))
        except OSError:  # the pipe is full (a byte is already waiting) or closed (restored)
            pass

    def relay() -> None:
        while data := os.read(r, 64):  # EOF once restore closes the write end
            if stops.intersection(data):
                stop.set()

    thread = threading.Thread(target=relay, name="signal-relay", daemon=True)
    thread.start()
    previous_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
    previous = {s: signal.signal(s, poke) for s in (signal.SIGINT, signal.SIGTERM)}

    def restore() -> None:
        for s, h in previous.items():
            signal.signal(s, h)
        signal.set_wakeup_fd(previous_fd)
        os.close(w)
        thread.join(1.0)  # at once; only a child forked without exec could still hold the write end
        if not thread.is_alive():
            os.close(r)

    return restore


def wait_stop(stop: threading.Event, duration: float | None = None, ended: threading.Event | None = None) -> bool:
    """Until `stop` (set by `stop_on_signals` on SIGINT/SIGTERM, at once), `duration` s or `ended`; True if
    `ended`. Only `ended`, a node's own event, is looked at on an interval (ENDED_POLL_S)."""
    deadline = None if duration is None else time.monotonic() + duration
    while not stop.is_set():
        if ended is not None and ended.is_set():
            return True
        left = None if deadline is None else deadline - time.monotonic()
        if left is not None and left <= 0:
            break
        stop.wait(left if ended is None else ENDED_POLL_S if left is None else min(ENDED_POLL_S, left))
    return False


def run_service(
    name: str,
    bus: BusConfig,
    start: Callable[[Any, Keys], ServiceNode],
    duration: float | None = None,
    banner: Callable[[Any], str] | None = None,
    alive: bool = True,
) -> dict[str, Any]:
    """Run one service until a signal, `duration` seconds or the node's `stopped` event (see the module doc).
    `alive`: declare the service's liveliness token here; False where the node declares its own (the
    planner, alive as soon as it answers run/control; the recorder, which withdraws it when it fails)."""
    if duration is not None and not duration > 0:
        raise BusError(f"--duration must be positive, got {duration}")
    keys = Keys(bus.rig)
    stop = threading.Event()
    restore = stop_on_signals(stop)
    t0 = time.monotonic()
    status: dict[str, Any] = {}
    stopped_by_node = False
    try:
        session = open_session(bus)
        try:
            node = start(session, keys)
            try:
                token = declare_alive(session, keys, name) if alive else None
                logging.getLogger(f"bagit.{name.replace('-', '_')}").info("%s (rig %s); Ctrl-C to stop", banner(node) if banner else "running", bus.rig)
                stopped_by_node = wait_stop(stop, None if duration is None else t0 + duration - time.monotonic(), getattr(node, "stopped", None))
                try:
                    if token is not None:
                        token.undeclare()
                except Exception:  # noqa: BLE001 - the session may already be gone
                    pass
            finally:
                status = node.close() or {}
        finally:
            session.close()
    finally:
        restore()
    out: dict[str, Any] = {"success": True, "service": name, "rig": bus.rig, "uptime_s": time.monotonic() - t0,
                           "interrupted": stop.is_set(), **status}
    if stopped_by_node:
        out["stopped_by"] = getattr(node, "stop_reason", None) or f"{name} stopped"
        if not getattr(node, "stop_ok", False):  # e.g. a camera that failed; a recording's end is fine
            out["success"] = False
            out["reason"] = out.get("reason") or out["stopped_by"]
    return out
