"""`bagit run`: the whole rig in one process, on the simulator's clock.

The same pure parts `bagit up` runs as services, wired by direct calls instead of Zenoh keys:
the simulator (`SimRig`: the world, the camera, the two CR5 controllers), perception
(`RimTracker` for the SOI, `detect_object` for the object's marker), the coordinator (`Coordinator`:
stages, limits, the run's result; `compute_plan`: goal and path), the controller (`ServoSession`)
and the arm side (`Cr5Arms`: the arm driver's `ServoPath` streaming to the CR5s; or `IdealArms`,
the floating-gripper ablation). Nothing here decides anything a service decides.

Time is the simulator's: every part is handed `now` = simulated seconds, the camera takes a frame
every 1/fps, the arm side runs a servo period every `servo_period_s`, and the world steps in
between, so a run is deterministic (same scenario and seed, the same ticks and error, bit for
bit on one machine) and goes as fast as the CPU allows. Processing takes no simulated time: a
command answers the frame it was computed from. Ground truth is read only to judge the run (and
the lift margin, when the lift from g† starts); no part ever sees it.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bagit.common.errors import BagItError, SimulationFailed, WallLimitReached
from bagit.common.geometry import enclosure
from bagit.common.messages import ArmState, Goal, Path, RunControl, RunState, SoiState
from bagit.common.names import DEFAULT_CONTROLLER, DEFAULT_PLANNER, FINAL_STAGES, PERCEIVE_STAGES, SERVO_STAGES, SIM_TIME_LIMIT_S, ArmsMode
from bagit.common.params import merge_params
from bagit.common.results import RunResult, points_list, provenance
from bagit.common.rig import ArmName, RigConfig
from bagit.common.scenario import Scenario
from bagit.services.controller.session import SOI_MAX_AGE_S, Outbox, ServoRuns, tick_period
from bagit.services.perception.marker import MarkerSchedule, ObjectLibrary, detect_object, with_run_object
from bagit.services.perception.tracker import RimTracker, frame_soi, start_hint
from bagit.services.planner.coordinator import Coordinator, CoordinatorConfig, Effect, compute_plan
from bagit.services.planner.goal import bottom_frame
from bagit.services.sim.judge import truth_of
from bagit.services.sim.lockstep import Schedule
from bagit.services.sim.rig_sim import SETTLE_S, SimRig, camera_fps
from bagit.sim_arms import Cr5Arms, IdealArms

log = logging.getLogger("bagit.run")

WALL_LIMIT_S = 900.0  # a run taking longer than this in wall time is stopped (normal runs take 10-60 s)
SERVICES = ("perception", "planner", "controller", "arm-driver")  # all in this process, so always alive


@dataclass
class RunOptions:
    """One in-process run: what to bag, with what, and the limits."""

    scenario: Scenario
    name: str | None = None
    controller: str = DEFAULT_CONTROLLER
    planner: str = DEFAULT_PLANNER
    seed: int = 0
    arms: ArmsMode = "cr5"
    overrides: dict[str, Any] = field(default_factory=dict)  # method parameters over the scenario's
    time_limit_s: float = SIM_TIME_LIMIT_S  # servoing longer than this (simulated) fails the run
    wall_limit_s: float | None = WALL_LIMIT_S
    fps: float | None = None  # camera frames per simulated second; None: the control rate
    rig: RigConfig | None = None
    object_source: str = "marker"  # the coordinator's: V from the object's marker when detected, else the scenario's
    on_state: Callable[[RunState], None] | None = None  # each new stage of the coordinator's run/state, as published


@dataclass
class _Trace:
    """What the host saw go by, for the result and the benchmark."""

    solve_ms: list[float] = field(default_factory=list)
    lift_margin_cm: float | None = None
    stages: list[str] = field(default_factory=list)


def run_inprocess(opts: RunOptions, progress: Callable[[str], None] = lambda s: None) -> RunResult:
    """One simulated run through the coordinator's stages; never raises for a failed run (the result says why)."""
    if not (np.isfinite(opts.time_limit_s) and opts.time_limit_s > 0):
        raise BagItError(f"the time limit must be a positive number of seconds, got {opts.time_limit_s}")
    if opts.wall_limit_s is not None and not (np.isfinite(opts.wall_limit_s) and opts.wall_limit_s > 0):
        raise BagItError(f"the wall-time limit must be a positive number of seconds, got {opts.wall_limit_s}")
    t_wall = time.perf_counter()
    sc = opts.scenario
    params = merge_params(sc.params, opts.overrides)
    rate = params.controller.control_rate_hz
    fps = camera_fps(opts.fps, True, rate)  # lockstep: a frame per control tick unless told
    if not 0 < fps <= 120:
        raise BagItError(f"fps must be in (0, 120], got {fps}")
    sim = SimRig(sc, (opts.rig or RigConfig()).for_bag(sc.bag.perimeter_m()), opts.seed)  # the arms keep to this bag's rim
    try:
        return _Run(sim, opts, fps, t_wall, progress).run()
    finally:
        sim.close()


