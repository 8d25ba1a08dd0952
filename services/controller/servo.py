"""What every shape-servoing controller does each tick, whatever its control law.

A tick: the guard vets the SOI (missing, stale, implausible -> zero input and the reason); the
Broyden estimate learns from the grippers' measured motion and the SOI change it caused (not from
the inputs sent: an arm driver slows, clips or drops commands, and J must not learn that the rim
ignored a motion that never happened); at the start of a run the exploration seeds J; the subgoal
tracker picks g_next on the path; the law (MPC, IBVS, SSVS) gives u (12,), which never leaves C7.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from bagit.common.dual_arm import ROTATION, DualArmIncrement, apply_increment, pose_increment
from bagit.common.errors import BadControlInput, NumericalFailure
from bagit.common.geometry import closed_polyline_length, enclosure
from bagit.common.messages import Command
from bagit.common.names import ServoMode
from bagit.common.params import MethodParams
from bagit.common.rig import ARMS, ArmName
from bagit.common.so3 import rotvec_between
from bagit.services.controller.broyden import TURN_SEEN, BroydenJacobian, Exploration, rigid_pair_motions, rigid_pair_response
from bagit.services.controller.guard import SoiGuard
from bagit.services.controller.subgoal import SubgoalTracker, slide_to

EXPLORE_PUSH_TICKS = 4  # ticks each exploratory push lasts (at the C7 limit)
EXPLORE_SETTLE_TICKS = 2  # ticks held after each push before its SOI change is measured
BROYDEN_WINDOW = 5  # ticks of input and SOI change summed per Broyden update: one tick is mostly noise
SEPARATION_MARGIN = 0.9  # C6: the grippers stay within this share of the rim's half perimeter apart
MIN_SEPARATION_M = 0.06  # C6: the two mounts never come closer than this
TAUT_MARGIN_M = 0.01  # C6: ... nor closer than the subgoal's rim, held taut, needs (less this)
SEP_RECOVER_M = 0.001  # outside the C6 band the grippers head back by at least this per tick
# Broyden's update is in units of each input's C7 limit (see BroydenJacobian), and windows that moved
# less than this share of a full-speed tick are not learnt from.
MIN_SCALED_STEP = 0.5
# When the arm side reports a step its joints could not follow (ArmState.slowed), the direction of the
# motion it still has in flight is barred for this many ticks: the law may not ask for more of it, and
# while the arms stay slowed the input takes it back (see ServoBase._bar_unmade). Traced on the CR5s:
# an arm at its elbow margin stood still for 15 s while the controller, blind to it, asked for the same
# turn every tick and the driver pulled its target back to the lead limit each time.
REACH_BAR_TICKS = 30
MIN_BAR_STEP = 0.5  # motion in flight under half a full-speed tick (in C7 units) names no direction to bar
GOAL_STALL_TICKS = 45  # at g*: no improvement for this long (within 2x subgoal_tol) ends the run
# With `dagger_round_v`, a settle at g† whose end finds V not inside the SOI is void and the servoing to
# g† goes on; after this long since the first void settle, the next settle's end lifts regardless.
DAGGER_ROUND_WAIT_S = 5.0
# What a numerical routine raises on bad data (LinAlgError: e.g. 'SVD did not converge'); a tick that
# meets one holds the arms with the reason.
NUMERIC_ERRORS = (NumericalFailure, np.linalg.LinAlgError, FloatingPointError)


@dataclass
class ControlOutput:
    """One tick's decision. u: (12,) = [left dx dy dz drx dry drz, right ...] (m, rad) for this tick."""

    u: np.ndarray
    mode: ServoMode  # settle: still, at g†
    reason: str | None  # why the arms are held (mode 'hold'), else None
    subgoal_index: int
    stage: str  # 'pre-bagging' before g† is reached, 'bagging' after
    error_to_subgoal: float  # RMS (m), NaN when there is no valid SOI
    error_to_goal: float
    solve_ms: float
    done: bool
    progress: float = 0.0  # subgoal_index / (n_nodes - 1)

    def to_command(self, dt: float, seq: int = 0, run_id: str | None = None, source_stamp: float = 0.0,
                   stamp: float | None = None) -> Command:
        """The wire command: exploration, servoing and settling (u = 0) are 'servo', holding and done are 'hold'.
        `source_stamp`: the camera stamp of the SOI this step was computed from; `stamp`: when it was made
        (the rig's clock; None: this host's)."""
        servo = self.mode in ("explore", "servo", "settle")
        return Command(u=self.u if servo else np.zeros(12), dt=dt, seq=seq, run_id=run_id,
                       mode="servo" if servo else "hold", reason=self.reason, source_stamp=source_stamp,
                       stamp=time.time() if stamp is None else stamp)


