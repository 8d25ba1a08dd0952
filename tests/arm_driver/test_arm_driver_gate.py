"""Who may move the arms and release the e-stop (services/arm_driver/gate.py and the node around it).

The pure rules first; then the arm-driver node on Zenoh against two simulated CR5s: a command moves
the arms only if it names the run run/state shows servoing; a process that is not the run's
controller (no run, no run id, another run) moves nothing, and every refusal is counted and shown;
holds always pass; when the run the arms streamed for ends they hold at once, even while its
commands keep coming; an e-stop engages from anyone but is released only by the dashboard or the CLI.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from arm_driver_support import SIM_CFG, node_on_bus, servo_positions, stream_at_rest
from bus_support import wait_until

from bagit.common.bus import LatestCache, Publisher
from bagit.common.messages import ArmState, Command, EStop, RunState
from bagit.common.names import ESTOP_RELEASE_SOURCES, ESTOP_SOURCE_CLI, ESTOP_SOURCE_DASHBOARD, SERVO_STAGES, STAGES
from bagit.services.arm_driver.gate import (
    CLOCK_SKEW,
    ESTOP_RELEASE_SOURCE,
    NO_ACTIVE_RUN,
    STALE,
    WRONG_RUN,
    command_refusal,
    estop_refusal,
    stale_refusal,
    stream_end,
)
from bagit.services.arm_driver.node import ArmDriverNode

U = np.zeros(12)
U[0] = U[6] = 0.05 / 30  # both mounts along +x at 5 cm/s, 30 commands a second


def servo(run_id: str | None, seq: int = 0, u: np.ndarray = U) -> Command:
    return Command(u=u, dt=1 / 30, seq=seq, run_id=run_id)


# -- the rules ----------------------------------------------------------------------------------


@pytest.mark.parametrize("stage", STAGES)
def test_a_servo_command_passes_only_for_the_run_in_a_servo_stage(stage):
    run = RunState(run_id="r1", stage=stage)
    why = command_refusal(servo("r1"), run)
    if stage in SERVO_STAGES:
        assert why is None
    else:
        assert why is not None and why.reason == NO_ACTIVE_RUN and f"run r1 {stage}" in why.detail


def test_no_run_no_run_id_or_another_run_is_refused_and_a_hold_always_passes():
    bagging = RunState(run_id="r1", stage="bagging")
    assert command_refusal(servo("r1"), None).reason == NO_ACTIVE_RUN  # no run/state heard yet
    assert command_refusal(servo("r1"), RunState(run_id=None, stage="bagging")).reason == NO_ACTIVE_RUN
    assert command_refusal(servo(None), bagging).reason == WRONG_RUN
    assert command_refusal(servo("r0"), bagging).reason == WRONG_RUN
    assert "for run r0, the servoing run is r1" in command_refusal(servo("r0", seq=7), bagging).detail
    hold = Command(u=np.zeros(12), mode="hold", reason="stale SOI")
    for run in (None, RunState(), RunState(run_id="r1", stage="done"), bagging):
        assert command_refusal(hold, run) is None


def test_a_command_older_or_further_ahead_than_the_watchdog_is_refused():
    assert stale_refusal(100.0, 100.15, 0.2) is None
    assert stale_refusal(100.15, 100.0, 0.2) is None  # a little ahead: clocks a few ms apart
    old = stale_refusal(100.0, 102.0, 0.2)
    assert old.reason == STALE and "2.00 s ago" in old.detail
    assert stale_refusal(102.0, 100.0, 0.2).reason == CLOCK_SKEW
    for bad in (float("nan"), float("inf"), float("-inf")):
        assert stale_refusal(bad, 100.0, 0.2).reason == CLOCK_SKEW


def test_the_stream_ends_when_its_run_leaves_the_servo_stages_or_another_run_replaces_it():
    assert stream_end(None, RunState(run_id="r1", stage="failed")) is None  # nothing streamed: nothing to stop
    assert stream_end("r1", RunState(run_id="r1", stage="bagging")) is None
    assert stream_end("r1", RunState(run_id="r1", stage="pre-bagging")) is None
    assert stream_end("r1", RunState(run_id="r1", stage="failed", reason="arm-driver gone")) == "run r1 failed: arm-driver gone"
    assert "run r1 is over" in stream_end("r1", RunState(run_id="r2", stage="bagging"))
    assert "run r1 is over" in stream_end("r1", RunState())  # reset to idle


def test_an_estop_engages_from_anyone_and_is_released_only_by_the_operators_tools():
    assert ESTOP_RELEASE_SOURCES == (ESTOP_SOURCE_DASHBOARD, ESTOP_SOURCE_CLI) == ("dashboard", "cli")
    for source in ("controller", "planner", "arm-driver", "unknown", "", ESTOP_SOURCE_DASHBOARD):
        assert estop_refusal(EStop(engage=True, source=source)) is None
    for source in ESTOP_RELEASE_SOURCES:
        assert estop_refusal(EStop(engage=False, source=source)) is None
    for source in ("controller", "test", "unknown", "", "Dashboard", "cli "):
        why = estop_refusal(EStop(engage=False, source=source))
        assert why is not None and why.reason == ESTOP_RELEASE_SOURCE and "only dashboard and cli" in why.detail


# -- the node on the bus ------------------------------------------------------------------------


@pytest.fixture
def rigbus(request):
    """(sims, node, peer session, keys): the node on one peer, the test's publishers on the other."""
    with node_on_bus("ag" + "".join(c for c in request.node.name if c.isalnum())[-30:], SIM_CFG) as bus:
        yield bus


