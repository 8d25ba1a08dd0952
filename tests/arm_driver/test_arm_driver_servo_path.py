"""The servo path and its layers: Ruckig smoothing jerk-limited, increments integrated exactly, rotations
composed, smooth stops, the ServoP each arm gets, and (property test) nothing outside the limits
whatever comes in."""

import numpy as np
import pytest
from arm_driver_support import home_poses
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from bagit.common import cr5
from bagit.common.rig import ARMS, RigConfig
from bagit.common.so3 import so3_exp
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.limits import Envelope, violations
from bagit.services.arm_driver.reach import ELBOW_MARGIN_RAD
from bagit.services.arm_driver.servo_path import Cycle, ServoPath
from bagit.services.arm_driver.smoothing import RuckigSmoother
from bagit.services.arm_driver.targets import TargetIntegrator

RIG = RigConfig()
ENV = Envelope.from_rig(RIG)
LIM = RIG.safety
T = LIM.servo_period_s


def run_stream(pipe, u_per_tick, ticks, dt=1 / 30, extra=60):
    """Submit `u_per_tick` at 30 Hz for `ticks` commands while ticking at the servo period; commanded poses."""
    out, now, t_cmd, sent = [], 0.0, 0.0, 0
    while sent < ticks or pipe.moving:
        while sent < ticks and t_cmd <= now:
            pipe.submit(u_per_tick, dt, t_cmd)
            sent += 1
            t_cmd += dt
        tick = pipe.tick(now)
        if tick.command is not None:
            out.append(tick)
        now += T
        if len(out) > ticks * 2 + extra:
            pipe.stop()
    return out


def positions(ticks, arm=0):
    a = "left" if arm == 0 else "right"
    return np.array([t.command[a][:3, 3] for t in ticks])


def finite_difference_limits(p):
    """Max norm of the 1st, 2nd and 3rd differences of sampled positions `(n, 3)`, in units of v, a, j."""
    d1 = np.linalg.norm(np.diff(p, 1, axis=0), axis=1).max() / T
    d2 = np.linalg.norm(np.diff(p, 2, axis=0), axis=1).max() / T**2
    d3 = np.linalg.norm(np.diff(p, 3, axis=0), axis=1).max() / T**3
    return d1, d2, d3


def test_a_steady_stream_is_jerk_limited_and_integrates_every_increment():
    pipe = ServoPath(RIG)
    start = home_poses()
    assert pipe.reset(start) == []
    u = np.zeros(12)
    u[:3] = np.array([0.05, 0.02, -0.03]) / 30  # left, m per 1/30 s
    u[6:9] = np.array([0.05, -0.02, 0.01]) / 30  # right
    u[3:6] = np.array([0.0, 0.0, 0.25]) / 30  # left turns about world z
    ticks = run_stream(pipe, u, 60)
    for arm in (0, 1):
        v, a, j = finite_difference_limits(positions(ticks, arm))
        assert v <= LIM.max_tcp_speed_mps * (1 + 1e-9)
        assert a <= LIM.max_tcp_accel_mps2 * (1 + 1e-6)
        assert j <= LIM.max_tcp_jerk_mps3 * (1 + 1e-6)
    vel = np.array([t.step.velocity for t in ticks])
    acc = np.array([t.step.acceleration for t in ticks])
    assert np.linalg.norm(vel[:, :, :3], axis=2).max() <= LIM.max_tcp_speed_mps + 1e-12
    assert np.linalg.norm(acc[:, :, :3], axis=2).max() <= LIM.max_tcp_accel_mps2 + 1e-9
    assert np.linalg.norm(vel[:, :, 3:], axis=2).max() <= LIM.max_angular_speed_rps + 1e-9
    assert not any(t.violations for t in ticks)
    end = ticks[-1].command
    assert np.allclose(end["left"][:3, 3], start["left"][:3, 3] + 60 * u[:3], atol=1e-9)
    assert np.allclose(end["right"][:3, 3], start["right"][:3, 3] + 60 * u[6:9], atol=1e-9)
    assert np.allclose(end["left"][:3, :3], so3_exp(60 * u[3:6]) @ start["left"][:3, :3], atol=1e-9)
    assert np.allclose(end["right"][:3, :3], start["right"][:3, :3], atol=1e-12)


