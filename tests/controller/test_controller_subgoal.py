"""Choosing g_next on the path: in order, never past g† before it is reached; and the SOI guard."""

import numpy as np
import pytest

from bagit.common.errors import BadControlInput
from bagit.services.controller import SoiGuard, SubgoalTracker
from bagit.services.controller.subgoal import rms_error, slide_to


def _ring(n=16, r=0.1, z=0.0):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([r * np.cos(t), r * np.sin(t), np.full(n, z)], 1)


def test_never_skips_past_dagger():
    path = np.stack([np.full((4, 3), k, float) for k in range(6)])
    tr = SubgoalTracker(path, dagger_index=2, subgoal_tol=0.1, goal_tol=0.1)
    assert tr.update(path[5]) == 2  # already at g*: still must reach g† first
    assert tr.stage == "pre-bagging" and not tr.done(path[5])
    assert tr.update(path[4]) == 2  # nearer a bagging node is no reason either
    assert tr.update(path[2]) == 3 and tr.stage == "bagging"
    assert tr.update(path[5]) == 5 and tr.done(path[5])
    assert tr.progress() == 1.0


def test_advances_when_close_or_when_a_later_node_is_nearer():
    path = np.stack([_ring(z=0.01 * k) for k in range(8)])
    tr = SubgoalTracker(path, dagger_index=6, subgoal_tol=0.003, goal_tol=0.002)
    assert tr.index == 1
    assert tr.update(path[0] + [0, 0, 0.005]) == 1  # between 0 and 1, not within tol: keep g_1
    assert tr.update(path[1] + [0, 0, 0.001]) == 2  # within tol of g_1: on to g_2
    assert tr.update(path[4] + [0, 0, 0.006]) == 5  # overshot along the path: g_5 is the nearest ahead
    assert tr.update(path[6]) == 7 and tr.stage == "bagging"


def test_advances_on_a_stall_close_to_a_node_the_bag_cannot_match():
    path = np.stack([_ring(z=0.02 * k) for k in range(4)])
    tr = SubgoalTracker(path, dagger_index=2, subgoal_tol=0.01, goal_tol=0.005, stall_ticks=5)
    x = path[1] + [0.0, 0.015, 0.0]  # 1.5 cm off g_1 (within 2x tol), not improving
    for _ in range(5):
        assert tr.update(x) == 1
    assert tr.update(x) == 2
    # the stall on g_1 says nothing about g_2: no chained advance
    assert tr.index == 2 and tr.stage == "pre-bagging"


def test_settles_at_dagger_before_the_lift():
    path = np.stack([np.full((4, 3), k, float) for k in range(5)])
    tr = SubgoalTracker(path, dagger_index=2, subgoal_tol=0.1, goal_tol=0.1, dagger_settle_ticks=3)
    assert tr.update(path[1]) == 2 and tr.settled_ticks == 0 and not tr.settling
    assert tr.update(path[2] + 0.5) == 2 and tr.settled_ticks == 0  # not yet at g†: no settle
    # from the first update at g†, three updates are the settle (wherever the bag drifts meanwhile);
    # the lift (g_3) comes on the fourth
    for k, x in enumerate((path[2], path[2] + 0.5, path[2]), start=1):
        assert tr.update(x) == 2 and tr.settled_ticks == k and tr.settling and tr.stage == "pre-bagging"
    assert tr.update(path[2] + 0.05) == 3 and tr.stage == "bagging" and not tr.settling
    with pytest.raises(BadControlInput):
        SubgoalTracker(path, 2, 0.1, 0.1, dagger_settle_ticks=-1)


def test_rejects_bad_paths():
    with pytest.raises(BadControlInput):
        SubgoalTracker(np.zeros((3, 4)), 0, 0.01, 0.01)
    with pytest.raises(BadControlInput):
        SubgoalTracker(np.zeros((3, 4, 3)), 3, 0.01, 0.01)
    with pytest.raises(BadControlInput):
        SubgoalTracker(np.full((3, 4, 3), np.nan), 1, 0.01, 0.01)


