"""The run coordinator: the rig's run state machine, with no transport in it.

    idle -> perceiving -> goal -> planning -> pre-bagging -> bagging -> done | failed | aborted

Events go in (`start`/`stop`/`reset` requests, a new SOI, a planning outcome, controller status,
a service appearing or disappearing, an e-stop engaged or released, a clock `tick`), and the coordinator answers with its
`state` (a RunState) and a list of `Effect`s for the node to carry out (plan in the background,
publish the goal and the path). Every method takes `now` (wall-clock seconds, the clock the
messages are stamped with), so tests drive it with a fake clock and the node with time.time().

Which object (as in the paper, its ArUco marker says): the plan job's V and object height come from
the freshest marker detection of the run (perception/object, from a frame at least `settle_s`
after the start) when it names the run's object (the scenario object's marker id; any object
when the scenario's object has no marker). A g0 that is ready before any detection waits up to
`marker_wait_s` for one (when perception has published any detection at all); then, or with `object_source: scenario`, V is the scenario's, and the
run's result says so (`object_from`, `object_reason`) with the marker's V error to the scenario's.

Why pure: the rules (one run at a time, which SOI counts as g0, when a silent controller fails a
run) are the part that must be right; the Zenoh node around it is thin and only wires them up.
"""

from __future__ import annotations

import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.errors import BadScenario, BagItError
from bagit.common.messages import ControllerStatus, EStop, Goal, ObjectDetection, Path, RunControl, RunControlReply, RunState, SoiState
from bagit.common.names import (
    ACTIVE_STAGES,
    CONTROLLER_NAMES,
    DEFAULT_CONTROLLER,
    DEFAULT_PLANNER,
    PERCEIVE_STAGES,
    PLAN_WALL_GUARD_S,
    PLANNER_NAMES,
    SERVO_STAGES,
)
from bagit.common.params import merge_params
from bagit.common.results import RunResult, axis_error_cm, points_list
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario


class CoordinatorConfig(BaseModel):
    """Timing rules of the coordinator (the `coordinator:` section of the planner's config)."""

    model_config = ConfigDict(extra="forbid")

    settle_s: float = Field(0.5, ge=0.0, le=30.0, description="g0 only from an SOI whose frame is this much newer than the start")
    perceive_timeout_s: float = Field(30.0, gt=0, le=600, description="no fresh SOI by then: the run fails")
    plan_time_budget_s: float = Field(PLAN_WALL_GUARD_S, gt=0, le=600,
                                      description="the planner's wall-clock guard (its iterations bound the search: names.PLAN_WALL_GUARD_S)")
    status_timeout_s: float = Field(3.0, gt=0, le=60, description="controller status silent this long during servoing: failed")
    first_status_timeout_s: float = Field(15.0, gt=0, le=120, description="no controller status this long after the path: failed")
    run_time_limit_s: float = Field(180.0, gt=0, le=3600, description="servoing (pre-bagging + bagging) longer than this: failed")
    required_services: list[str] = Field(
        default_factory=lambda: ["controller", "arm-driver"],
        description="a run fails at once when one of these disappears while it servos",
    )
    perception_service: str = "perception"
    perception_grace_s: float = Field(5.0, ge=0, le=120, description="perception may be gone this long before the run fails")
    # The controller holds on a stale SOI, so a rim perception no longer finds stays lost (nothing
    # moves the bag back into view): the run fails with that reason rather than hold to its time limit.
    soi_lost_s: float = Field(5.0, gt=0, le=600, description="no SOI this long while servoing: the run fails (perception lost the rim)")
    controllers: list[str] = Field(default_factory=lambda: list(CONTROLLER_NAMES))
    default_controller: str = DEFAULT_CONTROLLER
    default_planner: str = DEFAULT_PLANNER
    object_source: Literal["marker", "scenario"] = Field(
        "marker", description="V and height from the object's marker (perception/object) when detected, else the scenario's; or always the scenario's")
    marker_wait_s: float = Field(3.0, ge=0.0, le=60.0, description="a g0 ready before any marker detection waits this long for one")


