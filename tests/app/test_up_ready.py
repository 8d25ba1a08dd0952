"""`bagit up`'s readiness: what a run waits for, and when the rig is said to be all up.

The supervisor's bookkeeping (no process): the liveliness watcher is a set the test fills, as the bus
would; the start's retry asks a coordinator of the test's on two in-process peers. The whole path,
services included, is tests/app/test_up.py's.
"""

from __future__ import annotations

import io
import os
import threading

from bus_support import assert_same_message, example_message, wait_until

from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, open_session, serve_run_control
from bagit.common.messages import RunControl, RunControlReply, SoiState
from bagit.common.names import NO_SIM_CLOCK_YET
from bagit.up import SERVICES, UNIX_PATH_MAX, WATCHERS, Child, Up, UpOptions, local_endpoint


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


def test_the_rigs_processes_link_over_unix_sockets_in_its_folder_and_over_tcp_when_the_path_is_too_long(tmp_path):
    up = Up(UpOptions(scenario="exp02", workdir=tmp_path), log=io.StringIO())
    up._write_configs()  # noqa: SLF001 - the hub and the configs, no process started
    assert up.hub == f"unixsock-stream/{tmp_path.resolve()}/hub.sock"
    argv = up._argv("perception", tmp_path / "zenoh.json5", tmp_path / "rig.yaml")  # noqa: SLF001
    listen = argv[argv.index("--listen") + 1]
    assert listen == local_endpoint(tmp_path, "perception") == f"unixsock-stream/{tmp_path.resolve()}/perception.sock"
    # a message crosses such a link: one session listening on the service's socket, one connected to it
    with open_session(BusConfig(rig="t", listen=[listen])) as a, open_session(BusConfig(rig="t", listen=[], connect=[listen])) as b:
        got: list[SoiState] = []
        key = Keys("t").perception_soi
        sub = Subscriber(b, key, SoiState, got.append)
        pub = Publisher(a, key, SoiState)
        msg = example_message("soi")
        assert wait_until(lambda: (pub.put(msg), bool(got))[1], timeout=10.0)
        assert_same_message(got[0], msg)
        sub.close()
    deep = tmp_path / ("d" * (UNIX_PATH_MAX - len(os.fsencode(tmp_path.resolve())) - 6))
    deep.mkdir()
    assert local_endpoint(deep, "perception") is None  # sun_path has no room: loopback TCP instead
    deep_up = Up(UpOptions(scenario="exp02", workdir=deep), log=io.StringIO())
    deep_up._write_configs()  # noqa: SLF001
    assert deep_up.hub.startswith("tcp/127.0.0.1:")
    assert "--listen" not in deep_up._argv("perception", deep / "zenoh.json5", deep / "rig.yaml")  # noqa: SLF001


def test_a_start_refused_for_the_simulators_clock_not_yet_heard_is_asked_again_and_any_other_refusal_is_final(tmp_path, pair):
    # In lockstep the coordinator refuses a start before the simulator's first tick (NO_SIM_CLOCK_YET), which
    # "all up" can precede on a loaded machine; `bagit up` asks again until it is heard.
    a, b = pair
    up, _, _ = _up(tmp_path)
    up.session, up.keys = a, Keys(up.opts.rig)
    asked: list[RunControl] = []

    def coordinator(req: RunControl) -> RunControlReply:
        asked.append(req)
        if len(asked) < 3:
            return RunControlReply(accepted=False, reason=f"{NO_SIM_CLOCK_YET}: is `bagit sim` up?")
        return RunControlReply(accepted=len(asked) == 3, run_id="r1", reason=None if len(asked) == 3 else "a run is in progress")

    with serve_run_control(b, up.keys, coordinator):
        rep = up.start_run("exp02")
        assert rep.accepted and rep.run_id == "r1" and len(asked) == 3 and asked[-1].scenario == "exp02"
        rep = up.start_run("exp02")
        assert not rep.accepted and rep.reason == "a run is in progress" and len(asked) == 4  # at once: no retry
