"""The action-primitive controllers (autobag, shakingbot): their look-act state machines on a toy bag
whose rim hangs from the two mounts, moved at once by each increment (no arm side, no simulator)."""

from types import SimpleNamespace

import numpy as np
import pytest

from bagit.common.errors import BadControlInput
from bagit.common.geometry import make_transform
from bagit.common.params import MethodParams
from bagit.services.controller import make_controller
from bagit.services.controller.primitives import (
    ALIGN_TOL_M,
    AUTOBAG_ROUNDS,
    SETTLE_TICKS,
    SHAKINGBOT_SPREAD,
    ObjectView,
    opening_of,
)
from bagit.services.controller.servo import c7_limits

N_X = 32
P = MethodParams()
PERIMETER = 0.68
BOTTOM = np.array([0.0, 0.0, 0.5])
GOAL_HEIGHT = 0.075


def box_outline(half_x: float, half_y: float) -> np.ndarray:
    """The object's bottom outline V `(4, 3)` round BOTTOM."""
    return BOTTOM + np.array([[half_x, half_y, 0], [-half_x, half_y, 0], [-half_x, -half_y, 0], [half_x, -half_y, 0]])


def goal_for(V: np.ndarray) -> SimpleNamespace:
    """A Goal's fields the primitives read: the bottom frame, V and g* (a ring at the goal height)."""
    return SimpleNamespace(frame=make_transform(np.eye(3), BOTTOM), vertices=V, g_star=ring(BOTTOM + [0, 0, GOAL_HEIGHT], 0.1, 0.12))


def ring(centre: np.ndarray, a: float, b: float) -> np.ndarray:
    """An elliptic rim `(N_X, 3)`: semi-axis `a` along x, `b` along y (the mounts' axis)."""
    t = np.linspace(0, 2 * np.pi, N_X, endpoint=False)
    return centre + np.stack([a * np.cos(t), b * np.sin(t), np.zeros(N_X)], axis=1)


def toy_rim(poses: dict) -> np.ndarray:
    """The rim the mounts hold: centred between them, 2 cm below, its extent along their axis their
    separation plus 2 cm and across it what the perimeter leaves (a wider pull, a narrower opening)."""
    pl, pr = poses["left"][:3, 3], poses["right"][:3, 3]
    b = 0.5 * np.linalg.norm(pr - pl) + 0.01
    a = max(np.sqrt(max(2 * (PERIMETER / (2 * np.pi)) ** 2 - b**2, 1e-4)), 0.01)  # Ramanujan-free: a^2 + b^2 = 2 r^2
    return ring(0.5 * (pl + pr) - [0, 0, 0.02], a, b)


def mounts(centre: np.ndarray, separation: float) -> dict:
    return {"left": make_transform(np.eye(3), centre - [0, separation / 2, 0]),
            "right": make_transform(np.eye(3), centre + [0, separation / 2, 0])}


def drive(name: str, V: np.ndarray, start: np.ndarray, separation: float, ticks: int = 2000, frozen: bool = False):
    """Run a controller on the toy bag until done: (controller, poses, outputs). `frozen`: the arms never move."""
    c = make_controller(name, P, N_X)
    poses = mounts(start, separation)
    path = np.stack([toy_rim(poses), goal_for(V).g_star])
    c.reset(toy_rim(poses), path, poses, dagger_index=0, perimeter=PERIMETER, goal=goal_for(V))
    outs = []
    for k in range(ticks):
        out = c.step(toy_rim(poses), k * c.dt, poses)
        outs.append(out)
        if out.done:
            break
        if not frozen:
            for i, arm in enumerate(("left", "right")):
                poses[arm][:3, 3] += out.u[6 * i: 6 * i + 3]
    return c, poses, outs


def test_autobag_aligns_the_opening_under_the_object_then_raises_it_to_the_goal_height():
    V = box_outline(0.06, 0.04)
    c, poses, outs = drive("autobag", V, np.array([0.15, 0.0, 0.48]), 0.22)
    assert outs[-1].done and c.record.done == ["align", "insert"] and not c.record.cut_short
    rim = toy_rim(poses)
    view = opening_of(rim, ObjectView.of_goal(goal_for(V)))
    assert np.linalg.norm(view.offset) < 0.002 and abs(view.height - GOAL_HEIGHT) < 0.002 and view.margin > 0.01
    stages = [o.stage for o in outs]
    assert stages.index("bagging") > 0 and set(stages[stages.index("bagging"):]) == {"bagging"}  # never back to pre-bagging
    u_max = c7_limits(P)
    assert all(np.all(np.abs(o.u) <= u_max + 1e-12) for o in outs)  # C7 on every tick
    assert all(np.all(o.u[[3, 4, 5, 9, 10, 11]] == 0) for o in outs)  # orientation held