@dataclass
class PlanJob:
    """What the node hands to `compute_plan` in the background for run `run_id`."""

    run_id: str
    scenario: Scenario
    g0: np.ndarray  # (n_x, 3)
    planner: str
    seed: int
    time_budget_s: float
    rig: RigConfig | None = None  # whose arms must reach the goal (None: the default rig, RigConfig())


@dataclass
class PlanOutcome:
    """`compute_plan`'s answer: goal and path messages, or the stage and reason it failed at."""

    run_id: str
    goal: Goal | None = None
    path: Path | None = None
    failed_stage: Literal["goal", "planning"] | None = None
    reason: str | None = None
    time_s: float = 0.0


@dataclass
class Effect:
    """Something the node must do: `plan` (run compute_plan(job) in the background), `publish_goal`, `publish_path`."""

    kind: Literal["plan", "publish_goal", "publish_path"]
    job: PlanJob | None = None
    message: Goal | Path | None = None


def compute_plan(job: PlanJob, on_goal: Callable[[Goal], None] | None = None) -> PlanOutcome:
    """Goal (bagging ellipse, g†, g*) and SOI path from g0: the planner's real algorithms.

    `on_goal(goal)` is called as soon as the goal is known, before the (longer) path search.
    Never raises for bad input: an infeasible goal or a failed search comes back with the reason.
    """
    from bagit.services.planner.plan import bagging_goal, path_to_goal

    t0 = time.perf_counter()
    sc = job.scenario
    g0 = np.asarray(job.g0, dtype=float)
    try:
        if g0.ndim != 2 or g0.shape[1] != 3 or len(g0) < 4 or not np.all(np.isfinite(g0)):
            raise BadScenario(f"g0 must be (n >= 4, 3) and finite, got shape {g0.shape}")
        goal, R = bagging_goal(sc, g0, job.rig)  # InfeasibleGoal too when the arms cannot reach it
    except BagItError as e:
        return PlanOutcome(job.run_id, failed_stage="goal", reason=f"goal: {e}", time_s=time.perf_counter() - t0)
    goal_msg = goal.to_message(job.run_id, object_height=float(sc.object.effective_height()))
    if on_goal is not None:
        on_goal(goal_msg)
    try:
        res = path_to_goal(sc, g0, goal, R, job.planner, job.seed, job.time_budget_s)
    except BagItError as e:
        return PlanOutcome(job.run_id, goal=goal_msg, failed_stage="planning", reason=f"planning: {e}", time_s=time.perf_counter() - t0)
    if not res.success:
        return PlanOutcome(job.run_id, goal=goal_msg, failed_stage="planning", reason=f"planning: {res.reason}", time_s=res.time_s)
    return PlanOutcome(job.run_id, goal=goal_msg, path=res.to_message(job.run_id), time_s=res.time_s)


def new_run_id() -> str:
    """Sortable and unique: the wall clock's UTC time of the start (whatever clock the coordinator runs
    on: a simulator's starts at 0) plus 6 random hex digits."""
    return time.strftime("%Y%m%d-%H%M%S", time.gmtime()) + "-" + uuid.uuid4().hex[:6]


@dataclass
class _Run:
    run_id: str
    scenario: Scenario
    scenario_name: str
    doc: dict[str, Any]
    controller: str
    planner: str
    seed: int
    overrides: dict[str, Any]
    t_start: float
    t_servo: float | None = None
    t_last_status: float | None = None
    t_last_soi: float | None = None  # when the newest SOI of the run came (the coordinator's clock)
    planning_time_s: float = 0.0
    path_nodes: int = 0
    perception_gone_at: float | None = None
    last_status: ControllerStatus | None = None
    detection: ObjectDetection | None = None  # the freshest usable marker detection of this run
    detection_note: str | None = None  # why the last detection of this run was not usable
    waiting_soi: SoiState | None = None  # g0 ready, waiting up to marker_wait_s for a detection
    last_rim: np.ndarray | None = None  # (n_x, 3) the newest SOI of the run: the rig's own view of the end
    goal: Goal | None = None  # the run's goal (V and the bottom frame the error is measured in)
    extra: dict[str, Any] = field(default_factory=dict)