def test_rotations_compose_about_world_axes_not_as_euler_sums():
    pipe = ServoPath(RIG)
    start = home_poses()
    pipe.reset(start)
    a, b = np.zeros(12), np.zeros(12)
    a[5] = 0.2  # left: 0.2 rad about world z ...
    b[3] = 0.2  # ... then 0.2 rad about world x
    pipe.submit(a, 1.0, 0.0)
    pipe.submit(b, 1.0, 0.0)  # completes the first at once, then the second over 1 s
    now = 0.0
    while now < 6.0 and pipe.moving:
        pipe.tick(now)
        now += T
    R = pipe.commanded()["left"][:3, :3]
    expect = so3_exp(b[3:6]) @ so3_exp(a[3:6]) @ start["left"][:3, :3]
    assert np.allclose(R, expect, atol=1e-9)
    eul = Rotation.from_matrix(start["left"][:3, :3]).as_euler("xyz") + [0.2, 0.0, 0.2]
    assert not np.allclose(R, Rotation.from_euler("xyz", eul).as_matrix(), atol=1e-3)


def test_target_integrator_spreads_each_increment_over_its_dt():
    ti = TargetIntegrator()
    start = home_poses()
    ti.reset(start)
    u = np.zeros(12)
    u[0] = 0.01
    ti.add(ti.proposed_end(u), 0.1, now=1.0)
    assert ti.target(1.0)["left"][0, 3] == pytest.approx(start["left"][0, 3])
    assert ti.target(1.05)["left"][0, 3] == pytest.approx(start["left"][0, 3] + 0.005)
    assert ti.target(5.0)["left"][0, 3] == pytest.approx(start["left"][0, 3] + 0.01)
    ti.add(ti.proposed_end(u), 0.1, now=1.02)  # the first completes at once
    assert ti.target(1.02)["left"][0, 3] == pytest.approx(start["left"][0, 3] + 0.01)
    assert ti.target(2.0)["left"][0, 3] == pytest.approx(start["left"][0, 3] + 0.02)


def moving_streamer(ticks: int) -> tuple[RuckigSmoother, dict]:
    """A streamer tracking both arms 0.2 m along x from home, `ticks` cycles into the motion; and that target."""
    st_ = RuckigSmoother(LIM, T)
    start = home_poses()
    st_.reset(start)
    st_.track()
    far = {k: v.copy() for k, v in start.items()}
    far["left"][0, 3] += 0.2
    far["right"][0, 3] += 0.2
    for _ in range(ticks):
        st_.step(far)
    return st_, far


def test_a_smooth_stop_brakes_within_the_limits_without_reversing():
    st_, _ = moving_streamer(40)  # up to cruise (0.25/sqrt(3) m/s per axis)
    v0 = LIM.max_tcp_speed_mps / np.sqrt(3)
    assert st_.vel[0, 0] == pytest.approx(v0, rel=1e-6)
    p = [st_.p[0].copy()]
    st_.begin_stop()
    n = 0
    while st_.mode != "idle":
        out = st_.step()
        p.append(out.poses["left"][:3, 3])
        n += 1
        assert n < 100
    p = np.array(p)
    assert np.all(np.diff(p[:, 0]) >= -1e-12) and np.ptp(p[:, 1:], axis=0).max() < 1e-12  # along x, never backing up
    _, acc, jerk = finite_difference_limits(p)
    a, j = LIM.stop_tcp_accel_mps2, LIM.stop_tcp_jerk_mps3  # a stop's limits, not the path's
    assert acc <= a * (1 + 1e-6) and jerk <= j * (1 + 1e-6)
    assert acc > LIM.max_tcp_accel_mps2  # it does brake harder than the path may accelerate
    # the whole budget along x (not 1/sqrt(3) of it): braking from v with jerk j takes 2 sqrt(v/j) while
    # v <= a^2/j (else v/a + a/j); one period of slack
    assert n * T <= (2 * np.sqrt(v0 / j) if v0 <= a * a / j else v0 / a + a / j) + T
    assert st_.at_rest and np.all(st_.vel == 0)


