"""The arm-driver service on Zenoh against two simulated CR5s (ephemeral loopback ports): commands on
controller/cmd for the run run/state shows servoing move the arms, arm/<side>/state reports them,
the watchdog holds the arms when the commands stop, an e-stop over the bus reaches both controllers
and latches, and a new stream after a hold starts from the measured poses (never from a stale
target). Who may move the arms at all (the run gate) is tests/arm_driver/test_arm_driver_gate.py."""

import threading
import time

import numpy as np
import pytest
from arm_driver_support import SIM_CFG, node_on_bus, start_sims
from bus_support import wait_until

from bagit.cli import main
from bagit.common.bus import BusConfig, Keys, LatestCache, LivelinessWatcher, Publisher, Subscriber, locators, open_session
from bagit.common.dobot import Alarm, RobotMode
from bagit.common.messages import ArmState, Command, EStop, RunState
from bagit.common.names import ESTOP_SOURCE_DASHBOARD
from bagit.services.arm_driver.driver import ArmDriver


@pytest.fixture
def rigbus(request):
    """(sims, node, peer session, keys): the node on one peer, the test's publishers on the other."""
    with node_on_bus("ad" + "".join(c for c in request.node.name if c.isalnum())[-30:], SIM_CFG) as bus:
        yield bus


RUN = "r1"


def _announce(node, peer, keys, run_id=RUN, stage="bagging"):
    """Publish run/state for a servoing run (the node moves the arms for it only) and wait until the
    node has it; returns the publisher."""
    run = Publisher(peer, keys.run_state, RunState)
    assert wait_until(lambda: run.matched)
    run.put(RunState(run_id=run_id, stage=stage))
    assert wait_until(lambda: node.run_state is not None and (node.run_state.run_id, node.run_state.stage) == (run_id, stage))
    return run


def _stream(pub, u, seconds, rate=30.0, seq0=0, run_id=RUN):
    t0 = time.monotonic()
    k = 0
    while k / rate < seconds:
        wait = t0 + k / rate - time.monotonic()
        if wait > 0:
            time.sleep(wait)
        pub.put(Command(u=u, dt=1 / rate, seq=seq0 + k, run_id=run_id))
        k += 1
    return time.monotonic(), seq0 + k


def test_commands_over_zenoh_move_the_arms_and_they_hold_when_commands_stop(rigbus):
    sims, node, peer, keys = rigbus
    states = LatestCache(peer, keys.arm_state_any, ArmState)
    trace: list[tuple[float, str, np.ndarray, float, str | None]] = []
    Subscriber(peer, keys.arm_state_any, ArmState,
               lambda s: trace.append((time.monotonic(), s.arm, s.tool_pose.copy(), s.tool_speed, s.error_reason)))
    cmd = Publisher(peer, keys.controller_cmd, Command)
    assert wait_until(lambda: len(states.items()) == 2 and cmd.matched)
    _announce(node, peer, keys)
    before = {a: states.get(keys.arm_state(a)).tool_pose[:3].copy() for a in ("left", "right")}
    v0 = 0.04
    u = np.zeros(12)
    u[0] = u[6] = v0 / 30  # both mounts along +x at 4 cm/s
    t_last, _ = _stream(cmd, u, 0.7)
    assert wait_until(lambda: node.driver.mode == "holding")

    def braked_to_rest(a: str) -> bool:
        """On ArmState: still moving after the last command, then at rest (how soon: bench/stop_time.py)."""
        rows = [(t, sp) for t, arm, _, sp, _ in list(trace) if arm == a and t > t_last]
        fast = [t for t, sp in rows if sp > 0.5 * v0]
        return bool(fast) and any(t > fast[-1] and sp < 1e-3 for t, sp in rows)

    for a in ("left", "right"):
        assert wait_until(lambda: braked_to_rest(a)), a
    after = {a: states.get(keys.arm_state(a)).tool_pose[:3] for a in ("left", "right")}
    for a in before:  # the stream added up to 2.8 cm; the arms followed, then stopped short
        assert 0.015 < after[a][0] - before[a][0] < 0.035, (a, after[a] - before[a])
        assert abs(after[a][1] - before[a][1]) < 0.003
    assert node.driver.counters["watchdog_stops"] == 1
    assert any(r and r.startswith("watchdog") for *_, r in trace)  # the event is visible on ArmState
    assert any(e.startswith("watchdog") for e in node.events)  # and on stderr
    st = node.status()
    assert st["commands"] == 21 and st["refused"] == 0 and st["mode"] == "holding"