def _send(pub: Publisher, run_id: str | None, n: int, seq0: int = 0, rate: float = 30.0) -> None:
    for k in range(n):
        pub.put(servo(run_id, seq0 + k))
        time.sleep(1 / rate)


def _heard(node: ArmDriverNode, run_id: str | None, stage: str) -> bool:
    rs = node.run_state
    return rs is not None and (rs.run_id, rs.stage) == (run_id, stage)


def test_commands_move_the_arms_only_for_the_run_run_state_shows_servoing(rigbus):
    """The user's finding: an outside process moved both arms 180 mm with nothing running. Now a
    command moves them only if it names the servoing run; everything else is refused and counted."""
    sims, node, peer, keys = rigbus
    states = LatestCache(peer, keys.arm_state_any, ArmState)
    cmd = Publisher(peer, keys.controller_cmd, Command)
    run = Publisher(peer, keys.run_state, RunState)
    assert wait_until(lambda: len(states.items()) == 2 and cmd.matched and run.matched)
    start = {a: states.get(keys.arm_state(a)).tool_pose[:3].copy() for a in ("left", "right")}
    t0 = time.monotonic()
    big = np.zeros(12)
    big[0] = big[6] = 0.18 / 30  # the outsider's 180 mm in a second
    for k in range(10):  # nothing running, no run id: as the outsider did
        cmd.put(Command(u=big, dt=1 / 30, seq=k))
        time.sleep(1 / 30)
    run.put(RunState(run_id="r1", stage="planning"))  # a run, but the arms are not the controller's yet
    assert wait_until(lambda: _heard(node, "r1", "planning"))
    _send(cmd, "r1", 5, seq0=100)
    run.put(RunState(run_id="r1", stage="bagging"))
    assert wait_until(lambda: _heard(node, "r1", "bagging"))
    _send(cmd, None, 5, seq0=200)  # servoing now, but not for these
    _send(cmd, "r0", 5, seq0=300)
    cmd.put(Command(u=np.zeros(12), mode="hold", reason="an outsider's hold", seq=400))  # holds always pass
    assert wait_until(lambda: node.status()["commands"] == 26)
    time.sleep(0.3)
    st = node.status()
    assert st["rejections"] == {NO_ACTIVE_RUN: 15, WRONG_RUN: 10} and st["refused"] == 25, st
    for a, srv in sims.servers.items():  # nothing was streamed, nothing moved
        assert servo_positions(srv, t0=t0)[0].size == 0
        assert np.linalg.norm(states.get(keys.arm_state(a)).tool_pose[:3] - start[a]) < 1e-4
    assert any(e.startswith("refused: no_active_run: command 0 for run None: no run is servoing (no run/state yet)") for e in node.events)
    assert any(e.startswith("refused: wrong_run: command 200 is for run None, the servoing run is r1") for e in node.events)
    assert sum(e.startswith("refused: no_active_run") for e in node.events) == 1  # a flood prints one line per reason per 5 s
    # the servoing run's own commands move the arms
    _send(cmd, "r1", 12, seq0=500)
    assert wait_until(lambda: states.get(keys.arm_state("left")).tool_pose[0] > start["left"][0] + 0.01)
    late = node.status()["rejections"]
    assert {k: n for k, n in late.items() if k != STALE} == {NO_ACTIVE_RUN: 15, WRONG_RUN: 10}  # a loaded machine may deliver one late: refused stale


