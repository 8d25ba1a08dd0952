"""`bagit bench multihost`: the rig split over network namespaces (bench/multihost.py).

The short form (`--quick`) as root: the committed Procfiles and secured host configs bring the rig up
on three hosts, each its own network namespace and address; the arms' cable is pulled in a run's
servoing and plugged back; the next run servos. What happened and in what order is asserted here; how
fast (the arms' stop after the last command) is the full benchmark's record. Not root: the command
says so in one line and exits 2, and the namespace tests skip.
"""

from __future__ import annotations

import ipaddress
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bagit.bench import multihost
from bagit.common.messages import Command, RecorderStatus
from bagit.common.results import recording_report
from bagit.harness import ENV, wait_until

pytestmark = pytest.mark.processes  # namespaces, the rig's services, a router: processes of their own

LAB_NET = ipaddress.ip_network("198.18.0.0/15")


def _root_reason() -> str | None:
    try:
        multihost.need_root()
    except multihost.NotRoot as e:
        return str(e)
    if subprocess.run(["ip", "netns", "list"], capture_output=True).returncode != 0:
        return "no `ip netns` on this machine"
    return None


needs_root = pytest.mark.skipif(_root_reason() is not None, reason=_root_reason() or "")


def test_not_root_is_one_line_and_exit_status_2(monkeypatch, capsys):
    from bagit.cli import main

    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert main(["bench", "multihost"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs root" in err[0]


def test_soi_ages_are_judged_on_the_true_clock():
    """A hold for a stale SOI that was fresh, a servo step on one that was stale: counted against the
    ages the camera host's known offset gives back."""
    def cmd(stamp: float, source: float, mode: str, reason: str | None = None) -> tuple[float, Command]:
        return (0.0, Command(u=np.zeros(12), stamp=stamp, source_stamp=source, mode=mode, reason=reason))

    cmds = [cmd(100.0, 99.9 + 0.3, "servo"),  # cam 0.3 s ahead: 0.1 s old in truth, servoed on: right
            cmd(100.0, 99.4 + 0.3, "servo"),  # 0.6 s old in truth, servoed on: stale taken as fresh
            cmd(100.0, 99.8 + 0.3, "hold", "SOI is stale (0.5 s old)"),  # 0.2 s old in truth, held: fresh taken as stale
            cmd(100.0, 0.0, "hold", "no SOI received")]  # no SOI: not judged
    assert multihost.soi_judgement(cmds, 0.3, 0.5) == {"commands": 3, "fresh_taken_as_stale": 1, "stale_taken_as_fresh": 1}


def test_a_runs_recording_report_counts_from_the_runs_start_or_the_recorders():
    before = RecorderStatus(started=1.0, messages=100, lost=0)
    assert recording_report(before, RecorderStatus(started=1.0, messages=400)).ok
    full = recording_report(before, RecorderStatus(started=1.0, messages=100, lost=250, errors=20, error="disk full (ENOSPC) on x"))
    assert not full.ok and full.lost == 250 and full.errors == 20 and "disk full" in full.error
    restarted = recording_report(before, RecorderStatus(started=2.0, messages=7, lost=3, errors=1, last_error="disk full"))
    assert not restarted.ok and restarted.lost == 3 and restarted.messages == 7
    assert recording_report(before, None) is None


@needs_root
def test_the_short_form_across_three_namespaces_with_a_pulled_cable(tmp_path):
    r = subprocess.run([sys.executable, "-m", "bagit.cli", "bench", "multihost", "--quick", "--json", "--out", str(tmp_path)],
                       capture_output=True, text=True, env=ENV, timeout=900)
    assert r.returncode in (0, 1), r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    hosts = out["hosts"]
    assert {h for h, v in hosts.items() if v["services"]} == {"plan", "cam", "arms"}
    assert {"router", "planner", "controller", "dashboard", "recorder"} <= set(hosts["plan"]["services"])
    assert set(hosts["cam"]["services"]) == {"sim", "perception"} and hosts["arms"]["services"] == ["arm-driver"]
    assert all(ipaddress.ip_address(v["address"]) in LAB_NET for v in hosts.values())
    assert len({v["address"] for v in hosts.values()}) == 4
    assert out["distinct_namespaces"] >= 3 and out["tls"] is True
    cut = out["cut"]
    # the run servoed, the cable went, the run failed naming the lost service; the arms came to rest
    stages = cut["stages"]
    assert "pre-bagging" in stages and stages[-1] == "failed", stages
    assert "arm-driver" in cut["reason"] and cut["run_success"] is False
    assert cut["arms_stopped_ms"] is not None
    # plugged back: the driver is back by itself, nothing else had to be restarted, the next run servos
    assert cut["arm_driver_back"] and cut["all_processes_running"] and cut["next_run_servoing"]
    assert out["leftovers"] == [] and multihost.leftovers() == []
    assert out["checks"] == {"namespaces": True, "cut_reason": True, "cut_next": True, "clean": True}
    assert list(tmp_path.glob("multihost-*.md"))


@needs_root
def test_ctrl_c_and_a_killed_bench_leave_nothing_behind():
    """Ctrl-C while the rig comes up: the bench removes its namespaces, links and files itself. SIGKILL:
    what it left is found by its prefix and removed by the next start."""
    for sig in (signal.SIGINT, signal.SIGKILL):
        p = subprocess.Popen([sys.executable, "-m", "bagit.cli", "bench", "multihost", "--quick", "--json"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=ENV, text=True)
        try:
            assert wait_until(lambda: any(x.startswith(f"{multihost.PREFIX}-") for x in multihost.leftovers()), 120, 0.1)
            time.sleep(1.0)  # services starting in the namespaces
            p.send_signal(sig)
            code = p.wait(120)
        finally:
            if p.poll() is None:
                p.kill()
                p.wait()
        if sig == signal.SIGINT:
            assert code == 130 and multihost.leftovers() == [], p.stderr.read() if p.stderr else ""
        else:
            assert code == -signal.SIGKILL and multihost.leftovers()
            removed = multihost.clean_leftovers()
            assert removed and multihost.leftovers() == []