def c7_limits(params: MethodParams) -> np.ndarray:
    """C7: the largest |u| per component per tick `(12,)` from the arms' speed limits."""
    c = params.controller
    dt = 1.0 / c.control_rate_hz
    per_arm = np.array([c.max_linear_speed_mps * dt] * 3 + [c.max_angular_speed_rps * dt] * 3)
    return DualArmIncrement(per_arm, per_arm).to_array()


def project_box_halfspace(v: np.ndarray, d: np.ndarray, limit: float, iterations: int = 60) -> np.ndarray:
    """The point of {w : |w_i| <= 1, w·d <= limit} nearest `v (n,)` (`d (n,)` unit, `limit` >= -1: never
    empty): clip(v - λ d) for the smallest λ >= 0 that meets the half-space, found by bisection
    (w·d falls as λ grows)."""
    w = np.clip(v, -1.0, 1.0)
    if float(w @ d) <= limit:
        return w
    lo, hi = 0.0, 1.0
    while float(np.clip(v - hi * d, -1.0, 1.0) @ d) > limit:
        hi *= 2.0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        if float(np.clip(v - mid * d, -1.0, 1.0) @ d) > limit:
            lo = mid
        else:
            hi = mid
    return np.clip(v - hi * d, -1.0, 1.0)


def scale_into_box(u: np.ndarray, u_max: np.ndarray) -> np.ndarray:
    """`u (12,)` shrunk as a whole (direction kept) until every component is within `u_max (12,)`."""
    over = float(np.max(np.abs(u) / u_max))
    return u / over if over > 1.0 else u


def as_path(path: Any, dagger_index: int | None) -> tuple[np.ndarray, int]:
    """Nodes `(n_nodes, n_x, 3)` and g†'s index from a `bagit.common.messages.Path` or an array."""
    if hasattr(path, "nodes") and hasattr(path, "dagger_index"):
        nodes = np.asarray(path.nodes, dtype=float)
        dagger = path.dagger_index if dagger_index is None else dagger_index
    else:
        if dagger_index is None:
            raise BadControlInput("a path given as an array needs dagger_index")
        nodes, dagger = np.asarray(path, dtype=float), dagger_index
    return nodes, int(dagger)