def test_braking_shares_keep_the_norms_and_go_along_the_motion():
    from bagit.services.arm_driver.smoothing import braking_shares

    d = braking_shares(np.array([0.04, 0.0, 0.0]), np.zeros(3), 0.25, 1.0)
    assert np.sum(d**2) == pytest.approx(1.0) and d[0] > 0.999 and d[1] == d[2] > 0  # nearly all along x, none zero
    v, a = np.array([0.03, -0.04, 0.0]), np.array([0.0, 0.0, 0.5])  # turning: a across v
    d = braking_shares(v, a, 0.25, 1.0)
    assert np.sum(d**2) == pytest.approx(1.0)
    assert np.all(np.abs(v) <= 0.25 * d + 1e-15) and np.all(np.abs(a) <= 1.0 * d + 1e-15)  # the state starts inside
    assert d[1] > d[0] > 0  # the rest along the velocity, its larger component most
    assert np.allclose(braking_shares(np.zeros(3), np.zeros(3), 0.25, 1.0), 1 / np.sqrt(3))


axis_state = st.tuples(st.floats(-1.0, 1.0), st.floats(-1.0, 1.0))  # fractions of the per-axis limits


@settings(max_examples=80, deadline=None, derandomize=True)
@given(state=st.lists(axis_state, min_size=12, max_size=12))
def test_a_halt_from_any_tracking_state_stays_within_the_stop_limits_and_comes_to_rest(state):
    """Whatever the trajectory was doing (each axis within its per-axis limits, as tracking leaves it),
    braking keeps the norms of velocity (the path's), acceleration and jerk (the stop's) per arm, linear
    and angular, within the limits, and ends at rest."""
    st_ = RuckigSmoother(LIM, T)
    st_.reset(home_poses())
    fr = np.array(state)
    st_.vel = (fr[:, 0] * st_.max_velocity).reshape(2, 6)
    st_.acc = (fr[:, 1] * st_.max_acceleration).reshape(2, 6)
    st_.mode = "position"
    st_.begin_stop()
    vel, acc = [st_.vel.copy()], [st_.acc.copy()]
    for _ in range(100):
        out = st_.step()
        vel.append(out.velocity)
        acc.append(out.acceleration)
        if st_.mode == "idle":
            break
    assert st_.mode == "idle" and st_.at_rest and st_.errors == 0
    vel, acc = np.array(vel), np.array(acc)
    cart = LIM.stop_limits()  # [[v, a, j] linear, [v, a, j] angular]: the path's speed, the stop's acceleration and jerk
    # The orientation coordinates are re-based every period and the angular rates mapped back with the
    # left Jacobian J(r), |J(r) - I| <= |r| / 2 with |r| <= w_max T: the angular acceleration may read up
    # to a_max w_max T / 2 more, its change per period up to a_max w_max / 2 more (as when tracking)
    w, a = cart[1, 0], cart[1, 1]
    slack = [(1e-9, 1e-9), (a * w * T / 2, a * w / 2)]
    for k, sl in enumerate((slice(0, 3), slice(3, 6))):
        speed = np.linalg.norm(vel[:, :, sl], axis=2)
        accel = np.linalg.norm(acc[:, :, sl], axis=2)
        jerk = np.linalg.norm(np.diff(acc[:, :, sl], axis=0), axis=2) / T
        assert speed.max() <= max(cart[k, 0], speed[0].max()) + 1e-9
        assert accel.max() <= cart[k, 1] + slack[k][0] and jerk.max() <= cart[k, 2] + slack[k][1], (k, accel.max(), jerk.max())


