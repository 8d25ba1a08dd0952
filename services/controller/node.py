"""The controller on Zenoh: the only module of the controller that imports zenoh.

    node = ControllerNode(session, keys, ControllerServiceConfig())
    node.close()

It follows `run/state`. When `planner/path` for the current run arrives (with `planner/goal`,
whose perimeter is C6's R), it builds the run's controller (`RunState.controller`, default mpc;
params = the scenario's `params:` overlaid with `RunState.params`, the control rate among them;
the arm driver's watchdog from the rig config, `SafetyLimits.watchdog_s`) and servos on the wall clock:
a tick as soon as a new SOI arrives (at most one per 3/4 of a control period), and one a control
period after the last tick while none comes. Each tick takes the newest SOI (`perception/soi`) and both grippers' poses
(`arm/<side>/state` tool_pose: world [x y z roll pitch yaw], the driver's convention), calls the
pure controller, and publishes a `Command` on `controller/cmd` and a `ControllerStatus` on
`controller/status`. A tick without a new SOI (but a fresh one) learns nothing and sends a zero
increment while servoing, a keep-alive: the driver keeps streaming the last targets instead of
its watchdog braking the arms between two slow SOIs (see `session.py`).

It never extrapolates: no SOI, a stale one (older than `soi_max_age_s`: its age when sent, on the
camera host's clock, plus its time since arrival on this one's, so the hosts' clocks need not agree), an implausible one (the guard), or missing or
stale arm states -> a hold command (u = 0) with the reason, every tick while it lasts. A run that
stops, is aborted, fails or is done, a new run, or an e-stop -> one hold, and servoing stops. Any
exception in the controller (e.g. numpy's LinAlgError) -> hold with the reason in the status;
the loop thread never dies.

With `clock="sim"` (a lockstep simulator) there is no timer: the controller ticks once per camera
frame, when the coordinator has answered it on sim/ack (so on the stage that frame led to), on that
frame's SOI (if it made one) and the arms' states of that step, with ages on the simulator's clock;
then it answers the frame on sim/ack with the command it sent. A tick per frame is the control
rate when the camera runs at it, as in `bagit run`. With frames further apart than the keep-alive
pace the simulator also sends keep-alive ticks between them (`ClockTick.keepalive`, by the `Schedule`
`bagit run` steps by; on sim/clock and again on sim/clock/keepalive, the only ticks the controller
follows): while the run is servoed the controller ticks on its last SOI (a keep-alive, or a hold once
that SOI is stale) and answers each as it answers a frame, so a slow camera gives slower motion,
never a watchdog stop, and the same run as `bagit run`'s.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from typing import Any

import numpy as np
import zenoh  # noqa: F401 - the node is where the service meets the bus
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bagit.common.bus import Keys, LatestCache, Publisher, Subscriber
from bagit.common.clock import ClockKind, make_clock
from bagit.common.errors import refuse_moved
from bagit.common.lockstep import StepWait
from bagit.common.messages import ArmState, ClockTick, Command, ControllerStatus, EStop, Goal, Path, RunState, SoiState, StepAck
from bagit.common.names import DEFAULT_CONTROLLER, SERVO_STAGES
from bagit.common.params import MethodParams
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.controller.session import ARM_MAX_AGE_S, SOI_MAX_AGE_S, Outbox, ServoRuns, ServoSession

log = logging.getLogger("bagit.controller")

SERVICE_NAME = "controller"
CLOCK_SKEW_S = 3600.0  # a SOI made longer than this after its frame has stamps on two clocks (a simulator's): not used
SOI_TICK_SHARE = 0.75  # wall clock: a new SOI is ticked on at once, but at least this share of a period after the last one
KEEPALIVE_TICK = "sim-keepalive"  # lockstep: a keep-alive tick from sim/clock, queued with the frames to tick on


# Settings the controller's config once had, each now read from the one place that holds it for
# every service: a config naming one is refused, saying where it is.
MOVED_SETTINGS: dict[str, str] = {
    "controller": "the run's choice (bagit run/up --controller, the dashboard)",
    "control_rate_hz": "the run's parameter control_rate_hz (a scenario's params:, bagit run --params, the dashboard)",
    "params": "the run's parameters (a scenario's params:, bagit run --params, the dashboard)",
    "driver_watchdog_s": "the rig config's safety.watchdog_s (rig_config), which the arm driver enforces",
}


class ControllerServiceConfig(BaseModel):
    """`bagit controller`'s config file (YAML): what only this service sets. The controller, its
    parameters and the control rate are the run's; the arm driver's watchdog is the rig's."""

    model_config = ConfigDict(extra="forbid")

    rig_config: str | None = Field(None, description="rig config YAML: the arm driver's watchdog (safety.watchdog_s), which "
                                   "a command's dt stays under and keep-alives beat (default: built-in rig)")
    soi_max_age_s: float = Field(SOI_MAX_AGE_S, gt=0.0, le=10.0, description="a SOI older than this: hold")
    arm_max_age_s: float = Field(ARM_MAX_AGE_S, gt=0.0, le=10.0, description="an arm state older than this: hold")

    @model_validator(mode="before")
    @classmethod
    def _refuse_moved(cls, data: Any) -> Any:
        return refuse_moved(data, MOVED_SETTINGS, "controller")