def test_the_arms_hold_when_the_run_they_streamed_for_ends_while_its_commands_keep_coming(rigbus):
    sims, node, peer, keys = rigbus
    states = LatestCache(peer, keys.arm_state_any, ArmState)
    cmd = Publisher(peer, keys.controller_cmd, Command)
    run = Publisher(peer, keys.run_state, RunState)
    assert wait_until(lambda: len(states.items()) == 2 and cmd.matched and run.matched)
    run.put(RunState(run_id="r1", stage="bagging"))
    assert wait_until(lambda: _heard(node, "r1", "bagging"))
    t_start = time.monotonic()
    _send(cmd, "r1", 12)
    assert node.driver.mode == "streaming"
    run.put(RunState(run_id="r1", stage="failed", reason="perception gone"))  # a controller that has not noticed yet
    t_end = time.monotonic()
    _send(cmd, "r1", 12, seq0=100)
    assert wait_until(lambda: node.driver.mode == "holding")
    # braked on the run's end (not the watchdog: commands kept coming; a loaded machine may have let one
    # lapse before it, a stream the next command started again) and every later command was refused
    events = list(node.events)
    ended = events.index("hold: run r1 failed: perception gone")
    assert not [e for e in events[ended:] if e.startswith("watchdog")], events
    assert node.status()["rejections"].get(NO_ACTIVE_RUN, 0) >= 10
    # braked to rest, then nothing more moves (how soon: bench/stop_time.py). The stream is judged from its start:
    # the arms may have reached their last target before the run ended, and the hold then sends no ServoP at all
    for srv in sims.servers.values():
        assert wait_until(lambda: stream_at_rest(srv, t_start)), (servo_positions(srv, t0=t_end)[1][-4:], list(node.events))
        t_rest = servo_positions(srv, t0=t_start)[0][-1]
        time.sleep(0.2)
        _, xyz = servo_positions(srv, t0=t_rest)
        assert np.linalg.norm(xyz - xyz[0], axis=1).max() < 1e-4
    # another run takes over: its own commands move the arms, the last run's are refused
    x0 = states.get(keys.arm_state("left")).tool_pose[0]
    run.put(RunState(run_id="r2", stage="pre-bagging"))
    assert wait_until(lambda: _heard(node, "r2", "pre-bagging"))
    _send(cmd, "r1", 5, seq0=200)
    assert node.status()["rejections"].get(WRONG_RUN, 0) == 5
    _send(cmd, "r2", 12, seq0=300)
    assert wait_until(lambda: states.get(keys.arm_state("left")).tool_pose[0] > x0 + 0.01)
    # and a new run id while r2 streams holds the arms too
    run.put(RunState(run_id="r3", stage="perceiving"))
    assert wait_until(lambda: node.driver.mode == "holding")
    assert any(e.startswith("hold: run r2 is over (run/state: run r3 perceiving)") for e in node.events)


def test_an_estop_release_is_taken_only_from_the_dashboard_or_the_cli(rigbus):
    sims, node, peer, keys = rigbus
    estop = Publisher(peer, keys.estop, EStop)
    assert wait_until(lambda: estop.matched)
    estop.put(EStop(engage=True, source="perception", reason="anyone may stop the arms"))
    assert wait_until(lambda: node.driver.mode == "estopped")
    for source in ("controller", "test", "unknown"):
        estop.put(EStop(engage=False, source=source))
    assert wait_until(lambda: node.status()["estops_received"] == 4)
    time.sleep(0.3)
    assert node.driver.mode == "estopped" and all(sims.robots[a].estop_pressed for a in ("left", "right"))
    assert node.driver.counters["estop_releases_refused"] == 3
    assert any(e.startswith("estop: reset refused, the e-stop stays latched: estop_release_source: a release from 'controller'")
               for e in node.events), node.events
    estop.put(EStop(engage=False, source=ESTOP_SOURCE_CLI))
    assert wait_until(lambda: node.driver.mode == "holding")
    assert not any(sims.robots[a].estop_pressed for a in ("left", "right"))
    estop.put(EStop(engage=True, source="arm-driver"))
    assert wait_until(lambda: node.driver.mode == "estopped")
    estop.put(EStop(engage=False, source=ESTOP_SOURCE_DASHBOARD))
    assert wait_until(lambda: node.driver.mode == "holding")
