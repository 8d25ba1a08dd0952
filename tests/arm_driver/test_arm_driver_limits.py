"""The arm driver's safety gate: workspace boxes, mount separation, Cartesian speed, non-finite input."""

import numpy as np
import pytest
from arm_driver_support import home_poses
from hypothesis import given, settings
from hypothesis import strategies as st

from bagit.common.rig import RIM_SEPARATION_MARGIN_M, ArmConfig, RigConfig
from bagit.common.so3 import so3_exp
from bagit.services.arm_driver.limits import (
    Envelope,
    check_and_clip,
    clip_target,
    violations,
)

DT = 0.03
RIG = RigConfig()
ENV = Envelope.from_rig(RIG)
LIM = RIG.safety


def moved(poses, dl=(0, 0, 0), dr=(0, 0, 0), rl=(0, 0, 0), rr=(0, 0, 0)):
    out = {k: v.copy() for k, v in poses.items()}
    for a, d, r in (("left", dl, rl), ("right", dr, rr)):
        out[a][:3, 3] += d
        out[a][:3, :3] = so3_exp(np.asarray(r, dtype=float)) @ out[a][:3, :3]
    return out


def flange(T):
    return (T @ np.linalg.inv(RIG.arms["left"].T_flange_mount()))[:3, 3]


def test_a_target_inside_passes_unchanged():
    prev = home_poses()
    tgt = moved(prev, dl=(0.002, 0, 0), rr=(0, 0, 0.01))
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert out is tgt and found == []


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_is_rejected_and_both_arms_hold(bad):
    prev = home_poses()
    tgt = moved(prev, dl=(0.001, 0, 0))
    tgt["right"][1, 3] = bad
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert [v.kind for v in found] == ["non_finite"]
    assert all(np.array_equal(out[a], prev[a]) for a in prev)


def test_non_finite_without_a_safe_previous_sends_nothing():
    tgt = home_poses()
    tgt["left"][0, 0] = np.nan
    out, found = check_and_clip(tgt, None, DT, ENV)
    assert out is None and {v.kind for v in found} == {"non_finite", "unsafe_hold"}


def test_a_non_rigid_matrix_is_rejected():
    prev = home_poses()
    tgt = {k: v.copy() for k, v in prev.items()}
    tgt["left"][:3, :3] *= 1.5
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert found[0].kind == "non_finite" and np.array_equal(out["left"], prev["left"])


def test_outside_the_box_is_clipped_in_for_mount_and_flange():
    # start at the top of the left box (z max 0.95) and ask for more
    base = moved(home_poses(), dl=(0, 0, 0.0), dr=(0, 0, 0))
    prev = {a: T.copy() for a, T in base.items()}
    for a in prev:
        prev[a][2, 3] = 0.949
    tgt = moved(prev, dl=(0, 0, 0.004))
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert [v.kind for v in found] == ["workspace"] and found[0].arm == "left"
    assert out["left"][2, 3] == pytest.approx(0.95, abs=1e-9)
    assert violations(out, prev, DT, ENV) == []
    # a mount tilted so its flange would poke out of the box: the whole tool is shifted in
    tilt = {a: T.copy() for a, T in prev.items()}
    tilt["left"][:3, :3] = np.diag([1.0, -1.0, -1.0])  # tool axis down: the flange is above the mount
    out, found = check_and_clip(tilt, None, DT, ENV)
    assert "workspace" in [v.kind for v in found]
    assert flange(out["left"])[2] <= 0.95 + 1e-9


def test_separation_is_kept_between_the_limits():
    prev = home_poses()  # mounts 0.212 m apart
    far = moved(prev, dl=(0, -0.06, 0), dr=(0, 0.06, 0))  # 0.332 m > 0.32 m
    out, found = check_and_clip(far, None, DT, ENV)
    assert [v.kind for v in found] == ["max_distance"]
    d = np.linalg.norm(out["right"][:3, 3] - out["left"][:3, 3])
    assert d == pytest.approx(LIM.max_separation_m, abs=1e-9)
    mid_in, mid_out = (far["left"][:3, 3] + far["right"][:3, 3]) / 2, (out["left"][:3, 3] + out["right"][:3, 3]) / 2
    assert np.allclose(mid_in, mid_out)  # both arms give way equally
    near = moved(prev, dl=(0, 0.07, 0), dr=(0, -0.07, 0))  # 0.072 m < 0.08 m
    out, found = check_and_clip(near, None, DT, ENV)
    assert [v.kind for v in found] == ["min_distance"]
    assert np.linalg.norm(out["right"][:3, 3] - out["left"][:3, 3]) == pytest.approx(LIM.min_flange_distance_m, abs=1e-9)


