"""Helpers of the tests that run `bagit up` as a subprocess: start it with a status file, read the
status (child PIDs, hub endpoint, dashboard URL), its log, and whether a PID is still alive."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Iterator

from bus_support import wait_until


ENV = dict(os.environ, MUJOCO_GL="osmesa", PYOPENGL_PLATFORM="osmesa", PYTHONUNBUFFERED="1")
ALL = ("sim", "perception", "planner", "controller", "arm-driver")


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:  # a zombie is dead too
        return Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] != "Z"
    except OSError:
        return False


def start_up(tmp_path: Path, *args: str) -> tuple[subprocess.Popen, Path]:
    """`bagit up ARGS` with a status file in tmp_path; its stderr (the services' log) in up.log."""
    status = tmp_path / "status.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "bagit.cli", "up", "--status-file", str(status), "--workdir", str(tmp_path / "work"), *args],
        stdout=subprocess.PIPE, stderr=open(tmp_path / "up.log", "w"), env=ENV, text=True,
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

    assert wait_until(ready, timeout, 0.1), f"children {want} not started: {path}"
    return json.loads(path.read_text())


def up_log(tmp_path: Path) -> str:
    return (tmp_path / "up.log").read_text(errors="replace")


@contextmanager
def rig_up(tmp_path: Path, *args: str) -> Iterator[SimpleNamespace]:
    """`bagit up ARGS` with every service up and a test peer on its hub. Yields a namespace with
    `status` (the status dict), `status_path`, `session`, `keys`, `state` (run/state cache) and
    `cmds` (every controller/cmd as (monotonic time, Command)); SIGTERMs the rig afterwards."""
    from bagit.common.bus import BusConfig, Keys, LatestCache, Subscriber, open_session
    from bagit.common.messages import Command, RunState

    proc, status_path = start_up(tmp_path, *args)
    session = None
    try:
        d = wait_status(status_path, ALL)
        assert wait_until(lambda: "all services up" in up_log(tmp_path), 150, 0.2), up_log(tmp_path)
        session = open_session(BusConfig(rig=d["rig"], connect=[d["connect"]]))
        keys = Keys(d["rig"])
        cmds: list = []
        Subscriber(session, keys.controller_cmd, Command, lambda c: cmds.append((time.monotonic(), c)))
        yield SimpleNamespace(status=d, status_path=status_path, session=session, keys=keys,
                              state=LatestCache(session, keys.run_state, RunState), cmds=cmds)
    finally:
        if session is not None:
            session.close()
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)
