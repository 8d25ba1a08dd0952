"""The planner service on Zenoh: the run coordinator's node (the only planner module importing zenoh).

It answers run/control, takes g0 from perception/soi and the object from perception/object, plans in a background thread (so a long
search never holds up run/control or run/state), publishes planner/goal and planner/path, follows
controller/status, the e-stop (which aborts the run and refuses starts until released) and the
services' liveliness, and publishes run/state on every change and at `publish_hz`. All coordinator calls are serialised by
one lock; publishing happens outside it.

With `clock="sim"` (a lockstep simulator) the coordinator's time is the simulator's: it ticks on each
sim/clock message (limits, the marker wait), and answers each frame on sim/ack once perception has
answered it (with the SOI itself, or on sim/ack when it made none) and the SOI has been handled, with
the stage that follows. A frame that starts
a plan is answered when the plan is in, so planning takes no simulated time, as in `bagit run`.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from functools import partial
from typing import Any

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.bus import (
    Keys,
    LivelinessWatcher,
    Publisher,
    Subscriber,
    declare_alive,
    serve_run_control,
)
from bagit.common.clock import ClockKind, SimClock, make_clock
from bagit.common.lockstep import LOCKSTEP_TIMEOUT_S
from bagit.common.messages import (
    ClockTick,
    ControllerStatus,
    EStop,
    Goal,
    ObjectDetection,
    Path,
    RunControl,
    RunControlReply,
    RunState,
    SoiState,
    StepAck,
)
from bagit.common.names import NO_SIM_CLOCK_YET, SERVO_STAGES
from bagit.services.planner.coordinator import Coordinator, CoordinatorConfig, Effect, PlanJob, compute_plan

log = logging.getLogger("bagit.planner")

SERVICE_NAME = "planner"
STAMP_TOL_S = 1e-6  # lockstep: two stamps of the same step
MAX_HELD_SOIS = 64  # lockstep: SOIs held for their frame at most (strays of frames never answered are dropped)


class PlannerServiceConfig(BaseModel):
    """`bagit planner --config FILE`: the coordinator's rules, the state rate and the bus section."""

    model_config = ConfigDict(extra="forbid")

    coordinator: CoordinatorConfig = CoordinatorConfig()
    publish_hz: float = Field(2.0, gt=0, le=50, description="run/state republished this often")
    bus: dict[str, Any] = Field(default_factory=dict, description="BusConfig fields (the command-line flags override them)")


def _carried(own: str | None, theirs: str | None, whose: str) -> str | None:
    """What this answer went without, with what the answer it stands for went without (`theirs`, from `whose`)."""
    return "; ".join(filter(None, (own, f"{theirs} ({whose}'s)" if theirs else None))) or None