def test_hold_command_stops_the_arms_and_estop_over_zenoh_latches_both(rigbus):
    sims, node, peer, keys = rigbus
    states = LatestCache(peer, keys.arm_state_any, ArmState)
    cmd = Publisher(peer, keys.controller_cmd, Command)
    estop = Publisher(peer, keys.estop, EStop)
    assert wait_until(lambda: len(states.items()) == 2 and cmd.matched and estop.matched)
    _announce(node, peer, keys)
    u = np.zeros(12)
    u[1], u[7] = -0.03 / 30, 0.03 / 30
    _, seq = _stream(cmd, u, 0.3)
    cmd.put(Command(u=np.zeros(12), mode="hold", reason="SOI is stale (0.60 s old)", seq=seq))
    assert wait_until(lambda: node.driver.mode == "holding")  # braked on the hold, not the watchdog
    assert node.driver.counters["watchdog_stops"] == 0
    assert any("SOI is stale" in e for e in node.events)
    t_call = time.monotonic()
    estop.put(EStop(engage=True, source="test", reason="operator"))
    assert wait_until(lambda: all(sims.robots[a].estop_pressed for a in ("left", "right")))
    for srv in sims.servers.values():
        got = [t for t, text, _ in srv.log if text == "EmergencyStop(1)"]
        assert len(got) == 1 and got[0] >= t_call
    assert wait_until(lambda: all(states.get(keys.arm_state(a)).estopped for a in ("left", "right")))
    # latched: a new stream is refused and nothing moves (judged from where the arms came to rest: a state
    # already marked e-stopped may still show the brake's last tenth of a millimetre on a busy machine)
    def tools() -> dict[str, np.ndarray]:
        return {a: states.get(keys.arm_state(a)).tool_pose[:3].copy() for a in ("left", "right")}

    def at_rest() -> bool:
        before = tools()
        time.sleep(0.1)
        return all(np.allclose(p, before[a], atol=1e-6) for a, p in tools().items())

    assert wait_until(at_rest, step=0)
    pos = tools()
    _stream(cmd, u, 0.3, seq0=seq + 1)
    time.sleep(0.2)
    assert node.driver.rejections["estopped"] >= 5 and node.driver.mode == "estopped"
    for a in pos:
        assert np.allclose(states.get(keys.arm_state(a)).tool_pose[:3], pos[a], atol=1e-4)
        assert sims.robots[a].estop_pressed
    # reset over the bus: released, enabled, and a new stream moves again
    estop.put(EStop(engage=False, source=ESTOP_SOURCE_DASHBOARD))
    assert wait_until(lambda: node.driver.mode == "holding")
    assert wait_until(lambda: not any(states.get(keys.arm_state(a)).estopped for a in ("left", "right")))
    assert all(sims.robots[a].enabled and not sims.robots[a].estop_pressed for a in ("left", "right"))
    _stream(cmd, u, 0.3, seq0=seq + 100)
    assert wait_until(lambda: states.get(keys.arm_state("right")).tool_pose[1] > pos["right"][1] + 0.004)


def test_a_new_stream_after_a_hold_starts_from_the_measured_pose():
    """While the driver holds, the arm is moved behind its back (jogged, or a simulator resetting its
    world): the next command stream starts from where the arm IS, not from the old target."""
    sims = start_sims()
    drv = ArmDriver(sims.rig, SIM_CFG)
    try:
        drv.start()
        u = np.zeros(12)
        u[0] = u[6] = 0.03 / 30
        for k in range(12):
            assert drv.submit(Command(u=u, dt=1 / 30, seq=k))
            time.sleep(1 / 30)
        assert wait_until(lambda: drv.mode == "holding")
        time.sleep(0.2)
        held = drv.states()["left"].tool_pose[:3].copy()
        robot = sims.robots["left"]
        q = np.degrees(robot.q)
        robot.mov_j(joint_deg=q + np.array([4.0, 0, 0, 0, 0, 0]))  # the operator jogs joint 1 by 4 degrees
        assert wait_until(lambda: np.linalg.norm(drv.states()["left"].tool_pose[:3] - held) > 0.02)
        # the jog is over when the controller says so (RobotMode ENABLE, not RUNNING): a joint speed near zero
        # is also the quintic's last milliseconds, and a ServoP while the MovJ runs is refused (a fault)
        assert wait_until(lambda: int(drv.links.record("left")["RobotMode"]) == RobotMode.ENABLE)
        moved = drv.states()["left"].tool_pose[:3].copy()
        assert drv.mode == "holding"
        t0 = time.monotonic()
        small = np.zeros(12)
        small[2] = small[8] = 0.01 / 30  # 1 cm/s up
        for k in range(6):
            assert drv.submit(Command(u=small, dt=1 / 30, seq=100 + k)), (drv.last_refusal, drv.status())
            time.sleep(1 / 30)
        time.sleep(0.3)
        sent = [np.array([float(v) for v in text[len("ServoP("):].split(",")[:3]]) / 1000.0
                for t, text, reply in sims.servers["left"].commands("ServoP") if t > t0]
        assert sent, "no ServoP after the new stream"
        now = drv.states()["left"].tool_pose[:3]
        assert np.linalg.norm(now - moved) < 0.01, (now - moved)  # it stayed where it was jogged to (+ a few mm up)
        assert np.linalg.norm(now - held) > 0.015  # and was not driven back to the stale target
        assert drv.mode in ("holding", "streaming", "stopping") and drv.status()["fault"] is None
    finally:
        drv.close()
        sims.close()


