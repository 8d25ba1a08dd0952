"""One run's servoing without a bus (`ServoSession`): what the controller node and `bagit run` both host."""

import numpy as np
import pytest

from bagit.common.dual_arm import apply_increment, pose_increment
from bagit.common.messages import ArmState, Path, RunState, SoiState
from bagit.common.rig import RigConfig, SafetyLimits
from bagit.common.so3 import matrix_to_rpy
from bagit.services.controller.session import (
    KEEPALIVE,
    KEEPALIVE_SHARE,
    SOI_MAX_AGE_S,
    ServoSession,
    arms_slowed,
    gripper_poses,
    pending_motion,
)
from bagit.services.controller.synthetic import SyntheticRim

U_GOAL = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2]) * 0.5
FAST = {"max_linear_speed_mps": 0.15, "max_angular_speed_rps": 0.9, "control_rate_hz": 60.0}


def _session(n_x: int = 16, params: dict = FAST):
    m = SyntheticRim(n_x)
    nodes = np.stack([m.rim(apply_increment(m.home(), U_GOAL * s)) for s in np.linspace(0, 1, 6)])
    seqs = iter(range(1, 10**6))
    state = RunState(run_id="r1", stage="pre-bagging", controller="mpc", params=params)
    s, out = ServoSession.build(state, Path(run_id="r1", nodes=nodes, dagger_index=4), None, lambda: next(seqs), RigConfig().safety.watchdog_s)
    assert s.controller is not None and out.report.startswith(f"run r1: mpc at {params['control_rate_hz']:g} Hz")
    return s, m, nodes


def test_a_session_servos_to_the_goal_and_its_holds_say_where_the_run_is():
    s, m, nodes = _session()
    g, t, k = m.home(), 0.0, 0
    stages, held_while_bagging = [], False
    while s.finished is None and k < 2000:
        k += 1
        t += s.dt
        soi = SoiState(seq=k, source_stamp=t, rim=m.rim(g))
        out = s.tick(soi, 0.0, SOI_MAX_AGE_S, g, None, None, Path(run_id="r1", nodes=nodes, dagger_index=4), None, t)
        if out.command.mode == "servo":
            g = apply_increment(g, out.command.u)
        stages.append(out.status.stage)
        if out.status.stage == "bagging" and not held_while_bagging:
            held_while_bagging = True
            hold = s.hold("a gap in the SOIs", t)  # a hold while bagging ...
            assert hold.status.stage == "bagging" and hold.command.mode == "hold"  # ... says bagging, not the default
    assert held_while_bagging and s.finished == "done" and s.error_to_goal < 0.01


def test_the_same_soi_twice_is_a_keep_alive_that_moves_nothing():
    s, m, nodes = _session()
    g = m.home()
    path = Path(run_id="r1", nodes=nodes, dagger_index=4)
    soi = SoiState(seq=1, source_stamp=1.0, rim=m.rim(g))
    first = s.tick(soi, 0.0, SOI_MAX_AGE_S, g, None, None, path, None, 1.0)
    assert first.command.mode == "servo" and not first.keepalive and first.status is not None
    again = s.tick(soi, 0.05, SOI_MAX_AGE_S, g, None, None, path, None, 1.05)
    assert again.keepalive and again.status is None and again.command.reason == KEEPALIVE and not np.any(again.command.u)
    at_limit = s.tick(soi, SOI_MAX_AGE_S, SOI_MAX_AGE_S, g, None, None, path, None, 1.1)
    assert at_limit.keepalive  # up to the age limit the stream is kept alive ...
    stale = s.tick(soi, SOI_MAX_AGE_S + 1e-6, SOI_MAX_AGE_S, g, None, None, path, None, 1.6)  # ... the first tick past it holds
    assert stale.command.mode == "hold" and "stale" in stale.command.reason
    after = s.tick(soi, 0.0, SOI_MAX_AGE_S, g, None, None, path, None, 1.65)
    assert after.command is None  # after a hold, no keep-alive restarts the stream: only a new SOI does


def test_the_commands_come_often_enough_for_the_drivers_watchdog_at_any_control_rate():
    """The driver halts the arms after a gap of `halt_gap_s` between commands; the session is ticked at
    least every KEEPALIVE_SHARE of the watchdog, so even a whole lost tick leaves a gap under it."""
    lim = SafetyLimits()
    assert 2 * KEEPALIVE_SHARE * lim.watchdog_s < lim.halt_gap_s
    for rate in (1.0, 5.0, 10.0, 22.0, 30.0, 60.0, 500.0):
        s, _, _ = _session(params={**FAST, "control_rate_hz": rate})
        assert s.tick_s <= KEEPALIVE_SHARE * lim.watchdog_s and s.tick_s <= s.dt
        if s.dt < lim.watchdog_s:
            assert s.dt_max < lim.watchdog_s  # a slow SOI's increment does not outlast the watchdog either


