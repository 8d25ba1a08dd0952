"""Liveliness: services appear and disappear within a second, whether their session closes
cleanly or their process is killed outright (the 1 s link lease)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest
from bus_support import wait_until
from suite_support import HANG_S

from bagit.common.bus import BusConfig, Keys, LivelinessWatcher, declare_alive, locators, open_session


def test_service_appears_and_disappears_when_its_session_closes(pair):
    a, _ = pair
    keys = Keys("live")
    events: list[tuple[str, bool, float]] = []
    watcher = LivelinessWatcher(a, keys, on_change=lambda s, up: events.append((s, up, time.monotonic())))
    assert watcher.alive() == set()

    # a separate session, like a separate service, connected to A
    c = open_session(BusConfig(rig="live", connect=locators(a)))
    try:
        t0 = time.monotonic()
        token = declare_alive(c, keys, "controller")  # noqa: F841 - held: a dropped token is undeclared
        assert watcher.wait_for("controller", True, timeout=HANG_S)
        assert events[0][:2] == ("controller", True) and events[0][2] >= t0
        assert watcher.alive() == {"controller"}
    finally:
        t_close = time.monotonic()
        c.close()
    assert watcher.wait_for("controller", False, timeout=HANG_S)
    assert events[-1][:2] == ("controller", False) and events[-1][2] >= t_close
    assert watcher.alive() == set()


def test_a_dropped_token_is_undeclared(pair):
    a, b = pair
    keys = Keys("drop")
    watcher = LivelinessWatcher(a, keys)
    token = declare_alive(b, keys, "planner")
    assert watcher.wait_for("planner", True, HANG_S)
    del token  # a service must hold its token for as long as it runs
    assert watcher.wait_for("planner", False, HANG_S)


def test_undeclaring_the_token_and_history(pair):
    a, b = pair
    keys = Keys("hist")
    tok = declare_alive(b, keys, "perception")
    tok2 = declare_alive(b, keys, "planner")  # noqa: F841
    # a watcher that starts later still learns who is already alive
    assert wait_until(lambda: LivelinessWatcher(a, keys).alive() == {"perception", "planner"})
    w = LivelinessWatcher(a, keys)
    assert w.wait_for("perception", True, HANG_S)
    tok.undeclare()
    assert w.wait_for("perception", False, HANG_S)
    assert w.alive() == {"planner"}
    # another rig's services are not ours
    assert LivelinessWatcher(a, Keys("other")).wait_for("planner", True, 0.2) is False


@pytest.mark.processes
def test_a_killed_process_is_noticed_by_its_lease(pair):
    a, _ = pair
    keys = Keys("kill")
    events: list[tuple[str, bool, float]] = []
    watcher = LivelinessWatcher(a, keys, on_change=lambda s, up: events.append((s, up, time.monotonic())))
    child = textwrap.dedent(
        f"""
        import sys, time
        from bagit.common.bus import BusConfig, Keys, declare_alive, open_session
        s = open_session(BusConfig(rig="kill", connect={locators(a)!r}))
        token = declare_alive(s, Keys("kill"), "arm-driver")
        print("ready", flush=True)
        time.sleep(60)
        """
    )
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "ready"
        assert watcher.wait_for("arm-driver", True, HANG_S)
        t_kill = time.monotonic()
        os.kill(proc.pid, signal.SIGKILL)  # no goodbye: only the lease can tell
        assert watcher.wait_for("arm-driver", False, HANG_S)  # how soon after the kill: the lease, 1 s on an idle machine
        assert events[-1][:2] == ("arm-driver", False) and events[-1][2] > t_kill
    finally:
        proc.kill()
        proc.wait(5)
