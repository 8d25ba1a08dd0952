"""One run's servoing, with no bus and no clock of its own: what the controller does with each SOI.

Whoever hosts it (the `bagit controller` node on Zenoh, `bagit run`'s in-process loop on the
simulator's clock) hands it the newest SOI, the grippers' poses and what the arms report, and
publishes what it returns: the command for the arm driver and the status for the coordinator.

    runs = ServoRuns(next_seq, rig.safety.watchdog_s)           # what both hosts hold across runs
    outs = runs.tick(run_state, path, goal, False, soi, soi_age_s, soi_max_age_s, states, None, now)
    runs.servoing(run_id)                                       # a keep-alive tick is due while this holds

    s, out = ServoSession.build(run_state, path, goal, next_seq, rig.safety.watchdog_s)  # a finished s: out says why
    out = s.tick_on(soi, soi_age_s, soi_max_age_s, states, None, path, goal, now)  # out.command, out.status
    out = s.end("run aborted", now)                                           # one hold, then nothing

`ServoRuns.tick` is the one glue both hosts call at a control tick: the session of a run that ended
(or on an e-stop) ends with one hold, a run's session is built once its path is in, and `tick_on`
goes from the arms' states (and why they cannot be used, if a host judged them stale) to the
grippers, a latched fault, the motion in flight and the slow-down, then `tick`.

It never extrapolates: a stale SOI (`soi_max_age_s`), missing or stale arm states -> a hold
command (u = 0) with the reason. A latched arm fault ends the run (it will not clear by itself).
Each new SOI is one control tick. A tick on the same SOI again (a host that ticks faster than the
camera) learns nothing and moves nothing: while servoing it sends a zero increment, a keep-alive,
so the driver goes on streaming the last targets instead of its watchdog braking the arms between
two slow SOIs (stop-and-go); a controller that dies still stops them. Any exception in the
controller -> hold with the reason.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bagit.common.dual_arm import pose_increment
from bagit.common.geometry import pose_to_matrix
from bagit.common.messages import ArmState, Command, ControllerStatus, Goal, Path, RunState, SoiState
from bagit.common.names import ACTIVE_STAGES, DEFAULT_CONTROLLER
from bagit.common.params import MethodParams, merge_params
from bagit.common.rig import ARMS, ArmName
from bagit.common.scenario import Scenario
from bagit.services.controller.controller import Controller, make_controller

# A command's dt (the time the driver spreads its increment over) stays this far under the arm
# driver's watchdog (`SafetyLimits.watchdog_s`), so a slow SOI gives slower motion, never a stop.
WATCHDOG_MARGIN = 0.9
# While servoing a command goes out at least every KEEPALIVE_SHARE of the watchdog (at the control
# rate, and keep-alives between slower control ticks): the watchdog halts the arms after a gap of at
# least 3/4 of it (`SafetyLimits.halt_gap_s`), so one late or lost command never stops them.
KEEPALIVE_SHARE = 1 / 3
KEEPALIVE = "keep-alive: no new SOI yet"  # the reason a zero servo increment carries
SOI_MAX_AGE_S = 0.5  # a SOI older than this (by its camera stamp): hold
ARM_MAX_AGE_S = 0.3  # an arm state older than this: hold


def tick_period(rate_hz: float, watchdog_s: float) -> float:
    """How often a host ticks a session at control rate `rate_hz` (`ServoSession.tick_s`): the control
    period, or the keep-alive pace (KEEPALIVE_SHARE of the rig's watchdog, `SafetyLimits.watchdog_s`)
    when that is shorter. A lockstep
    simulator schedules keep-alive ticks at this pace between sparser camera frames (`Schedule`)."""
    return min(1.0 / rate_hz, KEEPALIVE_SHARE * watchdog_s)


def _finite_or_none(v: float | None) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


@dataclass
class Outbox:
    """What a session asks its host to send: a command, a status, a line for the operator's log."""

    command: Command | None = None
    status: ControllerStatus | None = None
    report: str | None = None
    keepalive: bool = False  # the command is a zero increment on an SOI already acted on


def gripper_poses(states: dict[ArmName, ArmState]) -> tuple[dict[ArmName, np.ndarray] | None, str | None]:
    """Both grippers' 4x4 world poses from the arms' states (tool_pose: world [x y z roll pitch yaw]),
    or why they cannot be used."""
    out = {}
    for a in ARMS:
        msg = states.get(a)
        if msg is None:
            return None, f"no state from the {a} arm"
        if msg.estopped:
            return None, f"the {a} arm is e-stopped"
        p = np.asarray(msg.tool_pose, dtype=float)
        if p.shape != (6,) or not np.all(np.isfinite(p)):
            return None, f"the {a} arm's tool pose is not 6 finite numbers"
        out[a] = pose_to_matrix(p[:3], p[3:])
    return out, None


def pending_motion(states: dict[ArmName, ArmState], grippers: dict[ArmName, np.ndarray] | None) -> np.ndarray | None:
    """The motion `(12,)` (the controller's u: world [dp, drotvec] left then right) the arm side has
    taken and not yet made: from each gripper's measured pose to the arm side's `target_pose`. None
    when an arm does not report one (the controller then predicts from the measured poses alone)."""
    if grippers is None:
        return None
    aims = {}
    for a in ARMS:
        msg = states.get(a)
        t = None if msg is None or msg.target_pose is None else np.asarray(msg.target_pose, dtype=float)
        if t is None or t.shape != (6,) or not np.all(np.isfinite(t)):
            return None
        aims[a] = pose_to_matrix(t[:3], t[3:])
    return pose_increment(grippers, aims)


def arms_slowed(states: dict[ArmName, ArmState]) -> bool:
    """The arm side reports that its last step was cut short: the joints could not follow it."""
    return any(msg is not None and msg.slowed for msg in states.values())


def arm_fault(states: dict[ArmName, ArmState]) -> str | None:
    """An arm reporting an error other than a lost link (which the driver reconnects by itself)."""
    for a in ARMS:
        msg = states.get(a)
        if msg is not None and msg.error and not (msg.error_reason or "").startswith("link lost"):
            return f"the {a} arm reports an error: {msg.error_reason or 'unknown'}"
    return None


class ServoSession:
    """One run being servoed (see the module docstring)."""

    def __init__(self, run_id: str | None, name: str, controller: Controller | None, params: MethodParams,
                 rate_hz: float, next_seq: Callable[[], int], watchdog_s: float):
        self.run_id = run_id
        self.name = name
        self.controller = controller
        self.params = params
        self.dt = 1.0 / rate_hz
        self.dt_max = max(WATCHDOG_MARGIN * watchdog_s, self.dt)
        self.keepalive_s = KEEPALIVE_SHARE * watchdog_s
        self.tick_s = tick_period(rate_hz, watchdog_s)  # how often the host ticks it (most ticks keep-alives when the rate is slower)
        self.next_seq = next_seq
        self.seq = 0  # the last command's
        self.last_soi: tuple[int, float] | None = None  # (seq, source stamp) of the last SOI acted on
        self.last_cmd_t: float | None = None  # when the last command on a new SOI went out
        self.servoing = False  # the last command on a new SOI moved the arms (a keep-alive may follow it)
        self.reset_done = False
        self.finished: str | None = None  # why servoing ended (done, the run's stage, e-stop)
        self.last_reason: str | None = None
        self.ticks = 0
        self.error_to_goal: float | None = None
        self.final_soi: np.ndarray | None = None  # (n_x, 3) the SOI of the last tick

    # -- building ----------------------------------------------------------------------------------

    @classmethod
    def build(cls, state: RunState, path: Path, goal: Goal | None, next_seq: Callable[[], int],
              watchdog_s: float) -> tuple[ServoSession, Outbox]:
        """The run's session from its run state and path: its controller (the run's choice), its params
        (the scenario's with the run's on top, the control rate among them) and the rig's watchdog
        (`SafetyLimits.watchdog_s`); a finished one whose outbox says why when it cannot be built."""
        if not path.success:
            why = f"the planner found no path for run {state.run_id}"
            return cls._finished(state.run_id, why, next_seq, watchdog_s), Outbox(status=ControllerStatus(run_id=state.run_id, reason=why))
        try:
            base = Scenario.model_validate(state.scenario_doc).params if state.scenario_doc is not None else MethodParams()
            params = merge_params(base, state.params)
            name = state.controller or DEFAULT_CONTROLLER
            rate = params.controller.control_rate_hz
            nodes = np.asarray(path.nodes, dtype=float)
            ctrl = make_controller(name, params, nodes.shape[1])
        except Exception as e:  # noqa: BLE001 - a bad run must not take the host down
            reason = f"cannot build the controller for run {state.run_id}: {type(e).__name__}: {str(e).splitlines()[0]}"
            return cls._finished(state.run_id, reason, next_seq, watchdog_s), Outbox(status=ControllerStatus(run_id=state.run_id, reason=reason), report=reason)
        note = f"run {state.run_id}: {name} at {rate:g} Hz on a path of {len(nodes)} nodes (g† at {path.dagger_index})"
        return cls(state.run_id, name, ctrl, params, rate, next_seq, watchdog_s), Outbox(report=note)

    @classmethod
    def _finished(cls, run_id: str | None, why: str, next_seq: Callable[[], int], watchdog_s: float) -> ServoSession:
        """A run that is never servoed (no path, or no controller): the reason is told once, not every tick."""
        s = cls(run_id, "none", None, MethodParams(), MethodParams().controller.control_rate_hz, next_seq, watchdog_s)
        s.finished = why
        return s

    # -- one tick ----------------------------------------------------------------------------------

    def tick_on(self, soi: SoiState | None, soi_age_s: float | None, soi_max_age_s: float, states: dict[ArmName, ArmState],
                states_problem: str | None, path: Path, goal: Goal | None, now: float) -> Outbox:
        """A control tick on the arms' `states` as a host has them (`states_problem`: why they cannot be used,
        e.g. stale; None: fresh): what both hosts, `bagit run` and the controller node, do around `tick`."""
        grippers, problem = (None, states_problem) if states_problem else gripper_poses(states)
        fault = arm_fault(states) if problem is None else None
        pending = pending_motion(states, grippers) if problem is None else None
        slowed = problem is None and arms_slowed(states)
        return self.tick(soi, soi_age_s, soi_max_age_s, grippers, problem, fault, path, goal, now, pending, slowed)

    def tick(self, soi: SoiState | None, soi_age_s: float | None, soi_max_age_s: float, grippers: dict[ArmName, np.ndarray] | None,
             arm_problem: str | None, arm_fault: str | None, path: Path, goal: Goal | None, now: float,
             pending: np.ndarray | None = None, slowed: bool = False) -> Outbox:
        """The newest SOI (None: none yet) `soi_age_s` old, the grippers' poses (or why there are none),
        a latched arm fault, the motion `pending (12,)` still in flight on the arm side (None: unknown,
        see `pending_motion`) and whether the arm side is `slowed` (`arms_slowed`): the command and
        status for this tick (an empty outbox: nothing new)."""
        if self.finished is not None or self.controller is None:
            return Outbox()
        if soi is None:
            return self.hold("no SOI received", now, forget=True)
        if soi_age_s is not None and soi_age_s > soi_max_age_s:
            return self.hold(f"SOI is stale ({soi_age_s:.2f} s old, limit {soi_max_age_s:g} s)", now, forget=True)
        if arm_problem is not None or grippers is None:
            return self.hold(arm_problem or "no arm state", now, forget=True)
        if arm_fault is not None:
            out = self.end(arm_fault, now)
            out.status = self._status(mode="hold", stage="failed", reason=arm_fault)
            return out
        key = (soi.seq, soi.source_stamp)
        if key == self.last_soi or not self.control_due(now):  # nothing new to act on yet: keep the stream alive
            if not self.servoing:
                return Outbox()
            self.seq = self.next_seq()
            cmd = Command(u=np.zeros(12), dt=self.dt, seq=self.seq, run_id=self.run_id, reason=KEEPALIVE, source_stamp=soi.source_stamp,
                          stamp=now)
            return Outbox(cmd, keepalive=True)
        self.last_soi = key
        c = self.controller
        report = None
        x = np.asarray(soi.rim, dtype=float)
        try:
            if not self.reset_done:
                perimeter = goal.perimeter if goal is not None and goal.perimeter > 0 else None
                c.reset(x, path, grippers, perimeter=perimeter, goal=goal)
                self.reset_done = True
            ctl = c.step(x, now, grippers, pending=pending, slowed=slowed)
        except Exception as e:  # noqa: BLE001 - LinAlgError, a solver failure, a bad input: hold and say so
            return self.hold(f"controller error: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}", now)
        self.ticks = c.ticks
        self.final_soi = x
        self.error_to_goal = _finite_or_none(ctl.error_to_goal)
        self.seq = self.next_seq()
        cmd = ctl.to_command(self.command_dt(now), seq=self.seq, run_id=self.run_id, source_stamp=soi.source_stamp, stamp=now)
        self.servoing = cmd.mode == "servo" and not ctl.done
        self.last_reason = ctl.reason
        status = self._status(mode=ctl.mode, stage=ctl.stage, reason=ctl.reason, subgoal_index=ctl.subgoal_index,
                              progress=ctl.progress, error_to_subgoal=_finite_or_none(ctl.error_to_subgoal),
                              error_to_goal=self.error_to_goal, solve_ms=ctl.solve_ms, done=ctl.done, ticks=self.ticks)
        if ctl.done:
            self.finished = "done"
            report = f"run {self.run_id}: at g* (error {ctl.error_to_goal * 1000:.1f} mm after {c.ticks} ticks)"
        return Outbox(cmd, status, report)

    def control_due(self, now: float) -> bool:
        """A new SOI may be acted on at `now`: always when the host ticks at the control rate; with a
        control rate slower than the keep-alive pace, a control period after the last control tick."""
        if self.dt <= self.keepalive_s or self.last_cmd_t is None:
            return True
        return now - self.last_cmd_t >= self.dt - 0.5 * self.tick_s

    def command_dt(self, now: float) -> float:
        """Over how long the driver spreads this increment: the time since the last command (a tick
        comes with each new SOI, so a slow camera gives longer, slower steps rather than a dash and a
        stop), at least the control period and at most `dt_max`, under the driver's watchdog. u is
        bounded per tick (C7 at the control rate), so a longer dt only ever means slower."""
        last, self.last_cmd_t = self.last_cmd_t, now
        if last is None:
            return self.dt
        return float(min(max(now - last, self.dt), self.dt_max))

    # -- holding -----------------------------------------------------------------------------------

    def hold(self, reason: str, now: float, forget: bool = False) -> Outbox:
        """A hold command (u = 0) with the reason, and the status saying so; `forget`: the controller
        also forgets the gap (no learning across it)."""
        if forget and self.reset_done and self.controller is not None:
            try:
                self.controller.step(None, now, {})
            except Exception:  # noqa: BLE001
                pass
        self.servoing = False
        self.seq = self.next_seq()
        cmd = Command(u=np.zeros(12), dt=self.dt, seq=self.seq, run_id=self.run_id, mode="hold", reason=reason, stamp=now)
        report = f"hold: {reason}" if reason != self.last_reason else None
        self.last_reason = reason
        return Outbox(cmd, self._status(mode="hold", reason=reason), report)

    def end(self, why: str, now: float) -> Outbox:
        """Servoing ends (the run ended, a new one began, an e-stop, a fault): one hold, then nothing."""
        self.finished = why
        return self.hold(why, now)

    def _status(self, **kw: Any) -> ControllerStatus:
        """A status; a hold's carries where the run is on its path (the tracker's stage and progress),
        not the message's defaults, so a hold during bagging never reads as pre-bagging."""
        tracker = getattr(self.controller, "tracker", None)
        if tracker is not None:
            kw.setdefault("stage", tracker.stage)
            kw.setdefault("progress", tracker.progress())
            kw.setdefault("subgoal_index", tracker.index)
        return ControllerStatus(run_id=self.run_id, seq=self.seq, controller=self.name if self.controller is not None else DEFAULT_CONTROLLER, **kw)


class ServoRuns:
    """The control tick around the session, written once for both hosts (`bagit run`'s loop, the controller
    node in lockstep or on the wall clock): which run is servoed, when its session is built and when it ends.
    Pure: the host hands it what it has heard (run state, path, goal, e-stop, SOI, arm states) and `now`, and
    sends what it returns, in order."""

    def __init__(self, next_seq: Callable[[], int], watchdog_s: float) -> None:
        """`watchdog_s`: the rig's (`SafetyLimits.watchdog_s`), which the arm driver enforces."""
        self.next_seq = next_seq
        self.watchdog_s = watchdog_s
        self.session: ServoSession | None = None
        self.runs = 0  # sessions built with a controller
        self.ticks = 0  # ticks of a session (control ticks, keep-alives and holds)

    def servoing(self, run_id: str | None) -> bool:
        """Run `run_id` is being servoed: a keep-alive tick between sparse frames is due on it."""
        s = self.session
        return s is not None and s.finished is None and s.run_id == run_id

    def end(self, why: str, now: float) -> list[Outbox]:
        """Servoing stops (the host closes, say): one hold if a run was being servoed."""
        s = self.session
        return [s.end(why, now)] if s is not None and s.finished is None else []

    def tick(self, state: RunState | None, path: Path | None, goal: Goal | None, estop: bool, soi: SoiState | None,
             soi_age_s: float | None, soi_max_age_s: float, states: dict[ArmName, ArmState], states_problem: str | None,
             now: float) -> list[Outbox]:
        """One control tick at `now` on the run `state` (its `path` and `goal`: None until heard): a run that ended,
        a new run or an e-stop -> one hold and no more servoing; a run in an active stage with its path -> its
        session (built on the first tick), ticked on the newest SOI and the arms' `states` (see `ServoSession.tick_on`)."""
        out: list[Outbox] = []
        s = self.session
        if s is not None and s.finished is None:
            why = None
            if estop:
                why = "e-stop engaged"
            elif state is None or state.run_id != s.run_id:
                why = "a new run started" if state is not None else "no run state"
            elif state.stage not in ACTIVE_STAGES:
                why = f"run {state.stage}" + (f": {state.reason}" if state.reason else "")
            if why is not None:
                out.append(s.end(why, now))
        if s is not None and (state is None or state.run_id != s.run_id):
            self.session = s = None
        if estop or state is None or state.stage not in ACTIVE_STAGES or path is None:
            return out
        if s is None:
            s, built = ServoSession.build(state, path, goal, self.next_seq, self.watchdog_s)
            self.session = s
            self.runs += s.controller is not None
            out.append(built)
        if s.finished is None:
            self.ticks += 1
            out.append(s.tick_on(soi, soi_age_s, soi_max_age_s, states, states_problem, path, goal, now))
        return out
