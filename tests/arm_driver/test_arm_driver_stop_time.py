"""How soon the arms are still after the last command, against the simulated CR5s (`bagit.bench.stop_time`,
and on a virtual clock `bagit.bench.stop_timeline`).

A controller-like stream (30 commands a second, both mounts at 4 cm/s) ends; 5 trials per case:

- the controller ends the stream with a hold: braking starts at once;
- the stream just stops: the watchdog (120 ms, issued a servo period ahead) stops the arms. Until then
  nothing differs from commands arriving late: the trajectory lands on the last target as it always does.

Either way the arms brake along their motion with the whole Cartesian jerk budget (2 sqrt(v0 / j): 126 ms
from 4 cm/s; `streaming.braking_shares`), and the braking ServoPs go with the halting aheadtime, so the
controller follows them without its lag. What is asserted is the order on the controllers' own logs:
braking after the last command, the last moving ServoP after the first braking one, the arms still in
the end. How soon is printed here and held to its goal (p95 within 250 ms, n >= 20) by the benchmark,
`python -m bagit.bench.stop_time`: a loaded machine makes it later, and a test must not fail for that.
A trial a starved process disturbed (a command refused as stale, the servo loop stalled past the
watchdog, a link time-out: the driver's protections, tested on their own elsewhere) is redone and printed.
The wall-clock trials run with the files that start simulated CR5s, one at a time (tests/conftest.py).
"""

from __future__ import annotations

import numpy as np
import pytest

from bagit.bench.stop_time import TARGET_S, V0, driver_trials
from bagit.bench.stop_timeline import CASES, PHASES_S, virtual_stop
from bagit.common import cr5
from bagit.common.rig import SafetyLimits

TRIALS = 5


@pytest.mark.slow
@pytest.mark.parametrize("end", ["hold", "silence"])
def test_the_arms_brake_after_the_last_command_and_come_to_rest(end):
    disturbed: list[str] = []
    trials = driver_trials(end, TRIALS, disturbed)
    still = np.array([t["still_s"] for t in trials])
    halt = np.array([t["halt_s"] for t in trials])
    servo = np.array([t["servo_s"] for t in trials])
    stall = float(np.median([t["stall_s"] for t in trials]))
    print(f"\nstop after the last command ({end}, {V0 * 100:.0f} cm/s, {TRIALS} trials): still at "
          f"{', '.join(f'{s * 1000:.0f}' for s in still)} ms, median {np.median(still) * 1000:.0f} ms; first braking ServoP "
          f"median {np.median(halt) * 1000:.0f} ms, last moving {np.median(servo) * 1000:.0f} ms; loop stall {stall * 1000:.0f} ms; redone: {disturbed}")
    assert len(trials) == TRIALS and np.all(np.isfinite(still)), still  # every trial came to rest
    assert np.all(halt > 0) and np.all(servo >= halt), (halt, servo)  # braking after the last command, then the last move


@pytest.mark.parametrize("case", ["from rest, x", "from rest, diagonal"])
def test_a_motion_the_last_command_started_from_rest_is_still_within_the_budget(case):
    """The cut cable of `bagit bench multihost`: the last command that reached the arms set them moving from
    rest, asking more than the path gives (its jerk and acceleration decide), and nothing came after. On a
    virtual clock (`bagit run`'s arm side and two simulated CR5s; deterministic, so the budget is the
    algorithm's, not the machine's), at every phase of the servo cycle: the watchdog starts the stop a servo
    period ahead of its deadline, no braking ServoP steps further than the one before (braking never speeds
    the arms up: with the path's jerk they sped up for 100 ms more), both arms are still within TARGET_S of
    the last command (with the path's limits: 348 and 456 ms), and the simulated CR5s followed without
    reaching their joints' acceleration bound."""
    lim = SafetyLimits()
    for phase in PHASES_S:
        r = virtual_stop(*CASES[case], phase)
        assert 1000 * lim.halt_gap_s < r["watchdog_ms"] <= 1000 * lim.watchdog_s, r
        braking = r["steps_mm"][1:]
        assert len(braking) >= 2 and all(b <= a for a, b in zip(braking, braking[1:], strict=False)), r
        assert r["watchdog_ms"] < r["still_ms"] <= 1000 * TARGET_S, r
        assert r["joint_accel_rps2"] < cr5.JOINT_ACCEL_LIMIT, r