def test_autobag_dilates_while_the_object_is_not_inside_the_opening():
    V = box_outline(0.05, 0.125)  # long along the mounts' axis: the rim must be pulled wider
    c, poses, outs = drive("autobag", V, np.array([0.0, 0.0, 0.48]), 0.20)
    assert c.record.done[0] == "dilate" and c.record.done[-1] == "insert"
    assert 1 <= c.record.done.count("dilate") <= AUTOBAG_ROUNDS
    sep = np.linalg.norm(poses["right"][:3, 3] - poses["left"][:3, 3])
    assert sep > 0.20 + 0.019  # each dilation pulled the mounts 2 cm further apart


def test_autobag_inserts_with_what_it_has_once_its_rounds_are_spent():
    V = box_outline(0.2, 0.2)  # can never fit: every round dilates, then it inserts anyway
    c, _, outs = drive("autobag", V, np.array([0.0, 0.0, 0.48]), 0.20)
    assert c.record.done == ["dilate"] * AUTOBAG_ROUNDS + ["insert"] and outs[-1].done


def test_autobag_aligns_again_when_one_alignment_leaves_the_opening_off_centre():
    """A bag whose rim follows only 80 % of the mounts' sideways motion: one alignment leaves 2 cm."""
    V = box_outline(0.06, 0.04)
    c = make_controller("autobag", P, N_X)
    start = np.array([0.1, 0.0, 0.48])
    poses = mounts(start, 0.22)

    def lagging(p: dict) -> np.ndarray:
        mid = 0.5 * (p["left"][:3, 3] + p["right"][:3, 3])
        return toy_rim(p) - 0.2 * np.array([mid[0] - start[0], mid[1] - start[1], 0.0])

    c.reset(lagging(poses), np.stack([lagging(poses)] * 2), poses, dagger_index=0, perimeter=PERIMETER, goal=goal_for(V))
    for k in range(2000):
        out = c.step(lagging(poses), k * c.dt, poses)
        if out.done:
            break
        for i, arm in enumerate(("left", "right")):
            poses[arm][:3, 3] += out.u[6 * i: 6 * i + 3]
    assert c.record.done == ["align", "align", "insert"] and out.done
    view = opening_of(lagging(poses), ObjectView.of_goal(goal_for(V)))
    assert np.linalg.norm(view.offset) < ALIGN_TOL_M


def test_shakingbot_adjusts_aligns_once_and_inserts_without_looking_in_between():
    V = box_outline(0.06, 0.04)
    c, poses, outs = drive("shakingbot", V, np.array([0.15, 0.02, 0.48]), 0.20)
    assert c.record.done == ["adjust", "align", "insert"] and outs[-1].done
    sep = np.linalg.norm(poses["right"][:3, 3] - poses["left"][:3, 3])
    assert abs(sep - SHAKINGBOT_SPREAD * PERIMETER / 2) < 0.002  # its preset spread
    settles = [i for i, o in enumerate(outs) if o.mode == "settle"]
    assert len(settles) == 3 * SETTLE_TICKS  # the bag settles after each primitive; the view after the insertion ends the run
    assert outs[settles[-1] + 1].done


def test_a_missing_soi_holds_and_the_primitive_goes_on_after():
    V = box_outline(0.06, 0.04)
    c = make_controller("autobag", P, N_X)
    poses = mounts(np.array([0.1, 0.0, 0.48]), 0.22)
    c.reset(toy_rim(poses), np.stack([toy_rim(poses)] * 2), poses, dagger_index=0, perimeter=PERIMETER, goal=goal_for(V))
    assert c.step(toy_rim(poses), 0.0, poses).mode == "servo"  # the first view: align
    held = c.step(None, c.dt * 10, poses)
    assert held.mode == "hold" and np.all(held.u == 0) and held.reason
    again = c.step(toy_rim(poses), c.dt * 11, poses)
    assert again.mode == "servo" and again.u[0] < 0  # still on its way to the object


def test_a_primitive_the_arms_do_not_make_is_cut_short_and_the_run_still_ends():
    V = box_outline(0.06, 0.04)
    c, _, outs = drive("shakingbot", V, np.array([0.15, 0.0, 0.48]), 0.20, frozen=True)
    assert outs[-1].done and c.record.cut_short == ["adjust", "align", "insert"]


def test_the_primitive_controllers_need_the_runs_goal():
    c = make_controller("autobag", P, N_X)
    poses = mounts(np.array([0.1, 0.0, 0.48]), 0.22)
    with pytest.raises(BadControlInput, match="goal"):
        c.reset(toy_rim(poses), np.stack([toy_rim(poses)] * 2), poses, dagger_index=0)
    with pytest.raises(BadControlInput, match="reset"):
        make_controller("shakingbot", P, N_X).step(toy_rim(poses), 0.0, poses)
