"""A step the joints cannot follow is shortened to what they can, on the CR5's own kinematics.

Near the wrist singularity (J5 near 0, J4 and J6 parallel) a tilt of the tool about the one axis the
wrist cannot turn about directly asks J4 and J6 for a large turn: a few millimetres at the mount,
tens of degrees at the joints. The driver must send only the part of
that step every joint can follow in a period, so the arm crosses slowly instead of alarming.
"""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.common import cr5, dobot
from bagit.common.rig import ARMS, RigConfig
from bagit.common.so3 import rotvec_between
from bagit.services.arm_driver.frames import ArmFrames
from bagit.services.arm_driver.limits import Envelope, violations
from bagit.services.arm_driver.reach import ELBOW_MARGIN_RAD, arm_solver, interpolate, joint_solver, solve_within, wrist_lag

PERIOD = 0.03
LIMIT = cr5.JOINT_SPEED_LIMIT * PERIOD * 0.5


def _setup(q_left: np.ndarray, q_right: np.ndarray):
    rig = RigConfig()
    frames = {a: ArmFrames.from_config(rig.arms[a]) for a in ARMS}
    offsets = {a: np.asarray(rig.arms[a].mount_offset, dtype=float) for a in ARMS}
    seeds = {"left": q_left, "right": q_right}
    poses = {a: frames[a].mount_in_world(cr5.fk(seeds[a])) for a in ARMS}
    return frames, offsets, seeds, poses


Q_NEAR_SINGULAR = np.radians([10.0, -20.0, 100.0, -80.0, 1.5, 30.0])
Q_EASY = np.radians([-10.0, -20.0, 100.0, -80.0, 60.0, 30.0])


def _tilted(frames, q: np.ndarray, deg: float) -> np.ndarray:
    """The left mount's pose with the flange at `q` tilted `deg` about its own y axis."""
    F = cr5.fk(q).copy()
    F[:3, :3] = F[:3, :3] @ Rotation.from_rotvec(np.radians(deg) * np.array([0.0, 1.0, 0.0])).as_matrix()
    return frames["left"].mount_in_world(F)


def test_a_step_past_the_wrist_singularity_is_shortened_to_the_joints_speed():
    frames, offsets, seeds, prev = _setup(Q_NEAR_SINGULAR, Q_EASY)
    cmd = {"left": _tilted(frames, Q_NEAR_SINGULAR, 3.0), "right": prev["right"].copy()}
    assert np.linalg.norm(cmd["left"][:3, 3] - prev["left"][:3, 3]) < 0.005  # a small Cartesian step ...
    solve = joint_solver(frames, seeds, offsets, LIMIT)
    q_full, why = solve(cmd)
    assert q_full is None and "faster than it can" in why  # ... that the joints cannot follow in one period
    r = solve_within(prev, cmd, solve)
    assert r.poses is not None and 0.0 < r.fraction < 1.0 and r.why == why
    for a in ARMS:
        assert np.max(np.abs(r.joints[a] - seeds[a])) <= LIMIT + 1e-12
        assert np.allclose(frames[a].mount_in_world(cr5.fk(r.joints[a])), r.poses[a], atol=1e-6)
    # the step sent lies on the way from the last command to the target, for both arms alike
    assert np.allclose(r.poses["left"], interpolate(prev, cmd, r.fraction)["left"], atol=1e-9)
    assert np.allclose(r.poses["right"], prev["right"], atol=1e-9)
    # and it is the longest such part (within the bisection's resolution)
    assert solve(interpolate(prev, cmd, min(1.0, r.fraction + 2.0 / 1024)))[0] is None


