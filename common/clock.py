"""The one clock every service reads time from: the wall clock on a real rig, the simulator's on a simulated one.

ROS 2's `use_sim_time` with `/clock`, in this project's terms: with `BusConfig.clock == "sim"`
every timer (control ticks, SOI and arm-state ages, the arm driver's servo period and watchdog,
the coordinator's limits) runs on the time `bagit sim` publishes on sim/clock, so a machine that
cannot keep up makes a run slower, never different. With "wall" (a real rig, or `bagit up
--clock wall`) they run on this host's clock; the e-stop and the TCP links to the controllers
always do (they guard against real processes dying, whatever the world's time).

    clock = WallClock()                  # now() = time.time(); wait_until() sleeps
    clock = SimClock()                   # now() = the newest sim/clock time; advance(t) from the bus
    clock.wait_until(t, stop)            # True once now() >= t; False if `stop` was set first
    clock.step_time(frame.stamp)         # when the step of a frame is handled: its stamp (sim) or now (wall)
    clock.age(msg.stamp, received, now)  # a message's age: by its stamp at the step (sim) or by arrival (wall)

The lockstep/wall difference of a service's timing lives in these two methods: a node is handed
its clock, not a flag to branch on.

This module holds no bus: `SimClock.advance` is fed by whoever subscribes to sim/clock (see
`bagit.common.bus.follow_sim_clock`).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from typing import Literal, Protocol

ClockKind = Literal["wall", "sim"]
CLOCK_KINDS: tuple[ClockKind, ...] = ("wall", "sim")

# The simulated rig's clock is quantised to 2^-20 s (~1 us), each world's time begins at a whole
# second (its epoch), and every time lies in [2^30, 2^31) s: one binade, so a time plus a constant
# (a period, a dt) rounds alike whatever the epoch. A run then computes the same ages, dts, limits and
# trajectory times, bit for bit, whether its world is `bagit run`'s only one or the simulator's
# tenth of the day.
SIM_QUANTUM_S = 2.0**-20
SIM_EPOCH0_S = 2.0**30  # the first world's epoch


def sim_time(world_t: float, epoch: float = SIM_EPOCH0_S) -> float:
    """The rig's clock for a world at `world_t` seconds whose time began at `epoch` (whole seconds)."""
    return epoch + round(world_t / SIM_QUANTUM_S) * SIM_QUANTUM_S


def next_epoch(clock_t: float) -> float:
    """The epoch of a new world begun when the clock read `clock_t`: the next whole second."""
    return float(math.floor(clock_t) + 1)


class Clock(Protocol):
    """Seconds on the rig's clock: stamps, ages and timers all read this."""

    simulated: bool

    def now(self) -> float: ...

    def wait_until(self, t: float, stop: threading.Event, timeout: float | None = None) -> bool: ...

    def step_time(self, t: float) -> float: ...

    def age(self, stamp: float, received: float, now: float) -> float: ...


class WallClock:
    """This host's clock (Unix seconds): a real rig's, or `--clock wall`."""

    simulated = False

    def now(self) -> float:
        return time.time()

    def wait_until(self, t: float, stop: threading.Event, timeout: float | None = None) -> bool:
        """Sleep until `t` (or `stop`, or `timeout` wall seconds); True if `t` was reached."""
        delay = t - time.time()
        if timeout is not None:
            delay = min(delay, timeout)
        if delay > 0 and stop.wait(delay):
            return False
        return time.time() >= t

    def step_time(self, t: float) -> float:
        """When a service handles what happened at `t` (a frame's stamp): now, on this host's clock."""
        return time.time()

    def age(self, stamp: float, received: float, now: float) -> float:
        """How old a message is: since it arrived (`received`, time.monotonic()), as another host's
        stamps may be on a clock that differs from this one."""
        return time.monotonic() - received


class SimClock:
    """The simulator's time as last heard on sim/clock; it only moves forward.

    `ticks` carries the servo ticks the simulator asks for (see `bagit.common.messages.ClockTick`):
    the arm driver cycles once per tick, so its servo period is the simulator's, not this host's.
    """

    simulated = True

    def __init__(self, t0: float = 0.0) -> None:
        self._t = float(t0)
        self._tick: tuple[int, float] = (-1, float("-inf"))  # (servo tick number, its time)
        self._event: tuple[float, int | None] = (float("-inf"), None)  # the newest step heard: (time, its servo tick or None)
        self._control_step = True  # whether the controller ticks at that step (a frame's or a keep-alive's)
        self._cond = threading.Condition()

    def now(self) -> float:
        with self._cond:
            return self._t

    @property
    def heard(self) -> bool:
        """Whether the simulator has said the time yet (before that, `now()` is `t0`, no time of the rig's)."""
        with self._cond:
            return self._event[0] > float("-inf")

    def step_time(self, t: float) -> float:
        """When a service handles what happened at `t`: at `t` itself, as the world waits for the services
        (processing takes no simulated time, as in `bagit run`)."""
        return t

    def age(self, stamp: float, received: float, now: float) -> float:
        """How old a message stamped `stamp` is at the step at `now`, on the simulator's clock (when it
        arrived says nothing: a busy machine makes a run slower, never different)."""
        return now - stamp

    def advance(self, t: float, servo_tick: int | None = None, control_step: bool = True) -> None:
        """The simulator says it is `t` (and, with `servo_tick`, that this is servo tick number n;
        `control_step`: that the controller ticks at `t` too, on a frame or a keep-alive)."""
        with self._cond:
            if t > self._t:
                self._t = float(t)
            if servo_tick is not None and servo_tick > self._tick[0]:
                self._tick = (int(servo_tick), float(t))
                self._event, self._control_step = (float(t), int(servo_tick)), control_step
            elif t > self._event[0]:
                self._event, self._control_step = (float(t), None), control_step
            self._cond.notify_all()

    def control_step_at(self, t: float) -> bool:
        """Whether the controller ticks at the step at `t` (True when `t` is not the newest step heard)."""
        with self._cond:
            return self._control_step or self._event[0] != t

    def _wait_for(self, ready: Callable[[], bool], stop: threading.Event, timeout: float | None) -> bool:
        """Until `ready()` (with the lock held), `stop` or `timeout` wall seconds; woken by `advance`, and
        every 50 ms to look at `stop`."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while not ready() and not stop.is_set():
            left = 0.05 if deadline is None else min(0.05, deadline - time.monotonic())
            if left <= 0:
                break
            self._cond.wait(left)
        return ready()

    def wait_until(self, t: float, stop: threading.Event, timeout: float | None = None) -> bool:
        """Block until the simulator's time reaches `t`, `stop` is set or `timeout` wall seconds pass."""
        with self._cond:
            return self._wait_for(lambda: self._t >= t, stop, timeout)

    def next_tick(self, after: int, stop: threading.Event, timeout: float | None = None) -> tuple[int, float] | None:
        """The first servo tick numbered above `after` as (n, t); None on `stop` or `timeout` (wall s)."""
        with self._cond:
            return self._tick if self._wait_for(lambda: self._tick[0] > after, stop, timeout) else None

    def next_event(self, after: float, stop: threading.Event, timeout: float | None = None) -> tuple[float, int | None] | None:
        """The newest step the simulator announced later than time `after`, as (t, servo tick number or
        None); None on `stop` or `timeout` (wall s)."""
        with self._cond:
            return self._event if self._wait_for(lambda: self._event[0] > after, stop, timeout) else None


def make_clock(kind: ClockKind) -> WallClock | SimClock:
    """The clock of a service on a rig whose bus config says `kind`."""
    return SimClock() if kind == "sim" else WallClock()
