"""The arm driver: both CR5s from one process, streaming smoothed, safe when anything else fails.

    drv = ArmDriver(rig, DriverConfig(), on_state=publish)    # on_state: each feedback packet as ArmState
                                                              # (on_event: (kind, detail) of each event)
    drv.start()                     # connect, ClearError, EnableRobot(payload), SpeedFactor; loop running
    drv.submit(command)             # the controller's 12-D increment (bagit.common.messages.Command)
    drv.hold("run over")            # brake to rest; a later command starts a new stream
    drv.estop("operator")           # EmergencyStop(1) to both controllers at once; latched
    drv.reset_estop()               # only this clears it
    drv.close()                     # smooth stop, hold, DisableRobot, disconnect

A thin shell: a command goes down the one `ServoPath` (targets, smoothing, limits, reach, wire:
servo_path.py) and out on the `Cr5Links` (links.py); the latches, the links' condition and the
restart are the pure machine's (machine.py), stepped under the one lock by `_dispatch`. Every servo
period (`SafetyLimits.servo_period_s`, 30 ms: Dobot recommends ServoP no faster; the schedule is
servo_loop.py's) a cycle sends each arm its ServoP with `t` the period, so each target is reached as
the next one arrives; replies are checked a period later.

What stops the arms, and how:
- watchdog: no command for `watchdog_s`: the path brakes to rest at the last tick before the deadline,
  then the arms hold; a later command starts a new stream from where the arms are. Every halt (the
  watchdog, a hold, a fault, a lost link) is a controlled stop at the stop's limits (`SafetyLimits.stop_*`,
  larger than the path's), along the motion (`smoothing.braking_shares`), its ServoPs sent with
  `halt_aheadtime` (`python -m bagit.bench.stop_timeline`, `python -m bagit.bench.stop_time`).
- a stale command: made (`stamp`) longer than `watchdog_s` before it is applied, or stamped that far
  ahead, is refused (`gate.stale_refusal`).
- a pause of the loop longer than a ServoP's `t` and a period (`ServoPath.stall_s`, 60 ms; SIGSTOP,
  starvation): the controllers stopped the arms at the last target when its `t` ran out, so the
  trajectory is dropped, not braked or resumed (either from its old velocity would start the arms
  again with a jump); nothing moves until a new command, which starts a new stream from rest.
- a controller in error or collision, an arm disabled behind the driver's back, a ServoP refused, or
  too many requests without a good reply: a fault; both arms brake; it stays until `clear_fault()`
  (the node clears it when a new run starts). The supervisor thread adds the alarm ids to its text.
- a connection dropped, or feedback silent for `feedback_timeout_s`: both arms brake; the client
  reconnects with back-off; then the stream restarts from the poses the controllers command and
  waits for a new command (increments sent meanwhile are refused, never replayed).
- e-stop: the latch is set first (nothing more is streamed), then EmergencyStop(1) goes to both
  controllers back to back; one that could not be reached gets it when it reconnects.
  `reset_estop()` releases, clears the alarms, re-enables and restarts from the measured poses.

On the simulated rig's clock (`set_clock(SimClock)`, `bagit up`'s lockstep) the loop cycles on the
simulator's servo ticks (servo_loop.py) and says when each is done (`on_tick`): the watchdog, the
stale-command rule and every motion limit run on that clock; the links' time-outs stay on the wall
clock (they guard a real socket).
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from bagit.common.clock import Clock, WallClock
from bagit.common.errors import BagItError, SafetyViolation
from bagit.common.messages import ArmState, Command, EStop
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.arm_driver import machine as m
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import feedback_state
from bagit.services.arm_driver.gate import Refusal, estop_refusal, stale_refusal
from bagit.services.arm_driver.links import Cr5Links
from bagit.services.arm_driver.machine import DriverState
from bagit.services.arm_driver.servo_loop import ServoLoop
from bagit.services.arm_driver.servo_path import Cycle, ServoPath

_MAX_EVENTS = 200
OnTick = Callable[[int, dict[str, int], str | None], None]  # lockstep: (tick, ServoPs sent per arm, what it went without)


class ArmDriver:
    """Both arms of the rig (see the module docstring)."""

    def __init__(self, rig: RigConfig | None = None, config: DriverConfig | None = None,
                 on_state: Callable[[ArmState], None] | None = None, on_event: Callable[[str, str], None] | None = None):
        self.rig, self.cfg = rig or RigConfig(), config or DriverConfig()
        self.limits = self.rig.safety
        self.period = float(self.limits.servo_period_s)
        self.clock: Clock = WallClock()
        self._now: Callable[[], float] = time.monotonic  # the motion's clock: monotonic wall, or the rig's
        self.on_state, self.on_event = on_state, on_event  # on_event must not block
        self.on_tick: OnTick | None = None
        self.counters: Counter[str] = Counter()
        self.events: deque[tuple[float, str, str]] = deque(maxlen=_MAX_EVENTS)
        self.path = ServoPath(self.rig, self.cfg, on_event=self.event, counters=self.counters)
        self.links = Cr5Links(self.rig, self.cfg, self._feedback_callback)
        self.clients, self.frames = self.links.clients, self.path.frames
        self._lock = threading.RLock()  # the machine's state and the path: one cycle, submit or event at a time
        self.loop = ServoLoop(self, self.period, self.limits.watchdog_s, self.counters, threading.Event())
        self.cycle_ms, self.cycle_starts, self.send_times = self.loop.cycle_ms, self.loop.cycle_starts, self.loop.send_times  # for benchmarks
        self.state = DriverState()  # immutable: readers without the lock see it whole
        self._last_seq: int | None = None
        self._last_cycle = -np.inf  # the motion clock's time of the last cycle (a pause shows as a gap)
        self.rejections: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None  # the last command refused, and why

    # -- life cycle ------------------------------------------------------------------------------

    def set_clock(self, clock: Clock, on_tick: OnTick | None = None) -> None:
        """Run on `clock` (before `start`): a SimClock makes the loop cycle on the simulator's servo ticks."""
        if self.state.started:
            raise BagItError("set_clock() before start()")
        self.clock, self.on_tick = clock, on_tick
        self._now = clock.now if clock.simulated else time.monotonic

    def start(self) -> ArmDriver:
        """Connect, bring both controllers up as on the real rig (`Cr5Links.open`: ProtocolError and both
        disabled if one cannot be) and start streaming."""
        if self.state.started:
            return self
        if self.state.estop:
            raise SafetyViolation(f"the e-stop is latched ({self.state.estop_reason}); reset_estop() first")
        self.links.open()
        self._last_cycle = self._now()
        self._dispatch(m.Started())
        self.loop.start(self.clock, (self._supervise, "supervisor"))
        return self

    def close(self) -> None:
        """Stop smoothly, hold, disable both arms and disconnect (idempotent)."""
        if not self.state.started:
            self.links.close(False, self.event)
            return
        self._dispatch(m.Closing())
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while self.path.moving and time.monotonic() < deadline and self.loop.running:
            time.sleep(self.period / 3)
        time.sleep(2 * self.period)  # the last ServoP's `t` runs out and its reply comes back
        self.loop.join()
        self.links.close(not self.state.estop, self.event)
        self._dispatch(m.Closed())

    def __enter__(self) -> ArmDriver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- input -----------------------------------------------------------------------------------

    def submit(self, cmd: Command) -> bool:
        """Take one controller command; False (counted with its reason, `last_refusal`) if refused.
        A hold brakes both arms to rest. Which run may command the arms is the node's business."""
        if cmd.mode == "hold":
            self.hold(cmd.reason or "controller asked to hold", command=True)
            return True
        return self.submit_increment(np.asarray(cmd.u), float(cmd.dt), seq=cmd.seq, stamp=cmd.stamp)

    def hold(self, reason: str, command: bool = False) -> None:
        """Brake both arms to rest (the node, when the run it streamed for ends; `command`: a hold command)."""
        with self._lock:
            if command:
                self.counters["commands"] += 1
            self.path.hold(reason, self._now())

    def refuse(self, refusal: Refusal) -> None:
        """Count a command refused before it reached the driver (the node's run gate) with the driver's own."""
        with self._lock:
            self.counters["commands"] += 1
            self._refused(refusal)

    def _refused(self, refusal: Refusal, counted: bool = False) -> bool:
        """Count `refusal` (with the lock held; `counted`: the path counted it as rejected); False."""
        self.rejections[refusal.reason] += 1
        if not counted:
            self.counters["rejected"] += 1
        self.last_refusal = refusal
        return False

    def submit_increment(self, u: np.ndarray, dt: float, seq: int | None = None, stamp: float | None = None) -> bool:
        """Increment `u (12,)` (world, m and rad; left then right) over `dt` s, made at `stamp` (None: now)."""
        with self._lock:
            now = self._now()  # under the lock: a submit that waited for it is timed when it applies
            if self.clock.simulated and stamp is not None and 0.0 < stamp - now <= self.limits.watchdog_s:
                now = stamp  # a lockstep command made at a time this host has not heard yet is timed at its stamp
            self.counters["commands"] += 1
            why = m.refusal(self.state)
            if why is not None:
                return self._refused(Refusal(why, f"command {seq}: the driver is {why.replace('_', ' ')}"))
            stale = None if stamp is None else stale_refusal(stamp, self.clock.now(), self.limits.watchdog_s)
            if stale is not None:
                return self._refused(Refusal(stale.reason, f"command {seq}: {stale.detail}"))
            self._check_stall(now)
            if not self.path.moving:
                # A new stream from rest starts at the MEASURED poses, never at the last commanded ones:
                # while the arms held, someone may have jogged them (or a simulator reset its world).
                if not self._restart_from_measured():
                    return self._refused(Refusal("no_feedback", f"command {seq}: no feedback to start a stream from"))
                if self.state.fault is not None:
                    return self._refused(Refusal("fault", f"command {seq}: {self.state.fault}"))
                self.counters["reseeds"] += 1
            if seq is not None and self._last_seq is not None and seq <= self._last_seq:
                self.counters["out_of_order"] += 1
            self._last_seq = seq if seq is not None else self._last_seq
            if any(v.kind == "non_finite" for v in self.path.submit(u, dt, now)):
                return self._refused(Refusal("non_finite", f"command {seq}: not 12 finite numbers over 0 < dt <= 10 s"), counted=True)
            return True

    def handle_estop(self, msg: EStop) -> None:
        """An `EStop` message: engage (from anyone) latches; a release from one of ESTOP_RELEASE_SOURCES
        resets, from anyone else it is SafetyViolation (counted) and the latch stays."""
        if msg.engage:
            self.estop(f"{msg.source}: {msg.reason or 'e-stop'}")
            return
        refused = estop_refusal(msg)
        if refused is not None:
            self.counters["estop_releases_refused"] += 1
            raise SafetyViolation(str(refused))
        self.reset_estop()

    def estop(self, reason: str = "e-stop") -> dict[ArmName, bool]:
        """Latch the e-stop (nothing more is streamed), then EmergencyStop(1) to both controllers at
        once; per arm, whether its controller confirmed. The latch holds whatever the answer."""
        self._dispatch(m.EstopEngaged(reason))
        reached = self.links.emergency_stop(self.event)
        self._dispatch(m.EstopSent(frozenset(a for a in ARMS if not reached[a])))
        return reached

    def reset_estop(self) -> None:
        """Release the e-stop: EmergencyStop(0), ClearError, EnableRobot, SpeedFactor on both arms; motion
        resumes with a new command stream. ProtocolError (latched still) if a controller refuses."""
        if self.state.estop:
            self.links.release_emergency_stop()
            self._dispatch(m.EstopReleased())

    def clear_fault(self) -> None:
        """Clear a latched fault: re-enable the arms that need it, restart from the measured poses."""
        if self.state.estop:
            raise SafetyViolation("the e-stop is latched: reset_estop() first")
        if self.state.fault is not None:
            self.links.clear_faults()
            self._dispatch(m.FaultCleared())

    # -- state -----------------------------------------------------------------------------------

    def _feedback_callback(self, arm: ArmName) -> Callable[[np.ndarray, float], None]:
        def on_packet(rec: np.ndarray, t: float) -> None:
            if self.clock.simulated:  # lockstep: the step's states go out from the loop, after its cycle
                self.loop.feedback.notify()
            elif (cb := self.on_state) is not None:
                cb(self._state_of(arm, rec))

        return on_packet

    def _state_of(self, arm: ArmName, rec: np.ndarray) -> ArmState:
        """An arm's state from a feedback record with the path's aim laid over (read without the lock:
        the feedback thread never waits on a cycle; a pose read as a command lands is a packet off)."""
        return self.path.lay_over(feedback_state(arm, rec, self.frames[arm], estopped=self.state.estop, stamp=self._stamp(rec)))

    def _stamp(self, rec: np.ndarray) -> float:
        """When a feedback packet was true, on the rig's clock (a simulated controller stamps its own time)."""
        return float(rec["TimeStamp"]) / 1000.0 if self.clock.simulated else time.time()

    def states(self) -> dict[ArmName, ArmState]:
        """The latest state of each arm that has reported since (re)connecting."""
        recs = {a: self.links.record(a) for a in ARMS}
        return {a: feedback_state(a, r, self.frames[a], estopped=self.state.estop) for a, r in recs.items() if r is not None}

    @property
    def mode(self) -> str:
        """off | estopped | fault | link_down | restarting | streaming | stopping | holding."""
        return m.mode(self.state, self.path.mode)

    def status(self) -> dict:
        """Mode, latches, counters (commands, clipped, rejected and why, violations by kind), links."""
        with self._lock:
            s = self.state
            return {
                "mode": self.mode,
                "estop": {"latched": s.estop, "reason": s.estop_reason, "unconfirmed": sorted(s.estop_unconfirmed)},
                "fault": s.fault, "links_down": s.links, "counters": dict(self.counters), "rejections": dict(self.rejections),
                "violations": dict(self.path.violation_counts), "last_violations": list(self.path.last_violations),
                **self.loop.timing(),
                "arms": {a: {**c.stats(), "feedback_age_s": c.feedback_age()} for a, c in self.clients.items()},
                "events": [f"{t:.3f} {k}: {d}" for t, k, d in list(self.events)[-20:]],
            }

    def event(self, kind: str, detail: str) -> None:
        self.events.append((time.monotonic(), kind, detail))
        if (cb := self.on_event) is not None:
            try:
                cb(kind, detail)
            except Exception as e:  # a subscriber's bug must not stop the arms' loop
                self.events.append((time.monotonic(), "event_callback", repr(e)))

    @property
    def fault(self) -> str | None:
        """The latched fault, or None (read without the lock: the state is swapped whole; so are
        `state.links`, the links down, and `state.needs_reset`)."""
        return self.state.fault

    # -- the machine -----------------------------------------------------------------------------

    def _dispatch(self, event: m.Event) -> list[m.Effect]:
        """Step the machine under the lock and carry out its effects in order; the ones that block
        (AskAlarms) are returned for the caller to carry out without it."""
        later: list[m.Effect] = []
        with self._lock:
            self.state, effects = m.step(self.state, event)
            for e in effects:
                if isinstance(e, m.StopPipe):
                    self.path.stop()
                elif isinstance(e, m.HaltPipe):
                    self.path.halt()
                elif isinstance(e, m.Restart):
                    self._restart_from_measured()
                elif isinstance(e, m.ClearInFlight):
                    self.links.in_flight[e.arm].clear()
                elif isinstance(e, m.ResendEstop):
                    later += self._dispatch(m.EstopResent(e.arm, self.links.resend_emergency_stop(e.arm)))
                elif isinstance(e, m.Count):
                    self.counters[e.name] += 1
                elif isinstance(e, m.Note):
                    self.event(e.kind, e.detail)
                else:
                    later.append(e)
        return later

    def _restart_from_measured(self) -> bool:
        """Reset the path at rest at the poses the controllers command (`ServoPath.restart`); a start
        outside the envelope is a fault. A restart waits at most SETTLE_TIMEOUT_S for the arms to settle."""
        recs = {a: r for a in ARMS if (r := self.links.record(a)) is not None}
        if len(recs) != len(ARMS):
            self._dispatch(m.Restarted("no_feedback"))
            return False
        found = self.path.restart(recs)
        self._dispatch(m.Restarted("non_finite") if found is None else m.Restarted("ok", tuple(str(v) for v in found)))
        return found is not None

    # -- the servo cycle (its schedule: servo_loop.py) -----------------------------------------------

    def make_cycle(self) -> tuple[Cycle, float] | None:
        """One servo period: replies, links, the watchdog, then the path's ServoPs and when they were made
        (on this host's monotonic clock); None if there is nothing to send."""
        self.links.check_replies(time.monotonic(), self.clock.simulated, self.state.failed, self._dispatch)
        with self._lock:
            now = self._now()  # under the lock: a cycle that waited for it must not act on an old clock
            made = time.monotonic()
            self.counters["cycles"] += 1
            self._check_stall(now)
            self._last_cycle = now
            self.links.watch(now if self.clock.simulated else None, lambda: not (self.state.estop or self.state.closing), self._dispatch)
            self.path.watchdog(now)
            if self.state.estop:
                return None
            moving = self.path.moving
            self._dispatch(m.Cycle(now, moving, not moving and self.state.needs_reset and self.links.settled()))
            out = self.path.cycle(now, [a for a in ARMS if m.commandable(self.state, a) and not self.links.in_error(a)])
            if out.fault is not None:
                self._dispatch(m.FaultRaised(out.fault))
            return None if out.poses is None else (out, made)

    def send_cycle(self, out: Cycle, stale: Callable[[], bool] | None = None) -> list[ArmName]:
        """The cycle's ServoPs, each unless the e-stop has latched by its turn on its connection: `estop`
        latches before its EmergencyStop goes out on the same connections, so a ServoP made before the latch
        goes out before the EmergencyStop or not at all (and no arm's e-stop waits for the other arm's link).
        Nor once `stale()` says its poses are too old, asked last before each write."""
        return self.links.send(out.servo, self._dispatch, lambda: self.state.estop or (stale is not None and stale()))

    def _check_stall(self, now: float) -> None:
        """A loop that has not run for `ServoPath.stall_s` (the arms stopped at the last target; with the lock held): `stalled`."""
        if self.path.moving and (gap := now - self._last_cycle) > self.path.stall_s:
            self.stalled(f"no servo cycle for {gap * 1000:.0f} ms (the process was paused or starved): "
                         "the arms stopped at their last target and hold; a new command starts a new stream")

    def stalled(self, why: str, unsent: bool = False) -> None:
        """Drop the trajectory (the arms stopped at their last target when its ServoP ran out: braking from
        the trajectory's old velocity would move them again); a new command starts a new stream. `unsent`:
        the last cycle's ServoPs did not go out, so the arms rest where the cycle before sent them."""
        with self._lock:
            if unsent:
                self.path.unsend()
            else:
                self.path.halt()
            self.counters["stalls"] += 1
            self.event("stalled", why)

    def cycle_failed(self, e: Exception) -> None:
        self._dispatch(m.FaultRaised(f"servo loop: {e if isinstance(e, BagItError) else repr(e)}"))

    def step_ready(self, t: float) -> bool:
        due_ms = round(t * 1000.0)  # a simulated controller stamps its packets with its step's time
        return all((r := self.links.record(a)) is not None and int(r["TimeStamp"]) >= due_ms for a in ARMS)

    def step_done(self, tick: int | None, sent: dict[str, int], late: str | None, states: bool = True) -> None:
        """Lockstep: the tick's answer (`on_tick`), then, with `states`, both arms' states (from here only,
        never the feedback thread: none races a cycle). The answer first: the simulator steps on at once,
        and whoever needs a state of this step waits for its stamp (the controller's tick, perception's
        hint), so the states may come after it without changing anything but the time the step took."""
        if tick is not None and (tick_cb := self.on_tick) is not None:
            try:
                tick_cb(tick, sent, late)
            except Exception as e:  # noqa: BLE001 - a closing bus must not stop the arms' loop
                self.event("tick_callback", repr(e))
        if states and (cb := self.on_state) is not None:
            for a in ARMS:
                if (rec := self.links.record(a)) is not None:
                    cb(self._state_of(a, rec))

    def _supervise(self) -> None:
        """Reconnect dropped controllers with back-off, and ask a faulted controller for its alarms, off
        the servo loop (a connect or a request may block)."""
        while not self.loop.stop.wait(0.02):
            for c in self.clients.values():
                if not c.connected and not self.state.closing:
                    c.reconnect_if_due()
            if self.state.fault is None or self.state.fault_alarms_asked:
                continue  # read without the lock: this thread must not contend with the servo loop
            if any(isinstance(e, m.AskAlarms) for e in self._dispatch(m.AlarmsDue())):
                self._dispatch(m.AlarmsFound(self.links.alarms()))
