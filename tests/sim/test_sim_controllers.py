"""The simulated CR5 controller without sockets: states, queued motions, servo tracking, alarms, feedback."""

import threading

import numpy as np
import pytest

from bagit.common import cr5, dobot
from bagit.services.sim.cr5_sim import SimulatedCR5

READY = np.radians([0.0, 0.0, -90.0, 0.0, 90.0, 0.0])


def run(arm: SimulatedCR5, seconds: float, dt: float = 0.004) -> None:
    for _ in range(int(round(seconds / dt))):
        arm.step(dt)


def settle(arm: SimulatedCR5, timeout: float = 10.0) -> float:
    """Step until the arm is idle; returns the simulated time it took."""
    t0 = arm.time
    while arm.robot_mode() == dobot.RobotMode.RUNNING and arm.time - t0 < timeout:
        arm.step(0.004)
    assert arm.robot_mode() == dobot.RobotMode.ENABLE
    return arm.time - t0


def test_start_disabled_then_enable_disable():
    a = SimulatedCR5(q0=READY)
    assert a.robot_mode() == 4 and not a.enabled
    assert a.mov_j(joint_deg=np.degrees(READY)) == (-1, 0)
    assert a.enable(load=0.3) == 0 and a.robot_mode() == 5
    assert a.disable() == 0 and a.robot_mode() == 4
    with pytest.raises(ValueError):
        SimulatedCR5(q0=np.radians([0, 0, 175, 0, 0, 0]))


def test_movj_reaches_its_target_and_speed_factor_scales_the_time():
    times = []
    for factor in (100, 25):
        a = SimulatedCR5(q0=READY)
        a.enable()
        a.set_speed_factor(factor)
        target = np.degrees(READY) + [40, -20, 30, 10, -15, 60]
        code, cmd_id = a.mov_j(joint_deg=target)
        assert code == 0 and cmd_id == 1
        times.append(settle(a))
        assert np.allclose(a.get_angle_deg(), target, atol=0.01)
        assert a.current_command_id == 1
    assert times[1] > 2.0 * times[0]  # a quarter of the speed and acceleration: at least twice as long


def test_movl_keeps_the_flange_on_a_straight_line():
    a = SimulatedCR5(q0=READY)
    a.enable()
    start = a.get_pose6()
    goal = start + [-150, 120, 80, 0, 0, 0]
    assert a.mov_l(pose6=goal, v=50)[0] == 0
    p0, p1 = start[:3], goal[:3]
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    worst = 0.0
    while a.robot_mode() == 7:
        a.step(0.004)
        p = a.get_pose6()[:3]
        worst = max(worst, float(np.linalg.norm((p - p0) - np.dot(p - p0, d) * d)))
    assert worst < 1.0  # mm off the line while tracking
    assert np.allclose(cr5.pose6_to_matrix(a.get_pose6()), cr5.pose6_to_matrix(goal), atol=5e-5)


def test_servo_tracking_lags_and_respects_the_joint_speed_limit():
    def lag_mm(gain: float) -> float:
        a = SimulatedCR5(q0=READY)
        a.enable()
        p = a.get_pose6()
        lags = []
        for _k in range(40):
            p[1] += 3.0  # 100 mm/s
            assert a.servo_p(p.copy(), t=0.03, gain=gain) == 0
            run(a, 0.03)
            lags.append(p[1] - a.get_pose6()[1])
            assert np.all(np.abs(a.qd) <= cr5.JOINT_SPEED_LIMIT + 1e-9)
        return float(np.median(lags[10:]))

    default, stiff = lag_mm(500), lag_mm(1000)
    assert 0.5 < default < 6.0  # a steady 100 mm/s trails by a few ms' worth
    assert stiff < default


def test_unreachable_and_forbidden_targets_raise_alarms():
    a = SimulatedCR5(q0=READY)
    a.enable()
    far = a.get_pose6() + [2000, 0, 0, 0, 0, 0]
    assert a.servo_p(far) == -1
    assert a.alarms() == [dobot.Alarm.IK_NO_SOLUTION] and a.robot_mode() == 9
    assert a.mov_j(joint_deg=np.degrees(READY)) == (-2, 0)  # refused while in error
    assert a.clear_error() == 0 and a.robot_mode() == 5
    assert a.mov_j(joint_deg=[0, 0, -170, 0, 90, 0])[0] == -1
    assert a.alarms() == [dobot.joint_limit_alarm(2, positive=False)]
    a.clear_error()
    q = np.degrees(a.q)
    q[1] += 30  # 30 deg in 50 ms is 600 deg/s
    assert a.servo_j(q, t=0.05) == -1 and a.alarms() == [dobot.overspeed_alarm(1)]


