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
restart are the pure machine's (machine.py), stepped under the one lock by `_dispatch`. What this
class adds is threads and time: every servo period (`SafetyLimits.servo_period_s`, 30 ms: Dobot
recommends ServoP no faster) the loop takes one cycle of the path and sends each arm its ServoP with
`t` the period, so each target is reached as the next one arrives; replies are checked a period later.

What stops the arms, and how:
- watchdog: no command for `watchdog_s`: the path brakes to rest at the last tick before the deadline,
  then the arms hold; a later command starts a new stream from where the arms are. Every halt (the
  watchdog, a hold, a fault, a lost link) brakes along the motion with the whole Cartesian budget
  (`smoothing.braking_shares`), its ServoPs sent with `halt_aheadtime` (`python -m bagit.bench.stop_time`).
- a stale command: made (`stamp`) longer than `watchdog_s` before it is applied, or stamped that far
  ahead, is refused (`gate.stale_refusal`).
- a pause of the loop longer than `watchdog_s` (SIGSTOP, starvation): the controllers stopped the arms
  at the last target when its `t` ran out, so the trajectory is dropped, not braked (braking from its
  old velocity would move the arms again); nothing moves until a new command.
- a controller in error or collision, an arm disabled behind the driver's back, a ServoP refused, or
  too many requests without a good reply: a fault; both arms brake; it stays until `clear_fault()`
  (the node clears it when a new run starts). The supervisor thread adds the alarm ids to its text.
- a connection dropped, or feedback silent for `feedback_timeout_s`: both arms brake; the client
  reconnects with back-off; then the stream restarts from the poses the controllers command and
  waits for a new command (increments sent meanwhile are refused, never replayed).
- e-stop: the latch is set first (nothing more is streamed), then EmergencyStop(1) goes to both
  controllers back to back; one that could not be reached gets it when it reconnects.
  `reset_estop()` releases, clears the alarms, re-enables and restarts from the measured poses.

On the simulated rig's clock (`set_clock(SimClock)`, `bagit up`'s lockstep) the loop runs one cycle per
servo tick of the simulator (sim/clock), on the feedback of that very step, publishes both arms'
states after it and says when it is done (`on_tick`): the watchdog, the stale-command rule and every
motion limit then run on that clock, with no wall-clock wait. The links' time-outs stay on the wall
clock: they guard a real socket.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable

import numpy as np