def test_slide_removes_the_points_sliding_along_the_rim():
    g = _ring(32)
    t = np.linspace(0, 2 * np.pi, 32, endpoint=False) + 0.3 * 2 * np.pi / 32  # a third of a spacing on
    x = np.stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros(32)], 1)
    assert rms_error(x, g) > 0.005
    assert rms_error(x, slide_to(g, x)) < 0.0005
    assert rms_error(np.roll(x, 1, axis=0), slide_to(g, np.roll(x, 1, axis=0))) < 0.0005
    assert np.array_equal(slide_to(g, g), g)


def test_guard_holds_on_missing_stale_jumping_and_malformed_soi():
    g = SoiGuard(timeout_s=0.2, max_age_s=0.3, n_x=8)
    x = np.zeros((8, 3))
    assert g.check(None, 0.0) == "no SOI received"
    assert g.check(x, 1.0) is None
    assert g.check(None, 1.1) == "no new SOI this tick"
    assert "stopped arriving" in g.check(None, 1.5)
    assert "stale" in g.check(x, 2.0, source_stamp=1.0)
    assert g.check(x, 2.0, source_stamp=1.95) is None
    assert "jumped" in g.check(x + [0.5, 0, 0], 2.033)
    assert g.check(x + [0.5, 0, 0], 2.066) is None  # a real change passes once it is consistent
    assert g.check(x + [0.5, 0.02, 0], 2.1) is None  # 2 cm in 33 ms: fast, but plausible
    assert "NaN" in g.check(np.full((8, 3), np.nan), 2.13)
    assert "shape" in g.check(np.zeros((7, 3)), 2.16)
    assert "stale" in g.check(x, 2.2, source_stamp=float("nan"))


def test_a_settle_whose_end_fails_the_check_is_void_and_the_servoing_to_dagger_goes_on():
    """With `dagger_check` (the SOI goes round V), the lift starts only from an SOI that passes it: a
    settle ending on one that fails is void, the next starts once the SOI passes, and after
    `dagger_wait_ticks` since the first void settle the next settle's end lifts regardless."""
    path = np.stack([np.full((4, 3), k, float) for k in range(5)])
    bad, good = path[2] + [0.05, 0, 0], path[2] - [0.05, 0, 0]  # both within tolerance of g†
    tr = SubgoalTracker(path, 2, 0.1, 0.1, dagger_settle_ticks=3, dagger_check=lambda x: bool(x[0, 0] < 2.0), dagger_wait_ticks=20)
    assert tr.update(path[1]) == 2
    for k in range(1, 4):  # the settle, wherever the bag drifts meanwhile
        assert tr.update(bad) == 2 and tr.settled_ticks == k and tr.settling
    assert tr.update(bad) == 2 and tr.void_settles == 1 and not tr.settling and tr.stage == "pre-bagging"  # void: no lift
    assert tr.update(bad) == 2 and tr.settled_ticks == 0  # within tolerance, but fails the check: no new settle
    for k in range(1, 4):
        assert tr.update(good) == 2 and tr.settled_ticks == k and tr.settling
    assert tr.update(good) == 3 and tr.stage == "bagging" and tr.void_settles == 1  # the lift, from an SOI round V

    # never round V: after the wait the next settle's end lifts (the run's time is bounded)
    tr = SubgoalTracker(path, 2, 0.1, 0.1, dagger_settle_ticks=3, dagger_check=lambda x: False, dagger_wait_ticks=10)
    stages = [tr.update(bad) for _ in range(25)]
    # the void settle ends on update 3; the wait is over on update 13, where the next settle starts
    assert stages.index(3) == 3 + 10 + 3 and tr.void_settles == 1, stages
    # a settle whose end passes the check is the settle without one (test_settles_at_dagger_before_the_lift)
    tr = SubgoalTracker(path, 2, 0.1, 0.1, dagger_settle_ticks=3, dagger_check=lambda x: True)
    assert [tr.update(path[2]) for _ in range(5)] == [2, 2, 2, 3, 3] and tr.void_settles == 0
    with pytest.raises(BadControlInput):
        SubgoalTracker(path, 2, 0.1, 0.1, dagger_wait_ticks=-1)