class Coordinator:
    """One run at a time per rig (see the module docstring). Not thread-safe: the node serialises calls."""

    def __init__(self, config: CoordinatorConfig | None = None, now: float | None = None, rig: RigConfig | None = None) -> None:
        self.cfg = config or CoordinatorConfig()
        self.rig = rig  # the arms the goals must be within reach of (None: the default rig)
        self.run: _Run | None = None
        self.state = RunState(stage="idle", stamp=time.time() if now is None else now)
        self.alive: set[str] = set()
        self.estop: str | None = None  # why the e-stop is engaged (latched until released), else None
        self.objects_heard = False  # perception publishes marker detections: worth waiting for one
        self.changed = True  # the node publishes the state when set, then clears it

    # -- helpers -------------------------------------------------------------------------------

    @property
    def active(self) -> bool:
        return self.state.stage in ACTIVE_STAGES

    def _set(self, now: float, **fields: Any) -> None:
        r = self.run
        base = dict(
            run_id=r.run_id if r else None,
            scenario=r.scenario_name if r else None,
            scenario_doc=r.doc if r else None,
            controller=r.controller if r else None,
            planner=r.planner if r else None,
            seed=r.seed if r else None,
            params=r.overrides if r else {},
            stage=self.state.stage,
            progress=self.state.progress,
            reason=self.state.reason,
            result=self.state.result,
        )
        base.update(fields)
        base["elapsed_s"] = max(0.0, now - r.t_start) if r else 0.0
        self.state = RunState(stamp=now, **base)
        self.changed = True

    def _finish(self, now: float, stage: Literal["done", "failed", "aborted"], reason: str | None) -> None:
        r = self.run
        res = self.result(now, stage, reason).model_dump(mode="json") if r is not None else {}
        self._set(now, stage=stage, reason=reason, result=res)

    def result(self, now: float, stage: str, reason: str | None) -> RunResult:
        """The run's result as the rig itself saw it (a host with a simulator adds the truth)."""
        r = self.run
        assert r is not None
        st, goal = r.last_status, r.goal
        V = np.asarray(goal.vertices, dtype=float) if goal is not None else None
        perceived = None
        if r.last_rim is not None and V is not None and goal is not None:
            perceived = round(axis_error_cm(r.last_rim, V, np.asarray(goal.frame, dtype=float)[:3, 2]), 4)
        info = dict(r.extra.get("object", {}))
        object_from, object_reason = info.pop("object_from", None), info.pop("object_reason", None)
        return RunResult(
            run_id=r.run_id, scenario=r.scenario_name, controller=r.controller, planner=r.planner, seed=r.seed,
            overrides=dict(r.overrides), success=stage == "done", stage_reached=self.state.stage if stage != "done" else "done",
            reason=reason, error_cm=perceived, perceived_error_cm=perceived,
            error_to_goal_m=st.error_to_goal if st is not None else None,
            duration_s=round(now - r.t_servo, 3) if r.t_servo is not None else None, wall_s=round(now - r.t_start, 3),
            planning_time_s=round(r.planning_time_s, 4), path_nodes=r.path_nodes, ticks=st.ticks if st is not None else 0,
            final_rim=points_list(r.last_rim), object_vertices=points_list(V), object_from=object_from,
            object_reason=object_reason, marker=info or None,
        )

    def tick_state(self, now: float) -> RunState:
        """The state to republish periodically, with elapsed time brought up to `now` while a run is active."""
        if self.active:
            self._set(now)
            self.changed = False
        return self.state

    # -- requests ------------------------------------------------------------------------------

    def handle(self, req: RunControl, now: float) -> tuple[RunControlReply, list[Effect]]:
        """Answer a run/control request."""
        if req.action == "start":
            return self.start(req, now), []
        if req.action == "stop":
            return self.stop(now), []
        return self.reset(now), []

    def start(self, req: RunControl, now: float) -> RunControlReply:
        if self.estop is not None:
            return RunControlReply(accepted=False, reason=f"the e-stop is engaged ({self.estop}); release it first")
        if self.active:
            r = self.run
            return RunControlReply(accepted=False, run_id=r.run_id if r else None,
                                   reason=f"a run is in progress (run {r.run_id if r else '?'}, stage {self.state.stage}); stop it first")
        try:
            scenario, name = self._scenario(req)
            scenario = scenario.model_copy(update={"params": merge_params(scenario.params, req.params)})
            controller = req.controller or self.cfg.default_controller
            if controller not in self.cfg.controllers:
                raise BadScenario(f"unknown controller {controller!r}; choose from {', '.join(self.cfg.controllers)}")
            planner = req.planner or self.cfg.default_planner
            if planner not in PLANNER_NAMES:
                raise BadScenario(f"unknown planner {planner!r}; choose from {', '.join(PLANNER_NAMES)}")
            seed = int(req.seed or 0)
            if seed < 0:
                raise BadScenario(f"seed must be >= 0, got {seed}")
        except BagItError as e:
            return RunControlReply(accepted=False, reason=str(e).splitlines()[0])
        doc = scenario.model_dump(mode="json", exclude_none=True)
        self.run = _Run(new_run_id(), scenario, name, doc, controller, planner, seed, dict(req.params or {}), now)
        self._set(now, stage="perceiving", progress=0.0, reason=None, result=None)
        return RunControlReply(accepted=True, run_id=self.run.run_id)

    def _scenario(self, req: RunControl) -> tuple[Scenario, str]:
        if req.scenario_doc is not None:
            sc = Scenario.from_dict(req.scenario_doc, "scenario_doc")
            return sc, req.scenario or sc.name
        if not req.scenario:
            raise BadScenario("start needs a scenario (a bundled name or a scenario_doc)")
        from bagit.scenarios import find_scenario

        path = find_scenario(req.scenario)
        return Scenario.from_file(path), path.stem

    def stop(self, now: float) -> RunControlReply:
        if not self.active:
            return RunControlReply(accepted=False, run_id=self.state.run_id, reason=f"no run in progress (stage {self.state.stage})")
        self._finish(now, "aborted", "stopped by the operator")
        return RunControlReply(accepted=True, run_id=self.state.run_id)

    def reset(self, now: float) -> RunControlReply:
        """Abort any run, then back to idle (the dashboard's Reset)."""
        run_id = self.state.run_id
        if self.active:
            self._finish(now, "aborted", "reset by the operator")
        self.run = None
        self.state = RunState(stage="idle", stamp=now)
        self.changed = True
        return RunControlReply(accepted=True, run_id=run_id)

    def fail(self, reason: str, now: float) -> None:
        """The host fails the running run (its simulator failed, it ran out of wall time)."""
        if self.active:
            self._finish(now, "failed", reason)

    def on_estop(self, engage: bool, source: str, reason: str | None, now: float) -> None:
        """An e-stop aborts the running run (the arm driver stops the arms) and latches until released
        (by the dashboard or the CLI only: `EStop.may_act`)."""
        if not engage:
            if EStop(engage=False, source=source).may_act():
                self.estop = None
            return
        self.estop = f"by {source}" + (f": {reason}" if reason else "")
        if self.active:
            self._finish(now, "aborted", f"emergency stop {self.estop}")

    # -- data ----------------------------------------------------------------------------------

    def on_soi(self, soi: SoiState, now: float) -> list[Effect]:
        """In `perceiving`, a fresh SOI becomes g0: stage goal, and a plan job for the node (after
        waiting up to marker_wait_s for the object's marker, see the module doc)."""
        r = self.run
        if r is None or not self.active:
            return []
        if len(soi.rim) == r.scenario.bag.n_x:
            r.last_rim, r.t_last_soi = soi.rim, now
        if self.state.stage != "perceiving":
            return []
        frame_t = soi.source_stamp or soi.stamp
        if frame_t < r.t_start + self.cfg.settle_s:
            return []  # from a frame of before the start (or of the world before its reset)
        n_x = r.scenario.bag.n_x
        if len(soi.rim) != n_x:
            return []  # perception not yet reconfigured for this run's n_x
        if self.cfg.object_source == "marker" and self.objects_heard and r.detection is None and not self._marker_wait_over(now):
            r.waiting_soi = soi  # the newest g0 candidate
            return []
        return self._begin_goal(r, soi, now)

    def on_object(self, det: ObjectDetection, now: float) -> list[Effect]:
        """A marker detection (perception/object): kept when it is of this run and names its object;
        a g0 waiting for it goes on at once."""
        self.objects_heard = True
        r = self.run
        if r is None or self.state.stage not in PERCEIVE_STAGES:
            return []
        if det.source_stamp < r.t_start + self.cfg.settle_s:
            return []  # a frame of before the start (or of the world before its reset)
        if not det.ok:
            r.detection_note = f"no marker detection: {det.error}"
            return []
        want = r.scenario.object.marker.id if r.scenario.object.marker is not None else None
        if want is not None and det.marker_id != want:
            r.detection_note = (f"the marker in view (id {det.marker_id}, {det.name}) is not the run's object's "
                                f"(id {want}, {r.scenario.object.name or r.scenario_name})")
            return []
        if r.detection is not None and det.source_stamp < r.detection.source_stamp:
            return []
        r.detection = det
        if self.state.stage == "perceiving" and r.waiting_soi is not None and self.cfg.object_source == "marker":
            soi, r.waiting_soi = r.waiting_soi, None
            return self._begin_goal(r, soi, now)
        return []

    def _marker_wait_over(self, now: float) -> bool:
        r = self.run
        return r is not None and now - r.t_start >= self.cfg.settle_s + self.cfg.marker_wait_s

    def _begin_goal(self, r: _Run, soi: SoiState, now: float) -> list[Effect]:
        """Stage goal for the run `r` (the current one) with g0 = soi and the object from the marker or
        the scenario (stated in the result)."""
        r.waiting_soi = None
        scenario, info = self._object_for_plan(r)
        r.extra["object"] = info
        self._set(now, stage="goal", progress=0.0)
        job = PlanJob(r.run_id, scenario, np.array(soi.rim, dtype=float), r.planner, r.seed, self.cfg.plan_time_budget_s, self.rig)
        return [Effect("plan", job=job)]

    def _object_for_plan(self, r: _Run) -> tuple[Scenario, dict[str, Any]]:
        """The scenario the plan job uses (its object's V and height from the marker when usable) and the
        run-result fields saying where the object came from."""
        det = r.detection
        info: dict[str, Any] = {}
        if det is not None:
            if det.vertices is None or det.height is None:
                raise ValueError(f"marker detection {det.marker_id} is kept as usable but has no vertices or height")
            V_sc = r.scenario.object.bottom_vertices()
            info.update(marker_id=det.marker_id, marker_object=det.name, marker_height_m=round(float(det.height), 5))
            if det.vertices.shape == V_sc.shape:
                info["marker_v_error_m"] = round(float(np.linalg.norm(det.vertices - V_sc, axis=1).max()), 5)
            else:
                info["marker_v_error_m"] = None
                info["marker_v_note"] = f"marker V has {len(det.vertices)} vertices, the scenario's {len(V_sc)}"
        if det is not None and det.vertices is not None and det.height is not None and self.cfg.object_source == "marker":
            obj = r.scenario.object.model_copy(update={"vertices": det.vertices.tolist(), "height": float(det.height)})
            info.update(object_from="marker", object_reason=None)
            return r.scenario.model_copy(update={"object": obj}), info
        if self.cfg.object_source == "scenario":
            reason = "object_source is scenario"
        elif not self.objects_heard:
            reason = "perception publishes no marker detections (perception/object)"
        else:
            reason = r.detection_note or f"no marker detection within {self.cfg.marker_wait_s:g} s"
        info.update(object_from="scenario", object_reason=reason)
        return r.scenario, info

    def on_goal(self, goal: Goal, now: float) -> list[Effect]:
        """The goal is known (compute_plan's on_goal): publish it, stage planning."""
        r = self.run
        if r is None or goal.run_id != r.run_id or self.state.stage != "goal":
            return []
        r.extra["goal_published"] = True
        r.goal = goal
        self._set(now, stage="planning")
        return [Effect("publish_goal", message=goal)]

    def on_plan(self, out: PlanOutcome, now: float) -> list[Effect]:
        """The planning outcome: publish goal and path and go to pre-bagging, or fail with the reason."""
        r = self.run
        if r is None or out.run_id != r.run_id or self.state.stage not in ("goal", "planning"):
            return []  # a run that was stopped meanwhile
        r.planning_time_s = out.time_s
        if out.goal is not None:
            r.goal = out.goal
        effects: list[Effect] = []
        if out.goal is not None and not r.extra.get("goal_published"):
            effects.append(Effect("publish_goal", message=out.goal))
        if out.failed_stage is not None or out.path is None:
            self._set(now, stage=out.failed_stage or "planning")
            self._finish(now, "failed", out.reason or "planning failed")
            return effects
        r.path_nodes = int(len(out.path.nodes))
        r.t_servo = now
        effects.append(Effect("publish_path", message=out.path))
        self._set(now, stage="pre-bagging", progress=0.0)
        return effects

    def on_status(self, st: ControllerStatus, now: float) -> None:
        """Follow the controller: its stage and progress; done ends the run."""
        r = self.run
        if r is None or st.run_id != r.run_id or self.state.stage not in SERVO_STAGES:
            return
        r.t_last_status = now
        r.last_status = st
        if st.stage in ("failed", "aborted"):
            self._finish(now, "failed", f"controller: {st.reason or st.stage}")
            return
        if st.done:
            self._set(now, progress=1.0)
            self._finish(now, "done", None)
            return
        stage = st.stage if st.stage in SERVO_STAGES else self.state.stage
        if self.state.stage == "bagging":
            stage = "bagging"  # the lift from g† has begun: a run never goes back to pre-bagging
        if stage != self.state.stage or abs(st.progress - self.state.progress) > 1e-9:
            self._set(now, stage=stage, progress=float(st.progress))

    def on_liveliness(self, service: str, alive: bool, now: float) -> None:
        """Services appearing and disappearing; a required one gone while servoing fails the run."""
        (self.alive.add if alive else self.alive.discard)(service)
        r = self.run
        if r is None or not self.active:
            return
        if service == self.cfg.perception_service:
            r.perception_gone_at = None if alive else now
            return
        if not alive and service in self.cfg.required_services and self.state.stage in SERVO_STAGES:
            self._finish(now, "failed", f"the {service} service is gone (liveliness lost during {self.state.stage})")

    def tick(self, now: float) -> list[Effect]:
        """Timeouts: no fresh SOI (perceiving), the rim lost (servoing), a silent controller, the run's time limit, perception gone too long; a g0
        whose wait for the marker is over goes on with the scenario's object (its plan job is returned)."""
        r = self.run
        if r is None or not self.active:
            return []
        stage = self.state.stage
        if stage == "perceiving" and r.waiting_soi is not None and self._marker_wait_over(now):
            return self._begin_goal(r, r.waiting_soi, now)
        if stage == "perceiving" and now - r.t_start > self.cfg.perceive_timeout_s:
            who = "" if self.cfg.perception_service in self.alive else f" (the {self.cfg.perception_service} service is not up)"
            self._finish(now, "failed", f"no fresh SOI from perception within {self.cfg.perceive_timeout_s:g} s{who}")
            return []
        if stage in SERVO_STAGES:
            t_servo = r.t_servo or now
            missing = [s for s in self.cfg.required_services if s not in self.alive]
            if missing and now - t_servo > self.cfg.status_timeout_s:
                self._finish(now, "failed", f"the {missing[0]} service is not up")
                return []
            if r.t_last_status is None:
                if now - t_servo > self.cfg.first_status_timeout_s:
                    self._finish(now, "failed", f"no controller status for this run within {self.cfg.first_status_timeout_s:g} s of the path")
                    return []
            elif now - r.t_last_status > self.cfg.status_timeout_s:
                self._finish(now, "failed", f"controller status silent for {now - r.t_last_status:.1f} s (> {self.cfg.status_timeout_s:g} s)")
                return []
            if now - t_servo > self.cfg.run_time_limit_s:
                self._finish(now, "failed", f"time limit of {self.cfg.run_time_limit_s:g} s reached in {stage}")
                return []
            lost = now - max(t_servo, r.t_last_soi if r.t_last_soi is not None else t_servo)
            if lost > self.cfg.soi_lost_s:
                self._finish(now, "failed", f"perception lost the rim: no SOI for {lost:.1f} s in {stage} (the controller held)")
                return []
        if r.perception_gone_at is not None and now - r.perception_gone_at > self.cfg.perception_grace_s:
            self._finish(now, "failed", f"the {self.cfg.perception_service} service is gone (for {now - r.perception_gone_at:.1f} s)")
        return []