from bagit.common.clock import Clock, SimClock, WallClock
from bagit.common.errors import BagItError, SafetyViolation
from bagit.common.lockstep import StepWait
from bagit.common.messages import ArmState, Command, EStop
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.arm_driver import machine as m
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import controller_fault, feedback_state
from bagit.services.arm_driver.gate import Refusal, estop_refusal, stale_refusal
from bagit.services.arm_driver.links import Cr5Links
from bagit.services.arm_driver.machine import DriverState
from bagit.services.arm_driver.servo_path import ServoPath

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
        self.on_state, self.on_event, self.on_tick = on_state, on_event, None  # on_event must not block
        self.on_tick: OnTick | None
        self.counters: Counter[str] = Counter()
        self.events: deque[tuple[float, str, str]] = deque(maxlen=_MAX_EVENTS)
        self.path = ServoPath(self.rig, self.cfg, on_event=self._event, counters=self.counters)
        self.links = Cr5Links(self.rig, self.cfg, self._feedback_callback)
        self.clients, self.frames = self.links.clients, self.path.frames
        self._lock = threading.RLock()  # the machine's state and the path: one cycle, submit or event at a time
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._feedback_wait = StepWait()  # lockstep: a feedback packet wakes the wait for a step's
        self.state = DriverState()  # immutable: readers without the lock see it whole
        self._last_seq: int | None = None
        self._last_send = self._last_cycle = -np.inf  # monotonic; the loop's last cycle (a pause shows as a gap)
        self.rejections: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None  # the last command refused, and why
        self.servo_sent = {a: 0 for a in ARMS}
        self.cycle_ms: deque[float] = deque(maxlen=1000)  # compute time of each cycle
        self.cycle_starts: deque[float] = deque(maxlen=1000)  # monotonic start of each cycle
        self.send_times: deque[float] = deque(maxlen=1000)  # when each period's ServoPs went out

    # -- life cycle ------------------------------------------------------------------------------

    def set_clock(self, clock: Clock, on_tick: OnTick | None = None) -> None:
        """Run on `clock` (before `start`): a SimClock makes the loop cycle on the simulator's servo ticks."""
        if self.started:
            raise BagItError("set_clock() before start()")
        self.clock, self.on_tick = clock, on_tick
        self._now = clock.now if clock.simulated else time.monotonic

    def start(self) -> ArmDriver:
        """Connect, bring both controllers up as on the real rig (`Cr5Links.open`: ProtocolError and both
        disabled if one cannot be) and start streaming."""
        if self.started:
            return self
        if self.state.estop:
            raise SafetyViolation(f"the e-stop is latched ({self.state.estop_reason}); reset_estop() first")
        self.links.open()
        self._last_cycle = self._now()
        self._dispatch(m.Started())
        self._stop.clear()
        loop = self._lockstep_loop if isinstance(self.clock, SimClock) else self._wall_loop
        for target, name in ((loop, "servo-loop"), (self._supervise, "supervisor")):
            self._threads.append(threading.Thread(target=target, name=f"arm-driver-{name}", daemon=True))
            self._threads[-1].start()
        return self

    def close(self) -> None:
        """Stop smoothly, hold, disable both arms and disconnect (idempotent)."""
        if not self.started:
            self.links.close(False, self._event)
            return
        self._dispatch(m.Closing())
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while self.path.moving and time.monotonic() < deadline and self._threads[0].is_alive():
            time.sleep(self.period / 3)
        time.sleep(2 * self.period)  # the last ServoP's `t` runs out and its reply comes back
        self._stop.set()
        self._feedback_wait.notify()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        self.links.close(not self.state.estop, self._event)
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
            with self._lock:
                self.counters["commands"] += 1
                self.path.hold(cmd.reason or "controller asked to hold", self._now())
            return True
        return self.submit_increment(np.asarray(cmd.u), float(cmd.dt), seq=cmd.seq, stamp=cmd.stamp)

    def hold(self, reason: str) -> None:
        """Brake both arms to rest (the node, when the run it streamed for ends)."""
        with self._lock:
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
        reached = self.links.emergency_stop(self._event)
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
                self._feedback_wait.notify()
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
            cycle = np.array(self.cycle_ms) if self.cycle_ms else np.zeros(1)
            period = np.diff(np.array(self.cycle_starts)) * 1000.0 if len(self.cycle_starts) > 1 else np.zeros(1)
            sends = np.diff(np.array(self.send_times)) * 1000.0 if len(self.send_times) > 1 else np.zeros(1)
            s = self.state
            return {
                "mode": self.mode,
                "estop": {"latched": s.estop, "reason": s.estop_reason, "unconfirmed": sorted(s.estop_unconfirmed)},
                "fault": s.fault, "links_down": s.links, "counters": dict(self.counters), "rejections": dict(self.rejections),
                "violations": dict(self.path.violation_counts), "last_violations": list(self.path.last_violations),
                "cycle_ms": {"median": float(np.median(cycle)), "max": float(cycle.max())},
                "period_ms": {"median": float(np.median(period)), "max": float(period.max())},
                "send_interval_ms": {"min": float(sends.min()), "median": float(np.median(sends))},
                "arms": {a: {**c.stats(), "feedback_age_s": c.feedback_age()} for a, c in self.clients.items()},
                "events": [f"{t:.3f} {k}: {d}" for t, k, d in list(self.events)[-20:]],
            }

    def _event(self, kind: str, detail: str) -> None:
        self.events.append((time.monotonic(), kind, detail))
        if (cb := self.on_event) is not None:
            try:
                cb(kind, detail)
            except Exception as e:  # a subscriber's bug must not stop the arms' loop
                self.events.append((time.monotonic(), "event_callback", repr(e)))

    @property
    def last_violations(self) -> list[str]:
        return self.path.last_violations

    @property
    def started(self) -> bool:
        return self.state.started

    @property
    def fault(self) -> str | None:
        """The latched fault, or None (read without the lock: the state is swapped whole)."""
        return self.state.fault

    @property
    def links_down(self) -> dict[str, str]:
        """Arm -> why, for each link that is down (read without the lock)."""
        return self.state.links

    @property
    def needs_reset(self) -> bool:
        """The stream restarts from the measured poses before anything moves."""
        return self.state.needs_reset

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
                    self._event(e.kind, e.detail)
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

    # -- the loop --------------------------------------------------------------------------------

    def _wall_loop(self) -> None:
        """A cycle every period of this host's clock. Never catching up after a late cycle: two ServoPs
        closer than a period would make the controller cover a step in less than its `t` (Dobot: no
        faster than every 30 ms); a late cycle shifts the schedule (the trajectory runs slightly slower,
        never faster) and the next starts so that its ServoPs go out about a period after the last."""
        next_t = time.monotonic()
        offsets: deque[float] = deque([0.0], maxlen=50)  # when in its cycle the ServoPs go out
        while not self._stop.is_set():
            t0 = time.monotonic()
            if self._timed_cycle(t0):
                offsets.append(self._last_send - t0)
            if t0 - next_t > 0.2 * self.period:
                self.counters["late_cycles"] += 1
            offset = min(float(np.median(offsets)), 0.2 * self.period)
            next_t = max(next_t + self.period, t0 + 0.5 * self.period, self._last_send + self.period - offset)
            if (delay := next_t - time.monotonic()) > 0:
                self._stop.wait(delay)

    def _lockstep_loop(self) -> None:
        """One pass per step the simulator announces on sim/clock: on the feedback of that step, a cycle if
        it is a servo tick, then both arms' states (after the cycle: what the step's frame sees, as
        `bagit run` reads the arms after its servo period), then `on_tick`. States come from here only,
        never from the feedback thread, so none races a cycle."""
        assert isinstance(self.clock, SimClock)
        last_t, last_tick = float("-inf"), -1
        while not self._stop.is_set():
            event = self.clock.next_event(last_t, self._stop, timeout=1.0)
            if event is None:
                continue
            last_t, n = event
            late = self._await_feedback(last_t)
            before = dict(self.servo_sent)
            if n is not None and n > last_tick:
                last_tick = n
                self._timed_cycle(time.monotonic())
            if (cb := self.on_state) is not None:
                for a in ARMS:
                    if (rec := self.links.record(a)) is not None:
                        cb(self._state_of(a, rec))
            if n is not None and (tick_cb := self.on_tick) is not None:
                try:
                    tick_cb(n, {a: self.servo_sent[a] - before[a] for a in ARMS}, late)
                except Exception as e:  # noqa: BLE001 - a closing bus must not stop the arms' loop
                    self._event("tick_callback", repr(e))

    def _await_feedback(self, t: float) -> str | None:
        """Until both arms' feedback shows the step at `t` (a simulated controller stamps it), woken by each
        packet, at most the lockstep time-out (a quiet link is the supervisor's business); what the
        step's cycle then goes without (`lockstep_late`), or None."""
        due_ms = round(t * 1000.0)

        def ready() -> bool:
            return all((r := self.links.record(a)) is not None and int(r["TimeStamp"]) >= due_ms for a in ARMS)

        if self._feedback_wait.wait(ready, self._stop) or self._stop.is_set():
            return None
        self.counters["lockstep_late"] += 1
        self._event("lockstep", f"servo tick at {t:.3f}: cycled without the feedback of that step")
        return "the feedback of its step"

    def _timed_cycle(self, t0: float) -> bool:
        """`_cycle`, timed; whatever goes wrong in it becomes a fault (the loop never dies)."""
        self.cycle_starts.append(t0)
        try:
            sent = self._cycle()
        except Exception as e:
            self._dispatch(m.FaultRaised(f"servo loop: {e if isinstance(e, BagItError) else repr(e)}"))
            sent = False
        self.cycle_ms.append((time.monotonic() - t0) * 1000.0)
        return sent

    def _cycle(self) -> bool:
        """One servo period: replies, links, watchdog, then the path's ServoPs; True if any went out."""
        self.links.check_replies(time.monotonic(), self.clock.simulated, self.state.failed, self._dispatch)
        with self._lock:
            now = self._now()  # under the lock: a cycle that waited for it must not act on an old clock
            made = time.monotonic()
            self.counters["cycles"] += 1
            self._check_stall(now)
            self._last_cycle = now
            self._watch(now)
            if self.state.estop:
                return False
            moving = self.path.moving
            self._dispatch(m.Cycle(now, moving, not moving and self.state.needs_reset and self.links.settled()))
            active = [a for a in ARMS if m.commandable(self.state, a) and not self.links.in_error(a)]
            out = self.path.cycle(now, active)
            if out.fault is not None:
                self._dispatch(m.FaultRaised(out.fault))
            if out.poses is None:
                return False
        # On the wall clock: never two ServoPs less than a period apart, whatever the schedule did, and
        # none made before a pause; on the simulator's the ticks are a period apart and the world waits.
        if not self.clock.simulated:
            if (wait := self._last_send + self.period - time.monotonic()) > 0:
                time.sleep(wait)
            if (late := time.monotonic() - made) > self.limits.watchdog_s:
                self._stalled(f"this period's poses were {late * 1000:.0f} ms old when they could go out "
                              "(the process was paused or starved): not sent; a new command starts a new stream")
                return False
        self._last_send = time.monotonic()
        self.send_times.append(self._last_send)
        for a in self.links.send(out.servo, self._dispatch):
            self.counters["servo_sent"] += 1
            self.servo_sent[a] += 1
        return bool(out.servo)

    def _check_stall(self, now: float) -> None:
        """Drop the trajectory if the loop has not run for longer than the watchdog's time: the arms stopped
        at the last target when its ServoP ran out, so braking from the trajectory's old velocity would
        move them again. A new command starts a new stream from the measured poses."""
        if self.path.moving and (gap := now - self._last_cycle) > self.limits.watchdog_s:
            self._stalled(f"no servo cycle for {gap * 1000:.0f} ms (the process was paused or starved): "
                          "the arms stopped at their last target and hold; a new command starts a new stream")

    def _stalled(self, why: str) -> None:
        with self._lock:
            self.path.halt()
            self.counters["stalls"] += 1
            self._event("stalled", why)

    def _watch(self, now: float) -> None:
        """Links, controller errors, the watchdog (with the lock held)."""
        for a, c in self.clients.items():
            if not c.connected:
                self._dispatch(m.LinkLost(a, c.last_error or "disconnected"))
                continue
            if (silent := self._silence(a)) > self.cfg.feedback_timeout_s:
                c.drop(f"no feedback for {silent * 1000:.0f} ms")
                self._dispatch(m.LinkLost(a, "feedback lost"))
                continue
            if c.epoch != self.links.seen_epoch[a]:
                if self.links.record(a) is None:
                    continue  # reconnected; wait for its first packet
                self.links.seen_epoch[a] = c.epoch  # re-assert a latched e-stop, or restart from the measured pose
                self._dispatch(m.LinkBack(a))
            rec = self.links.record(a)
            if rec is None or self.state.estop or self.state.closing:
                continue
            if (why := controller_fault(rec)) is not None:
                self._dispatch(m.ArmAlarm(a, why))
            elif not int(rec["EnableStatus"]):
                self._dispatch(m.FaultRaised(f"{a}: disabled (robot mode {int(rec['RobotMode'])})"))
        self.path.watchdog(now)

    def _silence(self, arm: ArmName) -> float:
        """How long an arm's feedback has been quiet: the socket's silence on the wall clock; on the
        simulator's, how far the rig's clock is past the newest packet's stamp (a simulator the machine
        starves sends nothing because nothing happens, which is no lost link)."""
        c, rec = self.clients[arm], self.links.record(arm)
        if not self.clock.simulated or rec is None:
            return c.silent_for()
        return max(0.0, self.clock.now() - self._stamp(rec))

    def _supervise(self) -> None:
        """Reconnect dropped controllers with back-off, and ask a faulted controller for its alarms, off
        the servo loop (a connect or a request may block)."""
        while not self._stop.wait(0.02):
            for c in self.clients.values():
                if not c.connected and not self.state.closing:
                    c.reconnect_if_due()
            if self.state.fault is None or self.state.fault_alarms_asked:
                continue  # read without the lock: this thread must not contend with the servo loop
            if any(isinstance(e, m.AskAlarms) for e in self._dispatch(m.AlarmsDue())):
                self._dispatch(m.AlarmsFound(self.links.alarms()))
