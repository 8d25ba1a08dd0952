"""When the arm driver's servo cycles run, and when their ServoPs may go out: the servo thread's schedule.

What a cycle decides is the driver's (`CycleHost.make_cycle`, under its lock); this module times it:
- on the wall clock (`run_wall`): a cycle every period, never catching up after a late one (two
  ServoPs closer than a period would make a controller cover a step in less than its `t`; Dobot: no
  faster than every 30 ms): a late cycle shifts the schedule, the trajectory runs slightly slower,
  never faster. ServoPs made before a pause longer than the watchdog's time are not sent.
- on the simulated rig's clock (`run_lockstep`, `bagit up`'s lockstep): one pass per step the
  simulator announces on sim/clock: once both arms' feedback shows that step, a cycle if it is a
  servo tick, then both arms' states (what the step's frame sees, as `bagit run` reads the arms after
  its servo period), then the tick's answer. No wall-clock wait but the feedback's, bounded.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable
from typing import Protocol

import numpy as np

from bagit.common.clock import Clock, SimClock
from bagit.common.lockstep import StepWait
from bagit.common.rig import ARMS, ArmName
from bagit.services.arm_driver.servo_path import Cycle


class CycleHost(Protocol):
    """What the loop needs of the driver."""

    def make_cycle(self) -> tuple[Cycle, float] | None: ...  # one period's ServoPs and when they were made (None: nothing)
    def send_cycle(self, out: Cycle, stale: Callable[[], bool] | None = None) -> list[ArmName]: ...  # the arms its ServoPs went to (none once `stale()`)
    def stalled(self, why: str, unsent: bool = False) -> None: ...  # the loop did not run in time / `unsent`: the poses made were too old to send
    def cycle_failed(self, e: Exception) -> None: ...  # a cycle raised: a fault
    def step_ready(self, t: float) -> bool: ...  # lockstep: both arms' feedback shows the step at `t`
    def step_done(self, tick: int | None, sent: dict[str, int], late: str | None, states: bool = True) -> None: ...  # lockstep: answer, states
    def event(self, kind: str, detail: str) -> None: ...


class ServoLoop:
    """The servo thread's schedule for `host` (see the module docstring); `stop` ends it."""

    def __init__(self, host: CycleHost, period: float, watchdog_s: float, counters: Counter[str], stop: threading.Event):
        self.host, self.period, self.watchdog_s, self.counters, self.stop = host, period, watchdog_s, counters, stop
        self.threads: list[threading.Thread] = []
        self.feedback = StepWait()  # lockstep: each feedback packet wakes the wait for a step's (`notify`)
        self.last_send = -np.inf  # monotonic time the last ServoPs went out
        self.servo_sent = {a: 0 for a in ARMS}
        self.cycle_ms: deque[float] = deque(maxlen=1000)  # compute time of each cycle
        self.cycle_starts: deque[float] = deque(maxlen=1000)  # monotonic start of each cycle
        self.send_times: deque[float] = deque(maxlen=1000)  # when each period's ServoPs went out

    def start(self, clock: Clock, *others: tuple[Callable[[], None], str]) -> None:
        """The servo thread on `clock` (one pass per step if it is the simulator's), `others` (target, name) beside it."""
        self.stop.clear()
        run = (lambda: self.run_lockstep(clock)) if isinstance(clock, SimClock) else self.run_wall
        for target, name in ((run, "servo-loop"), *others):
            self.threads.append(threading.Thread(target=target, name=f"arm-driver-{name}", daemon=True))
            self.threads[-1].start()

    @property
    def running(self) -> bool:
        return bool(self.threads) and self.threads[0].is_alive()

    def join(self) -> None:
        """End the threads (waking a lockstep wait) and wait for them."""
        self.stop.set()
        self.feedback.notify()
        for t in self.threads:
            t.join(timeout=2.0)
        self.threads.clear()

    def timing(self) -> dict[str, dict[str, float]]:
        """Cycle compute time, cycle period and the interval between sends (ms) over the last 1000."""
        cycle = np.array(self.cycle_ms) if self.cycle_ms else np.zeros(1)
        period = np.diff(np.array(self.cycle_starts)) * 1000.0 if len(self.cycle_starts) > 1 else np.zeros(1)
        sends = np.diff(np.array(self.send_times)) * 1000.0 if len(self.send_times) > 1 else np.zeros(1)
        return {
            "cycle_ms": {"median": float(np.median(cycle)), "max": float(cycle.max())},
            "period_ms": {"median": float(np.median(period)), "max": float(period.max())},
            "send_interval_ms": {"min": float(sends.min()), "median": float(np.median(sends))},
        }

    def once(self, spaced: bool) -> bool:
        """One cycle, timed; True if ServoPs went out. `spaced` (the wall clock): never two sends less than
        a period apart, and none of poses older than the watchdog's time (the process was paused)."""
        t0 = time.monotonic()
        self.cycle_starts.append(t0)
        sent = False
        try:
            made = self.host.make_cycle()
            if made is not None:
                out, made_at = made
                if spaced and (wait := self.last_send + self.period - time.monotonic()) > 0:
                    time.sleep(wait)
                late: list[float] = []  # how old the poses were when an arm's turn on the wire came, if too old

                def stale() -> bool:  # asked last before each write: a pause anywhere before it is caught
                    if (age := time.monotonic() - made_at) > self.watchdog_s:
                        late.append(age)
                        return True
                    return False

                t_send = time.monotonic()
                arms = self.host.send_cycle(out, stale if spaced else None)  # none once the e-stop has latched
                if arms:
                    self.last_send = t_send
                    self.send_times.append(t_send)
                for a in arms:
                    self.counters["servo_sent"] += 1
                    self.servo_sent[a] += 1
                sent = bool(arms)
                if late:
                    self.host.stalled(f"this period's poses were {late[0] * 1000:.0f} ms old when they could go out (the "
                                      "process was paused or starved): not sent; a new command starts a new stream", unsent=not arms)
        except Exception as e:  # never let the loop die: whatever went wrong becomes a fault
            self.host.cycle_failed(e)
        self.cycle_ms.append((time.monotonic() - t0) * 1000.0)
        return sent

    def run_wall(self) -> None:
        next_t = time.monotonic()
        offsets: deque[float] = deque([0.0], maxlen=50)  # when in its cycle the ServoPs go out
        while not self.stop.is_set():
            t0 = time.monotonic()
            if self.once(spaced=True):
                offsets.append(self.last_send - t0)
            if t0 - next_t > 0.2 * self.period:
                self.counters["late_cycles"] += 1
            # the next cycle starts so that its ServoPs go out about a period after the last ones
            offset = min(float(np.median(offsets)), 0.2 * self.period)
            next_t = max(next_t + self.period, t0 + 0.5 * self.period, self.last_send + self.period - offset)
            if (delay := next_t - time.monotonic()) > 0:
                self.stop.wait(delay)

    def run_lockstep(self, clock: SimClock) -> None:
        last_t, last_tick = float("-inf"), -1
        while not self.stop.is_set():
            event = clock.next_event(last_t, self.stop, timeout=1.0)
            if event is None:
                continue
            last_t, n = event
            # The arms' states of a servo tick the controller does not tick on are read by nobody whose
            # answer the world waits for (the next frame's states supersede them): not published. Read
            # before the answer, after which the simulator may announce the next step.
            states = clock.control_step_at(last_t)
            late = self._await_feedback(last_t)
            before = dict(self.servo_sent)
            if n is not None and n > last_tick:
                last_tick = n
                self.once(spaced=False)
            self.host.step_done(n, {a: self.servo_sent[a] - before[a] for a in ARMS}, late, states)

    def _await_feedback(self, t: float) -> str | None:
        """Until both arms' feedback shows the step at `t`, woken by each packet, at most the lockstep
        time-out (a link gone quiet is the supervisor's business); what the step's cycle goes without."""
        if self.feedback.wait(lambda: self.host.step_ready(t), self.stop) or self.stop.is_set():
            return None
        self.counters["lockstep_late"] += 1
        self.host.event("lockstep", f"servo tick at {t:.3f}: cycled without the feedback of that step")
        return "the feedback of its step"