def test_a_control_rate_slower_than_the_keep_alive_pace_acts_at_its_rate_with_keep_alives_between():
    """At 10 Hz the host ticks every 40 ms (1/3 of the 120 ms watchdog): a new SOI is acted on once a
    control period has passed, the ticks between are keep-alives; a command goes out on every tick."""
    s, m, nodes = _session(params={**FAST, "control_rate_hz": 10.0})
    path = Path(run_id="r1", nodes=nodes, dagger_index=4)
    g, t, control, keep = m.home(), 0.0, [], []
    for k in range(60):  # a 30 fps camera: a new SOI on every tick
        out = s.tick(SoiState(seq=k, source_stamp=t, rim=m.rim(g)), 0.0, SOI_MAX_AGE_S, g, None, None, path, None, t)
        assert out.command is not None and out.command.mode == "servo"
        (keep if out.keepalive else control).append(t)
        if not out.keepalive:
            g = apply_increment(g, out.command.u)
        t += s.tick_s
    assert len(keep) > len(control) > 10
    assert np.diff(control).min() >= s.dt - 0.5 * s.tick_s - 1e-9 and np.diff(control).max() <= s.dt + s.tick_s


class _WalledArms:
    """An arm side that lags (each tick it makes a quarter of the way to its target) and cannot take the
    left mount above `z_wall` (out of its reach): a step that would is cut short for both arms, as the
    driver's reach does, and the states say `slowed`; `target_pose` is where it is taking them."""

    def __init__(self, m: SyntheticRim, z_wall: float):
        self.g, self.aim, self.z_wall, self.slowed = m.home(), m.home(), z_wall, False

    def submit(self, cmd) -> None:
        self.aim = apply_increment(self.aim, np.asarray(cmd.u)) if cmd.mode == "servo" else {a: T.copy() for a, T in self.g.items()}

    def servo(self) -> None:
        step = pose_increment(self.g, self.aim) / 4
        z, dz = self.g["left"][2, 3], step[2]
        f = max(self.z_wall - z, 0.0) / dz if dz > 0 and z + dz > self.z_wall else 1.0
        self.g, self.slowed = apply_increment(self.g, f * step), f < 1.0

    def states(self) -> dict[str, ArmState]:
        pose = lambda T: np.r_[T[:3, 3], matrix_to_rpy(T[:3, :3])]  # noqa: E731
        return {a: ArmState(arm=a, q=np.zeros(6), qd=np.zeros(6), tool_pose=pose(self.g[a]), target_pose=pose(self.aim[a]), slowed=self.slowed)
                for a in self.g}


def _walled_run(told: bool, ticks: int = 500) -> tuple[_WalledArms, ServoSession, list[float]]:
    s, m, nodes = _session()
    path = Path(run_id="r1", nodes=nodes, dagger_index=4)
    arms = _WalledArms(m, m.home()["left"][2, 3] + 0.03)  # g* needs the left mount 7.5 cm up
    t, leads = 0.0, []
    for k in range(ticks):
        t += s.dt
        states = arms.states()
        g, _ = gripper_poses(states)
        pending, slowed = (pending_motion(states, g), arms_slowed(states)) if told else (None, False)
        out = s.tick(SoiState(seq=k + 1, source_stamp=t, rim=m.rim(g)), 0.0, SOI_MAX_AGE_S, g, None, None, path, None, t, pending, slowed)
        barred = s.controller.barred
        if told and barred is not None and out.command.mode == "servo":  # no share along what the arm side could not make
            assert float((out.command.u / s.controller.u_max) @ barred) <= 1e-9
        arms.submit(out.command)
        arms.servo()
        leads.append(arms.aim["left"][2, 3] - arms.g["left"][2, 3])
    return arms, s, leads


@pytest.mark.slow
def test_a_reported_reach_limit_stops_the_asking():
    """The arm side cannot take the left mount where the path goes. A controller blind to it asks for the
    same lift every tick and the target runs away (metres here; on the rig the driver pulls it back
    to its lead limit every period); told through the arm states (target_pose, slowed), it stops
    asking for that motion and takes back what is in flight, so the target stays by the arm."""
    blind_arms, _, blind = _walled_run(told=False)
    arms, s, told = _walled_run(told=True)
    assert max(blind) > 0.5, max(blind)
    assert max(told) < 0.01 and abs(told[-1]) < 0.003, (max(told), told[-1])
    assert arms.g["left"][2, 3] <= arms.z_wall + 1e-9 and s.finished is None  # the wall held: no g*, and no pretending
