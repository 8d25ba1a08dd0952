"""The arm driver: both CR5s from one process, streaming smoothed, safe when anything else fails.

    drv = ArmDriver(rig, DriverConfig(), on_state=publish)    # on_state: each feedback packet as ArmState
                                                              # (on_event: (kind, detail) of each event)
    drv.start()                     # connect, ClearError, EnableRobot(payload), SpeedFactor; loop running
    drv.submit(command)             # the controller's 12-D increment (bagit.common.messages.Command)
    drv.hold("run over")            # brake to rest; a later command starts a new stream
    drv.estop("operator")           # EmergencyStop(1) to both controllers at once; latched
    drv.reset_estop()               # only this clears it
    drv.close()                     # smooth stop, hold, DisableRobot, disconnect

Every servo period (`SafetyLimits.servo_period_s`, 30 ms by default: Dobot recommends ServoP no
faster) the loop thread takes one step of the motion pipeline (targets -> 12-DoF Ruckig ->
`check_and_clip`) and sends ServoP (or ServoJ through bagit.common.cr5.ik) to both arms with
`t` equal to the period, so each target is reached as the next one arrives. Replies are checked
one period later, so a slow controller never stalls the other arm.

What stops the arms, and how:
- watchdog: no command for `watchdog_s` (120 ms; the controller sends one every control tick while
  servoing). The stop is issued at the last tick before the deadline, Ruckig brakes to rest, then the
  arms hold. A later command starts a new stream from the pose the arms are at. Every halt (the
  watchdog, a hold, a fault, a lost link) brakes along the motion with the whole Cartesian budget
  (`streaming.braking_shares`), and its ServoPs go with `halt_aheadtime`, so the controllers follow
  the braking without their lag: ~200 ms from the last command to the arms still at 4 cm/s on the
  simulated CR5s (`python -m bagit.bench.stop_time`).
- a stale command: one made (its `stamp`) longer than `watchdog_s` before it is applied, e.g. queued
  while the process was stopped, is refused (`gate.stale_refusal`); so is one stamped that far ahead.
- a pause of the servo loop longer than `watchdog_s` (SIGSTOP, a machine that kept the process off
  the CPU): no ServoP went out, so the controllers stopped the arms at the last target when its `t`
  ran out. The trajectory is dropped, not braked (braking from its old velocity would move the
  arms again): nothing moves until a new command starts a new stream from the measured poses.
- a controller in error or collision, an arm disabled behind the driver's back, a ServoP refused,
  or too many requests without a good reply: a fault. Both arms brake (the arm in error is stopped
  by its controller); the fault stays until `clear_fault()` (the node clears it when a new run
  starts). The supervisor thread then asks the controllers for their alarm ids (GetErrorID) and
  adds them to the fault's text.
- a step the joints cannot follow (a wrist singularity) or a target out of reach: not a stop but a
  slow-down (`reach`): the longest part of the step every joint can follow is sent, so the arms
  pass a singularity at the joints' speed or stop short of an unreachable target.
- a connection dropped, or an arm's feedback silent for `feedback_timeout_s`: both arms brake; the
  client reconnects with back-off; after it is back the pipeline restarts from the poses the
  controllers command (the measured ones once the arms settle; see `_restart_from_measured`) and
  waits for a new command (increments sent meanwhile are refused, never replayed).
- on the simulated rig's clock (`set_clock(SimClock)`, `bagit up`'s lockstep) the loop runs one
  cycle per servo tick of the simulator (sim/clock) instead of every period of this host's clock,
  on the feedback of that very step, and says when it is done (`on_tick`): the watchdog, the
  stale-command rule and every motion limit then run on that clock too. The links' time-outs
  (feedback, replies) stay on the wall clock: they guard a real socket.
- e-stop (`estop()` or an `EStop` message): the latch is set first (nothing more is streamed), then
  EmergencyStop(1) goes to both controllers back to back without waiting for either reply. A
  controller that could not be reached gets it as soon as it reconnects. `reset_estop()` releases
  the controllers, clears their alarms, re-enables them and restarts from the measured poses.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from bagit.common import cr5
from bagit.common.clock import Clock, SimClock, WallClock
from bagit.common.dobot import RobotMode, describe_alarm
from bagit.common.errors import BagItError, ProtocolError, SafetyViolation
from bagit.common.lockstep import StepWait
from bagit.common.messages import ArmState, Command, EStop
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.common.so3 import matrix_to_rpy
from bagit.services.arm_driver import machine as m
from bagit.services.arm_driver.client import CommandRejected, ConnectionLost, DobotClient, PendingReply
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import ArmFrames, controller_fault, feedback_state
from bagit.services.arm_driver.gate import Refusal, estop_refusal, stale_refusal
from bagit.services.arm_driver.machine import SETTLE_TIMEOUT_S, DriverState  # noqa: F401 - SETTLE_TIMEOUT_S: where it was
from bagit.services.arm_driver.motion import ArmMotion

_RUNNING_MODES = (int(RobotMode.ENABLE), int(RobotMode.RUNNING))
_MAX_EVENTS = 200
SETTLED_MM_S = 1.0


class ArmDriver:
    """Both arms of the rig (see the module docstring)."""

    def __init__(
        self,
        rig: RigConfig | None = None,
        config: DriverConfig | None = None,
        on_state: Callable[[ArmState], None] | None = None,
        on_event: Callable[[str, str], None] | None = None,
    ):
        self.rig = rig or RigConfig()
        self.cfg = config or DriverConfig()
        self.limits = self.rig.safety
        self.period = float(self.limits.servo_period_s)
        self.servo_t = self.period * self.cfg.servo_t_factor
        self.frames = {a: ArmFrames.from_config(self.rig.arms[a]) for a in ARMS}
        self.clock: Clock = WallClock()
        self._now: Callable[[], float] = time.monotonic  # the motion's clock: monotonic wall, or the rig's
        self.on_tick: Callable[[int, dict[str, int], str | None], None] | None = None  # lockstep: (tick, ServoPs sent per arm, late)
        self._feedback_wait = StepWait()  # lockstep: a feedback packet wakes the wait for a step's
        self._late: str | None = None  # lockstep: what this step's cycle went without
        self.servo_sent = {a: 0 for a in ARMS}
        self.on_state = on_state
        self.on_event = on_event  # (kind, detail) for estop, fault, watchdog, link_lost, ...; must not block
        self.counters: Counter[str] = Counter()
        self.events: deque[tuple[float, str, str]] = deque(maxlen=_MAX_EVENTS)
        # the motion rules (pipeline, watchdog, reach), shared with the in-process run; it counts into ours
        self.motion = ArmMotion(self.rig, self.cfg, on_event=self._event, counters=self.counters)
        self.pipe = self.motion.pipe
        self.env = self.motion.env
        self.clients = {
            a: DobotClient(
                a,
                self.rig.arms[a].host,
                self.rig.arms[a].dashboard_port,
                self.rig.arms[a].feedback_port,
                reply_timeout_s=self.cfg.reply_timeout_s,
                connect_timeout_s=self.cfg.connect_timeout_s,
                reconnect_initial_s=self.cfg.reconnect_initial_s,
                reconnect_max_s=self.cfg.reconnect_max_s,
                on_feedback=self._feedback_callback(a),
            )
            for a in ARMS
        }
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        # the latches, the links, the restart and the replies' tally: a pure machine (machine.py), stepped
        # under the lock by `_dispatch`; an immutable state, so readers without the lock see it whole
        self.state = DriverState()
        self._seen_epoch = {a: 0 for a in ARMS}
        self._last_seq: int | None = None
        self._in_flight: dict[ArmName, deque[PendingReply]] = {a: deque() for a in ARMS}
        self._last_send = -np.inf
        self.violation_counts = self.motion.violation_counts
        self.rejections: Counter[str] = Counter()
        self.last_refusal: Refusal | None = None  # the last command refused, and why
        self._last_cycle = -np.inf  # monotonic time of the servo loop's last cycle (a pause shows as a gap)
        self.cycle_ms: deque[float] = deque(maxlen=1000)  # compute time of each cycle
        self.cycle_starts: deque[float] = deque(maxlen=1000)  # monotonic start of each cycle
        self.send_times: deque[float] = deque(maxlen=1000)  # when each period's motion commands went out

    # -- life cycle ------------------------------------------------------------------------------

    def set_clock(self, clock: Clock, on_tick: Callable[[int, dict[str, int], str | None], None] | None = None) -> None:
        """Run on `clock` (before `start`): a SimClock makes the loop cycle on the simulator's servo ticks."""
        if self.started:
            raise BagItError("set_clock() before start()")
        self.clock, self.on_tick = clock, on_tick
        self._now = clock.now if clock.simulated else time.monotonic

    def start(self) -> ArmDriver:
        """Connect to both controllers, bring them up as on the real rig, and start streaming.

        Raises ProtocolError (unreachable controller, refused command, arm that never reports
        enabled, a tool or user frame other than 0 selected); both arms are disabled again then.
        """
        if self.started:
            return self
        if self.state.estop:
            raise SafetyViolation(f"the e-stop is latched ({self.state.estop_reason}); reset_estop() first")
        try:
            for a in ARMS:
                self.clients[a].connect()
            for a in ARMS:
                self._seen_epoch[a] = self.clients[a].epoch
                if not self.clients[a].wait_feedback(max(self.cfg.feedback_timeout_s * 5, 1.0)):
                    raise ProtocolError(f"{a}: no feedback packet on port {self.clients[a].feedback_port}")
            for a in ARMS:
                self._bring_up(a)
            self._wait_enabled(ARMS)
            for a in ARMS:
                rec, _ = self.clients[a].latest()
                assert rec is not None
                if int(rec["Tool"]) != 0 or int(rec["User"]) != 0:
                    raise ProtocolError(
                        f"{a}: tool frame {int(rec['Tool'])} / user frame {int(rec['User'])} selected; "
                        "the driver commands the flange in the base frame (tool 0, user 0)"
                    )
        except BaseException:
            for a in ARMS:
                if self.clients[a].connected:
                    try:
                        self.clients[a].disable()
                    except ProtocolError:
                        pass
                self.clients[a].close()
            raise
        with self._lock:
            self._last_cycle = self._now()
            self._dispatch(m.Started())
        self._stop.clear()
        for target, name in ((self._loop, "servo-loop"), (self._supervise, "supervisor")):
            t = threading.Thread(target=target, name=f"arm-driver-{name}", daemon=True)
            t.start()
            self._threads.append(t)
        return self

    def _bring_up(self, arm: ArmName) -> None:
        c, conf = self.clients[arm], self.rig.arms[arm]
        c.clear_error()
        x, y, z = conf.mount_offset
        c.enable(conf.payload_kg, (1000.0 * x, 1000.0 * y, 1000.0 * z))
        c.speed_factor(conf.speed_factor)

    def _wait_enabled(self, arms: Sequence[ArmName]) -> None:
        deadline = time.monotonic() + self.cfg.enable_timeout_s
        while True:
            waiting = []
            for a in arms:
                rec, _ = self.clients[a].latest()
                if rec is None or not int(rec["EnableStatus"]) or int(rec["RobotMode"]) not in _RUNNING_MODES:
                    waiting.append(a)
            if not waiting:
                return
            if time.monotonic() > deadline:
                rec = self.clients[waiting[0]].latest()[0]
                mode = int(rec["RobotMode"]) if rec is not None else "unknown"
                raise ProtocolError(f"{waiting[0]}: not enabled {self.cfg.enable_timeout_s:.1f} s after EnableRobot (robot mode {mode})")
            time.sleep(0.01)

    def close(self) -> None:
        """Stop smoothly, hold, disable both arms and disconnect (idempotent)."""
        if not self.started:
            for c in self.clients.values():
                c.close()
            return
        with self._lock:
            self._dispatch(m.Closing())
        deadline = time.monotonic() + self.cfg.stop_timeout_s
        while self.pipe.moving and time.monotonic() < deadline and self._threads[0].is_alive():
            time.sleep(self.period / 3)
        time.sleep(2 * self.period)  # the last ServoP's `t` runs out and its reply comes back
        self._stop.set()
        self._feedback_wait.notify()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads.clear()
        for a in ARMS:
            c = self.clients[a]
            if c.connected and not self.state.estop:
                try:
                    c.disable()
                except ProtocolError as e:
                    self._event("shutdown", f"{a}: DisableRobot failed: {e}")
            c.close()
        with self._lock:
            self._dispatch(m.Closed())

    def __enter__(self) -> ArmDriver:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- input -----------------------------------------------------------------------------------

    def submit(self, cmd: Command) -> bool:
        """Take one controller command; False (and counted with its reason, `last_refusal`) if it was refused.

        `mode='hold'` brakes both arms to rest; a later servo command starts a new stream. A servo
        command whose `stamp` is further than the watchdog's time from this host's clock is refused.
        Which run may command the arms is the node's business (it knows run/state).
        """
        if cmd.mode == "hold":
            with self._lock:
                self.counters["commands"] += 1
            self.hold(cmd.reason or "controller asked to hold")
            return True
        return self.submit_increment(np.asarray(cmd.u), float(cmd.dt), seq=cmd.seq, stamp=cmd.stamp)

    def hold(self, reason: str) -> None:
        """Brake both arms to rest (a hold command, or the node when the run it streamed for ends)."""
        with self._lock:
            self.motion.hold(reason, self._now())

    def refuse(self, refusal: Refusal) -> None:
        """Count a command refused before it reached the driver (the node's run gate) with the driver's own."""
        with self._lock:
            self.counters["commands"] += 1
            self._count_refusal(refusal)

    def _count_refusal(self, refusal: Refusal) -> None:
        self.rejections[refusal.reason] += 1
        self.counters["rejected"] += 1
        self.last_refusal = refusal

    def submit_increment(self, u: np.ndarray, dt: float, seq: int | None = None, stamp: float | None = None) -> bool:
        """Increment `u (12,)` (world, m and rad; left then right) over `dt` seconds, made at `stamp`
        (wall clock; None: now, by an in-process caller)."""
        with self._lock:
            now = self._now()  # under the lock: a submit that waited for it is timed when it applies
            if self.clock.simulated and stamp is not None and 0.0 < stamp - now <= self.limits.watchdog_s:
                # the simulator's time may reach this host after the command made at it (another sender,
                # another route): a lockstep run times the command at its own stamp, never at arrival
                now = stamp
            self.counters["commands"] += 1
            why = m.refusal(self.state)
            if why is not None:
                self._count_refusal(Refusal(why, f"command {seq}: the driver is {why.replace('_', ' ')}"))
                return False
            if stamp is not None:
                stale = stale_refusal(stamp, self.clock.now(), self.limits.watchdog_s)
                if stale is not None:
                    self._count_refusal(Refusal(stale.reason, f"command {seq}: {stale.detail}"))
                    return False
            self._check_stall(now)
            if not self.pipe.moving:
                # A new stream from rest starts at the MEASURED poses, never at the last commanded
                # ones: while the arms held, someone may have jogged them (or a simulator reset its
                # world), and streaming from a stale target would drive them back to it.
                if not self._restart_from_measured():
                    self._count_refusal(Refusal("no_feedback", f"command {seq}: no feedback to start a stream from"))
                    return False
                if self.state.fault is not None:
                    self._count_refusal(Refusal("fault", f"command {seq}: {self.state.fault}"))
                    return False
                self.counters["reseeds"] += 1
            if seq is not None and self._last_seq is not None and seq <= self._last_seq:
                self.counters["out_of_order"] += 1
            self._last_seq = seq if seq is not None else self._last_seq
            found = self.motion.submit(u, dt, now)
            if any(v.kind == "non_finite" for v in found):
                self.rejections["non_finite"] += 1  # ArmMotion counted it as rejected
                self.last_refusal = Refusal("non_finite", f"command {seq}: not 12 finite numbers over 0 < dt <= 10 s")
                return False
            return True

    def handle_estop(self, msg: EStop) -> None:
        """An `EStop` message: engage (from anyone) latches the e-stop; `engage=False` resets it if its
        source is one of ESTOP_RELEASE_SOURCES, else SafetyViolation (counted) and the latch stays."""
        if msg.engage:
            self.estop(f"{msg.source}: {msg.reason or 'e-stop'}")
            return
        refused = estop_refusal(msg)
        if refused is not None:
            with self._lock:
                self.counters["estop_releases_refused"] += 1
            raise SafetyViolation(str(refused))
        self.reset_estop()

    # -- e-stop ----------------------------------------------------------------------------------

    def estop(self, reason: str = "e-stop") -> dict[ArmName, bool]:
        """Latch the e-stop and send EmergencyStop(1) to both controllers at once.

        Returns, per arm, whether its controller confirmed. The latch holds whatever the answer.
        """
        with self._lock:
            self._dispatch(m.EstopEngaged(reason))  # the pipeline halts: the controllers stop the arms; nothing more is streamed
        text = self.clients[ARMS[0]].emergency_stop_text(True)
        pending: dict[ArmName, PendingReply] = {}
        reached = {a: False for a in ARMS}
        for a in ARMS:  # both first, then wait: neither controller waits for the other's reply
            try:
                pending[a] = self.clients[a].send(text)
            except ProtocolError as e:
                self._event("estop", f"{a}: not sent: {e}")
        for a, p in pending.items():
            try:
                self.clients[a].check(self.clients[a].wait(p))
                reached[a] = True
            except ProtocolError as e:
                self._event("estop", f"{a}: not confirmed: {e}")
        with self._lock:
            self._dispatch(m.EstopSent(frozenset(a for a in ARMS if not reached[a])))
        return reached

    def reset_estop(self) -> None:
        """Release the e-stop: EmergencyStop(0), ClearError, EnableRobot, SpeedFactor on both arms.

        Motion resumes only with a new command stream, from the measured poses. Raises
        ProtocolError (and stays latched) if a controller refuses or cannot be reached.
        """
        if not self.state.estop:
            return
        for a in ARMS:
            c = self.clients[a]
            if not c.connected:
                raise ProtocolError(f"{a}: cannot reset the e-stop: not connected ({c.last_error})")
            c.check(c.request(c.emergency_stop_text(False)))
        for a in ARMS:
            self._bring_up(a)
        self._wait_enabled(ARMS)
        with self._lock:
            self._dispatch(m.EstopReleased())

    def clear_fault(self) -> None:
        """Clear a latched fault: ClearError and re-enable the arms that need it, restart from the measured poses."""
        if self.state.estop:
            raise SafetyViolation("the e-stop is latched: reset_estop() first")
        if self.state.fault is None:
            return
        for a in ARMS:
            rec, _ = self.clients[a].latest()
            if rec is None:
                raise ProtocolError(f"{a}: no feedback; cannot clear the fault")
            if int(rec["ErrorStatus"]) or int(rec["RobotMode"]) not in _RUNNING_MODES or not int(rec["EnableStatus"]):
                self._bring_up(a)
        self._wait_enabled(ARMS)
        with self._lock:
            self._dispatch(m.FaultCleared())

    # -- state -----------------------------------------------------------------------------------

    def _feedback_callback(self, arm: ArmName) -> Callable[[np.ndarray, float], None]:
        def on_packet(rec: np.ndarray, t: float) -> None:
            if self.clock.simulated:  # lockstep: the step's states go out from the loop, after its cycle
                self._feedback_wait.notify()
                return
            cb = self.on_state
            if cb is not None:
                cb(self._state_of(arm, rec))

        return on_packet

    def _state_of(self, arm: ArmName, rec: np.ndarray) -> ArmState:
        """An arm's state from a feedback record, with the driver's aim and e-stop laid over."""
        return self._with_aim(feedback_state(arm, rec, self.frames[arm], estopped=self.state.estop, stamp=self._stamp(rec)))

    def _stamp(self, rec: np.ndarray) -> float:
        """When a feedback packet was true, on the rig's clock (a simulated controller stamps its own time)."""
        return float(rec["TimeStamp"]) / 1000.0 if self.clock.simulated else time.time()

    def _with_aim(self, state: ArmState) -> ArmState:
        """`state` with where the driver is taking that mount (`ArmMotion.aim`) and whether its last
        period was slowed: what the controller predicts from and stops asking for. Read without the
        lock, as the node reads the fault: the feedback thread must never wait on a servo cycle, and a
        pose read while a command lands is one packet's worth off."""
        aim = self.motion.aim()
        slowed = bool(self.motion.slowing)
        update: dict[str, Any] = {"slowed": slowed}
        if aim is not None:
            T = aim[state.arm]
            update["target_pose"] = np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])
        return state.model_copy(update=update)

    def states(self) -> dict[ArmName, ArmState]:
        """The latest state of each arm that has reported since (re)connecting."""
        out = {}
        for a in ARMS:
            rec, _ = self.clients[a].latest()
            if rec is not None:
                out[a] = feedback_state(a, rec, self.frames[a], estopped=self.state.estop)
        return out

    @property
    def mode(self) -> str:
        """off | estopped | fault | link_down | restarting | streaming | stopping | holding."""
        with self._lock:
            return m.mode(self.state, self.pipe.mode)

    def status(self) -> dict:
        """Mode, latches, counters (commands, clipped, rejected and why, violations by kind), links."""
        with self._lock:
            cycle = np.array(self.cycle_ms) if self.cycle_ms else np.zeros(1)
            starts = np.array(self.cycle_starts)
            period = np.diff(starts) * 1000.0 if len(starts) > 1 else np.zeros(1)
            sends = np.diff(np.array(self.send_times)) * 1000.0 if len(self.send_times) > 1 else np.zeros(1)
            return {
                "mode": self.mode,
                "estop": {"latched": self.state.estop, "reason": self.state.estop_reason, "unconfirmed": sorted(self.state.estop_unconfirmed)},
                "fault": self.state.fault,
                "links_down": self.state.links,
                "counters": dict(self.counters),
                "rejections": dict(self.rejections),
                "violations": dict(self.violation_counts),
                "last_violations": list(self.motion.last_violations),
                "cycle_ms": {"median": float(np.median(cycle)), "max": float(cycle.max())},
                "period_ms": {"median": float(np.median(period)), "max": float(period.max())},
                "send_interval_ms": {"min": float(sends.min()), "median": float(np.median(sends))},
                "arms": {a: {**self.clients[a].stats(), "feedback_age_s": self.clients[a].feedback_age()} for a in ARMS},
                "events": [f"{t:.3f} {k}: {d}" for t, k, d in list(self.events)[-20:]],
            }

    def _event(self, kind: str, detail: str) -> None:
        self.events.append((time.monotonic(), kind, detail))
        cb = self.on_event
        if cb is not None:
            try:
                cb(kind, detail)
            except Exception as e:  # a subscriber's bug must not stop the arms' loop
                self.events.append((time.monotonic(), "event_callback", repr(e)))

    @property
    def last_violations(self) -> list[str]:
        return self.motion.last_violations

    # -- the machine -----------------------------------------------------------------------------

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

    def _dispatch(self, event: m.Event) -> list[m.Effect]:
        """Step the machine (with the lock held) and carry out its effects in order; the effects
        that block (AskAlarms) are returned for the caller to carry out without the lock."""
        self.state, effects = m.step(self.state, event)
        later: list[m.Effect] = []
        for e in effects:
            if isinstance(e, m.StopPipe):
                self.pipe.stop()
            elif isinstance(e, m.HaltPipe):
                self.pipe.halt()
            elif isinstance(e, m.Restart):
                self._restart_from_measured()
            elif isinstance(e, m.ClearInFlight):
                self._in_flight[e.arm].clear()
            elif isinstance(e, m.ResendEstop):
                try:
                    c = self.clients[e.arm]
                    c.send(c.emergency_stop_text(True))
                    later += self._dispatch(m.EstopResent(e.arm))
                except ProtocolError as err:
                    later += self._dispatch(m.EstopResent(e.arm, str(err)))
            elif isinstance(e, m.Count):
                self.counters[e.name] += 1
            elif isinstance(e, m.Note):
                self._event(e.kind, e.detail)
            else:
                later.append(e)
        return later

    def _set_fault(self, why: str) -> None:
        self._dispatch(m.FaultRaised(why))

    def _restart_from_measured(self) -> bool:
        """Reset the pipeline at rest at the poses the controllers command (QTarget, ToolVectorTarget:
        the measured ones once the arms settle); a start outside the envelope is a fault.

        Not the actual poses: an arm still following its last target (a restart waits at most
        SETTLE_TIMEOUT_S for it to settle) would get a first target back behind it, a jump the
        controller alarms on (joint overspeed) or a jerk the other way."""
        latest = {a: self.clients[a].latest()[0] for a in ARMS}
        recs = {a: r for a, r in latest.items() if r is not None}
        if len(recs) != len(latest):
            self._dispatch(m.Restarted("no_feedback"))
            return False
        found = self.motion.restart(recs)
        if found is None:
            self._dispatch(m.Restarted("non_finite"))
            return False
        self._dispatch(m.Restarted("ok", tuple(str(v) for v in found)))
        return True

    # -- the loop --------------------------------------------------------------------------------

    def _loop(self) -> None:
        if isinstance(self.clock, SimClock):
            self._lockstep_loop(self.clock)
            return
        next_t = time.monotonic()
        offsets: deque[float] = deque([0.0], maxlen=50)  # when in its cycle the commands go out
        while not self._stop.is_set():
            t0 = time.monotonic()
            self.cycle_starts.append(t0)
            try:
                if self._cycle(t0):
                    offsets.append(self._last_send - t0)
            except Exception as e:  # never let the loop die: whatever went wrong becomes a fault
                with self._lock:
                    self._set_fault(f"servo loop: {e if isinstance(e, BagItError) else repr(e)}")
            self.cycle_ms.append((time.monotonic() - t0) * 1000.0)
            if t0 - next_t > 0.2 * self.period:
                self.counters["late_cycles"] += 1
            # Never catch up after a late cycle: two ServoPs closer than a period would make the
            # controller cover a step in less than its `t` (Dobot: no faster than every 30 ms). A late
            # cycle shifts the schedule (the trajectory runs slightly slower, never faster), and the
            # next cycle starts so that its commands go out about a period after the last ones
            # (`_cycle` itself waits out any remainder before sending).
            offset = min(float(np.median(offsets)), 0.2 * self.period)
            next_t = max(next_t + self.period, t0 + 0.5 * self.period, self._last_send + self.period - offset)
            delay = next_t - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)

    def _lockstep_loop(self, clock: SimClock) -> None:
        """One pass per step the simulator announces on sim/clock: on the feedback of that step, a servo
        cycle if it is a servo tick, then both arms' states (`on_state`, after the cycle: what the step's
        frame sees, as `bagit run` reads the arms after its servo period), then `on_tick` for a servo tick.
        States come from here only, never from the feedback thread, so none races a cycle."""
        last_t, last_tick = float("-inf"), -1
        while not self._stop.is_set():
            event = clock.next_event(last_t, self._stop, timeout=1.0)
            if event is None:
                continue
            last_t, n = event
            self._late = None
            self._await_feedback(last_t)
            before = dict(self.servo_sent)
            if n is not None and n > last_tick:
                last_tick = n
                t0 = time.monotonic()
                self.cycle_starts.append(t0)
                try:
                    self._cycle(t0)
                except Exception as e:  # never let the loop die: whatever went wrong becomes a fault
                    with self._lock:
                        self._set_fault(f"servo loop: {e if isinstance(e, BagItError) else repr(e)}")
                self.cycle_ms.append((time.monotonic() - t0) * 1000.0)
            self._publish_states()
            cb = self.on_tick
            if n is not None and cb is not None:
                try:
                    cb(n, {a: self.servo_sent[a] - before[a] for a in ARMS}, self._late)
                except Exception as e:  # noqa: BLE001 - a closing bus must not stop the arms' loop
                    self._event("tick_callback", repr(e))

    def _publish_states(self) -> None:
        """Both arms' states from their newest feedback (lockstep: once per step, after its cycle)."""
        cb = self.on_state
        if cb is None:
            return
        for a in ARMS:
            rec, _ = self.clients[a].latest()
            if rec is not None:
                cb(self._state_of(a, rec))

    def _await_feedback(self, t: float) -> None:
        """Until both arms' feedback shows the step at `t` (a simulated controller stamps it), woken by each
        packet (`StepWait`), at most the lockstep time-out: a link that went quiet is the supervisor's
        business, not this wait's, and a tick cycled without its step's feedback says so (`lockstep_late`)."""
        due_ms = round(t * 1000.0)

        def ready() -> bool:
            recs = [self.clients[a].latest()[0] for a in ARMS]
            return all(r is not None and int(r["TimeStamp"]) >= due_ms for r in recs)

        if self._feedback_wait.wait(ready, self._stop) or self._stop.is_set():
            return
        self.counters["lockstep_late"] += 1
        self._late = "the feedback of its step"
        self._event("lockstep", f"servo tick at {t:.3f}: cycled without the feedback of that step")

    def _cycle(self, t0: float) -> bool:
        """One servo period; True if motion commands went out."""
        self._check_replies(time.monotonic())
        sends: dict[ArmName, str] = {}
        with self._lock:
            now = self._now()  # under the lock: a cycle that waited for it must not act on an old clock
            wall_now = time.monotonic()
            self.counters["cycles"] += 1
            self._check_stall(now)
            self._last_cycle = now
            self._watch(now)
            if self.state.estop:
                return False
            moving = self.pipe.moving
            self._dispatch(m.Cycle(now, moving, not moving and self.state.needs_reset and self._settled()))
            active = [a for a in ARMS if m.commandable(self.state, a) and not self._arm_in_error(a)]
            out = self.motion.cycle(now, active, check_reach=self.cfg.servo_command == "servoj" or self.cfg.check_reach)
            if out.fault is not None:
                self._set_fault(out.fault)
            command, joints = out.poses, out.joints
            if command is None:
                return False
            for a in active:
                sends[a] = self._servo_text(a, command[a], None if joints is None else joints[a], out.halting)
        # On the wall clock: never two ServoPs less than a period apart, whatever the schedule did, and
        # none made before a pause; on the simulator's the ticks are a period apart and the world waits.
        late = 0.0
        if not self.clock.simulated:
            wait = self._last_send + self.period - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            late = time.monotonic() - wall_now
        if late > self.limits.watchdog_s:  # paused between making these poses and sending them: they are stale
            with self._lock:
                self.pipe.halt()
                self.counters["stalls"] += 1
                self._event("stalled", f"this period's poses were {late * 1000:.0f} ms old when they could go out "
                            "(the process was paused or starved): not sent; a new command starts a new stream")
            return False
        self._last_send = time.monotonic()
        self.send_times.append(self._last_send)
        for a, text in sends.items():
            try:
                self._in_flight[a].append(self.clients[a].send(text))
                self.counters["servo_sent"] += 1
                self.servo_sent[a] += 1
            except ProtocolError as e:
                with self._lock:
                    self._link_lost(a, str(e))
        return bool(sends)

    def _servo_text(self, arm: ArmName, T_world_mount: np.ndarray, q: np.ndarray | None, halting: bool = False) -> str:
        """The ServoP for one arm's mount pose, or the ServoJ for its joints `q (6,)` (rad); `halting`:
        a braking pose, sent with the halting servo parameters (`DriverConfig.servo_params`)."""
        cfg = self.cfg
        aheadtime, gain = cfg.servo_params(halting)
        if cfg.servo_command == "servoj" and q is not None:
            return DobotClient.servo_text("ServoJ", np.degrees(q), self.servo_t, aheadtime, gain)
        T_bf = self.frames[arm].flange_in_base(T_world_mount)
        return DobotClient.servo_text("ServoP", cr5.matrix_to_pose6(T_bf), self.servo_t, aheadtime, gain)

    def _check_replies(self, now: float) -> None:
        """Earlier periods' ServoP replies: a refusal is a fault; missing or garbled ones add up to one."""
        # Lockstep: the simulated controller has taken every ServoP of the last tick (the world waited for
        # it), so its reply is on the way: waited for from now, never judged by a wall-clock age a pause
        # of this process (or of the simulator) would inflate.
        lockstep = self.clock.simulated
        for a in ARMS:
            queue = self._in_flight[a]
            while queue and (lockstep or queue[0].done or now - queue[0].sent_at >= self.cfg.reply_timeout_s):
                p = queue.popleft()
                c = self.clients[a]
                try:
                    c.check(c.wait(p, timeout=self.cfg.reply_timeout_s if lockstep and not p.done else 0.0))
                    if not self.state.failed(a):
                        continue  # a good reply with no tally to reset: no need to take the lock
                    event: m.Event = m.ReplyOk(a)
                except CommandRejected as e:
                    event = m.ReplyRejected(str(e))  # refused across the e-stop on the wire: expected, no fault
                except ConnectionLost as e:
                    event = m.LinkLost(a, str(e))
                except ProtocolError as e:
                    event = m.ReplyFailed(a, str(e), self.cfg.max_failed_requests)
                with self._lock:
                    self._dispatch(event)

    def _check_stall(self, now: float) -> None:
        """Drop the trajectory if the servo loop has not run for longer than the watchdog's time (with the
        lock held): the arms stopped at the last target when its ServoP ran out, so braking from the
        trajectory's old velocity would move them again. A new command starts a new stream from the
        measured poses; until one comes nothing moves."""
        gap = now - self._last_cycle
        if self.pipe.moving and gap > self.limits.watchdog_s:
            self.pipe.halt()
            self.counters["stalls"] += 1
            self._event("stalled", f"no servo cycle for {gap * 1000:.0f} ms (the process was paused or starved): "
                        "the arms stopped at their last target and hold; a new command starts a new stream")

    def _settled(self) -> bool:
        """Both controllers report the arm idle and still, so the measured pose is where it will stay."""
        for a in ARMS:
            rec, _ = self.clients[a].latest()
            if rec is None or int(rec["RobotMode"]) != int(RobotMode.ENABLE):
                return False
            if np.linalg.norm(rec["TCPSpeedActual"][:3]) > SETTLED_MM_S:
                return False
        return True

    def _arm_in_error(self, arm: ArmName) -> bool:
        rec, _ = self.clients[arm].latest()
        return rec is None or controller_fault(rec) is not None

    def _watch(self, now: float) -> None:
        """Links, controller errors, the watchdog (called with the lock held)."""
        for a in ARMS:
            c = self.clients[a]
            if not c.connected:
                self._link_lost(a, c.last_error or "disconnected")
                continue
            silent = self._silence(c)
            if silent > self.cfg.feedback_timeout_s:
                c.drop(f"no feedback for {silent * 1000:.0f} ms")
                self._link_lost(a, "feedback lost")
                continue
            if c.epoch != self._seen_epoch[a]:
                if c.latest()[0] is None:
                    continue  # reconnected; wait for its first packet
                self._link_back(a)
            rec, _ = c.latest()
            if rec is None or self.state.estop or self.state.closing:
                continue
            why = controller_fault(rec)
            if why is not None:
                self._dispatch(m.ArmAlarm(a, why))
            elif not int(rec["EnableStatus"]):
                self._set_fault(f"{a}: disabled (robot mode {int(rec['RobotMode'])})")
        self.motion.watchdog(now)

    def _silence(self, c: DobotClient) -> float:
        """How long an arm's feedback has been quiet. On the wall clock, the socket's silence. On the
        simulator's, how far the rig's clock has gone past the newest packet's stamp: a simulator the
        machine starves sends nothing because nothing happens, which is no lost link."""
        if not self.clock.simulated:
            return c.silent_for()
        rec, _ = c.latest()
        if rec is None:
            return c.silent_for()
        return max(0.0, self.clock.now() - self._stamp(rec))

    def _link_lost(self, arm: ArmName, why: str) -> None:
        self._dispatch(m.LinkLost(arm, why))

    def _link_back(self, arm: ArmName) -> None:
        """A reconnected controller: re-assert a latched e-stop, or restart from the measured pose."""
        self._seen_epoch[arm] = self.clients[arm].epoch
        self._dispatch(m.LinkBack(arm))

    def _supervise(self) -> None:
        """Reconnect dropped controllers with back-off, and ask a faulted controller for its alarms,
        off the servo loop (a connect or a request may block)."""
        while not self._stop.wait(0.02):
            for a in ARMS:
                c = self.clients[a]
                if not c.connected and not self.state.closing:
                    c.reconnect_if_due()
            if self.state.fault is None or self.state.fault_alarms_asked:
                continue  # read without the lock, as before the machine: this thread must not contend with the servo loop
            with self._lock:
                later = self._dispatch(m.AlarmsDue())
            if any(isinstance(e, m.AskAlarms) for e in later):
                self._report_alarms()

    def _report_alarms(self) -> None:
        """Add the controllers' latched alarm ids to the fault's text: which limit tripped, not just that one did."""
        found: list[str] = []
        for a in ARMS:
            if not self.clients[a].connected:
                continue
            try:
                ids = sorted({i for group in self.clients[a].error_ids() for i in group})
            except ProtocolError as e:
                found.append(f"{a}: GetErrorID failed ({e})")
                continue
            if ids:
                found.append(f"{a}: " + ", ".join(f"{i} ({describe_alarm(i)})" for i in ids))
        with self._lock:
            self._dispatch(m.AlarmsFound("; ".join(found)))