def control_tick(servo: ServoRuns, state: RunState, path: Path | None, goal: Goal | None, soi: SoiState | None,
                 states: dict[ArmName, ArmState], now: float, keepalive: bool = False) -> list[Outbox]:
    """`bagit run`'s control tick (at a frame, or a `keepalive` tick between sparse frames): what it has heard
    handed to `ServoRuns` as the controller node hands it, with every age on the simulator's clock (all of it
    is of this step) and no e-stop. A keep-alive tick is made only while the run is servoed, as the node's.
    Once the run is over the loop sends nothing more (it stops stepping the world), so a run that ends is not
    told to hold."""
    if state.stage in FINAL_STAGES or (keepalive and not servo.servoing(state.run_id)):
        return []
    age = None if soi is None else now - soi.source_stamp
    return servo.tick(state, path if path is not None and path.run_id == state.run_id else None, goal, False,
                      soi, age, SOI_MAX_AGE_S, states, None, now)


class _Run:
    """The loop of one in-process run (see the module docstring)."""

    def __init__(self, sim: SimRig, opts: RunOptions, fps: float, t_wall: float, progress: Callable[[str], None]):
        self.sim, self.opts, self.t_wall, self.say = sim, opts, t_wall, progress
        self.frame_dt = 1.0 / fps
        sc = opts.scenario
        self.arms: Cr5Arms | IdealArms = Cr5Arms.of(sim) if opts.arms == "cr5" else IdealArms(sim)
        self.coord = Coordinator(CoordinatorConfig(run_time_limit_s=opts.time_limit_s, object_source=opts.object_source), now=sim.clock_s,
                                 rig=sim.rig)
        r, g, b = sc.bag.color
        self.tracker = RimTracker(sc.bag.n_x, sc.bag.kind, (r, g, b), rim_color=sc.bag.rim.color)  # the lab's perception config
        library = ObjectLibrary.from_scenarios()
        try:
            library = with_run_object(library, sc)
        except BagItError as e:
            log.warning("the run's object is not added to the marker library: %s", e)
        self.library = library if len(library) else None
        self.soi: SoiState | None = None
        self.goal: Goal | None = None
        self.path: Path | None = None
        self.seq = 0
        self.servo = ServoRuns(self._next_seq, watchdog_s=sim.rig.safety.watchdog_s)  # the controller node's glue
        self.markers = MarkerSchedule()  # perception's (its node's defaults)
        self.frames = 0
        self.trace = _Trace()

    def _next_seq(self) -> int:
        self.seq += 1
        return self.seq

    # -- the loop ----------------------------------------------------------------------------------

    def run(self) -> RunResult:
        sim, coord, opts = self.sim, self.coord, self.opts
        sc = opts.scenario
        now = sim.clock_s
        for service in SERVICES:
            coord.on_liveliness(service, True, now)
        req = RunControl(action="start", scenario=opts.name or sc.name, scenario_doc=sc.model_dump(mode="json", exclude_none=True),
                         controller=opts.controller, planner=opts.planner, seed=opts.seed, params=dict(opts.overrides))
        rep = coord.start(req, now)
        self._emit()
        if not rep.accepted:
            return RunResult(scenario=opts.name or sc.name, controller=opts.controller, planner=opts.planner, seed=opts.seed,
                             arms=opts.arms, overrides=dict(opts.overrides), reason=rep.reason, wall_s=time.perf_counter() - self.t_wall)
        self.say(f"perceiving: the bag settles {SETTLE_S:g} s, then g0 from the camera")
        self.markers.run_started(now)
        if opts.wall_limit_s is not None:
            sim.world.wall_deadline = self.t_wall + opts.wall_limit_s  # checked at every physics step too
        try:
            self.arms.step(SETTLE_S)  # the bag hangs still before the first frame, as `bagit sim` does after a reset
            self.arms.start()
        except (SimulationFailed, WallLimitReached) as e:
            coord.fail(self._failure(e), sim.clock_s)
        # the events `bagit sim` steps by too (keep-alive ticks between frames sparser than the controller's pace)
        keep_s = tick_period(merge_params(sc.params, opts.overrides).controller.control_rate_hz, sim.rig.safety.watchdog_s)
        sched = Schedule.starting(sim.time, self.frame_dt, self.arms.period, keep_s=keep_s)
        while coord.state.stage not in FINAL_STAGES:
            now = sim.clock_s  # the rig's clock (as `bagit sim` publishes it); the events fall on the world's time
            if sched.servo_due(sim.time) is not None:
                self.arms.servo(now)
            if sched.frame_due(sim.time):
                self._frame(now)
            elif sched.keep_due(sim.time):
                self._control(self.arms.states(), now, keepalive=True)  # frames sparser than the keep-alive pace: a tick on the last SOI
            self._apply(coord.tick(now), now)
            if coord.state.stage in FINAL_STAGES:
                break
            if opts.wall_limit_s is not None and time.perf_counter() - self.t_wall > opts.wall_limit_s:
                coord.fail(self._failure(None), now)
                break
            step = sched.until_next(sim.time)
            try:
                self.arms.step(step)
            except (SimulationFailed, WallLimitReached) as e:
                coord.fail(self._failure(e), sim.clock_s)
        return self._result()

    def _failure(self, e: SimulationFailed | WallLimitReached | None) -> str:
        """Why the simulator stopped the run: its physics failed (`e`), or the wall-time limit passed (`e`
        raised inside a step, or None: between steps)."""
        if isinstance(e, SimulationFailed):
            return f"simulator: {e}"
        wall = time.perf_counter() - self.t_wall
        return (f"simulator: too slow, {wall:.0f} s of wall time for {self.sim.time:.2f} s simulated (the bag's settling included; "
                f"limit {self.opts.wall_limit_s:g} s; the contact solver crawls?)")

    def _frame(self, now: float) -> None:
        """A camera frame: perception (the SOI, the object's marker), then a control tick."""
        frame = self.sim.render_rgbd(self.frames)
        self.frames += 1
        effects: list[Effect] = []
        # (the coordinator takes detections only while perceiving: none is made after, as none would be heard)
        if self.library is not None and self.coord.state.stage in PERCEIVE_STAGES and self.markers.due(frame.stamp):
            effects += self.coord.on_object(detect_object(frame, self.library, self.coord.state.run_id), now)
        states = self.arms.states()  # read once a frame: the hint and the control tick see the same arms
        try:
            self.soi, _cloud = frame_soi(self.tracker, frame, start_hint(states["left"], 0.0, np.inf), now)  # this very step's state
            effects += self.coord.on_soi(self.soi, now)
        except BagItError as e:
            log.debug("frame %d: no SOI: %s", frame.seq, e)  # the controller holds once the last SOI is stale
        self._apply(effects, now)
        self._control(states, now)

    def _emit(self) -> None:
        """Tell `on_state` of a new stage (what the planner node would publish on run/state)."""
        st = self.coord.state
        if st.stage != (self.trace.stages[-1] if self.trace.stages else None):
            self.trace.stages.append(st.stage)
            if self.opts.on_state is not None:
                self.opts.on_state(st)

    def _apply(self, effects: list[Effect], now: float) -> None:
        """Carry out the coordinator's effects: plan (at once: planning takes no simulated time), publish."""
        self._emit()
        for e in effects:
            if e.kind == "plan" and e.job is not None:
                self.say(f"goal and plan: {e.job.planner} from g0")
                out = compute_plan(e.job, on_goal=lambda g: self._apply(self.coord.on_goal(g, now), now))
                self._apply(self.coord.on_plan(out, now), now)
                if out.path is not None:
                    self.say(f"pre-bagging: {len(out.path.nodes)} nodes, g† at {out.path.dagger_index} (planned in {out.time_s:.2f} s)")
            elif e.kind == "publish_goal" and isinstance(e.message, Goal):
                self.goal = e.message
            elif e.kind == "publish_path" and isinstance(e.message, Path):
                self.path = e.message

    def _control(self, states: dict[ArmName, ArmState], now: float, keepalive: bool = False) -> None:
        """One control tick on the newest SOI and the arms' `states`, through the controller node's `ServoRuns`."""
        for out in control_tick(self.servo, self.coord.state, self.path, self.goal, self.soi, states, now, keepalive):
            self._send(out, now)

    def _send(self, out: Outbox, now: float) -> None:
        if out.command is not None:
            self.arms.submit(out.command, now)
        if out.report:
            log.info("%s", out.report)
        st = out.status
        if st is None:
            return
        if st.solve_ms > 0:
            self.trace.solve_ms.append(st.solve_ms)
        if st.stage == "bagging" and st.mode == "servo" and self.trace.lift_margin_cm is None:
            self.trace.lift_margin_cm = self._lift_margin()  # judged on the truth, like the end; never fed back
        before = self.coord.state.stage
        self.coord.on_status(st, now)
        self._emit()
        if self.coord.state.stage != before and self.coord.state.stage in SERVO_STAGES:
            self.say(f"{self.coord.state.stage}: subgoal {st.subgoal_index}")

    def _lift_margin(self) -> float:
        """The true rim's smallest margin round the true V (cm) as the lift from g† begins."""
        V = self.opts.scenario.object.bottom_vertices()
        return round(float(enclosure(self.sim.world.true_rim(), V, bottom_frame(V))[0].min()) * 100, 4)

    # -- the result --------------------------------------------------------------------------------

    def _result(self) -> RunResult:
        self._emit()
        sc, opts = self.opts.scenario, self.opts
        res = RunResult.model_validate(self.coord.state.result)
        gt = self.sim.ground_truth()
        V = sc.object.bottom_vertices()
        truth = truth_of(gt.rim, gt.passed_through, gt.max_penetration_m, sc, bottom_frame(V)[:3, 2], self.trace.lift_margin_cm)
        success = res.success and truth.success
        reason = res.reason if not res.success else truth.reason
        solve = np.asarray(self.trace.solve_ms, dtype=float)
        params = merge_params(sc.params, opts.overrides)
        return res.model_copy(update=dict(
            arms=opts.arms, success=success, reason=reason, error_cm=truth.error_cm, truth=truth,
            final_rim=points_list(self.sim.world.true_rim(sc.bag.n_x)), wall_s=round(time.perf_counter() - self.t_wall, 3),
            solve_ms_median=float(np.median(solve)) if solve.size else None, arm_events=self.arms.events(),
            lift_margin_cm=self.trace.lift_margin_cm, provenance=provenance(params.flat()),
        ))
