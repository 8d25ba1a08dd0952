"""`bagit up`: every service its own process on loopback.

Process hygiene (SIGTERM stops every child, a SIGKILLed `bagit up` leaves no orphans, a dead child
is restarted) runs on a subset of the services; the full simulated run (judged on the simulator's
ground truth) and the fault tests run every service.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from bus_support import wait_until
from suite_support import HANG_S
from up_support import ENV, rig_up
from up_support import alive as _alive
from up_support import start_up as _up
from up_support import up_log as _log
from up_support import wait_status as _status

from bagit.common.results import RunResult
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario

# How long both arms must read still before a test calls them at rest (a loaded simulator's pauses are shorter).
REST_S = 0.75

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]  # whole runs: the simulator slows down under load


def test_sigterm_stops_every_child_and_sigkill_leaves_no_orphans(tmp_path):
    proc, status = _up(tmp_path, "--services", "sim,planner")
    try:
        d = _status(status, ("sim", "planner"))
        pids = list(d["children"].values())
        assert wait_until(lambda: "all services up" in _log(tmp_path), 120, 0.2), _log(tmp_path)
        assert "[planner]" in _log(tmp_path) and "[sim]" in _log(tmp_path)  # prefixed child output
        cpus = sorted(os.sched_getaffinity(0))
        if len(cpus) > 1:  # the simulator keeps the first CPU to itself: the planner runs on the rest, the simulator on all
            assert os.sched_getaffinity(d["children"]["sim"]) == set(cpus)
            assert os.sched_getaffinity(d["children"]["planner"]) == set(cpus[1:])
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(60) == 0
        assert not any(_alive(p) for p in pids), _log(tmp_path)
    finally:
        if proc.poll() is None:
            proc.kill()
    proc, status = _up(tmp_path, "--services", "sim,planner")
    d = _status(status, ("sim", "planner"))
    pids = list(d["children"].values())
    proc.kill()  # no chance to clean up: the children's parent-death signal must do it
    proc.wait(10)
    assert wait_until(lambda: not any(_alive(p) for p in pids), 30, 0.1), "orphans left behind"


def test_a_dead_child_is_restarted_and_its_new_pid_published(tmp_path):
    proc, status = _up(tmp_path, "--services", "planner")
    try:
        d = _status(status, ("planner",))
        old = d["children"]["planner"]
        assert wait_until(lambda: "all services up" in _log(tmp_path), 120, 0.2), _log(tmp_path)
        os.kill(old, signal.SIGKILL)

        def restarted() -> bool:
            d = json.loads(status.read_text())
            return d["restarts"]["planner"] == 1 and d["children"]["planner"] not in (None, old)

        assert wait_until(restarted, 60, 0.2), _log(tmp_path)
        assert wait_until(lambda: _log(tmp_path).count("[up] service planner up") >= 2, 60, 0.2), _log(tmp_path)
        new = json.loads(status.read_text())["children"]["planner"]
        assert os.sched_getaffinity(new) == os.sched_getaffinity(0)  # no simulator among the children: every CPU
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(60)


def test_bad_input_is_a_one_line_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "bagit.cli", "up", "no-such-scenario"], capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode == 2 and "no scenario" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    r = subprocess.run([sys.executable, "-m", "bagit.cli", "up", "--exit-when-done"], capture_output=True, text=True, env=ENV, timeout=60)
    assert r.returncode == 2 and "needs a SCENARIO" in r.stderr


def _why(log: str) -> str:
    """What a failed bagit up run said about itself: its alarm, fault, stale/implausible-SOI lines
    (first few of each kind) and how often the simulation fell behind real time and the watchdog fired."""
    keys = ("alarm", "fault", "stale", "implausible", "slowed", "error")
    kept: dict[str, list[str]] = {}
    for ln in log.splitlines():
        k = next((k for k in keys if k in ln), None)
        if k is not None and "clipped" not in ln and len(kept.setdefault(k, [])) < 3:
            kept[k].append(ln.strip())
    return (f"{log.count('behind real time')} behind-real-time and {log.count('watchdog')} watchdog lines; "
            + " | ".join(ln for v in kept.values() for ln in v))


@contextlib.contextmanager
def _reference_run(*args: str) -> Iterator[Callable[[], subprocess.CompletedProcess]]:
    """`bagit run ARGS --json` started now, in its own process beside the test's rig; the context's value
    waits for it (at most 300 s) and gives the finished process. Killed if the test ends first."""
    argv = [sys.executable, "-m", "bagit.cli", "run", *args, "--json"]
    p = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=ENV)

    def finished() -> subprocess.CompletedProcess:
        out, err = p.communicate(timeout=300)
        return subprocess.CompletedProcess(argv, p.returncode, out, err)

    try:
        yield finished
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()


def _paused_mid_run(argv: list[str], pauses: list[tuple[str, str, float]], status: Path, log: Path) -> tuple[subprocess.CompletedProcess, list[str]]:
    """`bagit up ... --status-file status`, each (when, service, seconds) of `pauses` in turn: once `when` is in
    its log, `service` stopped (SIGSTOP) for that long, then resumed (SIGCONT); the finished process (its log
    as stderr) and the order of what happened ("ended" last: the run ended after every pause)."""
    events: list[str] = []
    with open(log, "w") as err:
        p = subprocess.Popen(argv + ["--status-file", str(status)], stdout=subprocess.PIPE, stderr=err, text=True, env=ENV)
        try:
            for when, service, pause_s in pauses:
                assert wait_until(lambda: when in log.read_text(), 300, 0.02), log.read_text()[-3000:]
                pid = json.loads(status.read_text())["children"][service]
                os.kill(pid, signal.SIGSTOP)
                time.sleep(pause_s)  # longer than the 1 s link lease of the wall clock, and than any old bounded wait
                os.kill(pid, signal.SIGCONT)
                events.append(f"{service} paused at {when}")
            out, _ = p.communicate(timeout=420)
            events.append("ended")
        finally:
            if p.poll() is None:
                p.kill()
    return subprocess.CompletedProcess(p.args, p.returncode, out, log.read_text()), events


def test_a_full_simulated_run_of_its_own_bag_through_bagit_up_with_services_paused_is_bagit_runs_run_bit_for_bit(tmp_path):
    # Lockstep (the default): every service on the simulator's clock, which waits for their answers,
    # so however the two cores are shared, and even with a service stopped for seconds mid-run (SIGSTOP,
    # as a loaded machine or a debugger would), the run is the one `bagit run` computes in one process:
    # the same ticks, the same time and the same true rim, to the last bit, and it says it is exact. No retry.
    # The simulator stopped as the run starts (its world resetting, perception's first frames of it to come),
    # then the controller once the arms servo.
    # The scenario is a file of a lab's own (exp02's object in a stiffer, heavier, yellow bag with a green
    # binding): the simulated bag and perception's binding colour come from the file. Its camera runs at
    # 10 frames/s: a tick per frame leaves 100 ms between commands, past the watchdog's 90 ms gap, so the
    # simulator schedules keep-alive ticks between frames (as `bagit run` steps), which the controller
    # answers with a zero increment on its last SOI.
    doc = Scenario.from_file(find_scenario("exp02")).model_dump(mode="json", exclude_none=True)
    doc["bag"]["rim"]["color"], doc["bag"]["color"] = [0.1, 0.65, 0.2], [0.8, 0.72, 0.25]
    doc["bag"]["fabric"].update(stretch_n_per_m=16000.0, mass_kg=0.12)
    path = tmp_path / "green-hem.yaml"
    path.write_text(yaml.safe_dump(doc), encoding="utf-8")
    argv = [sys.executable, "-m", "bagit.cli", "up", str(path), "--exit-when-done", "--json", "--no-dashboard", "--fps", "10", "--timeout", "380"]
    pauses = [("perceiving", "sim", 2.0), ("pre-bagging", "controller", 3.0)]
    with _reference_run(str(path), "--fps", "10") as reference:  # beside it: a busy machine makes the rig slower, never different
        r, events = _paused_mid_run(argv, pauses, tmp_path / "status.json", tmp_path / "up.log")
        ref = reference()
    assert events == ["sim paused at perceiving", "controller paused at pre-bagging", "ended"], events
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert "watchdog" not in r.stderr and "no longer waiting" not in r.stderr and "without" not in r.stderr, _why(r.stderr)
    assert ref.returncode == 0, ref.stderr[-2000:]
    alone = RunResult.model_validate_json(ref.stdout.strip().splitlines()[-1])
    assert r.returncode == 0 and out["success"] and out["stage_reached"] == "done", (out.get("reason"), _why(r.stderr), out, r.stderr[-3000:])
    assert set(out) == set(RunResult.model_fields)  # the same top-level keys as `bagit run --json`
    res = RunResult.model_validate(out)
    assert res.exact is True and res.inexact == [] and alone.exact is None, (res.exact, res.inexact)
    assert res.arms == "cr5" and res.path_nodes > 2 and res.ticks > 0 and res.error_to_goal_m is not None
    assert res.arm_events["faults"] == 0 and res.arm_events["watchdog_stops"] == 0 and np.asarray(res.final_rim).shape == (32, 3)
    assert alone.arm_events["watchdog_stops"] == 0 and alone.ticks > 0
    # the object named by its ArUco marker (or, if perception had not yet seen it, the scenario's, said so)
    assert res.object_from == "scenario" and res.object_reason or res.object_from == "marker" and res.marker["marker_v_error_m"] < 0.005, out
    truth = res.truth  # judged on the simulator's true rim, which no service saw
    assert truth.success and not truth.passed_through and truth.error_cm < 2.0 and res.error_cm == truth.error_cm, truth
    assert (res.ticks, res.duration_s, res.error_cm, res.final_rim) == (alone.ticks, alone.duration_s, alone.error_cm, alone.final_rim)
    assert res.arm_events == alone.arm_events and res.arms == alone.arms == "cr5"
    assert "the world it started with, settled then" in r.stderr  # settled while the services started (`SimRig.resettle`)


def test_a_service_killed_in_lockstep_fails_the_run_with_the_reason_in_bounded_wall_time(tmp_path):
    # The simulator waits for the controller's answer to each frame; a dead controller's liveliness
    # token goes within ~1 s, the simulator stops waiting for it (and says so), the world steps on and
    # the coordinator fails the run on that liveliness; no wait is left hanging.
    from bagit.common.bus import LatestCache, request_run_control
    from bagit.common.messages import ClockTick, RunControl

    with rig_up(tmp_path, "--no-dashboard", "--speed", "50") as rig:
        d, session, keys, state, cmds = rig.status, rig.session, rig.keys, rig.state, rig.cmds
        clock = LatestCache(session, keys.sim_clock, ClockTick)
        rep = request_run_control(session, keys, RunControl(action="start", scenario="exp02"), timeout=10)
        assert rep.accepted, rep.reason
        assert wait_until(lambda: (s := state.get()) is not None and s.run_id == rep.run_id and s.stage in ("pre-bagging", "bagging"), 120, 0.1)
        assert wait_until(lambda: sum(c.mode == "servo" for _, c in cmds) > 10, 60, 0.05)
        os.kill(d["children"]["controller"], signal.SIGKILL)
        assert wait_until(lambda: state.get().stage == "failed", HANG_S, 0.05), (state.get(), _log(tmp_path)[-2000:])
        assert "controller" in (state.get().reason or ""), state.get()
        # and no wait is left hanging: the simulator's clock goes on (it stopped waiting for the controller,
        # or the run's end reached it first)
        t_end = clock.get().t
        assert wait_until(lambda: clock.get().t > t_end + 1.0, 20, 0.1), (clock.get(), _log(tmp_path)[-2000:])


def test_killing_the_controller_mid_run_holds_the_arms_fails_the_run_and_a_restart_runs_again(tmp_path):
    from bagit.common.bus import Subscriber, request_run_control
    from bagit.common.messages import ArmState, RunControl

    # On the wall clock, as on a real rig: the arms stop and stay still (within 250 ms of wall time on an
    # idle machine: the probe arm-kill-controller, `bagit bench probes`; a lockstep world does not move at
    # all while it waits for the dead controller: the test above).
    with rig_up(tmp_path, "--no-dashboard", "--clock", "wall") as rig:
        d, status, session, keys, state, cmds = rig.status, rig.status_path, rig.session, rig.keys, rig.state, rig.cmds
        assert os.sched_getaffinity(d["children"]["arm-driver"]) == os.sched_getaffinity(0)  # on the wall clock no CPU is kept
        seen: list[tuple[float, ArmState]] = []  # every arm state from now on, with its receive time
        arms = Subscriber(session, keys.arm_state_any, ArmState, lambda m: seen.append((time.monotonic(), m)))
        rep = request_run_control(session, keys, RunControl(action="start", scenario="exp02"), timeout=10)
        assert rep.accepted, rep.reason
        run1 = rep.run_id
        # mid-run: servoing, the arms moving
        assert wait_until(lambda: (s := state.get()) is not None and s.run_id == run1 and s.stage in ("pre-bagging", "bagging")
                          and s.progress > 0.05, 120, 0.1), state.get()
        assert wait_until(lambda: len(cmds) > 10, 30, 0.05)
        os.kill(d["children"]["controller"], signal.SIGKILL)
        # the run fails with the reason once the controller's liveliness lapses
        assert wait_until(lambda: state.get().stage == "failed", HANG_S, 0.05), state.get()
        assert "controller" in state.get().reason
        t_failed = time.monotonic()

        def still_since(t0: float) -> bool:
            """Both arms reported, and every state of either since `t0` reads < 1 mm/s."""
            since = [m for t, m in list(seen) if t >= t0]
            return {m.arm for m in since} == {"left", "right"} and all(m.tool_speed < 1e-3 for m in since)

        # the arms come to rest (braked when the commands stopped) and stay at rest for REST_S: one state reading
        # still is not rest on a loaded machine, whose simulated CR5 can go a few hundred ms without stepping while
        # its feedback still goes out (its last ServoPs, the brake's, carried out when it steps again)
        assert wait_until(lambda: still_since(time.monotonic() - REST_S) and time.monotonic() - t_failed > REST_S, HANG_S, 0.02)
        t_rest = time.monotonic()
        time.sleep(1.5)
        for arm in ("left", "right"):
            late = [(m.q, m.tool_speed) for t, m in list(seen) if t > t_rest and m.arm == arm]
            assert late, f"no {arm} arm state after the kill"
            # then they hold: no joint turns a thousandth of a radian (the speed may read a few mm/s of the
            # servo settling its last fraction of a millimetre)
            assert max(v for _, v in late) < 5e-3, f"{arm} arm moving again {max(v for _, v in late):.4f} m/s after it stopped"
            q0 = late[0][0]
            assert max(np.abs(q - q0).max() for q, _ in late) < 1e-3
        assert not [c for t, c in cmds if t > t_failed and c.run_id == run1], "commands of the run after the controller died"
        # restarted by bagit up; the next run succeeds
        assert wait_until(lambda: json.loads(status.read_text())["restarts"]["controller"] == 1, 30, 0.2)
        # bagit up's own line of the restarted controller (the planner logs one of the first start too)
        assert wait_until(lambda: _log(tmp_path).count("[up] service controller up") >= 2, 90, 0.2), _log(tmp_path)[-3000:]
        rep = request_run_control(session, keys, RunControl(action="start", scenario="exp02"), timeout=10)
        assert rep.accepted, rep.reason
        # the new controller servos the new run (a whole run to `done` is test_a_full_simulated_run's)
        n = len(cmds)
        assert wait_until(lambda: any(c.mode == "servo" and c.run_id == rep.run_id for _, c in cmds[n:]), 240, 0.2), (state.get(), _log(tmp_path)[-3000:])
        # run/state comes on its own subscription thread: it may trail the commands by a moment
        assert wait_until(lambda: (s := state.get()).run_id == rep.run_id and s.stage in ("pre-bagging", "bagging"), HANG_S, 0.05), state.get()
        stop = request_run_control(session, keys, RunControl(action="stop"), timeout=10)
        assert stop.accepted, stop.reason
        assert wait_until(lambda: state.get().stage in ("failed", "aborted"), 20, 0.1), state.get()
        arms.close()


def test_killing_perception_makes_the_controller_hold_on_stale_soi(tmp_path):
    from bagit.common.bus import request_run_control
    from bagit.common.messages import RunControl

    # On the wall clock the controller ticks on its own timer, so it sees the SOI go stale.
    with rig_up(tmp_path, "--no-dashboard", "--clock", "wall") as rig:
        d, session, keys, state, cmds = rig.status, rig.session, rig.keys, rig.state, rig.cmds
        rep = request_run_control(session, keys, RunControl(action="start", scenario="exp02"), timeout=10)
        assert rep.accepted, rep.reason
        assert wait_until(lambda: (s := state.get()) is not None and s.run_id == rep.run_id and s.stage in ("pre-bagging", "bagging"), 120, 0.1)
        assert wait_until(lambda: any(c.mode == "servo" for _, c in cmds), 30, 0.05)
        os.kill(d["children"]["perception"], signal.SIGKILL)
        t_kill = time.monotonic()
        assert wait_until(lambda: any(t > t_kill and c.mode == "hold" for t, c in cmds), HANG_S, 0.05), cmds[-3:]
        hold = next(c for t, c in cmds if t > t_kill and c.mode == "hold")
        assert hold.reason and ("stale" in hold.reason or "SOI" in hold.reason) and not np.any(hold.u)
