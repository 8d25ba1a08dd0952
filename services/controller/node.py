"""The controller on Zenoh: the only module of the controller that imports zenoh.

    node = ControllerNode(session, keys, ControllerServiceConfig())
    node.close()

It follows `run/state`. When `planner/path` for the current run arrives (with `planner/goal`,
whose perimeter is C6's R), it builds the run's controller (`RunState.controller`, default mpc;
params = the scenario's `params:` overlaid with `RunState.params`) and servos on the wall clock at
the control rate. Each tick takes the newest SOI (`perception/soi`) and both grippers' poses
(`arm/<side>/state` tool_pose: world [x y z roll pitch yaw], the driver's convention), calls the
pure controller, and publishes a `Command` on `controller/cmd` and a `ControllerStatus` on
`controller/status`. A tick without a new SOI (but a fresh one) sends nothing: the driver keeps
streaming the last targets, and the Broyden estimate never learns from a repeated SOI.

It never extrapolates: no SOI, a stale one (older than `soi_max_age_s`, by its camera stamp when
that is on this machine's clock, else by arrival), an implausible one (the guard), or missing or
stale arm states -> a hold command (u = 0) with the reason, every tick while it lasts. A run that
stops, is aborted, fails or is done, a new run, or an e-stop -> one hold, and servoing stops. Any
exception in the controller (e.g. numpy's LinAlgError) -> hold with the reason in the status;
the loop thread never dies.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from typing import Any, Callable

import numpy as np
import zenoh  # noqa: F401 - the node is where the service meets the bus
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.bus import Keys, LatestCache, Publisher, Subscriber
from bagit.common.geometry import pose_to_matrix
from bagit.common.messages import ArmState, Command, ControllerStatus, EStop, Goal, Path, RunState, SoiState
from bagit.common.params import MethodParams
from bagit.common.scenario import Scenario
from bagit.services.controller.controller import CONTROLLERS, make_controller

ACTIVE_STAGES = ("perceiving", "goal", "planning", "pre-bagging", "bagging")
DT_MAX_S = 0.18  # a command's dt stays under the arm driver's 0.2 s watchdog
CLOCK_SKEW_S = 3600.0  # a source stamp further than this from our clock is on another clock (a simulator's)


class ControllerServiceConfig(BaseModel):
    """`bagit controller`'s config file (YAML)."""

    model_config = ConfigDict(extra="forbid")

    controller: str | None = Field(None, description="mpc | ibvs | ssvs; None: the run's choice (RunState.controller), else mpc")
    control_rate_hz: float | None = Field(None, gt=0.0, le=500.0, description="None: the run's params.control_rate_hz")
    soi_max_age_s: float = Field(0.5, gt=0.0, le=10.0, description="a SOI older than this: hold")
    arm_max_age_s: float = Field(0.3, gt=0.0, le=10.0, description="an arm state older than this: hold")
    params: dict[str, Any] = Field(default_factory=dict, description="method parameter overrides laid over the run's")


def stderr_report(text: str) -> None:
    print(f"bagit controller: {text}", file=sys.stderr, flush=True)


