"""The shape-servoing controllers behind one interface: `mpc` (the paper's), `ibvs`, `ssvs`.

Each tick: the guard vets the SOI; the Broyden estimate learns from the last input and the SOI change
it caused; the subgoal tracker picks g_next on the path (ssvs aims straight at g*); the control law
gives u (12,) inside C7. A run starts with a short exploration of every input direction to seed J.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common.params import MethodParams
from bagit.services.controller.broyden import BroydenJacobian, jacobian_from_exploration
from bagit.services.controller.guard import SoiGuard
from bagit.services.controller.mpc import MpcSolver
from bagit.services.controller.subgoal import SubgoalTracker, rms_error, slide_to

CONTROLLERS = ("mpc", "ibvs", "ssvs")
IBVS_GAIN = 0.5
EXPLORE_TICKS = 4  # ticks each exploratory push lasts (at the C7 limit)
EXPLORE_SETTLE_TICKS = 2
BROYDEN_WINDOW = 5  # ticks of input and SOI change summed per Broyden update
SEPARATION_MARGIN = 0.9  # the grippers stay within this share of the rim's half perimeter apart


@dataclass
class ControlOutput:
    u: np.ndarray  # (12,)
    mode: str  # 'explore' | 'servo' | 'hold' | 'done'
    reason: str | None
    subgoal_index: int
    stage: str
    error_to_subgoal: float
    error_to_goal: float
    solve_ms: float
    done: bool


class ShapeServo:
    """One run's controller state. path: (n_nodes, n_x, 3) with g† at dagger_index and g* last."""

    def __init__(self, kind: str, params: MethodParams, path: np.ndarray, dagger_index: int, perimeter: float):
        if kind not in CONTROLLERS:
            raise ValueError(f"unknown controller {kind!r}; choose from {CONTROLLERS}")
        self.kind = kind
        self.p = params
        self.path = np.asarray(path, dtype=float)
        self.n_x = self.path.shape[1]
        self.dt = 1.0 / params.control_rate_hz
        lin, ang = params.max_linear_speed_mps * self.dt, params.max_angular_speed_rps * self.dt
        self.u_max = np.array([lin] * 3 + [ang] * 3 + [lin] * 3 + [ang] * 3)
        self.tracker = SubgoalTracker(self.path, dagger_index, params.subgoal_tol_m, params.goal_tol_m)
        self.guard = SoiGuard(timeout_s=max(3 * self.dt, 0.2), max_age_s=max(5 * self.dt, 0.3))
        self.mpc = MpcSolver(params.horizon, params.q_weight, params.r_weight)
        self.sep_limits = (0.06, SEPARATION_MARGIN * perimeter / 2)
        # Exploration: each input direction driven at its limit for EXPLORE_TICKS ticks, held, then
        # driven back; the SOI change over the whole push gives J's column above the camera's noise.
        self._explore = self._exploration_schedule()
        self._explore_u: list[np.ndarray] = []
        self._explore_s: list[np.ndarray] = []
        self._push_u = np.zeros(12)
        self._push_x0: np.ndarray | None = None
        self._win_u = np.zeros(12)
        self._win_s = np.zeros(3 * self.n_x)
        self._win_n = 0
        self.jacobian: BroydenJacobian | None = None
        self._x_prev: np.ndarray | None = None
        self._u_prev: np.ndarray | None = None

    def step(self, x: np.ndarray | None, now: float, grippers: dict[str, np.ndarray], source_stamp: float | None = None) -> ControlOutput:
        """u for this tick from the SOI `x (n_x, 3)` (None if none arrived) and the grippers' poses (4x4, world)."""
        reason = self.guard.check(x, now, source_stamp)
        if reason is not None:
            self._x_prev = None  # never learn across a gap
            return self._out(np.zeros(12), "hold", reason, x)
        x = np.asarray(x, dtype=float)
        xf = x.ravel()
        if self._x_prev is not None and self._u_prev is not None and self.jacobian is not None:
            # Broyden on windows of BROYDEN_WINDOW ticks: a tick's SOI change is mostly camera noise.
            self._win_u += self._u_prev
            self._win_s += xf - self._x_prev
            self._win_n += 1
            if self._win_n >= BROYDEN_WINDOW:
                self.jacobian.update(self._win_u, self._win_s)
                self._win_u[:], self._win_s[:], self._win_n = 0.0, 0.0, 0
        self._x_prev = xf
        if self.jacobian is None:
            if self._explore:
                u, mark = self._explore.pop(0)
                if mark == "start":
                    self._push_x0, self._push_u = xf.copy(), np.zeros(12)
                elif mark == "measure" and self._push_x0 is not None:
                    self._explore_u.append(self._push_u.copy())
                    self._explore_s.append(xf - self._push_x0)
                    self._push_x0, self._push_u = xf.copy(), np.zeros(12)
                self._push_u += u
                self._u_prev = u
                return self._out(u, "explore", None, x)
            J0 = jacobian_from_exploration(np.asarray(self._explore_u), np.asarray(self._explore_s))
            self.jacobian = BroydenJacobian(J0, self.p.epsilon)
        idx = self.tracker.update(x)
        finished = self.tracker.error(x, len(self.path) - 1) <= self.p.goal_tol_m if self.kind == "ssvs" else self.tracker.done(x)
        if finished:
            self._u_prev = np.zeros(12)
            return self._out(np.zeros(12), "done", None, x, done=True)
        target = slide_to(self.path[-1] if self.kind == "ssvs" else self.path[idx], x)
        J = self.jacobian.J
        solve_ms = 0.0
        if self.kind == "mpc":
            pl, pr = grippers["left"][:3, 3], grippers["right"][:3, 3]
            sep = float(np.linalg.norm(pr - pl))
            axis = (pr - pl) / max(sep, 1e-9)
            sol = self.mpc.solve(J, xf, target.ravel(), self.u_max, axis, sep, self.sep_limits)
            u, solve_ms = sol.u, sol.solve_ms
        else:  # ibvs / ssvs: u = -lambda J^+ e, clipped to C7
            e = xf - target.ravel()
            u = -IBVS_GAIN * np.linalg.lstsq(J, e, rcond=1e-6)[0]
            u = np.clip(u, -self.u_max, self.u_max)
        self._u_prev = u
        out = self._out(u, "servo", None, x)
        out.solve_ms = solve_ms
        return out

    def _exploration_schedule(self) -> list[tuple[np.ndarray, str]]:
        """(u, mark) per tick: for each direction, EXPLORE_TICKS out, hold, EXPLORE_TICKS back, hold;
        'start' and 'measure' mark where a push's SOI change is taken."""
        sched: list[tuple[np.ndarray, str]] = []
        for i in range(12):
            e = np.zeros(12)
            e[i] = self.u_max[i]
            for sign in (1.0, -1.0):
                sched.append((np.zeros(12), "start" if sign > 0 and i == 0 else "measure" if sign > 0 else "measure"))
                sched += [(sign * e, "")] * EXPLORE_TICKS
                sched += [(np.zeros(12), "")] * EXPLORE_SETTLE_TICKS
        sched.append((np.zeros(12), "measure"))
        return sched

    def _out(self, u: np.ndarray, mode: str, reason: str | None, x: np.ndarray | None, done: bool = False) -> ControlOutput:
        idx = self.tracker.index
        ok = x is not None and np.all(np.isfinite(x))
        e_sub = self.tracker.error(x, idx) if ok else float("nan")
        e_goal = self.tracker.error(x, len(self.path) - 1) if ok else float("nan")
        if mode == "hold":
            self._u_prev = np.zeros(12)
        return ControlOutput(np.asarray(u, dtype=float), mode, reason, idx, self.tracker.stage, e_sub, e_goal, 0.0, done)