def test_stepping_on_reaches_the_target_past_the_singularity_at_the_joints_speed():
    frames, offsets, seeds, prev = _setup(Q_NEAR_SINGULAR, Q_EASY)
    cmd = {"left": _tilted(frames, Q_NEAR_SINGULAR, 3.0), "right": prev["right"].copy()}
    for periods in range(1, 300):  # noqa: B007 - the count is read after the loop
        r = solve_within(prev, cmd, joint_solver(frames, seeds, offsets, LIMIT))
        assert r.poses is not None
        for a in ARMS:
            assert np.max(np.abs(r.joints[a] - seeds[a])) <= LIMIT + 1e-12
        seeds, prev = r.joints, r.poses
        if r.fraction == 1.0:
            break
    assert np.allclose(prev["left"], cmd["left"], atol=1e-9)
    assert periods > 10  # the joints, not the 3 mm Cartesian step, set the pace


def test_a_target_out_of_reach_is_approached_and_never_passed():
    frames, offsets, seeds, prev = _setup(Q_EASY, Q_EASY)
    cmd = {a: prev[a].copy() for a in ARMS}
    cmd["left"][:3, 3] += (cmd["left"][:3, 3] - frames["left"].T_world_base[:3, 3]) * 2.0  # twice as far out
    r = solve_within(prev, cmd, joint_solver(frames, seeds, offsets, LIMIT))
    assert r.poses is not None and r.fraction < 1.0
    assert "out of the arm's reach" in r.why or "faster than it can" in r.why
    for a in ARMS:
        assert np.max(np.abs(r.joints[a] - seeds[a])) <= LIMIT + 1e-12


def test_when_not_even_the_last_command_can_be_solved_nothing_is_sent():
    frames, offsets, seeds, prev = _setup(Q_EASY, Q_EASY)
    far = {a: prev[a].copy() for a in ARMS}
    for a in ARMS:
        far[a][:3, 3] += [5.0, 5.0, 5.0]
    r = solve_within(far, far, joint_solver(frames, seeds, offsets, LIMIT))
    assert r.poses is None and r.joints is None and "reach" in r.why


@pytest.mark.parametrize("s", [0.0, 0.25, 1.0])
def test_interpolate_ends_and_midpoints(s):
    _, _, _, a = _setup(Q_EASY, Q_EASY)
    _, _, _, b = _setup(Q_NEAR_SINGULAR, Q_EASY)
    out = interpolate(a, b, s)
    for arm in ARMS:
        R = out[arm][:3, :3]
        assert np.allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.allclose(out[arm][:3, 3], a[arm][:3, 3] + s * (b[arm][:3, 3] - a[arm][:3, 3]))
    if s in (0.0, 1.0):
        assert np.allclose(out["left"], (a, b)[int(s)]["left"], atol=1e-9)


def test_creeping_at_the_edge_of_the_reach_every_pose_sent_is_solvable_as_the_wire_carries_it():
    """Seen in CI: period after period the controller pushed both mounts out and up past the reach,
    the pose sent crept up to the stretched elbow (J3 = 0), and one ServoP, rounded to the text's
    6 decimals, had no solution: the CR5 alarmed. The driver keeps its margin from the straight elbow."""
    frames, offsets, seeds, prev = _setup(Q_EASY, Q_EASY)
    out_and_up = np.array([1.0, 0.0, 1.0]) / np.sqrt(2.0)
    for _ in range(150):
        cmd = {a: prev[a].copy() for a in ARMS}
        for a in ARMS:
            cmd[a][:3, 3] += 0.1 / 30 * out_and_up  # the controller's push, one period's worth
        r = solve_within(prev, cmd, joint_solver(frames, seeds, offsets, LIMIT))
        assert r.poses is not None
        for a in ARMS:
            assert abs(r.joints[a][2]) >= ELBOW_MARGIN_RAD
            text = dobot.format_command("ServoP", *cr5.matrix_to_pose6(frames[a].flange_in_base(r.poses[a])))
            wire = cr5.pose6_to_matrix(np.array(dobot.parse_command(text).args, dtype=float))
            assert cr5.ik(wire, r.joints[a]) is not None and cr5.ik(wire, seeds[a]) is not None, text
        seeds, prev = r.joints, r.poses
    assert r.fraction == 0.0 and "out of the arm's reach" in r.why  # stopped at the edge, still pushed