@pytest.mark.parametrize("perimeter", [0.4, 0.56, 0.68, 1.03, 1.06, 1.3])
def test_every_envelope_bag_starts_inside_its_own_limit_and_a_pull_past_it_stops_there(perimeter):
    """The simulator's start mounts (0.31 P apart) pass the gate of the rig holding that bag, from the smallest
    envelope bag to the largest; pulled apart past P/2 less the margin, both give way to exactly the limit."""
    from bagit.common.mounts import rim_frame
    from bagit.services.sim.bag import bag_layout

    env = Envelope.from_rig(RigConfig().for_bag(perimeter))
    start = bag_layout(perimeter, 0.3, rim_frame(np.array([0.1, 0.0, 0.47]))).mount_home
    assert violations(start, None, DT, env) == []
    d0 = np.linalg.norm(start["right"][:3, 3] - start["left"][:3, 3])
    pull = (perimeter / 2 - d0) / 2  # each mount: together they ask for P/2, past the limit by the margin
    out, found = check_and_clip(moved(start, dl=(0, -pull, 0), dr=(0, pull, 0)), None, DT, env)
    assert [v.kind for v in found] == ["max_distance"]
    assert np.linalg.norm(out["right"][:3, 3] - out["left"][:3, 3]) == pytest.approx(perimeter / 2 - RIM_SEPARATION_MARGIN_M, abs=1e-9)


def test_coincident_mounts_are_pushed_apart_along_the_previous_separation():
    prev = home_poses()
    tgt = {a: T.copy() for a, T in prev.items()}
    tgt["left"][:3, 3] = tgt["right"][:3, 3] = [0.15, 0.0, 0.5]
    p, _ = clip_target(tgt, ENV, previous=prev)
    sep = p["right"][:3, 3] - p["left"][:3, 3]
    assert np.linalg.norm(sep) == pytest.approx(LIM.min_flange_distance_m, abs=1e-9)
    assert sep[1] > 0  # right stays on the right


def test_speed_is_limited_along_the_step():
    prev = home_poses()
    tgt = moved(prev, dl=(0.02, 0.01, 0.0), rr=(0.0, 0.2, 0.0))
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert sorted(v.kind for v in found) == ["angular_speed", "speed"]
    step = out["left"][:3, 3] - prev["left"][:3, 3]
    assert np.linalg.norm(step) == pytest.approx(LIM.max_tcp_speed_mps * DT, rel=1e-9)
    assert np.allclose(step / np.linalg.norm(step), np.array([2, 1, 0]) / np.sqrt(5))
    rel = out["right"][:3, :3] @ prev["right"][:3, :3].T
    angle = np.arccos((np.trace(rel) - 1) / 2)
    assert angle == pytest.approx(LIM.max_angular_speed_rps * DT, rel=1e-6)
    assert violations(out, prev, DT, ENV) == []


def test_a_previous_command_outside_the_envelope_gives_nothing_to_send():
    prev = moved(home_poses(), dl=(0, 0, 0.6))  # left far above its box
    tgt = moved(prev, dl=(0, 0, -0.001))
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert out is None and found[-1].kind == "unsafe_hold"


def test_bad_boxes_and_dt_are_refused():
    arms = RigConfig().arms
    bad = dict(arms, left=arms["left"].model_copy(update={"workspace_min": (0.5, -0.4, 0.1)}))
    with pytest.raises(ValueError):
        Envelope.from_rig(RigConfig(arms=bad))
    with pytest.raises(ValueError):
        check_and_clip(home_poses(), home_poses(), 0.0, ENV)
    assert isinstance(RigConfig().arms["left"], ArmConfig)


finite = st.floats(-0.6, 0.6, allow_nan=False)
wild = st.one_of(finite, st.sampled_from([np.nan, np.inf, -np.inf, 1e9, -1e9]))


@settings(max_examples=300, deadline=None, derandomize=True)
@given(
    dl=st.tuples(wild, wild, wild),
    dr=st.tuples(wild, wild, wild),
    rl=st.tuples(finite, finite, finite),
    rr=st.tuples(finite, finite, finite),
)
def test_whatever_the_target_what_leaves_is_inside(dl, dr, rl, rr):
    prev = home_poses()
    with np.errstate(all="ignore"):
        tgt = moved(prev, dl, dr, rl, rr)
    out, found = check_and_clip(tgt, prev, DT, ENV)
    assert out is not None  # the previous command is safe, so there is always one
    assert violations(out, prev, DT, ENV) == []
    if out is not tgt:
        assert found
