"""Planning a whole bagging path g0 -> g† -> g* for a scenario, with any of the planners."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from os import PathLike

import numpy as np

from bagit.common.errors import BadCloud, BadScenario, InfeasibleGoal, NumericalFailure
from bagit.common.geometry import align_cyclic, as_points, closed_polyline_length
from bagit.common.messages import Path
from bagit.common.names import PLAN_WALL_GUARD_S
from bagit.common.params import MethodParams, merge_params
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario
from bagit.services.planner.collision import RimCollision, box_polytope, prism_polytope, rim_gap
from bagit.services.planner.goal import BaggingGoal, bagging_soi
from bagit.services.planner.reach import reach_problem
from bagit.services.planner.rrt import PLANNERS, densify, postprocess
from bagit.services.planner.space import MAX_NODE_STEP_M, SoiSpace, max_step

log = logging.getLogger(__name__)

OBJECT_MARGIN_M = (0.002, 0.02)  # the rim keeps half of g†'s clearance from the object, within these bounds
REGION_MARGIN = np.array([0.12, 0.12, 0.08])  # the sampled centres' box around g0, g† and g*
ESCAPE_STEP_M = 0.001  # `start_escape` tries translations of g0 in steps of this
ESCAPE_MAX_M = MAX_NODE_STEP_M  # ... up to this far: at most one step of the path


@dataclass
class PlanResult:
    """A planned SOI path. path: (n_nodes, n_x, 3); path[dagger_index] is g†, path[-1] is g*."""

    success: bool
    planner: str
    path: np.ndarray
    dagger_index: int
    time_s: float
    iterations: int
    reason: str | None = None
    goal: BaggingGoal | None = field(default=None, repr=False)

    def to_message(self, run_id: str | None = None) -> Path:
        return Path(
            run_id=run_id,
            success=self.success,
            planner=self.planner,
            nodes=self.path if self.success else np.zeros((0, 1, 3)),
            dagger_index=self.dagger_index,
            time_s=self.time_s,
            iterations=self.iterations,
        )

    def path_length(self) -> float:
        """Summed RMS point motion along the path (metres)."""
        if len(self.path) < 2:
            return 0.0
        return float(np.sqrt(np.mean(np.sum(np.diff(self.path, axis=0) ** 2, axis=2), axis=1)).sum())


def collision_model(scenario: Scenario, up: np.ndarray, clearance: float, g_dagger: np.ndarray | None = None) -> RimCollision:
    """The object (V extruded along `up`) and the scenario's cuboid obstacles.

    The rim is kept off the object by half the clearance g† itself has (between 2 mm and 2 cm): the
    real rim only approximates the planned ellipses, and a path that grazes the object lets the fabric
    catch on a corner.
    """
    obj = prism_polytope(scenario.object.bottom_vertices(), up, scenario.object.effective_height())
    margin = OBJECT_MARGIN_M[0]
    if g_dagger is not None:
        gap = rim_gap(g_dagger, obj)  # >= 0 outside; a lower bound at corners
        margin = float(np.clip(0.5 * gap, *OBJECT_MARGIN_M))
    polys = [obj]
    margins = [margin]
    for k, ob in enumerate(scenario.obstacles):
        polys.append(box_polytope(ob, f"obstacle {k}"))
        margins.append(clearance)
    return RimCollision(polys, margins)


def ends_touch(collision: RimCollision, ends: dict[str, np.ndarray]) -> str | None:
    """Why no collision-free path can start or end at the named rims `(n_x, 3)` (the first that touches the
    object or an obstacle by the collision model's margins), or None. The one rule for a path's ends: the
    planner checks g0, g† and g* with it (a g0 touching by a margin only is left first, `start_escape`),
    and `check_scenario_goal` checks g† and g* before anything moves."""
    for name, rim in ends.items():
        hit = collision.first_hit(rim)
        if hit is not None:
            return f"{name} touches the {hit}: no collision-free path can start or end there"
    return None


def start_escape(g0: np.ndarray, collision: RimCollision, up: np.ndarray, object_centre: np.ndarray) -> np.ndarray | None:
    """A start for the search when g0 `(n_x, 3)` is within the collision model's margin of the object or an
    obstacle but touches none of them itself (margin 0); None when it does touch one, or no escape is
    found. The start is the nearest translation of g0 clear by every margin, reached along a straight
    motion on which g0's clearance (`rim_gap`) to each thing it is within the margin of only grows and
    nothing is touched.

    Why: g0 is where the bag hangs, not a state the planner chose. The margin keeps the planned rims off
    the object (`collision_model`: up to 2 cm round a bag with room), and a bag that hangs with its
    opening a little under the object (the envelope zoo's large bags on exp01: 2.5 cm below the box's
    bottom, perceived 1.8-2.0 cm from it) would be refused although every rim the controller servos
    through moves away from the object. Tried down the object's axis (`-up`, the reverse of the lift
    g† -> g*), away from the object (`object_centre (3,)`) across that axis, and between the two; the
    shortest escape wins (ties in that order). A g0 clear by the margins never comes here: its plan is
    the one it had before, bit for bit."""
    within = collision.touched(g0)
    if not within or collision.touched(g0, margins=False):
        return None
    up = up / np.linalg.norm(up)
    across = g0.mean(axis=0) - object_centre
    across = across - (across @ up) * up
    directions = [-up]
    if np.linalg.norm(across) > 1e-9:
        across = across / np.linalg.norm(across)
        directions += [across, (across - up) / np.linalg.norm(across - up)]
    steps = np.arange(1, int(round(ESCAPE_MAX_M / ESCAPE_STEP_M)) + 1) * ESCAPE_STEP_M
    start_gaps = [rim_gap(g0, collision.polytopes[k]) for k in within]
    best: tuple[float, np.ndarray] | None = None
    for d in directions:
        gaps = start_gaps
        for dist in steps:
            if best is not None and dist >= best[0]:
                break
            rim = g0 + dist * d
            now = [rim_gap(rim, collision.polytopes[k]) for k in within]
            if any(b < a for a, b in zip(gaps, now, strict=True)) or collision.touched(rim, margins=False):
                break  # the clearance would shrink, or the rim would touch something: not this way
            gaps = now
            if not collision.touched(rim):
                best = (float(dist), rim)
                break
    return None if best is None else best[1]


def plan_path(
    g0: np.ndarray,
    goal: BaggingGoal,
    collision: RimCollision,
    perimeter: float,
    params: MethodParams,
    planner: str = "cbirrt",
    seed: int = 0,
    time_budget_s: float = PLAN_WALL_GUARD_S,
) -> PlanResult:
    """Plan g0 -> g† and g† -> g*, trimmed, smoothed and densified; every node aligned to g0. A g0 within
    the margins but touching nothing is first moved clear (`start_escape`) and the search starts there.

    A stage whose search fails within its iterations is the straight motion between its ends when that
    motion is free (`SoiSpace.edge_ok`). Why: CBiRRT tries to join its trees only after a step towards a
    random rim succeeds, and round a bag that barely holds the object every such step hits the object,
    so it never tries the join even when g† -> g* (g† lifted along the object's axis) is free (the bag
    zoo's zoo-core-0-10 and -74). Tried only once the search has failed, so every plan a search finds is
    the one it found before, the RNG's draws included."""
    if planner not in PLANNERS:
        raise BadScenario(f"unknown planner {planner!r}; choose from {sorted(PLANNERS)}")
    t0 = time.perf_counter()
    g0 = np.asarray(g0, dtype=float)
    gd = align_cyclic(goal.g_dagger, g0)
    gs = align_cyclic(goal.g_star, g0)
    empty = np.zeros((0,) + g0.shape)

    def fail(reason: str, iters: int = 0) -> PlanResult:
        return PlanResult(False, planner, empty, -1, time.perf_counter() - t0, iters, reason, goal)

    start = g0
    touch = ends_touch(collision, {"g0": g0})
    if touch is not None:
        escape = start_escape(g0, collision, goal.up, goal.vertices.mean(axis=0))
        if escape is None:
            return fail(touch)
        start = escape
        log.info("%s by its margin only: the path first moves it %.1f mm, its clearance only growing (`start_escape`)",
                 touch.split(":")[0], 1e3 * max_step(g0, start))
    touch = ends_touch(collision, {"g†": gd, "g*": gs})
    if touch is not None:
        return fail(touch)
    centres = np.stack([start.mean(0), gd.mean(0), gs.mean(0)])
    space = SoiSpace(
        perimeter=perimeter,
        collision=collision,
        rng=np.random.default_rng(seed),
        center_lo=centres.min(0) - REGION_MARGIN,
        center_hi=centres.max(0) + REGION_MARGIN,
        up=goal.up,
        lambda_4=params.planner.lambda_4,
        lambda_5=params.planner.lambda_5,
        perimeter_tol=params.planner.perimeter_tol,
        step_m=params.planner.step_m,
    )
    g0_perim = closed_polyline_length(g0)
    if abs(g0_perim / perimeter - 1) > params.planner.perimeter_tol:
        return fail(f"g0's perimeter {g0_perim:.3f} m is not within {params.planner.perimeter_tol:.0%} of R = {perimeter:.3f} m")
    deadline = t0 + time_budget_s
    search = PLANNERS[planner]
    total_iters = 0
    pieces = []
    for a, b, stage in ((start, gd, "pre-bagging"), (gd, gs, "bagging")):
        try:
            raw, iters = search(space, a, b, params.planner.connect_eps_m, params.planner.max_iterations, deadline)
            total_iters += iters
            if raw is None and space.edge_ok(a, b):
                raw = [a, b]  # the search failed and the straight motion is free: see the docstring
                log.info("%s found no %s path in %d iterations; the straight motion is free and is the path", planner, stage, iters)
            if raw is None:
                why = "time budget" if time.perf_counter() > deadline else f"{params.planner.max_iterations} iterations"
                return fail(f"{planner} found no {stage} path within its {why}", total_iters)
            piece = postprocess(space, raw)
        except (NumericalFailure, np.linalg.LinAlgError, FloatingPointError) as e:
            return fail(f"{planner} failed numerically in the {stage} search: {e}", total_iters)
        if not all(np.all(np.isfinite(r)) for r in piece):
            return fail(f"{planner} produced a non-finite {stage} path", total_iters)
        pieces.append(piece)
    pre, bag = pieces
    if start is not g0:
        pre = densify(space, [g0, start], min(space.step_m, MAX_NODE_STEP_M))[:-1] + pre  # the escape, then the search's path
    path = np.stack(pre + bag[1:])
    path[0], path[len(pre) - 1], path[-1] = g0, gd, gs
    return PlanResult(True, planner, path, len(pre) - 1, time.perf_counter() - t0, total_iters, None, goal)


def plan_scenario(
    scenario: Scenario,
    planner: str = "cbirrt",
    seed: int = 0,
    g0: np.ndarray | None = None,
    time_budget_s: float = PLAN_WALL_GUARD_S,
) -> PlanResult:
    """Goal and path for a scenario; g0 from the argument (perception) or the scenario's initial rim."""
    if g0 is None:
        g0 = scenario.bag.g0()
        if g0 is None:
            raise BadScenario(f"scenario {scenario.name!r} has no bag.initial_rim: perception must give g0")
    g0 = as_points(g0, BadCloud, "g0")
    if len(g0) < 4:
        raise BadCloud(f"g0 needs at least 4 rim points, got {len(g0)}")
    if not np.all(np.isfinite(g0)):
        raise BadCloud("g0 contains NaN or infinite coordinates")
    goal, perimeter = bagging_goal(scenario, g0)
    return path_to_goal(scenario, g0, goal, perimeter, planner, seed, time_budget_s)


def bagging_goal(scenario: Scenario, g0: np.ndarray | None, rig: RigConfig | None = None) -> tuple[BaggingGoal, float]:
    """The bagging ellipse, g† and g* for the scenario's object from g0 `(n_x, 3)`, and the rim perimeter R
    they were made for (the bag's, else g0's length). The one goal rule: the coordinator, `bagit goal` and
    `bagit plan` use it. Without g0 (not perceived yet) the goal has the bag's n_x points and R.

    InfeasibleGoal when no ellipse of perimeter R holds the object, or when the two arms of `rig` (the
    default rig when None) cannot hold g† or g* (`reach.reach_problem`): known before anything moves.

    The bag-shaped ellipse (`dagger_shape: bag`) keeps only `dagger_margin_share` of the tight one's
    margin round V; when that leaves its g† or g* within the planner's margin of the object
    (`ends_touch`: a tight bag, or an opening perceived a little askew), the goal is the tight ellipse
    (the paper's C1-C3 ellipse scaled up to R), which has the most margin the method can give.
    """
    perimeter = scenario.bag.rim_perimeter or (closed_polyline_length(g0) if g0 is not None else None)
    if perimeter is None:
        raise BadScenario(f"scenario {scenario.name!r} gives neither bag.rim_perimeter nor bag.initial_rim")
    n_x = len(g0) if g0 is not None else scenario.bag.n_x
    v = scenario.object.bottom_vertices()
    goal = bagging_soi(v, perimeter, n_x, scenario.params, lambda_d=scenario.lambda_d(), g0=g0)
    if goal.oriented_by == "bag" and _goal_touch(scenario, goal) is not None:
        tight = merge_params(scenario.params, {"dagger_shape": "tight"})
        goal = bagging_soi(v, perimeter, n_x, tight, lambda_d=scenario.lambda_d(), g0=g0)
    why = reach_problem({"g†": goal.g_dagger, "g*": goal.g_star}, rig)
    if why is not None:
        raise InfeasibleGoal(why)
    return goal, perimeter


def check_scenario_goal(scenario: Scenario, rig: RigConfig | None = None) -> None:
    """InfeasibleGoal now, for a host that would learn it only after perception (`bagit run`, `bagit up`),
    when the goal the scenario's own object and bag give cannot be made or reached (`bagging_goal`), or,
    made from the scenario's start rim, ends where the planner cannot (g† or g* touching the object or an
    obstacle by the planner's margins, `ends_touch`): the object does not fit the bag. This is what "the
    object fits" means for the bag zoo's draws. Needs R (bag.rim_perimeter, or an initial rim); without it
    the coordinator decides once g0 is seen."""
    if scenario.bag.rim_perimeter is None:
        return
    g0 = scenario.bag.g0()
    goal, _ = bagging_goal(scenario, g0, rig)
    # a bag-shaped goal is kept by `bagging_goal` only when it is free (`_goal_touch`): not checked twice
    touch = _goal_touch(scenario, goal) if g0 is not None and goal.oriented_by != "bag" else None
    if touch is not None:
        raise InfeasibleGoal(f"the object does not fit the bag: from the start rim, {touch}")


def _goal_touch(scenario: Scenario, goal: BaggingGoal) -> str | None:
    """Why a path cannot end at the goal's g† or g* (`ends_touch` under the planner's collision model), or None."""
    coll = collision_model(scenario, goal.up, scenario.params.planner.clearance_m, goal.g_dagger)
    return ends_touch(coll, {"g†": goal.g_dagger, "g*": goal.g_star})


def path_to_goal(scenario: Scenario, g0: np.ndarray, goal: BaggingGoal, perimeter: float, planner: str, seed: int,
                 time_budget_s: float) -> PlanResult:
    """The SOI path g0 -> g† -> g* round the scenario's object and obstacles (see `plan_path`)."""
    coll = collision_model(scenario, goal.up, scenario.params.planner.clearance_m, goal.g_dagger)
    return plan_path(g0, goal, coll, perimeter, scenario.params, planner, seed, time_budget_s)


def plan(
    scenario: Scenario | str | PathLike,
    planner: str = "cbirrt",
    seed: int = 0,
    *,
    g0: np.ndarray | None = None,
    time_budget_s: float = PLAN_WALL_GUARD_S,
) -> PlanResult:
    """`plan_scenario` for a Scenario, a scenario file or the name of a bundled scenario."""
    if not isinstance(scenario, Scenario):
        from bagit.scenarios import find_scenario

        scenario = Scenario.from_file(find_scenario(str(scenario)))
    return plan_scenario(scenario, planner, seed, g0, time_budget_s)