def test_an_alarm_stops_the_arm_where_it_is():
    a = SimulatedCR5(q0=READY)
    a.enable()
    a.mov_j(joint_deg=np.degrees(READY) + [60, 0, 0, 0, 0, 0])
    run(a, 0.5)
    a.raise_alarm(dobot.Alarm.FLANGE_INTERFERENCE)
    run(a, 0.5)
    q_stop = a.q
    run(a, 0.5)
    assert np.allclose(a.q, q_stop, atol=1e-6) and np.allclose(a.qd, 0, atol=1e-6)
    assert 5 < np.degrees(q_stop[0]) < 55  # it stopped on the way, not at the target


def test_emergency_stop_disables_and_latches():
    a = SimulatedCR5(q0=READY)
    a.enable()
    a.emergency_stop(True)
    assert not a.enabled and a.robot_mode() == 9
    assert a.gate() == -3 and a.enable() == -3
    a.clear_error()
    assert a.alarms() == [dobot.Alarm.SOFTWARE_ESTOP]
    a.emergency_stop(False)
    a.clear_error()
    assert a.robot_mode() == 4 and a.enable() == 0


def test_same_commands_same_motion():
    def trajectory() -> np.ndarray:
        a = SimulatedCR5(q0=READY)
        a.enable()
        p = a.get_pose6()
        out = []
        for _k in range(30):
            p[0] -= 2.0
            p[2] += 1.0
            a.servo_p(p.copy(), t=0.03)
            run(a, 0.03)
            out.append(a.q)
        a.mov_l(pose6=p + [0, 50, 0, 0, 0, 0])
        run(a, 0.5)
        out.append(a.q)
        return np.array(out)

    assert np.array_equal(trajectory(), trajectory())


def test_commands_from_other_threads_while_stepping():
    a = SimulatedCR5(q0=READY)
    a.enable()
    p0 = a.get_pose6()
    errors = []

    def stream() -> None:
        try:
            for k in range(200):
                p = p0 + [0, 0, 20 * np.sin(k / 20), 0, 0, 0]
                assert a.servo_p(p, t=0.05) == 0
                a.get_pose6()
                a.fill_feedback()
        except Exception as e:  # noqa: BLE001 - reported below
            errors.append(e)

    t = threading.Thread(target=stream)
    t.start()
    while t.is_alive():
        a.step(0.002)
    t.join()
    assert not errors and a.alarms() == []


def test_feedback_record_reflects_the_state():
    a = SimulatedCR5(q0=READY)
    a.enable(load=0.3)
    a.mov_j(joint_deg=np.degrees(READY) + [30, 0, 0, 0, 0, 0])
    run(a, 0.1)
    rec = a.fill_feedback()
    assert int(rec["RobotMode"]) == 7 and int(rec["RunningStatus"]) == 1 and int(rec["CurrentCommandId"]) == 1
    assert np.allclose(rec["QActual"], np.degrees(a.q))
    assert np.allclose(rec["ToolVectorActual"], a.get_pose6())
    assert rec["QDActual"][0] > 0 and rec["QTarget"][0] > rec["QActual"][0]
    assert float(rec["Load"]) == pytest.approx(0.3)
    # the Cartesian speed agrees with a finite difference of the pose
    p0 = a.get_pose6()[:3]
    a.step(0.002)
    v_fd = (a.get_pose6()[:3] - p0) / 0.002
    assert np.allclose(rec["TCPSpeedActual"][:3], v_fd, rtol=0.1, atol=5.0)
    settle(a)
    rec = a.fill_feedback()
    assert int(rec["RobotMode"]) == 5 and int(rec["RunningStatus"]) == 0 and int(rec["EnableStatus"]) == 1
    assert int(rec["BrakeStatus"]) == 0x3F