def test_tracking_never_goes_through_the_halting_profile():
    """Nominal motion (commands arriving) is the per-axis tracking computation alone: the halting
    Ruckig is only asked once the stream stops."""
    pipe = ServoPath(RIG)
    pipe.reset(home_poses())
    calls = []
    otg = pipe.smoother._halt_otg

    class Counting:
        def update(self, inp, out):
            calls.append(1)
            return otg.update(inp, out)

    pipe.smoother._halt_otg = Counting()
    u = np.zeros(12)
    u[0] = u[7] = 0.05 / 30
    ticks = []
    for k in range(90):  # 27 commands at 30 Hz, then the trajectory lands on the last target
        if k < 27:
            pipe.submit(u, 1 / 30, k / 30)
        ticks.append(pipe.tick(k * T))
    assert not calls and not any(t.halting for t in ticks) and sum(t.command is not None for t in ticks) == 90
    pipe.submit(u, 1 / 30, 3.0)
    for k in range(10):
        pipe.tick(3.0 + k * T)
    pipe.stop()
    braking = [pipe.tick(3.3 + k * T) for k in range(20)]
    assert calls and braking[0].halting and not pipe.moving


def test_a_ruckig_refusal_while_tracking_brakes_instead_of_escaping_the_servo_loop():
    """Ruckig raises RuckigError, which is not a RuntimeError: it once escaped as a driver fault
    (`bagit up` on a loaded machine). A refused cycle must take the braking path and report it."""
    from ruckig import RuckigError

    st_, far = moving_streamer(20)
    moving = st_.vel[0, 0]

    class RefuseOnce:  # the real Ruckig, which refuses its next cycle
        def __init__(self, otg):
            self.otg, self.calls = otg, 0

        def update(self, inp, out):
            self.calls += 1
            if self.calls == 1:
                raise RuckigError("[ruckig] error in step 2 in dof: 0 for t_min. (injected)")
            return self.otg.update(inp, out)

    st_._otg = RefuseOnce(st_._otg)
    out = st_.step(far)
    assert out.error and "step 2" in out.error and st_.mode == "stopping"
    assert 0 < st_.vel[0, 0] < moving  # the same cycle already brakes, within the limits
    n = 0
    while st_.mode != "idle":
        assert not st_.step().error
        n += 1
        assert n < 100
    assert st_.at_rest and st_.errors == 1


def test_a_new_stream_starts_where_the_arms_are_not_at_an_old_target():
    pipe = ServoPath(RIG)
    start = home_poses()
    pipe.reset(start)
    u = np.zeros(12)
    u[0] = 0.02
    pipe.submit(u, 1.0, 0.0)  # 2 cm over 1 s
    now = 0.0
    for _ in range(10):
        pipe.tick(now)
        now += T
    pipe.stop()  # the watchdog: brake, forget the target
    while pipe.moving:
        pipe.tick(now)
        now += T
    stopped = pipe.commanded()["left"][0, 3]
    assert start["left"][0, 3] < stopped < start["left"][0, 3] + 0.02
    pipe.submit(np.zeros(12), 1 / 30, now)  # a new stream with no motion
    for _ in range(20):
        tick = pipe.tick(now)
        now += T
    assert tick.command["left"][0, 3] == pytest.approx(stopped, abs=1e-12)


