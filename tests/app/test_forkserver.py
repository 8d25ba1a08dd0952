"""`bagit.forkserver`: `bagit up`'s services forked from one interpreter that imported what they share.

Each test runs the real server process and real `bagit` commands through it: what a child gets
(its output on its pipe, its own process group, its niceness, SIGSTOP and SIGCONT, its exit status)
and what happens when the server goes.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
from pathlib import Path

import pytest
from suite_support import HANG_S, wait_until

from bagit.forkserver import PRELOAD, ForkServer, _cpus, child_env

pytestmark = [pytest.mark.processes, pytest.mark.timeout(180)]


def _stat(pid: int) -> list[str]:
    """/proc/PID/stat's fields after the command name: [0] state, [1] ppid, [2] pgrp, [16] nice."""
    return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()


@pytest.fixture
def server():
    fs = ForkServer(child_env())
    yield fs
    fs.close()


@pytest.fixture
def planner_argv(tmp_path):
    """A real service with nothing to talk to: the planner on a bus of its own (no peers, no scouting)."""
    z = tmp_path / "zenoh.json5"
    z.write_text(json.dumps({"mode": "peer", "listen": {"endpoints": ["tcp/127.0.0.1:0"]},
                             "scouting": {"multicast": {"enabled": False}}}), encoding="utf-8")
    return ["planner", "--rig", "forktest", "--zenoh-config", str(z)]


def test_a_command_forked_by_the_server_prints_on_its_pipe_and_its_exit_status_is_reported(server):
    ok = server.spawn(["--version"])
    assert ok.stdout.read().strip().startswith("bagit ")
    assert ok.wait(HANG_S) == 0
    bad = server.spawn(["run", "exp02", "--seed", "-1"])
    err = bad.stdout.read()
    assert bad.wait(HANG_S) == 2  # a usage error, as `bagit run --seed -1` gives it
    assert err.count("\n") == 1 and "--seed" in err


def _ready(p) -> list[str]:
    """The service's lines up to its "Ctrl-C to stop" (it is up)."""
    lines: list[str] = []
    assert wait_until(lambda: lines.append(p.stdout.readline()) or "Ctrl-C to stop" in lines[-1] or not lines[-1], HANG_S, 0), lines
    assert "Ctrl-C to stop" in lines[-1], lines
    return lines


def test_a_service_forked_by_the_server_is_a_fork_in_its_own_group_niced_on_its_cpus_and_stops_on_sigterm(server, planner_argv):
    cpus = sorted(os.sched_getaffinity(0))
    p = server.spawn(planner_argv, niceness=1, cpus=cpus[-1:])  # a little: a loaded machine leaves a niced stop little CPU
    _ready(p)
    st = _stat(p.pid)
    assert int(st[1]) == server.proc.pid  # forked by the server, no interpreter of its own
    assert Path(f"/proc/{p.pid}/cmdline").read_bytes().split(b"\0")[1:3] == [b"-m", b"bagit.forkserver"]
    assert Path(f"/proc/{p.pid}/comm").read_text().strip() == "planner"  # what ps -o comm, top and pgrep -x show
    assert int(st[2]) == p.pid and int(st[16]) == min(19, os.nice(0) + 1)  # its own process group, its niceness (added to ours)
    group = Path(f"/proc/{p.pid}/autogroup")
    if group.exists():  # its session is a scheduling group of its own: the group is niced too, or the niceness counts for nothing
        assert group.read_text().split()[-1] == "1", group.read_text()
    assert os.sched_getaffinity(p.pid) == {cpus[-1]}  # the CPUs asked for, its threads' too
    assert all(os.sched_getaffinity(int(t.name)) == {cpus[-1]} for t in Path(f"/proc/{p.pid}/task").iterdir())
    with pytest.raises(subprocess.TimeoutExpired):
        p.wait(0.2)  # still running: wait gives up as Popen's does
    os.killpg(p.pid, signal.SIGTERM)
    assert p.wait(HANG_S) == 0  # the planner's clean stop, its last line flushed before the child's exit
    assert "planner stopped" in p.stdout.read()


def test_a_forked_service_can_be_paused_and_resumed_and_a_signal_ending_it_is_its_exit_status(server, planner_argv):
    p = server.spawn(planner_argv)
    _ready(p)
    os.kill(p.pid, signal.SIGSTOP)
    assert wait_until(lambda: _stat(p.pid)[0] == "T", HANG_S, 0.01)
    assert p.poll() is None  # a stopped child has not exited
    os.kill(p.pid, signal.SIGCONT)
    assert wait_until(lambda: _stat(p.pid)[0] != "T", HANG_S, 0.01)
    assert p.poll() is None
    os.killpg(p.pid, signal.SIGKILL)
    assert p.wait(HANG_S) == -signal.SIGKILL  # as subprocess gives a child ended by a signal


def test_the_server_imports_the_shared_modules_and_its_children_die_with_it(server, planner_argv):
    p = server.spawn(planner_argv)
    _ready(p)
    maps = Path(f"/proc/{server.proc.pid}/maps").read_text()
    assert "numpy" in maps and "scipy" in maps and "zenoh" in maps  # preloaded before any fork
    assert "open3d" not in maps and "mujoco" not in maps  # one service's library stays in its child
    assert "cv2" not in maps  # OpenCV starts a thread pool as it loads: never in a process that forks
    assert "jaxlib" not in maps  # nor JAX (XLA's thread pools): bimamanip loads it when its run starts
    assert {"numpy", "bagit.common.bus"} <= set(PRELOAD)
    server.proc.kill()
    assert p.wait(HANG_S) == -signal.SIGTERM  # its parent-death signal; nobody is left to report, so -SIGTERM
    assert not server.alive
    with pytest.raises(OSError):
        server.spawn(["--version"])  # `bagit up` then starts the service as an interpreter of its own


@pytest.mark.parametrize("flags", [(), ("--no-fork-server",)])
def test_bagit_up_forks_its_services_from_the_server_unless_told_not_to(tmp_path, flags):
    """The server is a fork of `bagit up` itself (its imports shared), made before OpenCV, Open3D or MuJoCo
    is loaded; with --no-fork-server each service is an interpreter of its own."""
    from up_support import start_up, up_log, wait_status

    from bagit.harness import stop_process

    proc, status = start_up(tmp_path, "--services", "planner", *flags)
    try:
        pid = wait_status(status, ("planner",))["children"]["planner"]
        assert wait_until(lambda: "all services up" in up_log(tmp_path), HANG_S, 0.1), up_log(tmp_path)
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        if flags:
            assert cmdline.split(b"\0")[1:3] == [b"-m", b"bagit.cli"]
        else:
            server = int(_stat(pid)[1])
            assert int(_stat(server)[1]) == proc.pid  # the planner's parent is the server, whose parent is bagit up
            assert cmdline == Path(f"/proc/{proc.pid}/cmdline").read_bytes()  # forks of bagit up, no interpreter started
            maps = Path(f"/proc/{server}/maps").read_text()
            assert "numpy" in maps and "zenoh" in maps
            assert "cv2" not in maps and "open3d" not in maps and "mujoco" not in maps
        assert "[planner]" in up_log(tmp_path)  # its output relayed with its prefix either way
    finally:
        assert stop_process(proc) == 0
    assert "stopped: planner " in up_log(tmp_path)  # its exit status reached bagit up


def test_a_requests_cpus_are_a_list_of_cpu_numbers_or_the_servers_own():
    assert _cpus([1, 3]) == {1, 3}
    for bad in (None, [], [-1], [True], ["1"], [1.0], "1", {"1": 1}):
        assert _cpus(bad) is None, bad
