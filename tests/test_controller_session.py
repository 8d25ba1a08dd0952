"""One run's servoing without a bus (`ServoSession`): what the controller node and `bagit run` both host."""

import numpy as np

from bagit.common.messages import Path, RunState, SoiState
from bagit.services.controller.increment import apply_increment
from bagit.common.rig import SafetyLimits
from bagit.services.controller.session import KEEPALIVE, KEEPALIVE_SHARE, SOI_MAX_AGE_S, ServoSession
from bagit.services.controller.synthetic import SyntheticRim

U_GOAL = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2]) * 0.5
FAST = {"max_linear_speed_mps": 0.15, "max_angular_speed_rps": 0.9, "control_rate_hz": 60.0}


def _session(n_x: int = 16, params: dict = FAST):
    m = SyntheticRim(n_x)
    nodes = np.stack([m.rim(apply_increment(m.home(), U_GOAL * s)) for s in np.linspace(0, 1, 6)])
    seqs = iter(range(1, 10**6))
    state = RunState(run_id="r1", stage="pre-bagging", controller="mpc", params=params)
    s, out = ServoSession.build(state, Path(run_id="r1", nodes=nodes, dagger_index=4), None, {}, lambda: next(seqs))
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
    stale = s.tick(soi, SOI_MAX_AGE_S + 0.1, SOI_MAX_AGE_S, g, None, None, path, None, 1.6)
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
