"""`bagit up`'s readiness: what a run waits for, and when the rig is said to be all up.

The supervisor's bookkeeping only (no process, no bus): the liveliness watcher is a set the test
fills, as the bus would. The whole path, services included, is tests/app/test_up.py's.
"""

from __future__ import annotations

import io
import threading

from bagit.up import SERVICES, WATCHERS, Child, Up, UpOptions


class Alive:
    """A LivelinessWatcher's `alive()`, filled by the test."""

    def __init__(self) -> None:
        self.names: set[str] = set()

    def alive(self) -> set[str]:
        return set(self.names)


def _up(tmp_path) -> tuple[Up, Alive, io.StringIO]:
    log = io.StringIO()
    up = Up(UpOptions(scenario="exp02", workdir=tmp_path), log=log)
    up.children = {n: Child(n, [n]) for n in SERVICES}
    watcher = Alive()
    up.watcher = watcher  # type: ignore[assignment]
    return up, watcher, log


def _come_up(up: Up, watcher: Alive, name: str) -> None:
    watcher.names.add(name)
    up._on_alive(name, True)  # noqa: SLF001 - what the watcher calls


def test_a_run_waits_for_every_service_but_the_dashboard_and_all_up_is_said_once_when_the_last_comes(tmp_path):
    up, watcher, log = _up(tmp_path)
    assert WATCHERS == ("dashboard",)
    for n in SERVICES:
        if n != "dashboard":
            _come_up(up, watcher, n)
    assert up.wait_ready(timeout=0.0, but=WATCHERS) == []  # the run may start
    assert up.wait_ready(timeout=0.0) == ["dashboard"]  # the rig is not all up
    assert up.not_up(WATCHERS) == ("dashboard",)
    assert "all services up" not in log.getvalue()
    _come_up(up, watcher, "dashboard")
    assert up.wait_ready(timeout=0.0) == [] and up.not_up(WATCHERS) == ()
    assert log.getvalue().count("all services up") == 1
    watcher.names.discard("planner")  # a service gone and back (restarted): said up, not all up again
    up._on_alive("planner", False)  # noqa: SLF001
    _come_up(up, watcher, "planner")
    assert log.getvalue().count("all services up") == 1
    assert log.getvalue().count("[up] service planner up") == 2


def test_a_wait_for_services_wakes_when_the_last_comes_up(tmp_path):
    up, watcher, _ = _up(tmp_path)
    got: list[list[str]] = []
    t = threading.Thread(target=lambda: got.append(up.wait_ready(timeout=30.0, but=WATCHERS)))
    t.start()
    for n in SERVICES:
        if n != "dashboard":
            _come_up(up, watcher, n)
    t.join(30.0)
    assert got == [[]]