def test_cycles_made_but_never_sent_leave_the_next_stream_where_the_arms_were_sent():
    """A starved servo loop makes a cycle whose poses are too old to send: the arms stay at the last
    ServoP they got, so the next stream starts there, not at the poses never sent (a jump per lost step)."""
    pipe = restarted(ServoPath(RIG))  # at rest with its joints known: the reach check runs as the driver's
    u = np.zeros(12)
    u[0] = 0.1 / 30  # 0.1 m/s to the left arm's x
    now, sent = 0.0, []
    for k in range(40):
        pipe.submit(u, 1 / 30, now)
        out = pipe.cycle(now)
        if k < 30:
            sent.append(out.poses["left"][:3, 3])
        else:  # the last ten were made and never went out: each time the loop drops them
            pipe.unsend()
        now += T
    last = sent[-1]
    assert pipe.commanded()["left"][:3, 3] == pytest.approx(last, abs=1e-12)
    pipe.submit(u, 1 / 30, now)  # a fresh command: a new stream from rest where the arm was sent
    for _ in range(5):
        out = pipe.cycle(now)
        sent.append(out.poses["left"][:3, 3])
        now += T
        pipe.submit(u, 1 / 30, now)
    v, a, j = finite_difference_limits(np.array(sent[-6:]))
    assert v <= LIM.max_tcp_speed_mps * (1 + 1e-9)
    assert a <= LIM.max_tcp_accel_mps2 * (1 + 1e-6)  # from rest: no jump over the steps never sent


def _cycles(path: ServoPath, u: np.ndarray, now: float, periods: int) -> tuple[list[tuple[Cycle, bool]], float]:
    """`periods` servo cycles from `now`, none a fault, with `u (12,)` submitted every fourth (about 30 Hz):
    each cycle with whether its step was shortened, and the time after the last."""
    outs = []
    for k in range(periods):
        if k % 4 == 0:
            path.submit(u, 1 / 30, now)
        out = path.cycle(now)
        assert out.fault is None, out.fault
        outs.append((out, path.slowing))
        now += T
    return outs, now


def test_a_restart_from_a_target_a_hair_inside_the_elbow_margin_holds_there_and_can_pull_back():
    """Seen in CI, with the machine busy: creeping at the edge of the reach puts each pose sent ever closer
    to the elbow's margin from straight, and the ServoP's 6 decimals put the controller's target up to
    ~3e-7 rad inside it. A stall then restarted the stream from that target, which the reach check refused
    as out of reach: "cannot hold the last command either", a fault. It is held, and can be left."""
    path = restarted(ServoPath(RIG))
    out_and_up = np.zeros(12)
    out_and_up[[0, 2, 6, 8]] = 0.1 / 30  # both mounts out and up, past the arms' reach (inside the boxes)
    outs, now = _cycles(path, out_and_up, 0.0, 450)  # 3.6 s: to the edge, then creeping at it
    assert all(slowed for _, slowed in outs[-50:])  # at the edge: every step shortened
    q_edge = path.q_seed["left"]
    assert 0.0 <= abs(q_edge[2]) - ELBOW_MARGIN_RAD < 1e-5  # crept up to the margin
    # the controller's target, as the wire's rounding can leave it: 3e-7 rad inside the margin
    q_ctrl = q_edge.copy()
    q_ctrl[2] = np.sign(q_edge[2]) * (ELBOW_MARGIN_RAD - 3e-7)
    records = {a: {"ToolVectorTarget": cr5.matrix_to_pose6(cr5.fk(q)), "QTarget": np.degrees(q)}
               for a, q in (("left", q_ctrl), ("right", path.q_seed["right"]))}
    path.halt()  # a stall: the stream dropped, a new one restarts from the controllers' targets
    assert path.restart(records) == []
    held = path.commanded()["left"]
    outs, now = _cycles(path, out_and_up, now, 40)  # pushed on: held where it is, the elbow never straighter
    for out, _ in outs:
        if out.poses is not None:
            assert np.linalg.norm(out.poses["left"][:3, 3] - held[:3, 3]) < 1e-9
            assert abs(out.joints["left"][2]) >= abs(q_ctrl[2]) - 1e-9
    path.halt()
    outs, _ = _cycles(path, -out_and_up, now, 40)  # pulled back in from the edge
    last = [out.poses["left"] for out, _ in outs if out.poses is not None][-1]
    assert np.linalg.norm(last[:3, 3] - held[:3, 3]) > 0.001


