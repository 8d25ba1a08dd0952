"""The planner service on Zenoh: the run coordinator's node (the only planner module importing zenoh).

It answers run/control, takes g0 from perception/soi and the object from perception/object, plans in a background thread (so a long
search never holds up run/control or run/state), publishes planner/goal and planner/path, follows
controller/status, the e-stop (which aborts the run and refuses starts until released) and the
services' liveliness, and publishes run/state on every change and at `publish_hz`. All coordinator calls are serialised by one lock; publishing happens outside it.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Callable

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
from bagit.common.messages import ControllerStatus, EStop, Goal, ObjectDetection, Path, RunControl, RunControlReply, RunState, SoiState
from bagit.services.planner.coordinator import Coordinator, CoordinatorConfig, Effect, PlanJob, compute_plan

log = logging.getLogger("bagit.planner")

SERVICE_NAME = "planner"


class PlannerServiceConfig(BaseModel):
    """`bagit planner --config FILE`: the coordinator's rules, the state rate and the bus section."""

    model_config = ConfigDict(extra="forbid")

    coordinator: CoordinatorConfig = CoordinatorConfig()
    publish_hz: float = Field(2.0, gt=0, le=50, description="run/state republished this often")
    bus: dict[str, Any] = Field(default_factory=dict, description="BusConfig fields (the command-line flags override them)")


class PlannerNode:
    """The coordinator wired to the bus (see the module docstring)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        config: PlannerServiceConfig | None = None,
        on_state: Callable[[RunState], None] | None = None,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.cfg = config or PlannerServiceConfig()
        self.keys = keys
        self.clock = clock
        self.on_state = on_state
        self.coord = Coordinator(self.cfg.coordinator, now=clock())
        self._lock = threading.RLock()
        self._stop = threading.Event()
        self._state_pub = Publisher(session, keys.run_state, RunState)
        self._goal_pub = Publisher(session, keys.planner_goal, Goal)
        self._path_pub = Publisher(session, keys.planner_path, Path)
        self._pub_lock = threading.RLock()  # taken before _lock, never after it
        self._closed = False
        self._last_stage: tuple[str | None, str] | None = None
        self._watcher = LivelinessWatcher(session, keys, self._on_alive)
        self._subs = [
            Subscriber(session, keys.perception_soi, SoiState, self._on_soi),
            Subscriber(session, keys.perception_object, ObjectDetection, self._on_object),
            Subscriber(session, keys.controller_status, ControllerStatus, self._on_status),
            Subscriber(session, keys.estop, EStop, self._on_estop),
        ]
        self._server = serve_run_control(session, keys, self._on_control)
        self._token = declare_alive(session, keys, SERVICE_NAME)
        self._ticker = threading.Thread(target=self._tick_loop, name="planner-tick", daemon=True)
        self._ticker.start()
        self._publish_if_changed()

    # -- events --------------------------------------------------------------------------------

    def _on_control(self, req: RunControl) -> RunControlReply:
        with self._pub_lock:  # as in _apply
            with self._lock:
                rep, effects = self.coord.handle(req, self.clock())
            self._after(effects)
        log.info("run/control %s -> %s%s", req.action, "accepted" if rep.accepted else "refused",
                 f" ({rep.reason})" if rep.reason else "")
        return rep

    def _on_soi(self, soi: SoiState) -> None:
        self._apply(lambda: self.coord.on_soi(soi, self.clock()))

    def _on_object(self, det: ObjectDetection) -> None:
        self._apply(lambda: self.coord.on_object(det, self.clock()))

    def _on_status(self, st: ControllerStatus) -> None:
        self._apply(lambda: self.coord.on_status(st, self.clock()))

    def _on_estop(self, msg: EStop) -> None:
        log.warning("e-stop %s by %s%s", "engaged" if msg.engage else "released", msg.source, f": {msg.reason}" if msg.reason else "")
        self._apply(lambda: self.coord.on_estop(msg.engage, msg.source, msg.reason, self.clock()))

    def _on_alive(self, service: str, alive: bool) -> None:
        log.info("service %s %s", service, "up" if alive else "gone")
        self._apply(lambda: self.coord.on_liveliness(service, alive, self.clock()))

    def _tick_loop(self) -> None:
        period = 1.0 / self.cfg.publish_hz
        while not self._stop.wait(min(period, 0.1)):
            self._apply(lambda: self.coord.tick(self.clock()))
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
        if self.on_state is not None:
            self.on_state(state)

    @property
    def state(self) -> RunState:
        with self._lock:
            return self.coord.state

    def close(self) -> None:
        self._stop.set()
        self._ticker.join(timeout=2.0)
        for x in (self._server, *self._subs, self._watcher):
            x.close()
        with self._pub_lock:  # never undeclare a publisher in the middle of a put
            self._closed = True
            for p in (self._state_pub, self._goal_pub, self._path_pub):
                p.close()
        try:
            self._token.undeclare()
        except zenoh.ZError:
            pass

    def __enter__(self) -> "PlannerNode":
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