def _pass_by_the_wrist_singularity(frames, miss_deg: float, periods: int = 60, step_m: float = 0.001):
    """The left mount's poses, one per period: a straight 6 cm path at a fixed tool rotation that swings J1
    past the wrist singularity, the wrist passing `miss_deg` from J5 = 0 (seen in the core zoo's -62)."""
    q_close = np.radians([48.6, -16.9, -92.1, 179.4, miss_deg, -91.1])
    F = cr5.fk(q_close)
    way = cr5.jacobian(q_close, np.array([0.0, 0.0, 0.06]))[:3, 0]
    way /= np.linalg.norm(way)
    out = []
    for k in range(periods + 1):
        T = F.copy()
        T[:3, 3] += (k - periods / 2) * step_m * way
        out.append(frames["left"].mount_in_world(T))
    return out


def test_a_wrist_passing_near_j5_zero_lags_its_rotation_and_follows_the_path_without_winding_j4():
    """Issue 35: a fixed tool rotation carried past J5 = 0 asks J4 and J6 for half a turn each in a few
    periods. Shortening the step (the old reach) slows the arm to the joints' speed and winds J4 and J6
    round; every pass winds them further, to J4's limit. With the wrist's rotation lagging, the mount
    follows the path period by period, the joints within their speed, and the rotation catches up after."""
    frames, offsets, _, _ = _setup(Q_EASY, Q_EASY)
    path = _pass_by_the_wrist_singularity(frames, miss_deg=1.0)
    env = Envelope.from_rig(RigConfig())
    mirror = np.diag([1.0, -1.0, 1.0, 1.0])
    right = mirror @ path[0] @ mirror  # the right mount opposite, as it holds the rim
    seeds = {"left": cr5.ik(frames["left"].flange_in_base(path[0]), np.radians([48.6, -16.9, -92.1, 179.4, 1.0, -91.1])),
             "right": cr5.ik(frames["right"].flange_in_base(right), Q_EASY)}
    assert not violations({"left": path[-1], "right": right}, None, PERIOD, env)  # the path keeps the envelope
    start = dict(seeds)

    def run(lagging: bool):
        q, prev, fractions, lagged = dict(start), {"left": path[0], "right": right}, [], 0
        for T in path[1:] + [path[-1]] * 40:  # the path, then 40 periods at its end
            cmd = {"left": T, "right": right}
            solve = joint_solver(frames, q, offsets, LIMIT)
            lag = wrist_lag(frames, q, offsets, arm_solver(frames, q, offsets, LIMIT)) if lagging else None
            r = solve_within(prev, cmd, solve, lag=lag, accept=lambda poses, prev=prev: not violations(poses, prev, PERIOD, env))
            assert r.poses is not None and r.joints is not None
            for a in ARMS:
                assert np.max(np.abs(r.joints[a] - q[a])) <= LIMIT + 1e-12 and cr5.within_limits(r.joints[a])
                assert np.allclose(frames[a].mount_in_world(cr5.fk(r.joints[a])), r.poses[a], atol=1e-6)
            fractions.append(r.fraction)
            lagged += r.lagged is not None
            q, prev = r.joints, r.poses
        return q, prev, fractions, lagged

    q_old, _, fractions_old, _ = run(lagging=False)
    assert min(fractions_old) < 0.5  # the old reach: slowed to the joints' speed ...
    assert np.degrees(abs(q_old["left"][3] - seeds["left"][3])) > 90  # ... and J4 wound round
    q_new, sent, fractions_new, lagged = run(lagging=True)
    assert fractions_new == [1.0] * len(fractions_new) and lagged > 0  # every period's position sent whole
    assert np.degrees(abs(q_new["left"][3] - seeds["left"][3])) < 30  # J5 crossed zero instead of J4 and J6 spinning
    assert np.allclose(sent["left"][:3, 3], path[-1][:3, 3], atol=1e-9)
    caught_up = np.degrees(np.linalg.norm(rotvec_between(sent["left"][:3, :3], path[-1][:3, :3])))
    assert caught_up < 0.1