def _finite_or_none(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


class _Run:
    """One run being servoed: its id, controller, rate and counters."""

    def __init__(self, run_id: str | None, name: str, controller: Any, params: MethodParams, rate_hz: float):
        self.run_id = run_id
        self.name = name
        self.controller = controller
        self.params = params
        self.dt = 1.0 / rate_hz
        self.last_soi_seq: int | None = None
        self.last_soi_stamp: float | None = None
        self.last_cmd_t: float | None = None  # monotonic time of the last servo command
        self.reset_done = False
        self.finished: str | None = None  # why servoing ended (done, the run's stage, e-stop)


class ControllerNode:
    """Servoes the current run (see the module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        cfg: ControllerServiceConfig | None = None,
        report: Callable[[str], None] = stderr_report,
    ) -> None:
        self.cfg = cfg or ControllerServiceConfig()
        if self.cfg.controller is not None and self.cfg.controller not in CONTROLLERS:
            from bagit.common.errors import BadControlInput

            raise BadControlInput(f"unknown controller {self.cfg.controller!r}; choose from {', '.join(CONTROLLERS)}")
        self.keys = keys
        self.report = report
        self._lock = threading.Lock()
        self._run_state: RunState | None = None
        self._paths: dict[str | None, Path] = {}
        self._goals: dict[str | None, Goal] = {}
        self._estop = False
        self._run: _Run | None = None
        self._seq = 0
        self.counters: dict[str, int] = {"ticks": 0, "servo": 0, "hold": 0, "skipped": 0, "errors": 0, "runs": 0}
        self.last_reason: str | None = None
        self.runs_done: list[dict[str, Any]] = []
        self._cmd = Publisher(session, keys.controller_cmd, Command)
        self._status = Publisher(session, keys.controller_status, ControllerStatus)
        self.soi = LatestCache(session, keys.perception_soi, SoiState)
        self.arms = LatestCache(session, keys.arm_state_any, ArmState)
        self._subs = [
            Subscriber(session, keys.run_state, RunState, self._on_run_state),
            Subscriber(session, keys.planner_path, Path, self._on_path),
            Subscriber(session, keys.planner_goal, Goal, self._on_goal),
            Subscriber(session, keys.estop, EStop, self._on_estop),
        ]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="controller-loop", daemon=True)
        self._thread.start()

    # -- in ----------------------------------------------------------------------------------------

    def _on_run_state(self, msg: RunState) -> None:
        with self._lock:
            self._run_state = msg

    def _on_path(self, msg: Path) -> None:
        with self._lock:
            self._paths = {msg.run_id: msg}  # one run at a time: an older run's path is dropped

    def _on_goal(self, msg: Goal) -> None:
        with self._lock:
            self._goals = {msg.run_id: msg}

    def _on_estop(self, msg: EStop) -> None:
        with self._lock:
            self._estop = bool(msg.engage)

    # -- the loop ----------------------------------------------------------------------------------

    def _loop(self) -> None:
        next_t = time.monotonic()
        while not self._stop.is_set():
            period = self._period()
            try:
                self._tick()
            except Exception as e:  # noqa: BLE001 - a bug here must hold the arms, never kill the loop
                self.counters["errors"] += 1
                self._hold(f"controller node error: {type(e).__name__}: {e}", self._run)
            next_t += period
            now = time.monotonic()
            if next_t < now - period:
                next_t = now  # late: never catch up with a burst of ticks
            self._stop.wait(max(0.0, next_t - now))

    def _period(self) -> float:
        run = self._run
        if run is not None:
            return run.dt
        return 1.0 / (self.cfg.control_rate_hz or MethodParams().control_rate_hz)

    def _tick(self) -> None:
        with self._lock:
            state, estop = self._run_state, self._estop
            path = None if state is None else (self._paths.get(state.run_id) or self._paths.get(None))
            goal = None if state is None else (self._goals.get(state.run_id) or self._goals.get(None))
        run = self._run
        # a run that ended, a new run, an e-stop: one hold, and no more servoing
        if run is not None and run.finished is None:
            why = None
            if estop:
                why = "e-stop engaged"
            elif state is None or state.run_id != run.run_id:
                why = "a new run started" if state is not None else "no run state"
            elif state.stage not in ACTIVE_STAGES:
                why = f"run {state.stage}" + (f": {state.reason}" if state.reason else "")
            if why is not None:
                self._end(run, why)
        if run is not None and (state is None or state.run_id != run.run_id):
            self._run = run = None
        if estop or state is None or state.stage not in ACTIVE_STAGES or path is None:
            return
        if run is None:
            self._run = run = self._build(state, path, goal)
            if run is None:
                return
        if run.finished is None:
            self._servo(run, path, goal)

    def _build(self, state: RunState, path: Path, goal: Goal | None) -> _Run | None:
        """The run's controller from its run state and path; None (and a status saying why) if it cannot be."""
        if not path.success:
            self._publish_status(state.run_id, reason=f"the planner found no path for run {state.run_id}")
            return _finished_run(state.run_id, "no path")
        try:
            scen_params: dict[str, Any] = {}
            if state.scenario_doc is not None:
                scen_params = Scenario.model_validate(state.scenario_doc).params.model_dump(exclude_unset=True)
            over = {**state.params, **self.cfg.params}
            fields = MethodParams.model_fields
            ignored = sorted(k for k in over if k not in fields)
            params = MethodParams(**{**scen_params, **{k: v for k, v in over.items() if k in fields}})
            name = self.cfg.controller or state.controller or "mpc"
            rate = self.cfg.control_rate_hz or params.control_rate_hz
            if rate != params.control_rate_hz:
                params = params.model_copy(update={"control_rate_hz": rate})
            nodes = np.asarray(path.nodes, dtype=float)
            ctrl = make_controller(name, params, nodes.shape[1])
        except Exception as e:  # noqa: BLE001 - a bad run must not take the node down
            reason = f"cannot build the controller for run {state.run_id}: {type(e).__name__}: {str(e).splitlines()[0]}"
            self.report(reason)
            self._publish_status(state.run_id, reason=reason)
            return _finished_run(state.run_id, reason)
        if ignored:
            self.report(f"run {state.run_id}: parameters not for the controller ignored: {', '.join(ignored)}")
        self.counters["runs"] += 1
        self.report(f"run {state.run_id}: {name} at {rate:g} Hz on a path of {len(nodes)} nodes (g† at {path.dagger_index})")
        return _Run(state.run_id, name, ctrl, params, rate)

    def _grippers(self) -> tuple[dict[str, np.ndarray] | None, str | None]:
        out = {}
        for a in ("left", "right"):
            item = self.arms.get_with_time(self.keys.arm_state(a))
            if item is None:
                return None, f"no state from the {a} arm"
            msg, t = item
            age = time.monotonic() - t
            if age > self.cfg.arm_max_age_s:
                return None, f"the {a} arm's state is stale ({age:.2f} s old)"
            if msg.estopped:
                return None, f"the {a} arm is e-stopped"
            p = np.asarray(msg.tool_pose, dtype=float)
            if p.shape != (6,) or not np.all(np.isfinite(p)):
                return None, f"the {a} arm's tool pose is not 6 finite numbers"
            out[a] = pose_to_matrix(p[:3], p[3:])
        return out, None

    def _arm_fault(self) -> str | None:
        """An arm reporting an error other than a lost link (which the driver reconnects by itself)."""
        for a in ("left", "right"):
            item = self.arms.get_with_time(self.keys.arm_state(a))
            if item is not None and item[0].error and not (item[0].error_reason or "").startswith("link lost"):
                return f"the {a} arm reports an error: {item[0].error_reason or 'unknown'}"
        return None

    def soi_age(self, soi: SoiState, received: float) -> float:
        """Seconds since the SOI's camera frame was taken (by arrival when stamped on another clock)."""
        by_arrival = time.monotonic() - received
        by_stamp = time.time() - soi.source_stamp
        if abs(by_stamp) < CLOCK_SKEW_S:
            return max(by_stamp, by_arrival)
        return by_arrival

    def _servo(self, run: _Run, path: Path, goal: Goal | None) -> None:
        self.counters["ticks"] += 1
        item = self.soi.get_with_time()
        grippers, arm_problem = self._grippers()
        now = time.time()
        if item is None:
            self._hold("no SOI received", run, step_none=True)
            return
        soi, received = item
        age = self.soi_age(soi, received)
        if age > self.cfg.soi_max_age_s:
            self._hold(f"SOI is stale ({age:.2f} s old, limit {self.cfg.soi_max_age_s:g} s)", run, step_none=True)
            return
        if arm_problem is not None:
            self._hold(arm_problem, run, step_none=True)
            return
        fault = self._arm_fault()
        if fault is not None:
            # a latched fault (the driver's or a controller's) will not clear by itself: the run has failed
            self._end(run, fault)
            self._publish_status(run.run_id, controller=run.name, mode="hold", stage="failed", reason=fault)
            return
        if soi.seq == run.last_soi_seq and soi.source_stamp == run.last_soi_stamp:
            self.counters["skipped"] += 1  # fresh but not new: nothing to learn from, nothing to send
            return
        run.last_soi_seq, run.last_soi_stamp = soi.seq, soi.source_stamp
        c = run.controller
        try:
            if not run.reset_done:
                perimeter = goal.perimeter if goal is not None and goal.perimeter > 0 else None
                outline, frame = (None, None) if goal is None else (np.asarray(goal.vertices, dtype=float), np.asarray(goal.frame, dtype=float))
                c.reset(np.asarray(soi.rim, dtype=float), path, grippers, perimeter=perimeter, outline=outline, frame=frame)
                run.reset_done = True
                if run.params.enclose_margin_m is not None and c.tracker.outline is not None:
                    self.report(f"run {run.run_id}: the rim must go round the object's {len(outline)} bottom vertices "
                                f"by {run.params.enclose_margin_m * 1000:.0f} mm before the lift and at g*")
                elif run.params.enclose_margin_m is not None and goal is None:
                    self.report(f"run {run.run_id}: no goal (with the object's V) yet at the first tick: no enclosure rule")
            out = c.step(np.asarray(soi.rim, dtype=float), now, grippers)
        except Exception as e:  # noqa: BLE001 - LinAlgError, a solver failure, a bad input: hold and say so
            self.counters["errors"] += 1
            self._hold(f"controller error: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}", run)
            return
        self._seq += 1
        cmd = out.to_command(self._command_dt(run), seq=self._seq, run_id=run.run_id, source_stamp=soi.source_stamp)
        self._cmd.put(cmd)
        self.counters["servo" if cmd.mode == "servo" else "hold"] += 1
        self.last_reason = out.reason
        self._publish_status(run.run_id, controller=run.name, mode=out.mode, stage=out.stage, reason=out.reason,
                             subgoal_index=out.subgoal_index, progress=out.progress,
                             error_to_subgoal=_finite_or_none(out.error_to_subgoal),
                             error_to_goal=_finite_or_none(out.error_to_goal), solve_ms=out.solve_ms, done=out.done)
        if out.done:
            run.finished = "done"
            self.runs_done.append({"run_id": run.run_id, "error_to_goal": _finite_or_none(out.error_to_goal), "ticks": c.ticks})
            self.report(f"run {run.run_id}: at g* (error {out.error_to_goal * 1000:.1f} mm after {c.ticks} ticks)")

    def _command_dt(self, run: _Run) -> float:
        """Over how long the driver spreads this increment: the time since the last command (a tick
        comes with each new SOI, so a slow camera gives longer, slower steps rather than a dash and
        a stop), at least the control period and at most DT_MAX_S, under the driver's 0.2 s watchdog.
        u is bounded per tick (C7 at the control rate), so a longer dt only ever means slower."""
        now = time.monotonic()
        last, run.last_cmd_t = run.last_cmd_t, now
        if last is None:
            return run.dt
        return float(min(max(now - last, run.dt), max(DT_MAX_S, run.dt)))

    # -- out ---------------------------------------------------------------------------------------

    def _hold(self, reason: str, run: _Run | None, step_none: bool = False) -> None:
        """A hold command (u = 0) with the reason, and the status saying so."""
        if run is not None and step_none and run.reset_done:
            try:
                run.controller.step(None, time.time(), {})  # the controller forgets the gap (no learning across it)
            except Exception:  # noqa: BLE001
                pass
        self._seq += 1
        run_id = run.run_id if run is not None else None
        self._cmd.put(Command(u=np.zeros(12), dt=run.dt if run is not None else 1 / 30, seq=self._seq, run_id=run_id,
                              mode="hold", reason=reason))
        self.counters["hold"] += 1
        if reason != self.last_reason:
            self.report(f"hold: {reason}")
        self.last_reason = reason
        self._publish_status(run_id, controller=run.name if run is not None else "mpc", mode="hold", reason=reason)

    def _end(self, run: _Run, why: str) -> None:
        run.finished = why
        self._hold(why, run)

    def _publish_status(self, run_id: str | None, **kw: Any) -> None:
        try:
            self._status.put(ControllerStatus(run_id=run_id, seq=self._seq, **kw))
        except Exception as e:  # noqa: BLE001
            self.report(f"cannot publish the status: {type(e).__name__}: {e}")

    def status(self) -> dict[str, Any]:
        return {"counters": dict(self.counters), "last_reason": self.last_reason, "runs_done": list(self.runs_done)}

    def close(self) -> dict[str, Any]:
        """Stop the loop (holding the arms if a run was being servoed) and stop listening."""
        self._stop.set()
        self._thread.join(timeout=5.0)
        run = self._run
        if run is not None and run.finished is None:
            self._end(run, "controller stopping")
        for s in self._subs:
            s.close()
        self.soi.close()
        self.arms.close()
        self._cmd.close()
        self._status.close()
        return self.status()


def _finished_run(run_id: str | None, why: str) -> _Run:
    """A placeholder run that is never servoed (no path, or no controller): remembered so the
    reason is reported once, not every tick."""
    r = _Run(run_id, "none", None, MethodParams(), MethodParams().control_rate_hz)
    r.finished = why
    return r
