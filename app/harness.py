"""The deployed stack driven from outside, as a user (or a test, a benchmark, a probe) meets it:
`bagit up` as a subprocess with its status file and a peer on its hub, two in-process Zenoh peers on
loopback (multicast scouting off), and waiting for a condition with a time-out.

    with rig_up(workdir, "--no-dashboard") as rig:   # every service up; rig.session peers on the hub
        os.kill(rig.status["children"]["controller"], signal.SIGKILL)
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace

from bagit.common.bus import BusConfig, Keys, LatestCache, Subscriber, locators, open_session
from bagit.common.headless import headless_gl
from bagit.common.messages import Command, RunState

DEPLOY = Path(__file__).resolve().parent.parent / "deploy"
SECURE_ROUTER_CFG = DEPLOY / "secure" / "zenoh-router-secure.json5"
SECURE_CLIENT_CFG = DEPLOY / "secure" / "client.json5"
SECURE_IDENTITIES = ("router", "controller", "arm-driver", "perception", "planner", "dashboard", "cli", "intruder")

ENV = headless_gl(dict(os.environ, PYTHONUNBUFFERED="1"))
ALL = ("sim", "perception", "planner", "controller", "arm-driver")


def wait_until(pred: Callable[[], bool], timeout: float = 3.0, step: float = 0.005) -> bool:
    """Poll `pred` until true or `timeout` seconds pass."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(step)
    return bool(pred())


def session_pair(rig: str) -> Iterator[tuple]:
    """Peer A listens on tcp/127.0.0.1:0 (port read back from its admin space), peer B connects to it.
    Multicast scouting is off (the BusConfig default), so nothing else joins."""
    a = open_session(BusConfig(rig=rig, adminspace=True))
    b = None
    try:
        b = open_session(BusConfig(rig=rig, connect=locators(a)))
        if not wait_until(lambda: len(list(b.info.peers_zid())) == 1, 3.0):
            raise TimeoutError("the two peers did not connect")
        yield a, b
    finally:
        if b is not None:
            b.close()
        a.close()


@contextmanager
def secure_rig(pki_dir: Path, rig: str, identities: tuple[str, ...] = SECURE_IDENTITIES) -> Iterator[SimpleNamespace]:
    """The committed secure deployment in process: the router from deploy/secure/ (mutual TLS, access
    control) on loopback with throwaway certificates, and a client session per identity (common name;
    "intruder" is CA-signed but in no rule). Yields `router`, `clients` by name, `pki`, `endpoint`, `port`."""
    from bagit.deploy.certs import write_lab_pki

    pki = write_lab_pki(pki_dir, list(identities), ["localhost", "127.0.0.1"])
    router = open_session(BusConfig(mode="router", config_file=SECURE_ROUTER_CFG, listen=["tls/127.0.0.1:0"], adminspace=True,
                                    tls_ca=pki["ca"], tls_cert=pki["router"], tls_key=pki["router.key"]))
    port = locators(router)[0].rsplit(":", 1)[1]
    endpoint = f"tls/localhost:{port}"
    clients = {}
    try:
        for name in identities:
            if name != "router":
                clients[name] = open_session(BusConfig(rig=rig, config_file=SECURE_CLIENT_CFG, connect=[endpoint],
                                                       tls_ca=pki["ca"], tls_cert=pki[name], tls_key=pki[f"{name}.key"]))
        yield SimpleNamespace(router=router, clients=clients, pki=pki, endpoint=endpoint, port=port)
    finally:
        for c in clients.values():
            c.close()
        router.close()


def stop_process(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout: float = 20.0) -> int:
    """Send `sig` and wait; SIGKILL if it does not exit within `timeout` s. Its exit status."""
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        return proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        return proc.wait(5)


def alive(pid: int) -> bool:
    """The process exists and is no zombie."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def start_up(workdir: Path, *args: str) -> tuple[subprocess.Popen, Path]:
    """`bagit up ARGS` with a status file in `workdir`; its stderr (the services' log) in up.log."""
    status = workdir / "status.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bagit.cli", "up", "--status-file", str(status), "--workdir", str(workdir / "work"), *args],
        stdout=subprocess.PIPE, stderr=open(workdir / "up.log", "w"), env=ENV, text=True,
    )
    return proc, status


def wait_status(path: Path, want: tuple[str, ...], timeout: float = 90) -> dict:
    """The status file once every child in `want` has a PID."""

    def ready() -> bool:
        try:
            d = json.loads(path.read_text())
        except (OSError, ValueError):
            return False
        return all(d["children"].get(s) for s in want)

    if not wait_until(ready, timeout, 0.1):
        raise TimeoutError(f"children {want} not started within {timeout:g} s: {path}")
    return json.loads(path.read_text())


def up_log(workdir: Path) -> str:
    return (workdir / "up.log").read_text(errors="replace")


@contextmanager
def rig_up(workdir: Path, *args: str) -> Iterator[SimpleNamespace]:
    """`bagit up ARGS` with every service up and a peer on its hub. Yields a namespace with `status`
    (the status dict), `status_path`, `session`, `keys`, `state` (run/state cache) and `cmds` (every
    controller/cmd as (monotonic time, Command)); SIGTERMs the rig afterwards."""
    proc, status_path = start_up(workdir, *args)
    session = None
    try:
        d = wait_status(status_path, ALL)
        if not wait_until(lambda: "all services up" in up_log(workdir), 150, 0.2):
            raise TimeoutError(f"bagit up: services not up within 150 s; its log:\n{up_log(workdir)[-3000:]}")
        session = open_session(BusConfig(rig=d["rig"], connect=[d["connect"]]))
        keys = Keys(d["rig"])
        cmds: list[tuple[float, Command]] = []
        Subscriber(session, keys.controller_cmd, Command, lambda c: cmds.append((time.monotonic(), c)))
        yield SimpleNamespace(status=d, status_path=status_path, session=session, keys=keys,
                              state=LatestCache(session, keys.run_state, RunState), cmds=cmds)
    finally:
        if session is not None:
            session.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
