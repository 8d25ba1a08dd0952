"""Limits one part sets and another depends on: the controller's command pacing against the arm
driver's watchdog (common/rig.py `SafetyLimits`), whatever the control rate, the camera rate or
the rig's watchdog. A controller that went quiet for longer than the watchdog would have the
driver brake the arms in the middle of a run."""

import numpy as np
import pytest

from bagit.common.dual_arm import apply_increment
from bagit.common.messages import Path, RunState, SoiState
from bagit.common.rig import SafetyLimits
from bagit.services.controller.session import SOI_MAX_AGE_S, ServoSession
from bagit.services.controller.synthetic import SyntheticRim

U_GOAL = np.array([0.05, 0.03, 0.15, 0, 0, 0.2, 0.05, -0.03, 0.15, 0, 0, 0.2]) * 0.5


@pytest.mark.parametrize("watchdog_s", [0.12, 0.2, 0.5])
@pytest.mark.parametrize("rate_hz", [2.0, 10.0, 30.0, 60.0])
@pytest.mark.parametrize("frame_every", [1, 3, 10])
def test_while_servoing_no_gap_between_commands_reaches_the_watchdogs_halt(watchdog_s, rate_hz, frame_every):
    """Ticked at its own pace (`tick_s`), with a new SOI only every `frame_every` ticks, the session
    sends a command on every tick while it servos, so the longest gap is one tick, under the gap
    that halts the arms (`halt_gap_s`); a command's dt (the time the driver spreads it over) never
    outlasts the watchdog when a control period fits inside it."""
    lim = SafetyLimits(watchdog_s=watchdog_s)
    m = SyntheticRim(16)
    nodes = np.stack([m.rim(apply_increment(m.home(), U_GOAL * s)) for s in np.linspace(0, 1, 6)])
    seqs = iter(range(1, 10**6))
    params = {"max_linear_speed_mps": 0.15, "max_angular_speed_rps": 0.9, "control_rate_hz": rate_hz}
    state = RunState(run_id="r1", stage="pre-bagging", controller="mpc", params=params)
    path = Path(run_id="r1", nodes=nodes, dagger_index=4)
    s, _ = ServoSession.build(state, path, None, lambda: next(seqs), lim.watchdog_s)
    assert s.controller is not None
    g, t, sent, frame = m.home(), 0.0, [], None
    for k in range(int(3.0 / s.tick_s)):  # three seconds of the rig's time
        if k % frame_every == 0:
            frame = SoiState(seq=k, source_stamp=t, rim=m.rim(g))
        out = s.tick(frame, t - frame.source_stamp, SOI_MAX_AGE_S, g, None, None, path, None, t)
        if out.command is not None:
            sent.append(t)
            assert out.command.dt <= max(lim.watchdog_s, s.dt)
            if s.dt < lim.watchdog_s:
                assert out.command.dt < lim.watchdog_s
            if out.command.mode == "servo":
                g = apply_increment(g, out.command.u)
        if s.finished is not None:
            break
        t += s.tick_s
    assert len(sent) > 10
    assert max(np.diff(sent)) < lim.halt_gap_s, (max(np.diff(sent)), lim.halt_gap_s)