def pose_problem(grippers: Any) -> str | None:
    """None if `grippers` is {'left': 4x4, 'right': 4x4} finite world poses, else what is wrong."""
    try:
        for k in ("left", "right"):
            T = np.asarray(grippers[k], dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                return f"the {k} gripper pose is not a finite 4x4 transform"
    except (KeyError, TypeError, ValueError):
        return "gripper poses must be {'left': 4x4, 'right': 4x4}"
    return None


class ControllerCore:
    """What every controller holds (the shape servos and the primitive methods alike): its parameters,
    n_x, control period and C7; and how each starts a run: the path's nodes checked, a fresh SOI guard."""

    name = "base"

    def __init__(self, params: MethodParams, n_x: int):
        if n_x < 3:
            raise BadControlInput(f"n_x must be at least 3, got {n_x}")
        self.p = params
        self.n_x = n_x
        self.dt = 1.0 / params.controller.control_rate_hz
        self.u_max = c7_limits(params)
        self.ticks = 0

    def _nodes(self, path: Any, dagger_index: int | None) -> tuple[np.ndarray, int]:
        """The path's nodes `(n_nodes, n_x, 3)` and g†'s index (see `as_path`), BadControlInput if misshapen."""
        nodes, dagger = as_path(path, dagger_index)
        if nodes.ndim != 3 or nodes.shape[1:] != (self.n_x, 3):
            raise BadControlInput(f"path nodes must have shape (n_nodes, {self.n_x}, 3), got {nodes.shape}")
        return nodes, dagger

    def _start_rim(self, x0: np.ndarray | None, nodes: np.ndarray, perimeter: float | None, margin: float = SEPARATION_MARGIN) -> None:
        """A run's rim: its perimeter (given, else x0's `(n_x, 3)`, else the path's first node's), C6's
        separation bounds from it, and a fresh SOI guard."""
        if perimeter is None:
            perimeter = closed_polyline_length(x0 if x0 is not None else nodes[0])
        self.perimeter = float(perimeter)
        self.sep_limits = (MIN_SEPARATION_M, margin * self.perimeter / 2)
        self.guard = self._new_guard()

    def _new_guard(self) -> SoiGuard:
        """The SOI guard of a run: no SOI for 3 ticks (at least 0.2 s) or one 5 ticks old (0.3 s) holds."""
        return SoiGuard(timeout_s=max(3 * self.dt, 0.2), max_age_s=max(5 * self.dt, 0.3), n_x=self.n_x)


class ServoBase(ControllerCore):
    """One run's controller state; subclasses give the control law `_law`.

    Use: `reset(x0, path, gripper_poses)` once per run, then `step(x_t, now, gripper_poses)` every
    control tick with the latest SOI (None if none arrived this tick).
    """

    name = "base"
    aims_at_goal = False  # True: servo straight at g* (no path), as SSVS does

    def __init__(
        self,
        params: MethodParams,
        n_x: int,
        *,
        explore_push_ticks: int = EXPLORE_PUSH_TICKS,
        explore_settle_ticks: int = EXPLORE_SETTLE_TICKS,
        broyden_window: int = BROYDEN_WINDOW,
        separation_margin: float = SEPARATION_MARGIN,
    ):
        super().__init__(params, n_x)
        if broyden_window < 1:
            raise BadControlInput(f"broyden_window must be >= 1, got {broyden_window}")
        self.explore_push_ticks = explore_push_ticks
        self.explore_settle_ticks = explore_settle_ticks
        self.broyden_window = broyden_window
        self.separation_margin = separation_margin
        self.tracker: SubgoalTracker | None = None
        self.jacobian: BroydenJacobian | None = None
        self.path = np.zeros((0, n_x, 3))

    # ---- life cycle -------------------------------------------------------------------------

    def reset(
        self,
        x0: np.ndarray | None,
        path: Any,
        gripper_poses: dict[ArmName, np.ndarray] | None,
        dagger_index: int | None = None,
        perimeter: float | None = None,
        goal: Any = None,
    ) -> None:
        """Start a run on `path` (a Path message, or nodes `(n_nodes, n_x, 3)` with `dagger_index`).

        x0 `(n_x, 3)`: the first SOI (its length is the rim perimeter for C6 unless `perimeter` is
        given; without either, the path's first node's). gripper_poses: {'left','right'}: 4x4 world.
        `goal` (the run's Goal) is not needed: the path carries g† and g*.
        """
        nodes, dagger = self._nodes(path, dagger_index)
        if x0 is not None:
            x0 = np.asarray(x0, dtype=float)
            if x0.shape != (self.n_x, 3) or not np.all(np.isfinite(x0)):
                raise BadControlInput(f"x0 must be a finite ({self.n_x}, 3) SOI, got shape {x0.shape}")
        if gripper_poses is not None and (why := pose_problem(gripper_poses)):
            raise BadControlInput(why)
        # a law aiming straight at g* (ssvs) has no g† to settle at
        c = self.p.controller
        settle = 0 if self.aims_at_goal else int(round(c.experimental.dagger_settle_s * c.control_rate_hz))
        self.tracker = SubgoalTracker(nodes, dagger, c.subgoal_tol_m, c.goal_tol_m, GOAL_STALL_TICKS, settle,
                                      dagger_check=self._round_v_check(goal), dagger_wait_ticks=int(round(DAGGER_ROUND_WAIT_S * c.control_rate_hz)))
        self.path = self.tracker.path
        self._start_rim(x0, nodes, perimeter, self.separation_margin)
        if not (np.isfinite(self.perimeter) and self.perimeter > 2 * MIN_SEPARATION_M):
            raise BadControlInput(f"rim perimeter {self.perimeter:.3f} m is too small to servo")
        self.exploration = Exploration(self.u_max, self.explore_push_ticks, self.explore_settle_ticks)
        self.jacobian = None
        self._x_prev: np.ndarray | None = None
        self._poses_prev: dict[ArmName, np.ndarray] | None = None  # the grippers at the last tick with a valid SOI
        self._win_u = np.zeros(12)
        self._win_s = np.zeros(3 * self.n_x)
        self._win_n = 0
        self._goal_best = np.inf
        self._goal_since = 0
        self._sep_offset: float | None = None
        self.ticks = 0
        self._barred: np.ndarray | None = None  # (12,) unit, C7 units: motion the arm side could not make (see _note_reach)
        self._barred_ticks = 0
        self._start_turns: dict[ArmName, np.ndarray] | None = None  # each gripper's rotation (3, 3) at the first tick (see _bound_turn)
        if x0 is not None and gripper_poses is not None:
            self._learn_separation_offset(x0, gripper_poses)
        self._on_reset()

    def _round_v_check(self, goal: Any) -> Callable[[np.ndarray], bool] | None:
        """With `dagger_round_v` and the run's Goal: does an SOI `(n_x, 3)` go round the goal's V (its
        outline seen along the goal frame's z axis; `common.geometry.enclosure`)? None: no check (the
        parameter off, no goal, or a goal without a usable outline)."""
        if goal is None or not self.p.controller.experimental.dagger_round_v:
            return None
        V = np.asarray(getattr(goal, "vertices", np.zeros((0, 3))), dtype=float)
        T = np.asarray(getattr(goal, "frame", np.eye(4)), dtype=float)
        if V.ndim != 2 or V.shape[1:] != (3,) or len(V) < 1 or T.shape != (4, 4) or not (np.all(np.isfinite(V)) and np.all(np.isfinite(T))):
            return None

        def goes_round(x: np.ndarray) -> bool:
            try:
                return bool(enclosure(np.asarray(x, dtype=float).reshape(-1, 3), V, T)[0].min() >= 0.0)
            except ValueError:  # an SOI the guard let through but the outline test cannot use: no say
                return True

        return goes_round

    def _on_reset(self) -> None:
        """Per-run state of the law (e.g. the MPC's solver)."""

    def _law(
        self, J: np.ndarray, x: np.ndarray, target: np.ndarray, grippers: dict[ArmName, np.ndarray]
    ) -> tuple[np.ndarray, float, str | None]:
        """u `(12,)`, solve time (ms) and a reason to hold (None to servo) for SOI `x (3 n_x,)` towards
        `target (3 n_x,)` with the estimate `J (3 n_x, 12)`."""
        raise NotImplementedError

    # ---- one tick ---------------------------------------------------------------------------

    def step(
        self,
        x: np.ndarray | None,
        now: float,
        gripper_poses: dict[ArmName, np.ndarray],
        source_stamp: float | None = None,
        pending: np.ndarray | None = None,
        slowed: bool = False,
    ) -> ControlOutput:
        """u for this tick from the SOI `x (n_x, 3)` (None if none arrived) at time `now` (s) and the
        grippers' poses; `source_stamp`: when the SOI's camera frame was taken (staleness check);
        `pending (12,)`: the motion the arm side has taken and not yet made (None: none known), which
        the law predicts from (see `_predicted`); `slowed`: the arm side could not make its last step
        (its joints), so that motion is not coming and is not asked for again (see `_bar_unmade`)."""
        tracker = self._path_tracker()
        self.ticks += 1
        if self._start_turns is None and gripper_poses and pose_problem(gripper_poses) is None:
            self._start_turns = {a: np.array(gripper_poses[a], dtype=float)[:3, :3] for a in ARMS}
        reason = self.guard.check(x, now, source_stamp) or pose_problem(gripper_poses)
        if reason is not None:
            self._x_prev = None  # never learn across a gap
            shaped = x is not None and np.shape(x) == (self.n_x, 3)
            return self._hold(reason, np.asarray(x, dtype=float) if shaped else None)
        x = np.asarray(x, dtype=float)
        xf = x.ravel()
        if self._sep_offset is None:
            self._learn_separation_offset(x, gripper_poses)
        moved = None if self._poses_prev is None else pose_increment(self._poses_prev, gripper_poses)
        self._poses_prev = {a: np.array(gripper_poses[a], dtype=float) for a in ("left", "right")}
        self._learn(xf, moved)
        self._x_prev = xf
        if self.jacobian is None:
            u = self.exploration.next_input(xf, moved)
            if u is not None:
                return self._out(u, "explore", None, x)
            try:
                J0 = self.exploration.jacobian()
                self.jacobian = BroydenJacobian(J0, self.p.controller.epsilon, min_step=MIN_SCALED_STEP, input_scale=self.u_max)
            except NUMERIC_ERRORS as e:
                return self._hold(f"no Jacobian estimate from the exploration: {e}", x)
            self._pin_rigid(x, gripper_poses)  # J's initial estimate has the rigid model in it
        idx = tracker.update(x)
        if self._finished(x):
            return self._out(np.zeros(12), "done", None, x, done=True)
        if tracker.settling:  # still at g†: the bag settles before the lift
            return self._out(np.zeros(12), "settle", None, x)
        goal = self.path[-1] if self.aims_at_goal else self.path[idx]
        pending = self._valid_pending(pending)
        self._note_reach(pending, slowed)
        try:
            if self.p.controller.jacobian_update != "frozen":  # frozen: J stays its initial estimate
                self._pin_rigid(x, gripper_poses)
            xp, grippers = self._predicted(xf, gripper_poses, None if slowed else pending)
            target = slide_to(goal, xp.reshape(-1, 3)).ravel()
            u, solve_ms, why = self._law(self.jacobian.J, xp, target, grippers)
        except NUMERIC_ERRORS as e:  # hold with the reason; never let a numerical error out of a tick
            return self._hold(f"the {self.name} law failed numerically: {e}", x)
        u = np.asarray(u, dtype=float).ravel()
        if why is None and (u.shape != (12,) or not np.all(np.isfinite(u))):
            why = "the control law gave a non-finite input"
        if why is not None:
            out = self._hold(why, x)
            out.solve_ms = solve_ms
            return out
        u = np.clip(u, -self.u_max, self.u_max)  # C7, whatever the law
        u = self._bar_unmade(u, pending if slowed else None)
        u = self._bound_turn(u, gripper_poses)
        out = self._out(u, "servo", None, x)
        out.solve_ms = solve_ms
        return out

    def _pin_rigid(self, x: np.ndarray, grippers: dict[ArmName, np.ndarray]) -> None:
        """J's rigid motions of the gripper pair set from the rigid model at this SOI `x (n_x, 3)` and these
        grippers (`rigid_pair_response`); the rest of J stays the exploration's and Broyden's."""
        if self.jacobian is None or not self.p.controller.experimental.rigid_pair:
            return
        pl, pr = grippers["left"][:3, 3], grippers["right"][:3, 3]
        turns = self.p.controller.experimental.rigid_pair_turns
        B, R = rigid_pair_motions(pl, pr, turns), rigid_pair_response(x, pl, pr, turns)
        if turns == "measured":  # B's columns: three translations, the line's turn, then the turns across it
            always = 4  # the translations and the line's turn; a turn across it only while not yet measured
            keep = [k for k in range(B.shape[1]) if k < always or self.jacobian.seen(B[:, k]) < TURN_SEEN]
            B, R = B[:, keep], R[:, keep]
        self.jacobian.pin(B, R)

    def _predicted(
        self, xf: np.ndarray, grippers: dict[ArmName, np.ndarray], pending: np.ndarray | None
    ) -> tuple[np.ndarray, dict[ArmName, np.ndarray]]:
        """The SOI `(3 n_x,)` and gripper poses this tick's input will act on: the measured ones moved by
        the motion `pending (12,)` still in flight (x + J p; the grippers at the arm side's aim).

        Why: the CR5s follow a command over 4-6 ticks (the driver's target, Ruckig, the controllers'
        servo loop; measured on the simulated rig), while the paper's model x_{t+1} = x_t + J u_t has
        each input act at once. Predicting from the measured SOI alone, the MPC asks again for motion
        already on its way, saturates C7 and overshoots, then reverses: the rim circles a subgoal."""
        if pending is None or self.jacobian is None:
            return xf, grippers
        return xf + self.jacobian.J @ pending, apply_increment(grippers, pending)

    @staticmethod
    def _valid_pending(pending: np.ndarray | None) -> np.ndarray | None:
        """`pending` as a finite `(12,)`, or None (unknown)."""
        if pending is None:
            return None
        p = np.asarray(pending, dtype=float).ravel()
        return p if p.shape == (12,) and np.all(np.isfinite(p)) else None

    def _note_reach(self, pending: np.ndarray | None, slowed: bool) -> None:
        """Bar the direction (unit, in C7 units `(12,)`) of the motion in flight while the arm side
        reports it slowed; the bar lapses REACH_BAR_TICKS ticks after the last such report."""
        if slowed and pending is not None:
            v = pending / self.u_max
            n = float(np.linalg.norm(v))
            if n >= MIN_BAR_STEP:
                self._barred, self._barred_ticks = v / n, REACH_BAR_TICKS
                return
        if self._barred is not None:
            self._barred_ticks -= 1
            if self._barred_ticks <= 0:
                self._barred = None

    def _bar_unmade(self, u: np.ndarray, unmade: np.ndarray | None) -> np.ndarray:
        """`u (12,)` with no share along the barred direction (C7 units), and while the arms are slowed
        taking back up to one full-speed tick of the `unmade (12,)` motion still in flight along it:
        the arm side's target then returns within reach and its other axes move again (the driver cuts
        a step its joints cannot follow as a whole). Stays inside C7."""
        d = self._barred
        if d is None:
            return u
        v = np.asarray(u, dtype=float) / self.u_max
        limit = 0.0 if unmade is None else -min(max(float((unmade / self.u_max) @ d), 0.0), 1.0)
        return project_box_halfspace(v, d, limit) * self.u_max

    def _bound_turn(self, u: np.ndarray, grippers: dict[ArmName, np.ndarray]) -> np.ndarray:
        """`u (12,)` with no share turning a gripper further from its pose at the first tick once it has turned
        `max_turn_deg` from it (its turn back, and every other axis, untouched; inside C7). Why: a hem with
        little bending stiffness barely follows a turn of its clamps while J's rigid model of the pair has
        the rim turn with them, and unbounded the MPC turns the grippers on past 100°. 0: unbounded, u as given."""
        cap = np.radians(self.p.controller.experimental.max_turn_deg)
        if cap <= 0.0 or self._start_turns is None:
            return u
        out = u
        for arm in ARMS:
            r = rotvec_between(self._start_turns[arm], np.asarray(grippers[arm], dtype=float)[:3, :3])
            angle = float(np.linalg.norm(r))
            if angle <= cap:
                continue
            axis = r / angle
            w = out[ROTATION[arm]]
            further = float(w @ axis)
            if further > 0.0:
                out = out.copy()
                out[ROTATION[arm]] = w - further * axis
        return out

    @property
    def barred(self) -> np.ndarray | None:
        """The direction `(12,)` (unit, in C7 units) the controller does not ask for, or None."""
        return None if self._barred is None else self._barred.copy()

    def _learn_separation_offset(self, x: np.ndarray, grippers: dict[ArmName, np.ndarray]) -> None:
        """How far inside the rim's ends the mounts hold it: the rim's extent along the grippers' axis
        less their separation, from the first SOI `x (n_x, 3)` (the bag hangs taut from its mounts)."""
        pl, pr = grippers["left"][:3, 3], grippers["right"][:3, 3]
        sep = float(np.linalg.norm(pr - pl))
        if sep > 1e-6:
            proj = np.asarray(x, dtype=float).reshape(-1, 3) @ ((pr - pl) / sep)
            self._sep_offset = float(proj.max() - proj.min()) - sep

    def separation_band(self, target: np.ndarray, axis: np.ndarray) -> tuple[float, float]:
        """C6 for a subgoal `target (3 n_x,)` and the grippers' unit `axis (3,)`: (lower, upper) separation.

        upper: the rim cannot be pulled further apart than a share of half its perimeter. lower: a
        rim with its mounts closer than its shape needs goes slack, and a slack fabric rim folds in
        (the fold is what leaves an object's corner outside): the subgoal's extent along the axis,
        less the mounts' offset inside the rim, less a margin."""
        lower, upper = self.sep_limits
        if self._sep_offset is not None:
            proj = np.asarray(target, dtype=float).reshape(-1, 3) @ axis
            taut = float(proj.max() - proj.min()) - self._sep_offset - TAUT_MARGIN_M
            lower = float(np.clip(taut, lower, upper - TAUT_MARGIN_M))
        return lower, upper

    def _learn(self, xf: np.ndarray, moved: np.ndarray | None) -> None:
        """Broyden on windows of `broyden_window` ticks: the grippers' summed motion `moved (12,)`
        and the SOI change it caused (None on a run's first valid tick: nothing to learn yet); nothing
        with `jacobian_update: frozen` (J stays the exploration's)."""
        if self._x_prev is None or moved is None or self.jacobian is None or self.p.controller.jacobian_update == "frozen":
            return
        self._win_u += moved
        self._win_s += xf - self._x_prev
        self._win_n += 1
        if self._win_n >= self.broyden_window:
            self.jacobian.update(self._win_u, self._win_s)
            self._win_u[:], self._win_s[:], self._win_n = 0.0, 0.0, 0

    def _path_tracker(self) -> SubgoalTracker:
        """The subgoal tracker of the path `reset` gave; BadControlInput before that."""
        if self.tracker is None:
            raise BadControlInput("step() before reset(): the controller has no path")
        return self.tracker

    def _finished(self, x: np.ndarray) -> bool:
        """At g*: within goal_tol, or as close as the bag gets (no progress for GOAL_STALL_TICKS
        within 2x subgoal_tol; the run is then judged on what the rim really does)."""
        tr = self._path_tracker()
        if not self.aims_at_goal:
            return tr.done(x)
        e = tr.error(x, len(self.path) - 1)
        if e < self._goal_best - 1e-3:
            self._goal_best, self._goal_since = e, 0
        else:
            self._goal_since += 1
        return e <= self.p.controller.goal_tol_m or (self._goal_since >= GOAL_STALL_TICKS and e <= 2 * self.p.controller.subgoal_tol_m)

    def _hold(self, reason: str, x: np.ndarray | None) -> ControlOutput:
        return self._out(np.zeros(12), "hold", reason, x)

    def _out(self, u: np.ndarray, mode: ServoMode, reason: str | None, x: np.ndarray | None, done: bool = False) -> ControlOutput:
        tr = self._path_tracker()
        if x is not None and np.all(np.isfinite(x)):
            e_sub, e_goal = tr.error(x, tr.index), tr.error(x, len(self.path) - 1)
        else:
            e_sub = e_goal = float("nan")
        return ControlOutput(np.asarray(u, dtype=float), mode, reason, tr.index, tr.stage, e_sub, e_goal, 0.0, done, tr.progress())
