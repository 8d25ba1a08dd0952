"""BimaManip (Zhou et al., arXiv 2401.11432) as a controller of the one run path: MPC through a learned
graph-network model of the SOI's dynamics (services/controller/soi_gnn.py), trained in the simulator
(`bagit bench bimamanip --train`), commanding the same pose increments as every controller.

The method servos the SOI towards goal shapes, with no planned path between them: here the goal
shapes are the ones the harness gives every controller, g† (the rim open under the object) and then
g* (the rim round it at the goal height); the planner's nodes in between are not used. Every
MODEL_TICKS ticks the MPC plans MPC_HORIZON model steps of both grippers' translations by projected
gradient descent (Adam, clipped into C7) through the model from where the SOI will be once the motion still in flight has
been made (the arms lag their commands by 4-6 ticks), then streams the plan's first step over the
next MODEL_TICKS ticks within C7. Its cost: the predicted SOI's distance to the goal shape (slid
along itself to match, as SOI points have no material identity), the motion, and the grippers'
separation leaving C6. Orientation is held (the model was trained on translations only).

g† and g* are tracked as the shape servos track their path (SubgoalTracker: g† reached, the bag
settles, then g*; done at g* within goal_tol or stalled within 2x subgoal_tol). JAX is imported when a
run starts (reset), never with this module: `bagit up`'s fork server preloads the controller package.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.common.dual_arm import Poses
from bagit.common.errors import BadControlInput
from bagit.common.params import MethodParams
from bagit.services.controller.servo import (
    GOAL_STALL_TICKS,
    ControllerCore,
    ControlOutput,
    pose_problem,
    scale_into_box,
)
from bagit.services.controller.subgoal import SubgoalTracker, slide_to

MPC_HORIZON = 5  # model steps planned ahead (5/6 s at MODEL_TICKS = 5, 30 Hz)
MPC_ITERATIONS = 30  # Adam steps on the action sequence per plan
MODEL_TICKS = 5  # ticks per model step: soi_gnn.MODEL_TICKS (checked when the model loads; JAX stays out of this module)

log = logging.getLogger("bagit.controller")

_PLANNERS: dict[tuple[str, int, int, float], Any] = {}  # one jitted planner per process and setting: JAX compiles once


def planner(weights: Path | None, horizon: int, iterations: int, a_max: float) -> Any:
    """The jitted MPC through the saved model (soi_gnn.make_planner), loaded and compiled once per process;
    BadControlInput when JAX (the `learn` extra) or the weights are missing."""
    try:
        from bagit.services.controller import soi_gnn
    except ImportError as e:
        raise BadControlInput(f"bimamanip needs JAX and Equinox: pip install 'bagit[learn]' ({e})") from None
    if soi_gnn.MODEL_TICKS != MODEL_TICKS:
        raise BadControlInput(f"the model's step is {soi_gnn.MODEL_TICKS} ticks, the controller's {MODEL_TICKS}")
    path = weights or soi_gnn.WEIGHTS_FILE
    key = (str(path), horizon, iterations, a_max)
    if key not in _PLANNERS:
        try:
            model = soi_gnn.load(path, path.with_suffix(".json"))
        except (OSError, ValueError, KeyError) as e:
            raise BadControlInput(f"no BimaManip model at {path} ({e}); make one with `bagit bench bimamanip --train`") from None
        _PLANNERS[key] = soi_gnn.make_planner(model, horizon, iterations, a_max)
    return _PLANNERS[key]


def within_reach(goal: np.ndarray, x: np.ndarray, reach: float) -> np.ndarray:
    """The goal shape `(n_x, 3)` moved back towards the SOI `x (n_x, 3)` until its centroid is at most `reach` (m)
    from x's: the MPC's reference over one horizon. Aimed at a goal many horizons away, every motion that shrinks
    the large error a little looks alike, and the model's small errors in how a sideways motion moves the rim
    decide the plan: the grippers swing from one bound of C7 to the other on the axes that should stay still."""
    d = goal.mean(axis=0) - x.mean(axis=0)
    n = float(np.linalg.norm(d))
    return goal if n <= reach else goal - (1.0 - reach / n) * d


class BimaManipController(ControllerCore):
    """See the module docstring. Satisfies `Controller`: `reset` once per run, `step` every tick."""

    name = "bimamanip"

    def __init__(self, params: MethodParams, n_x: int, *, horizon: int = MPC_HORIZON, iterations: int = MPC_ITERATIONS,
                 weights: Path | None = None):
        super().__init__(params, n_x)
        self.horizon = horizon
        self.iterations = iterations
        self.weights = weights
        self.a_max = MODEL_TICKS * float(self.u_max[0])  # a gripper's largest translation per axis over one model step
        self.tracker: SubgoalTracker | None = None

    def reset(self, x0: np.ndarray | None, path: Any, gripper_poses: Poses | None, dagger_index: int | None = None,
              perimeter: float | None = None, goal: Any = None) -> None:
        """Start a run: the goal shapes g† and g* from `path`; the model loaded (and compiled) on the first run."""
        nodes, dagger = self._nodes(path, dagger_index)
        c = self.p.controller
        settle = int(round(c.experimental.dagger_settle_s * c.control_rate_hz))
        goals = nodes[[0, dagger, len(nodes) - 1]]  # the start, then the two goal shapes (the tracker's first target is index 1)
        self.tracker = SubgoalTracker(goals, 1, c.subgoal_tol_m, c.goal_tol_m, GOAL_STALL_TICKS, settle)
        self.dagger_index, self.last_index = dagger, len(nodes) - 1
        self._start_rim(x0, nodes, perimeter)
        self.plan = planner(self.weights, self.horizon, self.iterations, self.a_max)
        self.planned = np.zeros((self.horizon, 2, 3))  # the last plan's actions, the next plan's warm start
        self.action = np.zeros((2, 3))  # the model step being streamed: each gripper's translation (m)
        self.left = 0  # ticks of it still to stream
        self.ticks = 0

    def step(self, x: np.ndarray | None, now: float, gripper_poses: Poses, source_stamp: float | None = None,
             pending: np.ndarray | None = None, slowed: bool = False) -> ControlOutput:
        """This tick's increment `u (12,)` (translations only) from the SOI `x (n_x, 3)`, the grippers' poses
        and the motion `pending (12,)` in flight (ignored when `slowed`: it is not coming)."""
        tracker = self.tracker
        if tracker is None:
            raise BadControlInput("step() before reset(): the controller has no goal")
        self.ticks += 1
        reason = self.guard.check(x, now, source_stamp) or pose_problem(gripper_poses)
        if reason is not None:
            self.left = 0  # plan afresh from the next valid view
            shaped = x is not None and np.shape(x) == (self.n_x, 3)
            return self._out(np.zeros(12), "hold", reason, np.asarray(x, dtype=float) if shaped else None)
        x = np.asarray(x, dtype=float)
        tracker.update(x)
        if tracker.done(x):
            return self._out(np.zeros(12), "done", None, x, done=True)
        if tracker.settling:
            self.left = 0
            return self._out(np.zeros(12), "settle", None, x)
        solve_ms = 0.0
        if self.left == 0:
            t0 = time.perf_counter()
            self._replan(x, gripper_poses, None if slowed else pending, tracker.path[tracker.index])
            solve_ms = (time.perf_counter() - t0) * 1e3
        u = np.zeros(12)
        u[0:3], u[6:9] = self.action / MODEL_TICKS
        self.left -= 1
        if not np.all(np.isfinite(u)):
            self.left = 0
            return self._out(np.zeros(12), "hold", "the bimamanip MPC gave a non-finite input", x)
        out = self._out(scale_into_box(u, self.u_max), "servo", None, x)
        out.solve_ms = solve_ms
        return out

    def _replan(self, x: np.ndarray, grippers: Poses, pending: np.ndarray | None, goal: np.ndarray) -> None:
        """A new action sequence from the SOI `x (n_x, 3)` towards `goal (n_x, 3)`, warm-started from the last one shifted by a step."""
        g = np.stack([np.asarray(grippers[a], dtype=float)[:3, 3] for a in ("left", "right")])
        p = np.zeros((2, 3))
        if pending is not None and np.shape(pending) == (12,) and np.all(np.isfinite(pending)):
            p = np.clip(np.stack([pending[0:3], pending[6:9]]), -self.a_max, self.a_max)
        a0 = np.concatenate([self.planned[1:], self.planned[-1:]])
        target = within_reach(slide_to(goal, x), x, self.horizon * self.a_max)
        acts, _ = self.plan(x, g, p, target, a0, *self.sep_limits)
        self.planned = np.asarray(acts, dtype=float)
        self.action = self.planned[0]
        self.left = MODEL_TICKS

    def _out(self, u: np.ndarray, mode: Any, reason: str | None, x: np.ndarray | None, done: bool = False) -> ControlOutput:
        tr = self.tracker
        assert tr is not None
        ok = x is not None and bool(np.all(np.isfinite(x)))
        e_sub = tr.error(x, tr.index) if ok and x is not None else float("nan")
        e_goal = tr.error(x, 2) if ok and x is not None else float("nan")
        index = self.last_index if done or tr.index == 2 else self.dagger_index
        progress = 1.0 if done else (0.5 if tr.index == 2 else 0.0)
        return ControlOutput(np.asarray(u, dtype=float), mode, reason, index, tr.stage, e_sub, e_goal, 0.0, done, progress)
