"""How soon the arms are still after the last command, against the simulated CR5s (`bagit.bench.stop_time`).

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
"""

from __future__ import annotations

import numpy as np
import pytest

from bagit.bench.stop_time import V0, driver_trials

TRIALS = 5


@pytest.mark.slow
@pytest.mark.parametrize("end", ["hold", "silence"])
def test_the_arms_brake_after_the_last_command_and_come_to_rest(end):
    trials = driver_trials(end, TRIALS)
    still = np.array([t["still_s"] for t in trials])
    halt = np.array([t["halt_s"] for t in trials])
    servo = np.array([t["servo_s"] for t in trials])
    stall = float(np.median([t["stall_s"] for t in trials]))
    print(f"\nstop after the last command ({end}, {V0 * 100:.0f} cm/s, {TRIALS} trials): still at "
          f"{', '.join(f'{s * 1000:.0f}' for s in still)} ms, median {np.median(still) * 1000:.0f} ms; first braking ServoP "
          f"median {np.median(halt) * 1000:.0f} ms, last moving {np.median(servo) * 1000:.0f} ms; loop stall {stall * 1000:.0f} ms")
    assert len(trials) == TRIALS and np.all(np.isfinite(still)), still  # every trial came to rest
    assert np.all(halt > 0) and np.all(servo >= halt), (halt, servo)  # braking after the last command, then the last move
