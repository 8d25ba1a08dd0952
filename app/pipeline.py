"""The whole bagging run in one process: simulator -> perception -> goal -> planner -> controller.

This is a composition root: the only code, with the CLI, that imports several stages. Perception
sees only the simulated camera's frames and control only perception's SOI; the simulator's ground
truth is read once, at the end, to judge the run.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np
from matplotlib.path import Path as MplPath

from bagit.common.errors import BagItError, SimulationFailed
from bagit.common.geometry import closed_polyline_length, enclosure, transform_points
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario
from bagit.services.controller import ShapeServo
from bagit.services.controller.servo import NUMERIC_ERRORS
from bagit.services.controller.increment import apply_increment
from bagit.services.perception import extract_soi, red_rim_mask, rim_cloud
from bagit.services.perception.rgbd import solid_rim_segmenter
from bagit.services.planner import bagging_soi, collision_model, plan_path
from bagit.services.sim.objects import object_parts, object_slice
from bagit.services.sim.world import SimWorld

SETTLE_S = 1.0  # let the hanging bag come to rest before the first frame
WALL_LIMIT_S = 900.0  # a run taking longer than this in wall time is stopped (normal runs take 20-120 s)


@dataclass
class RunResult:
    success: bool
    stage_reached: str
    reason: str | None
    error_cm: float
    duration_s: float
    planning_time_s: float
    ticks: int
    final_rim: np.ndarray
    object_vertices: np.ndarray
    passed_through: bool
    controller: str
    planner: str
    seed: int
    wall_s: float
    path_nodes: int = 0
    max_penetration_mm: float = 0.0
    # the true rim's margin round V (seen along the object's axis, cm, < 0: a vertex outside) when the
    # lift from g† began: how close the run came to catching the bottom (None: it never got there)
    lift_margin_cm: float | None = None
    history: dict[str, list[float]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        d = dict(self.__dict__)
        d.pop("history")
        return d


def judge(final_rim: np.ndarray, scenario: Scenario, lambda_d: float, up: np.ndarray) -> tuple[bool, float, str | None]:
    """Does the final rim `(m, 3)` go round the object at least lambda_d/2 above its bottom?
    Returns (enclosed, error_cm, reason). error_cm: the rim centre's distance to the object's axis.

    Seen along the object's axis, the rim must enclose the object's cross-section at the goal's lift
    lambda_d (or at the rim's top, if it is lower). For a prism that is V itself; for a sphere or a
    tapering object it is the narrower section the rim actually lies against: a rim resting on a
    grapefruit above its equator has the widest part inside the bag yet lies inside V seen from above.
    """
    v = scenario.object.bottom_vertices()
    c = v.mean(axis=0)
    rel = final_rim - c
    height = rel @ up
    axis_dist = np.linalg.norm(rel.mean(axis=0) - (rel.mean(axis=0) @ up) * up)
    h_ref = max(min(lambda_d, float(height.max())), 0.0)
    section = object_slice(object_parts(scenario.object), c, up, h_ref)
    if len(section) == 0:  # above the object: the rim must at least go round its axis
        section = (c + h_ref * up)[None]
    # In the bottom plane's coordinates: does the rim's projection contain the section's?
    e1 = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(up, e1)
    rim2 = np.column_stack([rel @ e1, rel @ e2])
    section2 = np.column_stack([(section - c) @ e1, (section - c) @ e2])
    enclosed = bool(MplPath(rim2).contains_points(section2).all())
    if not enclosed:
        return False, axis_dist * 100, "the final rim does not go round the object"
    if np.median(height) < lambda_d / 2:
        return False, axis_dist * 100, f"the rim is only {np.median(height) * 100:.1f} cm above the bottom (< lambda_d/2)"
    return True, axis_dist * 100, None


def run_bagging(
    scenario: Scenario,
    controller: str = "mpc",
    planner: str = "cbirrt",
    seed: int = 0,
    time_limit_s: float = 40.0,
    rig: RigConfig | None = None,
    progress: Callable[[str], None] = lambda s: None,
    wall_limit_s: float | None = WALL_LIMIT_S,
) -> RunResult:
    """One simulated bagging run; every stage's failure ends it with a reason.

    wall_limit_s: the run also ends (failed, with the reason) when it has taken this much wall time,
    e.g. when MuJoCo's contact solver crawls on a bunched-up bag; None: no limit."""
    t_wall = time.perf_counter()
    p = scenario.params
    n_x = scenario.bag.n_x
    world = SimWorld(scenario, rig, seed)
    V = scenario.object.bottom_vertices()
    dt = 1.0 / p.control_rate_hz
    history: dict[str, list[float]] = {"t": [], "err_sub": [], "err_goal": [], "u_norm": [], "solve_ms": []}

    lift_margin: list[float] = []

    def finish(ok: bool, stage: str, reason: str | None, err: float = float("nan"), plan_t: float = 0.0, ticks: int = 0, nodes: int = 0) -> RunResult:
        gt = world.ground_truth()
        world.close()
        return RunResult(ok, stage, reason, err, max(world.time - SETTLE_S, 0.0), plan_t, ticks, gt.rim, V, gt.passed_through,
                         controller, planner, seed, time.perf_counter() - t_wall, nodes, gt.max_penetration_m * 1e3,
                         lift_margin[0] if lift_margin else None, history)

    # How the rim looks is a property of the bag the rig is set up for, not ground truth.
    segmenter = red_rim_mask if scenario.bag.kind == "red-edged" else solid_rim_segmenter(scenario.bag.color)
    try:
        world.step(SETTLE_S)
    except SimulationFailed as e:
        return finish(False, "settling", f"simulator: {e}")
    grippers = world.mount_home_poses()
    seq = 0
    progress("perceiving: g0 from the camera")
    try:
        g0 = extract_soi(rim_cloud(world.render_rgbd(seq), segmenter), n_x, start_hint=grippers["left"][:3, 3])
    except BagItError as e:
        return finish(False, "perceiving", f"no SOI in the first frame: {e}")
    R = scenario.bag.rim_perimeter or closed_polyline_length(g0)
    progress(f"goal: bagging ellipse for R = {R:.3f} m")
    try:
        goal = bagging_soi(V, R, n_x, p, lambda_d=scenario.lambda_d(), g0=g0)
    except BagItError as e:
        return finish(False, "goal", str(e))
    progress(f"planning: {planner}")
    plan = plan_path(g0, goal, collision_model(scenario, goal.up, p.planner_clearance_m, goal.g_dagger), closed_polyline_length(g0), p, planner, seed)
    if not plan.success:
        return finish(False, "planning", plan.reason, plan_t=plan.time_s)
    progress(f"pre-bagging: {len(plan.path)} nodes, g† at {plan.dagger_index} (planned in {plan.time_s:.2f} s)")
    servo = ShapeServo(controller, p, plan.path, plan.dagger_index, R, outline=V, frame=goal.frame)
    x, ticks, stage = g0, 0, "pre-bagging"
    limit = servo.u_max
    holding: str | None = None  # why the controller holds the arms, while it does
    while world.time - SETTLE_S < time_limit_s:
        try:
            out = servo.step(x, world.time, grippers, source_stamp=world.time)
        except (BagItError, *NUMERIC_ERRORS) as e:  # the controller holds on these itself; a last net
            return finish(False, stage, f"controller: {e}", plan_t=plan.time_s, ticks=ticks, nodes=len(plan.path))
        holding = out.reason if out.mode == "hold" else None
        if np.any(np.abs(out.u) > limit + 1e-12) or not np.all(np.isfinite(out.u)):
            return finish(False, stage, "the controller commanded outside the arm limits", ticks=ticks)
        if out.stage != stage and out.mode == "servo":
            if out.stage == "bagging" and not lift_margin:  # judged on the truth, like the end; never fed back
                lift_margin.append(float(enclosure(world.true_rim(), V, goal.frame)[0].min()) * 100)
            stage = out.stage
            progress(f"{stage}: subgoal {out.subgoal_index}/{len(plan.path) - 1}")
        history["t"].append(world.time)
        history["err_sub"].append(out.error_to_subgoal)
        history["err_goal"].append(out.error_to_goal)
        history["u_norm"].append(float(np.linalg.norm(out.u)))
        history["solve_ms"].append(out.solve_ms)
        if out.done:
            break
        grippers = apply_increment(grippers, out.u)
        try:
            world.set_mount_targets(grippers)
            world.step(dt)
        except SimulationFailed as e:
            return finish(False, stage, f"simulator: {e}", plan_t=plan.time_s, ticks=ticks, nodes=len(plan.path))
        ticks += 1
        seq += 1
        wall = time.perf_counter() - t_wall
        if wall_limit_s is not None and wall > wall_limit_s:
            return finish(False, stage, f"simulator: too slow, {wall:.0f} s of wall time for {world.time - SETTLE_S:.1f} s simulated "
                          f"(limit {wall_limit_s:.0f} s; the contact solver crawls?)", plan_t=plan.time_s, ticks=ticks, nodes=len(plan.path))
        try:
            x = extract_soi(rim_cloud(world.render_rgbd(seq), segmenter), n_x, init=x)
        except BagItError:
            x = None  # the guard holds the arms and says why
    gt = world.ground_truth()
    ok, err_cm, reason = judge(gt.rim, scenario, scenario.lambda_d(), goal.up)
    if gt.passed_through:
        ok, reason = False, "the bag passed through the object"
    elif ok and world.time - SETTLE_S >= time_limit_s:
        ok, reason = False, f"time limit of {time_limit_s:.0f} s reached"
    elif not out.done and ok:
        reason = None  # enclosed at the time limit counts only if done; keep the judge's verdict otherwise
    if not ok and holding:
        reason = f"{reason}; the controller was holding: {holding}"
    return finish(ok, "done" if ok else stage, reason, err_cm, plan.time_s, ticks, len(plan.path))