def test_a_restart_from_arms_a_following_error_past_a_limit_is_no_fault_and_the_stream_pulls_them_in():
    # targets clipped onto the separation limit are reached with the servo's following error: a
    # restart from where the arms then measure is not a fault, and the next commands are inside again
    lim = LIM.min_flange_distance_m
    for past, fault in ((0.0005, False), (0.0015, False), (0.01, True)):
        pipe = ServoPath(RIG)
        start = home_poses(half_sep=(lim - past) / 2)
        kinds = [v.kind for v in pipe.reset(start)]
        assert kinds == (["min_distance"] if fault else []), (past, kinds)
        if fault:
            continue
        u = np.zeros(12)
        u[1], u[7] = 0.002, -0.002  # the controller pushes them closer still
        pipe.submit(u, 1 / 30, 0.0)
        now = 0.0
        for _ in range(40):
            tick = pipe.tick(now)
            now += T
            if tick.command is not None:
                d = np.linalg.norm(tick.command["right"][:3, 3] - tick.command["left"][:3, 3])
                assert d >= lim - 1e-9, d
        assert tick.command is not None


def restarted(path: ServoPath) -> ServoPath:
    """`path` at rest at home, as from the controllers' feedback (poses and the joints they are solved at)."""
    records = {}
    for a in ARMS:
        T_bf = path.frames[a].flange_in_base(home_poses()[a])
        records[a] = {"ToolVectorTarget": cr5.matrix_to_pose6(T_bf), "QTarget": np.degrees(cr5.ik_all(T_bf)[0])}
    assert path.restart(records) == []
    return path


def test_each_cycle_ends_in_a_servop_per_active_arm_of_the_pose_it_sent_with_the_halting_parameters_only_when_braking():
    cfg = DriverConfig()
    path = restarted(ServoPath(RIG, cfg))
    u = np.zeros(12)
    u[0] = u[6] = 0.001
    path.submit(u, 1 / 30, 0.0)
    out = path.cycle(0.0)
    assert out.poses is not None and list(out.servo) == list(ARMS) and not out.halting
    for a in ARMS:
        cmd = out.servo[a]
        assert cmd.name == "ServoP" and (cmd.t, cmd.aheadtime, cmd.gain) == (T, cfg.aheadtime, cfg.gain)
        assert np.array_equal(cmd.values, cr5.matrix_to_pose6(path.frames[a].flange_in_base(out.poses[a])))
        assert np.array_equal(cmd.on_wire(), np.round(cmd.values, 6))
    assert list(path.cycle(T, ["left"]).servo) == ["left"]  # an arm not commandable gets nothing
    path.stop()
    braking = path.cycle(2 * T)
    assert braking.halting and {c.aheadtime for c in braking.servo.values()} == {cfg.halt_aheadtime}


def test_servoj_sends_the_joints_the_reach_check_solved():
    path = restarted(ServoPath(RIG, DriverConfig(servo_command="servoj")))
    path.submit(np.zeros(12), 1 / 30, 0.0)
    out = path.cycle(0.0)
    assert out.joints is not None
    for a in ARMS:
        assert out.servo[a].name == "ServoJ" and np.array_equal(out.servo[a].values, np.degrees(out.joints[a]))


def test_a_runaway_target_is_pulled_back_and_reported():
    pipe = ServoPath(RIG, DriverConfig(max_target_lead_m=0.05))
    pipe.reset(home_poses())
    u = np.zeros(12)
    u[2] = 0.3  # 30 cm up in one go
    found = pipe.submit(u, 1 / 30, 0.0)
    assert [v.kind for v in found] == ["lead"]
    assert pipe.targets.end()["left"][2, 3] == pytest.approx(home_poses()["left"][2, 3] + 0.05)


