"""The action-primitive baselines of the paper's Table I: AutoBag (Chen et al., ICRA 2023) and
ShakingBot (Gu et al., Robotica 2024), with their shaking left out (the bags start open, as in the
BagIt! paper's own comparison).

Both methods look, then act with a primitive, then look again: a primitive is a short, fixed motion
of the two mounts chosen from one camera view and carried out without looking (open loop on the
bag). Here a primitive is a straight-line displacement of both mounts, streamed as pose increments at
the controllers' speed limit (C7) through the same arm driver as every controller, tracked on the
arms' reported poses (the measured pose plus the motion still in flight, so a step the arms slowed is
asked for again, never twice). Between primitives the mounts stand still `SETTLE_TICKS` ticks and the
next view decides. Orientation is held where it was at the start of the primitive.

The views are the SOI (the rim from the camera) and the object (its bottom outline V, its axis and the
goal height above its bottom from the run's Goal: the marker's pose, as for every controller). No
planned path is followed: the path is only read for g*, the error reported in the status.

In BagIt's geometry the opening faces up and the bag is raised round the object from below, so the
papers' "insert the object" and "lift the bag" are one primitive here, `insert`: raise the rim along
the object's axis to the goal height.

AutoBag (its opening metrics and the dilation primitive): align the opening's centre under the
object's axis; while the object's outline is not inside the opening with `FOOTPRINT_MARGIN_M` to
spare, dilate (pull the mounts apart along their axis, within C6) and align again, at most
`AUTOBAG_ROUNDS` rounds; then insert. ShakingBot (its Bag Adjustment, then insertion; the shaking and
the one-arm holding, which frees an arm to place the items, have no counterpart with the object
fixed and both arms on the rim): adjust the mounts to its preset spread, align once from one view,
insert, with no view in between.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from bagit.common.dual_arm import Poses, apply_increment, pose_increment
from bagit.common.errors import BadControlInput
from bagit.common.params import MethodParams
from bagit.common.rig import ARMS
from bagit.services.controller.servo import ControllerCore, ControlOutput, pose_problem, scale_into_box
from bagit.services.controller.subgoal import rms_error, slide_to

SETTLE_TICKS = 15  # ticks the mounts stand still after a primitive before the next view is taken (0.5 s at 30 Hz)
ARRIVE_TOL_M = 0.001  # a primitive is made when both mounts are this close to its end
PRIMITIVE_SLACK = 3.0  # a primitive still not made after this many times its duration at C7 (+ 1 s) ends
ALIGN_TOL_M = 0.01  # AutoBag aligns again while the opening's centre is further than this from the object's axis
FOOTPRINT_MARGIN_M = 0.01  # AutoBag's opening metric: the object's outline inside the opening by this much
DILATE_STEP_M = 0.02  # AutoBag's dilation: the mounts' separation grows by this per primitive
AUTOBAG_ROUNDS = 4  # AutoBag's look-act rounds (align, dilate) before it inserts with the opening it has
SHAKINGBOT_SPREAD = 0.75  # ShakingBot's Bag Adjustment: the mounts' preset separation, as a share of half the rim's perimeter

log = logging.getLogger("bagit.controller")

Phase = Literal["settle", "move", "done"]


@dataclass(frozen=True)
class ObjectView:
    """What the primitives aim at: the object's bottom centre `c (3,)`, its unit axis `up (3,)`, its
    bottom outline `V (n_v, 3)` and the goal height of the rim above the bottom (m)."""

    c: np.ndarray
    up: np.ndarray
    V: np.ndarray
    goal_height: float

    @classmethod
    def of_goal(cls, goal: Any) -> ObjectView:
        """From the run's Goal (`frame` world <- F_m, z up out of the object; `vertices`; `g_star`)."""
        T = np.asarray(goal.frame, dtype=float)
        V = np.asarray(goal.vertices, dtype=float)
        g_star = np.asarray(goal.g_star, dtype=float)
        if T.shape != (4, 4) or V.ndim != 2 or V.shape[1] != 3 or len(V) < 3 or not (np.all(np.isfinite(T)) and np.all(np.isfinite(V))):
            raise BadControlInput("the goal has no usable object frame or outline")
        c, up = T[:3, 3], T[:3, 2] / np.linalg.norm(T[:3, 2])
        return cls(c=c, up=up, V=V, goal_height=float((g_star.mean(axis=0) - c) @ up))

    def plane(self) -> np.ndarray:
        """Two unit vectors `(2, 3)` spanning the plane normal to the axis."""
        e1 = np.cross(self.up, [1.0, 0.0, 0.0] if abs(self.up[0]) < 0.9 else [0.0, 1.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return np.stack([e1, np.cross(self.up, e1)])


@dataclass(frozen=True)
class Opening:
    """One view of the bag's opening against the object (the vision both methods act on).

    offset `(3,)`: from the opening's centre to the object's axis, in the plane normal to it (m);
    height: the rim's median height above the object's bottom (m); margin: how far the object's
    outline lies inside the opening, seen along the axis (m, negative: a vertex outside)."""

    offset: np.ndarray
    height: float
    margin: float


def opening_of(x: np.ndarray, obj: ObjectView) -> Opening:
    """The opening `x (n_x, 3)` seen against `obj`."""
    import cv2  # here, not at the top: `bagit up`'s fork server preloads this package and must never load OpenCV (its thread pool)

    rel = np.asarray(x, dtype=float) - obj.c
    E = obj.plane()
    rim2 = (rel @ E.T).astype(np.float32)
    v2 = (obj.V - obj.c) @ E.T
    centre = rim2.mean(axis=0)
    poly = rim2.reshape(-1, 1, 2)
    margin = min(float(cv2.pointPolygonTest(poly, (float(p[0]), float(p[1])), True)) for p in v2)
    return Opening(offset=-(centre[0] * E[0] + centre[1] * E[1]), height=float(np.median(rel @ obj.up)), margin=margin)


@dataclass(frozen=True)
class Primitive:
    """A motion of both mounts: `delta (12,)` (the u layout, translations only) from where they are aimed
    when it starts; `stage`: the run's stage while it is made."""

    name: str
    delta: np.ndarray
    stage: str = "pre-bagging"


def translate(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    """The `(12,)` displacement moving the left mount by `left (3,)` and the right by `right (3,)`."""
    d = np.zeros(12)
    d[0:3], d[6:9] = left, right
    return d


@dataclass
class _Move:
    """A primitive under way: the mounts' end poses and the ticks it may take."""

    primitive: Primitive
    targets: Poses
    max_ticks: int
    ticks: int = 0


@dataclass
class PrimitiveRun:
    """What a primitive controller did in a run, for its status and the tests: the primitives in order."""

    done: list[str] = field(default_factory=list)
    cut_short: list[str] = field(default_factory=list)  # primitives the arms had not made when their time ran out


class PrimitiveController(ControllerCore):
    """A look-act state machine over primitives (see the module docstring); subclasses decide the next
    primitive from a view (`_decide`). Satisfies `Controller`: `reset` once per run, `step` every tick."""

    name = "primitives"

    def __init__(self, params: MethodParams, n_x: int, *, settle_ticks: int = SETTLE_TICKS):
        super().__init__(params, n_x)
        self.settle_ticks = settle_ticks
        self.obj: ObjectView | None = None

    def reset(self, x0: np.ndarray | None, path: Any, gripper_poses: Poses | None, dagger_index: int | None = None,
              perimeter: float | None = None, goal: Any = None) -> None:
        """Start a run: `goal` (the run's Goal) gives the object; `path` only g* for the reported error."""
        nodes, dagger = self._nodes(path, dagger_index)
        if goal is None:
            raise BadControlInput(f"{self.name} needs the object's pose: the run's goal")
        self.obj = ObjectView.of_goal(goal)
        self.g_star = nodes[-1]
        self.dagger_index = dagger
        self.last_index = len(nodes) - 1
        self._start_rim(x0, nodes, perimeter)
        self.phase: Phase = "settle"
        self.settled = self.settle_ticks  # the first view is taken at once: the bag has hung still before the run
        self.move: _Move | None = None
        self.stage = "pre-bagging"
        self.record = PrimitiveRun()
        self.ticks = 0
        self._on_reset()

    def _on_reset(self) -> None:
        """Per-run state of the method."""

    def _decide(self, view: Opening, grippers: Poses) -> Primitive | None:
        """The next primitive from this view and the mounts' poses; None: the method is finished."""
        raise NotImplementedError

    # ---- one tick ---------------------------------------------------------------------------

    def step(self, x: np.ndarray | None, now: float, gripper_poses: Poses, source_stamp: float | None = None,
             pending: np.ndarray | None = None, slowed: bool = False) -> ControlOutput:
        """This tick's increment `u (12,)` from the SOI `x (n_x, 3)` (None: none arrived), the grippers'
        poses and the motion `pending (12,)` the arm side has taken and not yet made."""
        if self.obj is None:
            raise BadControlInput("step() before reset(): the controller has no goal")
        self.ticks += 1
        reason = self.guard.check(x, now, source_stamp) or pose_problem(gripper_poses)
        if reason is not None:
            shaped = x is not None and np.shape(x) == (self.n_x, 3)
            return self._out(np.zeros(12), "hold", reason, np.asarray(x, dtype=float) if shaped else None)
        x = np.asarray(x, dtype=float)
        if self.phase == "done":
            return self._out(np.zeros(12), "done", None, x, done=True)
        aimed = self._aimed(gripper_poses, pending)
        if self.phase == "move" and self.move is not None:
            u = self._track(self.move, aimed)
            if u is not None:
                return self._out(u, "servo", None, x)
            self.phase, self.settled = "settle", 0
        if self.settled < self.settle_ticks:
            self.settled += 1
            return self._out(np.zeros(12), "settle", None, x)
        view = opening_of(x, self.obj)
        nxt = self._decide(view, aimed)
        if nxt is None:
            self.phase = "done"
            return self._out(np.zeros(12), "done", None, x, done=True)
        self.stage = nxt.stage
        self.move = self._start(nxt, aimed)
        log.debug("%s: %s by %s mm (view: offset %.1f mm, height %.1f mm, margin %.1f mm)", self.name, nxt.name,
                  np.round(nxt.delta[[0, 1, 2, 6, 7, 8]] * 1e3, 1).tolist(), np.linalg.norm(view.offset) * 1e3, view.height * 1e3, view.margin * 1e3)
        self.phase = "move"
        u = self._track(self.move, aimed)
        return self._out(np.zeros(12) if u is None else u, "servo", None, x)

    def _aimed(self, grippers: Poses, pending: np.ndarray | None) -> Poses:
        """Where the mounts are going: the measured poses moved by the motion still in flight."""
        if pending is not None:
            p = np.asarray(pending, dtype=float).ravel()
            if p.shape == (12,) and np.all(np.isfinite(p)):
                return apply_increment(grippers, p)
        return {a: np.array(grippers[a], dtype=float) for a in ARMS}

    def _start(self, prim: Primitive, aimed: Poses) -> _Move:
        """The primitive's end poses from where the mounts are aimed, and the ticks it may take."""
        span = float(np.max(np.abs(prim.delta) / self.u_max))  # ticks at C7
        return _Move(prim, apply_increment(aimed, prim.delta), int(PRIMITIVE_SLACK * span + 1.0 / self.dt) + 1)

    def _track(self, move: _Move, aimed: Poses) -> np.ndarray | None:
        """The increment towards the primitive's end (at most C7), or None when it is made (or out of time)."""
        rest = pose_increment(aimed, move.targets)
        trans = np.concatenate([rest[0:3], rest[6:9]])
        if float(np.max(np.abs(trans))) <= ARRIVE_TOL_M:
            self.record.done.append(move.primitive.name)
            return None
        move.ticks += 1
        if move.ticks > move.max_ticks:
            self.record.done.append(move.primitive.name)
            self.record.cut_short.append(move.primitive.name)
            return None
        return scale_into_box(rest, self.u_max)

    def _out(self, u: np.ndarray, mode: Any, reason: str | None, x: np.ndarray | None, done: bool = False) -> ControlOutput:
        e_goal = rms_error(x, slide_to(self.g_star, x)) if x is not None and np.all(np.isfinite(x)) else float("nan")
        bagging = self.stage == "bagging"
        index = self.last_index if done else (self.dagger_index if bagging else 0)
        progress = 1.0 if done else (0.5 if bagging else 0.0)
        return ControlOutput(np.asarray(u, dtype=float), mode, reason, index, self.stage, float("nan"), e_goal, 0.0, done, progress)

    # ---- the primitives both methods share --------------------------------------------------

    def _align(self, view: Opening) -> Primitive:
        """Both mounts moved in the plane normal to the object's axis by the opening's offset from it."""
        return Primitive("align", translate(view.offset, view.offset))

    def _insert(self, view: Opening) -> Primitive:
        """Both mounts raised along the object's axis until the rim is at the goal height."""
        assert self.obj is not None
        d = (self.obj.goal_height - view.height) * self.obj.up
        return Primitive("insert", translate(d, d), stage="bagging")

    def _spread(self, name: str, grippers: Poses, separation: float) -> Primitive:
        """Both mounts moved apart (or together) along their axis to `separation` (m), inside C6."""
        pl, pr = grippers["left"][:3, 3], grippers["right"][:3, 3]
        sep = float(np.linalg.norm(pr - pl))
        axis = (pr - pl) / max(sep, 1e-9)
        target = float(np.clip(separation, *self.sep_limits))
        half = 0.5 * (target - sep) * axis
        return Primitive(name, translate(-half, half))

    def separation(self, grippers: Poses) -> float:
        return float(np.linalg.norm(grippers["right"][:3, 3] - grippers["left"][:3, 3]))


class AutoBagController(PrimitiveController):
    """AutoBag without its shaking: align and dilate, each from a fresh view, until the object's outline
    is inside the opening (or `AUTOBAG_ROUNDS` rounds are spent), then insert."""

    name = "autobag"

    def _on_reset(self) -> None:
        self.rounds = 0

    def _decide(self, view: Opening, grippers: Poses) -> Primitive | None:
        if self.stage == "bagging":
            return None  # inserted: the run is over
        centred = float(np.linalg.norm(view.offset)) <= ALIGN_TOL_M
        if self.rounds < AUTOBAG_ROUNDS:
            if not centred:
                self.rounds += 1
                return self._align(view)
            if view.margin < FOOTPRINT_MARGIN_M and self.separation(grippers) + 0.5 * DILATE_STEP_M < self.sep_limits[1]:
                self.rounds += 1
                return self._spread("dilate", grippers, self.separation(grippers) + DILATE_STEP_M)
        return self._insert(view)


class ShakingBotController(PrimitiveController):
    """ShakingBot without its shaking: the Bag Adjustment to its preset spread, one alignment from one
    view, then insertion from the next, with no check in between."""

    name = "shakingbot"

    def _on_reset(self) -> None:
        self.plan = ["adjust", "align", "insert"]

    def _decide(self, view: Opening, grippers: Poses) -> Primitive | None:
        if not self.plan:
            return None
        step = self.plan.pop(0)
        if step == "adjust":
            return self._spread("adjust", grippers, SHAKINGBOT_SPREAD * self.perimeter / 2)
        if step == "align":
            return self._align(view)
        return self._insert(view)