def test_cli_arm_driver_brings_up_publishes_states_with_liveliness_and_disables_on_exit(tmp_path, capsys):
    sims = start_sims()
    rig = sims.rig.model_copy(update={"name": "adcli"})
    (tmp_path / "rig.yaml").write_text(rig.to_yaml())
    (tmp_path / "arm-driver.yaml").write_text("rig_config: rig.yaml\nstate_rate_hz: 50\ndriver:\n  feedback_timeout_s: 0.5\n")
    keys = Keys("adcli")
    s = open_session(BusConfig(rig="adcli", adminspace=True))
    got: list[ArmState] = []
    alive: list[bool] = []
    try:
        Subscriber(s, keys.arm_state_any, ArmState, got.append)
        LivelinessWatcher(s, keys, on_change=lambda name, up: alive.append(up) if name == "arm-driver" else None)
        result: dict = {}
        args = ["arm-driver", "--config", str(tmp_path / "arm-driver.yaml"), "--duration", "2", "-e", locators(s)[0], "--json"]
        t = threading.Thread(target=lambda: result.setdefault("code", main(args)))
        t.start()
        t.join(20)
        assert not t.is_alive() and result["code"] == 0
        assert alive[:1] == [True] and wait_until(lambda: alive[-1] is False)
    finally:
        s.close()
        sims.close()
    assert {m.arm for m in got} == {"left", "right"} and any(m.enabled for m in got)
    n_left = sum(m.arm == "left" for m in got)
    assert 20 <= n_left <= 50 * 2.2 + 5, n_left  # about 50 Hz for up to ~2 s (not every 8 ms packet)
    assert not any(sims.robots[a].enabled for a in ("left", "right"))  # disabled on exit
    out = capsys.readouterr()
    assert '"states_published"' in out.out and "both arms enabled" in out.err


def test_cli_arm_driver_with_no_controller_is_a_one_line_error(tmp_path, capsys):
    from bagit.common.rig import RigConfig

    rig = RigConfig(name="adnone")
    arms = {a: c.model_copy(update={"dashboard_port": 1, "feedback_port": 2}) for a, c in rig.arms.items()}
    (tmp_path / "rig.yaml").write_text(rig.model_copy(update={"arms": arms}).to_yaml())
    assert main(["arm-driver", "--rig-config", str(tmp_path / "rig.yaml"), "--duration", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "error" in err


def test_a_new_run_clears_a_fault_latched_in_the_last_one_but_never_the_estop(rigbus):
    sims, node, peer, keys = rigbus
    states = LatestCache(peer, keys.arm_state_any, ArmState)
    cmd = Publisher(peer, keys.controller_cmd, Command)
    run = Publisher(peer, keys.run_state, RunState)
    estop = Publisher(peer, keys.estop, EStop)
    assert wait_until(lambda: len(states.items()) == 2 and cmd.matched and run.matched and estop.matched)
    run.put(RunState(run_id="r1", stage="planning"))  # nothing latched: nothing to clear
    sims.robots["left"].raise_alarm(int(Alarm.FLANGE_INTERFERENCE))
    assert wait_until(lambda: node.driver.mode == "fault")
    assert wait_until(lambda: states.get(keys.arm_state("right")).error)  # the fault is on ArmState
    run.put(RunState(run_id="r1", stage="bagging"))  # the same run going on: the fault stays
    run.put(RunState(run_id="r2", stage="done"))  # a run that is over: the fault stays
    time.sleep(0.5)
    assert node.driver.mode == "fault"
    run.put(RunState(run_id="r3", stage="perceiving"))  # a new run: ClearError, enable, restart
    assert wait_until(lambda: node.driver.mode == "holding"), node.driver.status()
    assert not sims.robots["left"].alarms() and any(e.startswith("fault_cleared: run r3") for e in node.events)
    run.put(RunState(run_id="r3", stage="pre-bagging"))  # r3 servoes: its commands move the arms again
    assert wait_until(lambda: node.run_state.stage == "pre-bagging")
    u = np.zeros(12)
    u[2] = u[8] = 0.03 / 30
    z0 = states.get(keys.arm_state("left")).tool_pose[2]
    _stream(cmd, u, 0.4, run_id="r3")
    assert wait_until(lambda: states.get(keys.arm_state("left")).tool_pose[2] > z0 + 0.004)
    # an e-stop latched is not released by starting a run
    estop.put(EStop(engage=True, source="test"))
    assert wait_until(lambda: node.driver.mode == "estopped")
    run.put(RunState(run_id="r4", stage="perceiving"))
    time.sleep(0.5)
    assert node.driver.mode == "estopped" and all(sims.robots[a].estop_pressed for a in ("left", "right"))