def test_an_overshoot_past_the_box_is_clipped_at_the_gate_and_the_trajectory_continues_from_it():
    pipe = ServoPath(RIG)
    start = home_poses()
    for a in start:
        start[a][2, 3] = 0.948  # 2 mm under the top of the box, with the flange under the mount
    pipe.reset(start)
    pipe.submit(np.zeros(12), 1 / 30, 0.0)
    pipe.smoother.vel[:, 2] = LIM.max_tcp_speed_mps / np.sqrt(3)  # rising at full speed: cannot brake in 2 mm
    prev, now, kinds, z = pipe.commanded(), 0.0, [], []
    for _ in range(40):
        tick = pipe.tick(now)
        now += T
        kinds += [v.kind for v in tick.violations]
        if tick.command is not None:
            assert violations(tick.command, prev, T, ENV) == []
            prev = tick.command
            z.append(prev["left"][2, 3])
    assert "workspace" in kinds
    assert max(z) == pytest.approx(0.95, abs=1e-9)  # held at the wall, not through it
    assert z[-1] == pytest.approx(0.948, abs=1e-9)  # then back to the target, smoothly again
    assert np.abs(pipe.smoother.vel).max() < 1e-9


def test_non_finite_increments_are_rejected_and_leave_no_trace():
    pipe = ServoPath(RIG)
    pipe.reset(home_poses())
    bad = np.zeros(12)
    bad[4] = np.nan
    assert [v.kind for v in pipe.submit(bad, 1 / 30, 0.0)] == ["non_finite"]
    assert [v.kind for v in pipe.submit(np.zeros(12), np.inf, 0.0)] == ["non_finite"]
    assert [v.kind for v in pipe.submit(np.zeros(11), 0.03, 0.0)] == ["non_finite"]
    assert not pipe.moving and pipe.tick(0.0).command is None


wild = st.one_of(
    st.floats(-0.05, 0.05, allow_nan=False),
    st.floats(-5.0, 5.0, allow_nan=False),
    st.sampled_from([np.nan, np.inf, -np.inf, 1e12, -1e12, 0.0]),
)
op = st.one_of(
    st.tuples(st.just("cmd"), st.lists(wild, min_size=12, max_size=12), st.sampled_from([1 / 30, 0.01, 0.2, 1.0, np.nan])),
    st.tuples(st.just("tick"), st.integers(1, 8), st.none()),
    st.tuples(st.just("stop"), st.none(), st.none()),
)


def within_its_limits(tick) -> bool:
    """The trajectory behind a tick's command accelerates within the limits that apply to it: the stop's
    while it brakes, the path's while it follows (linear exactly; angular with the re-basing's slack, see
    the halting test). A tick the gate or Ruckig changed says so in its violations instead."""
    if tick.violations or tick.step is None:
        return True
    lim = LIM.stop_limits() if tick.halting else LIM.path_limits()
    acc = tick.step.acceleration
    lin, ang = np.linalg.norm(acc[:, :3], axis=1).max(), np.linalg.norm(acc[:, 3:], axis=1).max()
    return bool(lin <= lim[0, 1] + 1e-9 and ang <= lim[1, 1] * (1 + lim[1, 0] * T / 2) + 1e-9)


@settings(max_examples=150, deadline=None, derandomize=True)
@given(ops=st.lists(op, min_size=1, max_size=40))
def test_no_input_sequence_gets_a_command_outside_the_limits(ops):
    pipe = ServoPath(RIG)
    pipe.reset(home_poses())
    prev = pipe.commanded()
    now = 0.0
    for kind, a, b in ops:
        if kind == "cmd":
            pipe.submit(np.array(a, dtype=float), b, now)
        elif kind == "stop":
            pipe.stop()
        else:
            for _ in range(a):
                tick = pipe.tick(now)
                now += T
                if tick.command is not None:
                    assert violations(tick.command, prev, T, ENV) == [], tick.violations
                    assert within_its_limits(tick), (tick.halting, tick.step.acceleration)
                    prev = tick.command
    for _ in range(200):  # and it always comes to rest
        tick = pipe.tick(now)
        now += T
        if tick.command is not None:
            assert violations(tick.command, prev, T, ENV) == []
            assert within_its_limits(tick), (tick.halting, tick.step.acceleration)
            prev = tick.command
        if not pipe.moving:
            break
        if _ == 20:
            pipe.stop()
    assert not pipe.moving