class PlannerNode:
    """The coordinator wired to the bus (see the module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        config: PlannerServiceConfig | None = None,
        on_state: Callable[[RunState], None] | None = None,
        clock: ClockKind = "wall",
    ) -> None:
        self.cfg = config or PlannerServiceConfig()
        self.keys = keys
        self.lockstep = clock == "sim"
        self._clock = make_clock(clock)  # fed from sim/clock below when simulated
        self.clock: Callable[[], float] = self._clock.now
        self._planning = 0  # plan threads running
        self._frames: list[tuple[StepAck, float]] = []  # lockstep: perception's answers (and when they came) not yet answered
        self._sois: dict[float, SoiState] = {}  # lockstep: SOIs by frame stamp, held until their frame is taken in order
        self._deferred_tick: float | None = None  # lockstep: a step's coordinator tick waiting for its frame to be handled
        self._taken: tuple[float, str | None] | None = None  # lockstep: the frame handed to the coordinator, not yet answered (and
        # what it went without)
        self._statuses: list[StepAck] = []  # lockstep: the controller's answers whose status is not handled yet
        self._held_statuses: dict[int, ControllerStatus] = {}  # lockstep: statuses by seq, held for the controller's answer
        self._object_handled = float("-inf")  # lockstep: the newest stamp of an ObjectDetection handled
        self.on_state = on_state
        self.runs: dict[str, str] = {}  # run id -> its last stage: what `bagit planner` reports when it stops
        self.coord = Coordinator(self.cfg.coordinator, now=self.clock())
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._state_pub = Publisher(session, keys.run_state, RunState, lockstep=self.lockstep)
        self._goal_pub = Publisher(session, keys.planner_goal, Goal)
        self._path_pub = Publisher(session, keys.planner_path, Path)
        self._pub_lock = threading.RLock()  # taken before _lock, never after it
        self._closed = False
        self._last_stage: tuple[str | None, str] | None = None
        self._watcher = LivelinessWatcher(session, keys, self._on_alive)
        self._subs: list[Subscriber[Any]] = [
            Subscriber(session, keys.perception_soi, SoiState, self._on_soi),
            Subscriber(session, keys.perception_object, ObjectDetection, self._on_object),
            Subscriber(session, keys.controller_status, ControllerStatus, self._on_status),
            Subscriber(session, keys.estop, EStop, self._on_estop),
        ]
        self._ack_pub: Publisher[StepAck] | None = None
        self._status_ack_pub: Publisher[StepAck] | None = None
        if self.lockstep:  # the lockstep protocol: the simulator's steps in, this node's answers out
            self._ack_pub = Publisher(session, keys.step_ack(SERVICE_NAME), StepAck)  # to frames: the controller's and simulator's
            self._status_ack_pub = Publisher(session, keys.status_ack(SERVICE_NAME), StepAck)  # to statuses: the simulator's
            self._subs += [Subscriber(session, keys.sim_clock, ClockTick, self._on_clock),
                           *(Subscriber(session, keys.step_ack(s), StepAck, self._on_ack) for s in ("perception", "controller"))]
        self._server = serve_run_control(session, keys, self._on_control)
        self._token = declare_alive(session, keys, SERVICE_NAME)
        self._ticker = threading.Thread(target=self._tick_loop, name="planner-tick", daemon=True)
        self._ticker.start()
        self._publish_if_changed()

    # -- events --------------------------------------------------------------------------------

    def _on_control(self, req: RunControl) -> RunControlReply:
        if req.action == "start" and isinstance(self._clock, SimClock) and not self._clock.heard:
            # its start would be stamped 0 and its first tick (2**30 s on) would time it out at once
            log.info("run/control start -> refused (no sim/clock yet)")
            return RunControlReply(accepted=False, reason=f"{NO_SIM_CLOCK_YET}: is `bagit sim` up?")
        with self._pub_lock:  # as in _apply
            with self._lock:
                rep, effects = self.coord.handle(req, self.clock())
            self._after(effects)
        log.info("run/control %s -> %s%s", req.action, "accepted" if rep.accepted else "refused",
                 f" ({rep.reason})" if rep.reason else "")
        return rep

    def _on_soi(self, soi: SoiState) -> None:
        if not self.lockstep:
            self._apply(lambda: self.coord.on_soi(soi, self.clock()))
            return
        with self._pub_lock:  # lockstep: handed over in `_answer_frames`, after its frame's object detection
            self._sois[soi.source_stamp] = soi
            while len(self._sois) > MAX_HELD_SOIS:  # (answered frames take theirs; this only bounds strays)
                self._sois.pop(min(self._sois))
            self._frames.append((soi.answer(), time.monotonic()))  # the SOI is perception's answer to its frame too
            self._answer_frames()

    # -- lockstep ------------------------------------------------------------------------------

    def _on_clock(self, tick: ClockTick) -> None:
        """The simulator's time: the coordinator's limits run on it. At a step with a frame or a keep-alive
        tick, `bagit run` ticks the coordinator after that frame and its control tick are handled: so does
        this node (`_tick_after`); a tick still deferred when a later step comes is done first."""
        with self._pub_lock:
            self._flush_tick(before=tick.t)
            if isinstance(self._clock, SimClock):  # subscribed only in lockstep
                self._clock.advance(tick.t, tick.servo_tick)
            if tick.frame or tick.keepalive:
                self._deferred_tick = tick.t
            else:
                self._apply(lambda: self.coord.tick(tick.t))

    def _advance(self, t: float) -> None:
        """Lockstep: the coordinator's clock at least at step `t`, whose messages are being handled."""
        if isinstance(self._clock, SimClock):
            self._clock.advance(t)

    def _flush_tick(self, before: float | None = None, at: float | None = None) -> None:
        """The deferred coordinator tick, if any (and earlier than `before`, or at `at`). With _pub_lock held."""
        t = self._deferred_tick
        if t is None or (before is not None and t >= before) or (at is not None and abs(t - at) > STAMP_TOL_S):
            return
        self._deferred_tick = None
        self._apply(lambda: self.coord.tick(t))

    def _tick_after(self, t: float, stage: str | None) -> None:
        """Frame or keep-alive `t` handled as far as this node waits: outside a servo stage nothing more comes
        for it (no control tick), so the coordinator ticks now. With _pub_lock held."""
        if stage not in SERVO_STAGES:
            self._flush_tick(at=t)

    def _on_ack(self, ack: StepAck) -> None:
        if ack.frame is None:
            return
        if ack.service == "controller" and ack.status_seq is not None:
            with self._pub_lock:
                self._statuses.append(ack)
                self._answer_statuses()
            return
        if ack.service == "controller":  # its tick sent no status: the frame is handled, the coordinator ticks
            with self._pub_lock:
                self._flush_tick(at=ack.frame)
            return
        if ack.service != "perception":
            return
        with self._pub_lock:
            self._frames.append((ack, time.monotonic()))
            self._answer_frames()

    def _answer_statuses(self) -> None:
        """The controller's ticks in order: once a tick's statuses are in (its answer names the last), each is
        handed to the coordinator at the tick's time, then the step's coordinator tick, then the answer with
        the stage after them (with _pub_lock held)."""
        while self._statuses and (self._statuses[0].status_seq or 0) in self._held_statuses:
            ack = self._statuses.pop(0)
            t, last = float(ack.frame or 0.0), ack.status_seq or 0
            self._advance(t)
            for seq in sorted(k for k in self._held_statuses if k <= last):
                st_msg = self._held_statuses.pop(seq)
                self._apply(partial(self.coord.on_status, st_msg, t))
            self._flush_tick(at=ack.frame)  # the step's coordinator tick, after its control tick (as `bagit run`)
            with self._lock:
                st = self.coord.state
            if self._closed or self._status_ack_pub is None:  # (only lockstep's acks come to be answered)
                return
            late = _carried(None, ack.late, "the controller")  # the simulator hears the controller's answer here
            self._status_ack_pub.put(StepAck(service=SERVICE_NAME, run_id=st.run_id, frame=ack.frame, status_seq=ack.status_seq,
                                             cmd_seq=ack.cmd_seq, late=late, stage=st.stage, stamp=self.clock()))

    def _answer_frames(self) -> None:
        """Take perception's frames in order, as `bagit run` does within one: the frame's object detection
        (if it made one) handled first, then its SOI handed to the coordinator, and the frame answered once
        that is done (a plan it started included). Both come on their own keys, in any order, before or
        after perception's answer; what has not come after the lockstep time-out is gone without (the
        answer says so). With _pub_lock held."""
        while self._frames and not self._planning:
            ack, came = self._frames[0]
            t = float(ack.frame or 0.0)
            if self._taken is None or self._taken[0] != t:
                missing = ("its object detection" if ack.object_stamp is not None and ack.object_stamp > self._object_handled else
                           "its SOI" if ack.soi_seq is not None and t not in self._sois else None)
                if missing is not None:
                    if time.monotonic() - came < LOCKSTEP_TIMEOUT_S:
                        return
                    log.warning("lockstep: frame %.3f taken without %s after %g s", t, missing, LOCKSTEP_TIMEOUT_S)
                soi = self._sois.pop(t, None)
                self._taken = (t, missing)
                self._advance(t)  # the frame's time, whichever of sim/clock and the SOI came first
                if soi is not None:
                    self._apply(partial(self.coord.on_soi, soi, t))
                    if self._planning:
                        return  # answered when the plan is in (`_plan`)
            missing = self._taken[1]
            missing = _carried(missing, ack.late, "perception")  # the simulator hears perception's answer here
            self._frames.pop(0)
            self._taken = None
            with self._lock:
                stage = self.coord.state.stage
            self._tick_after(t, stage)
            with self._lock:
                st = self.coord.state
            if self._closed or self._ack_pub is None:  # (only lockstep's acks come to be answered)
                return
            self._ack_pub.put(StepAck(service=SERVICE_NAME, run_id=st.run_id, frame=ack.frame, soi_seq=ack.soi_seq, stage=st.stage,
                                      stamp=self.clock(), late=missing))

    def _on_object(self, det: ObjectDetection) -> None:
        # lockstep: at its frame's time, as `bagit run` hands it over (sim/clock may come after it)
        now = self._clock.step_time(det.source_stamp)
        self._apply(lambda: self.coord.on_object(det, now))
        with self._pub_lock:  # a frame waiting for its detection goes on (none wait on the wall clock)
            self._object_handled = max(self._object_handled, det.source_stamp)
            self._answer_frames()

    def _on_status(self, st: ControllerStatus) -> None:
        if not self.lockstep:
            self._apply(lambda: self.coord.on_status(st, self.clock()))
            return
        with self._pub_lock:  # lockstep: handed over with the controller's answer, at its frame's time (`_answer_statuses`)
            self._held_statuses[st.seq] = st
            while len(self._held_statuses) > MAX_HELD_SOIS:
                self._held_statuses.pop(min(self._held_statuses))
            if st.frame is not None:  # the tick's last status: the controller's answer to its step too
                self._statuses.append(st.answer())
            self._answer_statuses()

    def _on_estop(self, msg: EStop) -> None:
        log.warning("e-stop %s by %s%s", "engaged" if msg.engage else "released", msg.source, f": {msg.reason}" if msg.reason else "")
        self._apply(lambda: self.coord.on_estop(msg.engage, msg.source, msg.reason, self.clock()))

    def _on_alive(self, service: str, alive: bool) -> None:
        log.info("service %s %s", service, "up" if alive else "gone")
        self._apply(lambda: self.coord.on_liveliness(service, alive, self.clock()))

    def _tick_loop(self) -> None:
        period = 1.0 / self.cfg.publish_hz
        while not self._stop.wait(min(period, 0.1)):
            if not self.lockstep:  # lockstep: the coordinator ticks on sim/clock
                self._apply(lambda: self.coord.tick(self.clock()))
            else:
                with self._pub_lock:
                    self._answer_frames()  # one whose SOI or detection never came is answered after LOCKSTEP_WAIT_S
            now = time.monotonic()
            if now >= getattr(self, "_next_periodic", 0.0):
                self._next_periodic = now + period
                with self._pub_lock:
                    with self._lock:
                        state = self.coord.tick_state(self.clock())
                    self._publish(state)

    # -- effects -------------------------------------------------------------------------------

    def _apply(self, change: Callable[[], list[Effect] | None]) -> None:
        """Change the coordinator and publish what follows as one step: no run/state (the periodic one
        included) that says a path exists goes out before the path itself."""
        with self._pub_lock:
            with self._lock:
                effects = change()
            self._after(effects or [])

    def _after(self, effects: list[Effect]) -> None:
        """Start the plan and publish goal, path and run/state; called with _pub_lock held."""
        if self._closed:  # a callback late for close(): its publishers are gone
            return
        for e in effects:
            if e.kind == "plan" and e.job is not None:
                self._planning += 1
                threading.Thread(target=self._plan, args=(e.job,), name=f"plan-{e.job.run_id}", daemon=True).start()
            elif e.kind == "publish_goal" and isinstance(e.message, Goal):
                self._goal_pub.put(e.message)
            elif e.kind == "publish_path" and isinstance(e.message, Path):
                self._path_pub.put(e.message)
        self._publish_if_changed()

    def _plan(self, job: PlanJob) -> None:
        def on_goal(goal: Goal) -> None:
            self._apply(lambda: self.coord.on_goal(goal, self.clock()))

        log.info("run %s: planning with %s from g0", job.run_id, job.planner)
        try:
            out = compute_plan(job, on_goal=on_goal)
        except Exception as e:  # noqa: BLE001 - a bug in planning must fail the run, not kill the node
            log.exception("planning crashed")
            from bagit.services.planner.coordinator import PlanOutcome

            out = PlanOutcome(job.run_id, failed_stage="planning", reason=f"planning: internal error: {type(e).__name__}: {e}")
        self._apply(lambda: self.coord.on_plan(out, self.clock()))
        with self._pub_lock:
            self._planning -= 1
            self._answer_frames()  # lockstep: the frame that started the plan is answered now (none wait on the wall clock)

    def _publish_if_changed(self) -> None:
        with self._lock:
            if not self.coord.changed:
                return
            self.coord.changed = False
            state = self.coord.state
        self._publish(state)

    def _publish(self, state: RunState) -> None:
        with self._pub_lock:
            if self._closed:
                return
            try:
                self._state_pub.put(state)
            except Exception:  # noqa: BLE001 - a closing session must not raise in a thread
                log.exception("could not publish run/state")
                return
        key = (state.run_id, state.stage)
        if key != self._last_stage:
            self._last_stage = key
            log.info("run %s: %s%s", state.run_id or "-", state.stage, f" ({state.reason})" if state.reason else "")
        if state.run_id:
            self.runs[state.run_id] = state.stage
        if self.on_state is not None:
            self.on_state(state)

    @property
    def state(self) -> RunState:
        with self._lock:
            return self.coord.state

    def close(self) -> dict[str, Any]:
        """Stop coordinating; the runs coordinated (id -> last stage) and the last run state."""
        last = self.state
        self._stop.set()
        self._ticker.join(timeout=2.0)
        self._server.close()
        for sub in self._subs:
            sub.close()
        self._watcher.close()
        with self._pub_lock:  # never undeclare a publisher in the middle of a put
            self._closed = True
            for p in (self._state_pub, self._goal_pub, self._path_pub, self._ack_pub, self._status_ack_pub):
                if p is not None:
                    p.close()
        try:
            self._token.undeclare()
        except zenoh.ZError:
            pass
        return {"runs": dict(self.runs), "last_state": last.model_dump(mode="json", exclude={"scenario_doc"})}

    def __enter__(self) -> PlannerNode:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