class ControllerNode:
    """Servoes the current run (see the module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        cfg: ControllerServiceConfig | None = None,
        clock: ClockKind = "wall",
        rig: RigConfig | None = None,
    ) -> None:
        self.cfg = cfg or ControllerServiceConfig()
        self.lockstep = clock == "sim"
        self.clock = make_clock(clock)  # ages: by stamps at the step (lockstep) or by arrival
        self.keys = keys
        self.rig_watchdog_s = (rig or RigConfig()).safety.watchdog_s
        self._lock = threading.Lock()
        self._run_state: RunState | None = None
        self._paths: dict[str | None, Path] = {}
        self._goals: dict[str | None, Goal] = {}
        self._estop = False
        self._seq = 0
        self.servo = ServoRuns(self._next_seq, self.rig_watchdog_s)
        self.counters: dict[str, int] = {"ticks": 0, "servo": 0, "hold": 0, "keepalive": 0, "errors": 0, "runs": 0}
        self.last_reason: str | None = None
        self.runs_done: list[dict[str, Any]] = []
        self._cmd = Publisher(session, keys.controller_cmd, Command)
        self._status = Publisher(session, keys.controller_status, ControllerStatus, lockstep=self.lockstep)
        self._soi_new = threading.Event()  # wall clock: a new SOI wakes the loop for a tick at once
        self._step_wait = StepWait()  # lockstep: a tick's SOI, run state, path and arm states wake its wait
        self.soi = LatestCache(session, keys.perception_soi, SoiState, self._on_soi)
        self.arms = LatestCache(session, keys.arm_state_any, ArmState, self._step_wait.notify)
        self._subs: list[Subscriber[Any]] = [
            Subscriber(session, keys.run_state, RunState, self._on_run_state),
            Subscriber(session, keys.planner_path, Path, self._on_path),
            Subscriber(session, keys.planner_goal, Goal, self._on_goal),
            Subscriber(session, keys.estop, EStop, self._on_estop),
        ]
        self._stop = threading.Event()
        self._frames: deque[StepAck] = deque()  # lockstep: the coordinator's answers to frames, to tick on
        self._frames_cond = threading.Condition()
        self._ack: Publisher[StepAck] | None = None
        self._sent: int | None = None  # the seq of the last command a tick sent
        self._status_sent: int | None = None  # ... and of its status
        self._held_statuses: list[ControllerStatus] | None = None  # lockstep: a step's statuses, sent when it ends (the last as its answer)
        # The schedule of the ticks (what the loop runs in both is `_tick`, i.e. `ServoRuns`, as in `bagit run`):
        # on the wall clock a timer and each new SOI; in lockstep the simulator's steps, answered on sim/ack.
        loop = self._loop
        if self.lockstep:
            self._ack = Publisher(session, keys.step_ack(SERVICE_NAME), StepAck)
            self._subs.append(Subscriber(session, keys.step_ack("planner"), StepAck, self._on_ack))
            self._subs.append(Subscriber(session, keys.sim_keepalive, ClockTick, self._on_clock))
            loop = self._lockstep_loop
        self._thread = threading.Thread(target=loop, name="controller-loop", daemon=True)
        self._thread.start()

    # -- in ----------------------------------------------------------------------------------------

    @property
    def _run(self) -> ServoSession | None:
        """The session of the run being servoed (or last servoed)."""
        return self.servo.session

    def _on_soi(self, _msg: SoiState) -> None:
        """A new SOI wakes the tick waiting for it: lockstep's step wait, or the wall-clock loop."""
        self._step_wait.notify()
        self._soi_new.set()

    def _on_run_state(self, msg: RunState) -> None:
        with self._lock:
            self._run_state = msg
        self._step_wait.notify()

    def _on_path(self, msg: Path) -> None:
        with self._lock:
            self._paths = {msg.run_id: msg}  # one run at a time: an older run's path is dropped
        self._step_wait.notify()

    def _on_goal(self, msg: Goal) -> None:
        with self._lock:
            self._goals = {msg.run_id: msg}

    def _on_estop(self, msg: EStop) -> None:
        if not msg.may_act():
            log.warning(f"e-stop release from {msg.source!r} ignored: only the dashboard or the CLI may release it")
            return
        with self._lock:
            self._estop = bool(msg.engage)

    def _on_ack(self, ack: StepAck) -> None:
        if ack.service == "planner" and ack.frame is not None and ack.status_seq is None:  # not its answer to our status
            with self._frames_cond:
                self._frames.append(ack)
                self._frames_cond.notify()

    def _on_clock(self, tick: ClockTick) -> None:
        """A keep-alive tick (frames sparser than the keep-alive pace): ticked and answered as a frame is."""
        if tick.keepalive:
            with self._frames_cond:
                self._frames.append(StepAck(service=KEEPALIVE_TICK, run_id=tick.run_id, frame=tick.t, stamp=tick.t))
                self._frames_cond.notify()

    # -- the loop ----------------------------------------------------------------------------------

    def _lockstep_loop(self) -> None:
        """One tick per frame the coordinator answered (see the module doc), then the answer. A frame (or
        keep-alive tick) that comes again is answered again as it was, not ticked twice."""
        answered: tuple[str, float, int | None, int | None, str | None] | None = None  # the last: kind, time, cmd, status, late
        while not self._stop.is_set():
            with self._frames_cond:
                while not self._frames and not self._stop.is_set():
                    self._frames_cond.wait(1.0)
                if self._stop.is_set():
                    return
                while len(self._frames) > 1:  # between runs the world does not wait: only the newest frame matters
                    self._frames.popleft()
                ack = self._frames.popleft()
            assert ack.frame is not None
            late: str | None = None
            if answered is not None and answered[:2] == (ack.service, ack.frame):
                self._sent, self._status_sent, late = answered[2:]
            else:
                self._sent = self._status_sent = None
                self._held_statuses = []
                try:
                    if ack.service == KEEPALIVE_TICK:
                        late = self._keepalive_tick(ack.frame, ack.run_id)
                    else:
                        late = self._await_frame(ack)
                        self._tick(ack.frame)
                except Exception as e:  # noqa: BLE001 - a bug here must hold the arms, never kill the loop
                    self.counters["errors"] += 1
                    self._hold(f"controller node error: {type(e).__name__}: {e}", self._run, ack.frame)
                answered = (ack.service, ack.frame, self._sent, self._status_sent, late)
                statuses, self._held_statuses = self._held_statuses, None
                if statuses:  # the step's last status is its answer (only the coordinator waits for it)
                    *before, last = statuses
                    for st in (*before, last.model_copy(update={"frame": ack.frame, "cmd_seq": self._sent, "late": late})):
                        self._put_status(st)
                    continue
            assert self._ack is not None
            self._ack.put(StepAck(service=SERVICE_NAME, run_id=ack.run_id, frame=ack.frame, cmd_seq=self._sent,
                                  status_seq=self._status_sent, stamp=ack.frame, late=late))

    def _arms_at(self, t: float) -> bool:
        """Both arms have reported the step at `t`."""
        arms = [self.arms.get(self.keys.arm_state(a)) for a in ARMS]
        return all(m is not None and m.stamp >= t - 1e-6 for m in arms)

    def _keepalive_tick(self, t: float, run_id: str | None) -> str | None:
        """A lockstep keep-alive tick at `t`: while run `run_id` is servoed, a tick on the last SOI (a
        keep-alive, or a hold when it has gone stale) with both arms' states of that step, as `bagit run`
        ticks (before the run's first control tick, or after its end, there is nothing to tick).
        Returns what the tick went without after the lockstep time-out (None: nothing)."""
        if not self.servo.servoing(run_id):
            return None
        late = None if self._step_wait.wait(lambda: self._arms_at(t), self._stop) or self._stop.is_set() else "the arms' states"
        if late is not None:
            log.warning(f"lockstep: keep-alive tick {t:.3f} ticked without {late}")
        self._tick(t)
        return late

    def _await_frame(self, ack: StepAck) -> str | None:
        """In a servo stage: until run/state shows that run servoing, the frame's SOI is in and both arms
        report the step (they come on their own keys, in any order; `StepWait` wakes on each). Outside one
        the tick only ends a finished run's servoing: nothing to wait for. Returns what is still missing
        after the lockstep time-out (the tick goes on without it: the step may differ from `bagit run`'s)."""
        if ack.stage not in SERVO_STAGES:
            return None
        t = float(ack.frame or 0.0)

        def missing() -> list[str]:
            with self._lock:
                st = self._run_state
                has_path = ack.run_id in self._paths
            soi = self.soi.get()
            checks = (("run/state", st is not None and st.run_id == ack.run_id and st.stage in SERVO_STAGES and has_path),
                      ("its SOI", ack.soi_seq is None or (soi is not None and soi.seq == ack.soi_seq and abs(soi.source_stamp - t) < 1e-6)),
                      ("the arms' states", self._arms_at(t)))
            return [what for what, ok in checks if not ok]

        if self._step_wait.wait(lambda: not missing(), self._stop) or self._stop.is_set():
            return None
        late = ", ".join(missing())
        self.counters["lockstep_late"] = self.counters.get("lockstep_late", 0) + 1
        log.warning(f"lockstep: frame {t:.3f} ticked without {late}")
        return late

    def _loop(self) -> None:
        """Ticks on the wall clock: at once when a new SOI arrives (its frame waits for no timer), but
        no sooner than SOI_TICK_SHARE of a period after the last tick on a new SOI (a camera faster than
        the control rate does not tick faster than it), and a period after the last tick without one
        (`_period`: keep-alives between SOIs, so the driver's watchdog never sees a gap)."""
        last_soi_tick = -float("inf")
        while not self._stop.is_set():
            period = self._period()
            started = time.monotonic()
            if self._soi_new.is_set():
                last_soi_tick = started
            self._soi_new.clear()
            try:
                self._tick()
            except Exception as e:  # noqa: BLE001 - a bug here must hold the arms, never kill the loop
                self.counters["errors"] += 1
                self._hold(f"controller node error: {type(e).__name__}: {e}", self._run)
            deadline, soonest = started + period, last_soi_tick + SOI_TICK_SHARE * period
            while not self._stop.is_set():
                now = time.monotonic()
                if now >= deadline or (self._soi_new.is_set() and now >= soonest):
                    break
                if self._soi_new.is_set():
                    self._stop.wait(min(deadline, soonest) - now)
                else:
                    self._soi_new.wait(deadline - now)

    def _period(self) -> float:
        run = self._run
        if run is not None:
            return run.tick_s  # the control period, or the keep-alive pace of a slower control rate
        return 1.0 / MethodParams().controller.control_rate_hz  # no run yet: the default rate

    def _tick(self, now: float | None = None) -> None:
        """One control tick at `now` (the rig's clock; None: this host's), through `ServoRuns` as `bagit run` ticks."""
        now = self.clock.now() if now is None else now
        with self._lock:
            state, estop = self._run_state, self._estop
            path = None if state is None else (self._paths.get(state.run_id) or self._paths.get(None))
            goal = None if state is None else (self._goals.get(state.run_id) or self._goals.get(None))
        item = self.soi.get_with_time()
        states, arm_problem = self._states(now)
        soi, age = (None, None) if item is None else (item[0], self.soi_age(*item, now=now))
        for out in self.servo.tick(state, path, goal, estop, soi, age, self.cfg.soi_max_age_s, states, arm_problem, now):
            if out.keepalive:
                self.counters["keepalive"] += 1
                self._put(out.command)  # not a control tick: no status, no count as servo
                continue
            self._send(out)
            run = self.servo.session
            if run is not None and run.finished == "done" and out.status is not None and out.status.done:
                self.runs_done.append({"run_id": run.run_id, "error_to_goal": run.error_to_goal, "ticks": run.ticks})
        self.counters.update(ticks=self.servo.ticks, runs=self.servo.runs)

    def _next_seq(self) -> int:
        self._seq += 1
        return self._seq

    def _states(self, now: float) -> tuple[dict[ArmName, ArmState], str | None]:
        """Both arms' newest states, or why there are none fresh enough (lockstep: by their stamps at `now`)."""
        out: dict[ArmName, ArmState] = {}
        for a in ARMS:
            item = self.arms.get_with_time(self.keys.arm_state(a))
            if item is None:
                return out, f"no state from the {a} arm"
            msg, t = item
            age = self.clock.age(msg.stamp, t, now)
            if age > self.cfg.arm_max_age_s:
                return out, f"the {a} arm's state is stale ({age:.2f} s old)"
            out[a] = msg
        return out, None

    def soi_age(self, soi: SoiState, received: float, now: float) -> float:
        """Seconds since the SOI's camera frame was taken at `now`: on the simulator's clock in lockstep (the
        frame's time); on the wall clock its age when perception sent it (its stamp less its frame's, both
        on the camera host's clock) plus its time since it arrived here (this host's monotonic clock). So the
        camera host's clock may be off this one's (no NTP, a drift): only the network's transit, a LAN's
        fraction of a millisecond, goes uncounted. A SOI without a usable stamp: its time since arrival."""
        since_arrival = self.clock.age(soi.source_stamp, received, now)
        if self.clock.simulated:
            return since_arrival
        at_send = soi.stamp - soi.source_stamp
        return since_arrival + at_send if 0.0 <= at_send < CLOCK_SKEW_S else since_arrival

    def _send(self, out: Outbox) -> None:
        """Publish what the session asks for (command, status) and log its line."""
        if out.command is not None:
            self._put(out.command)
            self.counters["servo" if out.command.mode == "servo" else "hold"] += 1
            self.last_reason = out.command.reason
        if out.status is not None:
            self._publish_status_msg(out.status)
        if out.report:
            log.info("%s", out.report)

    # -- out ---------------------------------------------------------------------------------------

    def _put(self, cmd: Command | None) -> None:
        if cmd is not None:
            self._cmd.put(cmd)
            self._sent = cmd.seq

    def _hold(self, reason: str, run: ServoSession | None, now: float | None = None) -> None:
        """A hold command (u = 0) with the reason, outside any run's session (a node error)."""
        now = time.time() if now is None else now
        if run is not None:
            self._send(run.hold(reason, now))
            return
        self._put(Command(u=np.zeros(12), dt=1 / 30, seq=self._next_seq(), mode="hold", reason=reason, stamp=now))
        self.counters["hold"] += 1
        if reason != self.last_reason:
            log.warning("hold: %s", reason)
        self.last_reason = reason
        self._publish_status(None, controller=DEFAULT_CONTROLLER, mode="hold", reason=reason)


    def _publish_status(self, run_id: str | None, **kw: Any) -> None:
        self._publish_status_msg(ControllerStatus(run_id=run_id, seq=self._seq, **kw))

    def _publish_status_msg(self, st: ControllerStatus) -> None:
        self._status_sent = st.seq
        if self._held_statuses is not None:  # lockstep: sent when the step is done, the last one as its answer
            self._held_statuses.append(st)
            return
        self._put_status(st)

    def _put_status(self, st: ControllerStatus) -> None:
        try:
            self._status.put(st)
        except Exception as e:  # noqa: BLE001
            log.warning(f"cannot publish the status: {type(e).__name__}: {e}")

    def status(self) -> dict[str, Any]:
        return {"counters": dict(self.counters), "last_reason": self.last_reason, "runs_done": list(self.runs_done)}

    def close(self) -> dict[str, Any]:
        """Stop the loop (holding the arms if a run was being servoed) and stop listening."""
        self._stop.set()
        self._step_wait.notify()
        with self._frames_cond:  # the lockstep loop waits here for the next frame: woken, not timed out
            self._frames_cond.notify_all()
        self._thread.join(timeout=5.0)
        for out in self.servo.end("controller stopping", time.time()):
            self._send(out)
        for s in self._subs:
            s.close()
        self.soi.close()
        self.arms.close()
        self._cmd.close()
        self._status.close()
        if self._ack is not None:
            self._ack.close()
        return self.status()
