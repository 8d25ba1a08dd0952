"""A service stops on SIGTERM whatever thread the kernel hands the signal to.

A SIGTERM right after a SIGCONT (a paused service stopped, as `bagit up` and a debugger do) can land
on a non-main thread; Python only flags it there and runs the handler when the main thread wakes. A
command whose main thread waited with no time-out never stopped (4 runs in 4 here): each command's
wait now wakes to look (`wait_stop`)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from up_support import ENV

pytestmark = pytest.mark.processes


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_a_paused_planner_resumed_and_terminated_at_once_stops():
    # Once is enough for the bug it guards (it hung 4 times in 4). A rarer hang remains, seen twice in about
    # 140 tries across two stops (no line after the banner; not reproduced in 60 tries in a loop): an open bug,
    # in docs/testing.md, not something to retry past.
    argv = [sys.executable, "-m", "bagit.cli", "planner", "--rig", "sigterm", "-l", f"tcp/127.0.0.1:{_free_port()}"]
    p = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, env=ENV)
    lines: list[str] = []
    banner = threading.Event()

    def read() -> None:  # all of its log, so that a full pipe never blocks it
        assert p.stderr is not None
        for line in p.stderr:
            lines.append(line)
            if "Ctrl-C to stop" in line:  # its banner: the signal handlers are in place, its threads are up
                banner.set()

    threading.Thread(target=read, daemon=True).start()
    try:
        assert banner.wait(120), "".join(lines)[-2000:]
        time.sleep(0.2)
        os.kill(p.pid, signal.SIGSTOP)
        time.sleep(0.2)
        os.kill(p.pid, signal.SIGCONT)
        os.kill(p.pid, signal.SIGTERM)
        try:
            code = p.wait(30)
        except subprocess.TimeoutExpired:  # where it waits: every thread's stack (the CLI's SIGUSR1), in the failure
            code = None
            os.kill(p.pid, signal.SIGUSR1)
            time.sleep(1.0)
        assert code == 0, "".join(lines)[-6000:]  # stopped as asked (a lost signal left it waiting for ever)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
