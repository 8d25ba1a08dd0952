"""The simulated world: a fabric bag that behaves like one, an object it cannot pass through, mounts
that shape the rim, determinism, and bad input rejected."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.common.dual_arm import apply_increment
from bagit.common.errors import BadScenario, BagItError, SafetyViolation
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.judge import inside_polygon
from bagit.services.sim.objects import ConvexPart
from bagit.services.sim.truth import PENETRATION_TOL_M, PenetrationMonitor
from bagit.services.sim.world import MAX_MOUNT_SPEED_MPS, SimWorld


@pytest.fixture(scope="module")
def coffee():
    return Scenario.from_file(find_scenario("exp01-coffee-box"))


@pytest.fixture(scope="module")
def can():
    return Scenario.from_file(find_scenario("exp02-canned-pineapple"))


def move_mounts(w: SimWorld, offsets: dict, seconds: float, settle: float = 0.3, rotvecs: dict | None = None) -> None:
    """Move each mount by `offsets[name]` (m, world) and turn it by `rotvecs[name]` (rad, world, about
    the mount), with a smooth start and stop, as the arms would."""
    start = w.mount_poses()
    rotvecs = rotvecs or {}
    steps = max(1, int(seconds / 0.02))
    for k in range(1, steps + 1):
        s = 0.5 - 0.5 * np.cos(np.pi * k / steps)
        targets = {}
        for name, T in start.items():
            T2 = T.copy()
            T2[:3, 3] += s * np.asarray(offsets.get(name, (0, 0, 0)), dtype=float)
            T2[:3, :3] = Rotation.from_rotvec(s * np.asarray(rotvecs.get(name, (0, 0, 0)), dtype=float)).as_matrix() @ T[:3, :3]
            targets[name] = T2
        w.set_mount_targets(targets)
        w.step(0.02)
    w.step(settle)


def extent(w: SimWorld) -> np.ndarray:
    rim = w.true_rim()
    return rim.max(axis=0) - rim.min(axis=0)


def test_pulled_apart_the_rim_narrows_then_goes_taut_pushed_together_it_buckles(coffee):
    """Fabric hardly stretches and does not resist compression: a little apart, the rim straightens
    and gets narrow, and then pulls back hard (tens of N) for a few per cent of stretch; pushed
    together, its free stretches buckle and sag, and the pull drops to the bag's weight."""
    w = SimWorld(coffee, seed=0, camera=False)
    w.step(0.5)
    e0, R0 = extent(w), w.ground_truth().rim_perimeter
    f0 = w.mount_forces()
    assert f0["left"][2] == pytest.approx(-0.08 * 9.81 / 2, rel=0.1)  # at rest each mount carries half the bag
    move_mounts(w, {"left": [0, -0.01, 0], "right": [0, 0.01, 0]}, 0.4)
    e_apart, R_apart, f_apart = extent(w), w.ground_truth().rim_perimeter, w.mount_forces()
    assert e_apart[0] < e0[0] - 0.03 and e_apart[1] > e0[1] + 0.015  # narrower across, longer along
    assert f_apart["left"][1] > 5.0 and f_apart["right"][1] < -5.0  # taut: the bag pulls the mounts together
    assert abs(R_apart / R0 - 1) < 0.04  # fabric, not rubber
    move_mounts(w, {"left": [0, 0.06, 0], "right": [0, -0.06, 0]}, 1.0)
    e_together, R_together, f_together = extent(w), w.ground_truth().rim_perimeter, w.mount_forces()
    assert e_together[1] < e0[1] - 0.06 and e_together[2] > e0[2] + 0.015  # shorter, and sagging
    assert abs(R_together / R0 - 1) < 0.03
    assert np.linalg.norm(f_together["left"]) < 2.0
    assert np.all(np.isfinite(w.bag_vertices()))


@pytest.mark.slow
def test_every_mount_input_moves_the_rim_and_the_response_is_learnable(coffee):
    """The controller's 12-D input (each mount's translation and rotation) has a real, repeatable,
    locally linear effect on the rim: finite differences from one bag state give a Jacobian of rank >= 8."""
    w = SimWorld(coffee, seed=0, camera=False)
    w.step(0.8)
    base, start = w.save_state(), w.mount_poses()

    def rim_after(u: np.ndarray) -> np.ndarray:
        w.restore_state(base)
        w.set_mount_targets(apply_increment(start, u))
        w.step(0.3)
        return w.true_rim().ravel()

    r0 = rim_after(np.zeros(12))
    assert np.array_equal(r0, rim_after(np.zeros(12)))  # branching from a snapshot replays exactly
    cols, nonlinear = [], []
    for i in range(12):
        du = np.zeros(12)
        du[i] = 0.01 if i % 6 < 3 else 0.1  # 1 cm or 0.1 rad
        rp, rm = rim_after(du), rim_after(-du)
        cols.append((rp - rm) / 2)
        nonlinear.append(np.linalg.norm(rp + rm - 2 * r0) / np.linalg.norm(rp - rm))
    J = np.array(cols).T  # (3 * 24, 12): rim change per input step
    norms = np.linalg.norm(J, axis=0)
    translations = [0, 1, 2, 6, 7, 8]
    assert norms[translations].min() > 0.02  # a 1 cm mount move moves the rim points by cm in all
    assert norms[[4, 5, 10, 11]].min() > 0.01  # turning a mount about y or z reshapes the rim
    sv = np.linalg.svd(J, compute_uv=False)
    assert np.sum(sv > 0.05 * sv[0]) >= 8
    assert max(nonlinear[i] for i in translations) < 0.3  # small moves: close to linear, so learnable


def test_clamped_rim_stretch_moves_rigidly_with_its_mount(coffee):
    w = SimWorld(coffee, seed=0, camera=False)
    ids = w.layout.handles["left"]
    T0 = w.mount_poses()["left"]
    local0 = (w.bag_vertices()[ids] - T0[:3, 3]) @ T0[:3, :3]
    move_mounts(w, {"left": [0.03, 0.02, 0.05]}, 0.6, rotvecs={"left": [0.2, -0.3, 0.4]})
    T = w.mount_poses()["left"]
    local = (w.bag_vertices()[ids] - T[:3, 3]) @ T[:3, :3]
    assert not np.allclose(T, T0, atol=1e-3)
    assert np.abs(local - local0).max() < 0.003  # clamped: at most the give of a stiff constraint


def test_home_poses_hold_the_handles_from_outside(coffee):
    w = SimWorld(coffee, seed=0, camera=False)
    homes = w.mount_home_poses()
    c = w.true_rim().mean(axis=0)
    for name, sign in (("left", -1), ("right", 1)):
        T = homes[name]
        assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-9) and np.linalg.det(T[:3, :3]) > 0
        assert np.sign(T[1, 3] - c[1]) == sign  # left handle at -y, right at +y
        flange = T @ np.linalg.inv(w.rig.arms[name].T_flange_mount())
        rim_reach = np.abs(w.true_rim()[:, 1] - c[1]).max()
        assert abs(flange[1, 3] - c[1]) > rim_reach  # the flange (and the arm) stay outside the bag
        assert np.allclose(w.mount_poses()[name], T, atol=1e-12)


def test_default_start_without_a_given_rim_is_below_the_object():
    s = Scenario.from_file(find_scenario("exp03-grapefruit"))
    data = s.model_dump()
    data["bag"]["initial_rim"] = None
    s2 = Scenario.from_dict(data)
    w = SimWorld(s2, seed=0, camera=False)
    rim = w.true_rim()
    lowest = min(p[2] for p in s2.object.shape.hull_points())
    assert rim[:, 2].max() < lowest - 0.05
    assert w.ground_truth().rim_perimeter == pytest.approx(s2.bag.rim_perimeter, rel=0.02)


@pytest.mark.slow
def test_raising_around_the_object_wraps_without_passing_through(can):
    w = SimWorld(can, seed=0, camera=False)
    w.step(0.3)
    c = w.true_rim().mean(axis=0)
    V = can.object.bottom_vertices()
    bottom = V[:, 2].min()
    down = min(0.0, bottom - 0.06 - w.true_rim()[:, 2].max())
    both = lambda v: {"left": v, "right": v}  # noqa: E731
    move_mounts(w, both([0, 0, down]), 0.6, settle=0.0)
    move_mounts(w, both([V[:, 0].mean() - c[0], V[:, 1].mean() - c[1], 0]), 1.2, settle=0.0)
    move_mounts(w, both([0, 0, bottom + 0.05 - w.true_rim()[:, 2].mean()]), 1.2)
    gt = w.ground_truth()
    assert not gt.passed_through and gt.max_penetration_m < 0.003
    assert gt.rim[:, 2].min() > bottom + 0.02  # the rim is above the object's bottom ...
    assert inside_polygon(gt.rim[:, :2], V[:, :2]).all()  # ... and goes round it


def test_the_object_stops_the_fabric(can):
    """Lifting the bag off-centre drags its rim and wall against the can's bottom edge: the fabric
    gets caught and pushed aside, but no part of it enters the can."""
    w = SimWorld(can, seed=0, camera=False)
    w.step(0.3)
    c = w.true_rim().mean(axis=0)
    V = can.object.bottom_vertices()
    bottom = V[:, 2].min()
    both = lambda v: {"left": v, "right": v}  # noqa: E731
    move_mounts(w, both([V[:, 0].mean() + 0.04 - c[0], -c[1], min(0.0, bottom - 0.06 - w.true_rim()[:, 2].max())]), 1.0, settle=0.0)
    touched = 0.0
    start = w.mount_poses()
    for k in range(1, 41):  # up by 0.14 m at 0.17 m/s
        targets = {n: T.copy() for n, T in start.items()}
        for T in targets.values():
            T[2, 3] += 0.14 * k / 40
        w.set_mount_targets(targets)
        w.step(0.02)
        gt = w.ground_truth()
        assert gt.clearance_m == -w._monitor.depth(w.bag_vertices())  # the last step's depth is the world's now
        touched = max(touched, -gt.clearance_m)
    gt = w.ground_truth()
    assert touched > -0.006  # the fabric's mid-surface came within its half-thickness and the contact gap
    assert not gt.passed_through and gt.max_penetration_m < 0.003


def test_the_penetration_check_sees_an_edge_poking_between_vertices():
    """A fabric triangle the size of the bag's (3 x 7 cm) with all corners outside a box, its middle
    cut by the box's edge 1 cm deep, counts as passed through; and the verdict is latched."""
    box = ConvexPart.from_points(np.array([[x, y, z] for x in (0, 0.1) for y in (0, 0.1) for z in (0, 0.1)], dtype=float))
    mon = PenetrationMonitor([box], np.array([[0, 1, 2]]))
    outside = np.array([[-0.01, 0.05, 0.13], [-0.01, 0.035, 0.06], [-0.01, 0.065, 0.06]])
    mon.update(outside)
    assert not mon.passed and mon.max_depth <= 0
    # the triangle slices the box's top-front edge (x = 0, z = 0.1) in the plane x - z = -0.08:
    # its corners lie outside, its middle 1 cm deep inside
    across = np.array([[-0.02, 0.035, 0.06], [-0.02, 0.065, 0.06], [0.04, 0.05, 0.12]])
    assert all(box.depth(across) <= 0)
    assert mon.depth(across) > PENETRATION_TOL_M
    mon.update(across)
    mon.update(outside)
    assert mon.passed and mon.max_depth > PENETRATION_TOL_M


def test_round_parts_measure_depth_exactly():
    s = Scenario.from_file(find_scenario("exp11-two-bound-tilted"))
    from bagit.services.sim.objects import object_parts

    parts = object_parts(s.object)
    assert len(parts) == 2 and all(p.kind == "cylinder" for p in parts)
    c, a = parts[0].center, parts[0].axis
    ortho = np.cross(a, [1.0, 0.0, 0.0])
    ortho /= np.linalg.norm(ortho)
    on_wall = c + parts[0].radius * ortho
    assert parts[0].depth(np.array([c, on_wall, c + 0.5 * parts[0].half_height * a]))[:2] == pytest.approx([0.035, 0.0], abs=1e-12)


@pytest.mark.slow
def test_fast_mount_motion_stays_stable(coffee):
    """Random motion at the arms' limits (0.25 m/s, 1 rad/s) for 3 s, the mounts kept no further apart
    than the rim allows (as the arm driver keeps them): finite, and the fabric keeps its length."""
    w = SimWorld(coffee, seed=0, camera=False)
    w.step(0.3)
    rng = np.random.default_rng(0)
    poses = w.mount_poses()
    R0 = w.ground_truth().rim_perimeter
    reach = np.linalg.norm(poses["left"][:3, 3] - poses["right"][:3, 3]) + 0.01
    for _ in range(90):
        for T in poses.values():
            T[:3, 3] += rng.normal(size=3) / np.sqrt(3) * 0.25 / 30
            T[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * 1.0 / 30).as_matrix() @ T[:3, :3]
        d = np.linalg.norm(poses["left"][:3, 3] - poses["right"][:3, 3])
        if d > reach:
            mid = (poses["left"][:3, 3] + poses["right"][:3, 3]) / 2
            for T in poses.values():
                T[:3, 3] = mid + (T[:3, 3] - mid) * reach / d
        w.set_mount_targets(poses)
        w.step(1 / 30)
    assert np.all(np.isfinite(w.bag_vertices()))
    assert abs(w.ground_truth().rim_perimeter / R0 - 1) < 0.05


def test_a_target_jump_is_followed_at_the_arm_speed_limit(coffee):
    w = SimWorld(coffee, seed=0, camera=False)
    T = w.mount_poses()["left"].copy()
    p0 = T[:3, 3].copy()
    T[:3, 3] += [0.0, -0.5, 0.3]  # 0.58 m away
    w.set_mount_targets({"left": T})
    w.step(0.1)
    moved = np.linalg.norm(w.mount_poses()["left"][:3, 3] - p0)
    assert moved == pytest.approx(MAX_MOUNT_SPEED_MPS * 0.1, rel=0.05)
    w.step(1.0)
    assert np.allclose(w.mount_poses()["left"][:3, 3], T[:3, 3], atol=1e-9)
    assert np.all(np.isfinite(w.bag_vertices()))


def test_determinism_with_contact(can):
    rims = []
    for _ in range(2):
        w = SimWorld(can, seed=3, camera=False)
        move_mounts(w, {"left": [-0.12, 0.0, 0.06], "right": [-0.12, 0.0, 0.06]}, 0.6, settle=0.2)
        rims.append(w.bag_vertices())
    assert np.array_equal(rims[0], rims[1])


def test_bad_input_is_rejected(coffee):
    w = SimWorld(coffee, seed=0, camera=False)
    T = np.eye(4)
    T[0, 3] = np.nan
    with pytest.raises(ValueError):
        w.set_mount_targets({"left": T})
    with pytest.raises(ValueError):
        w.set_mount_targets({"middle": np.eye(4)})
    skew = np.eye(4)
    skew[0, 1] = 0.5
    with pytest.raises(ValueError):
        w.set_mount_targets({"left": skew})
    with pytest.raises(ValueError):
        w.set_mount_targets({"left": np.eye(3)})
    for dt in (np.nan, -0.1, np.inf):
        with pytest.raises(ValueError):
            w.step(dt)
    with pytest.raises(BagItError):  # the project's error, so the CLI reports it in one line
        w.step(-1)
    # a rejected call changes nothing
    assert np.allclose(w.mount_poses()["left"], w.mount_home_poses()["left"])
    with pytest.raises(RuntimeError):
        w.render_rgbd(0)
    assert issubclass(SafetyViolation, BagItError)


def test_a_start_through_the_table_or_the_object_is_a_bad_scenario(coffee):
    low = coffee.model_dump()
    low["bag"]["initial_rim"] = (np.asarray(low["bag"]["initial_rim"]) - [0, 0, 0.3]).tolist()
    with pytest.raises(BadScenario, match="table"):
        SimWorld(Scenario.from_dict(low), camera=False)
    inside = coffee.model_dump()
    rim = np.asarray(inside["bag"]["initial_rim"])
    # the rim beside the box at its middle height: the bag's wall would run through the box
    inside["bag"]["initial_rim"] = (rim - rim.mean(axis=0) + [0.09, 0.0, 0.6]).tolist()
    with pytest.raises(BadScenario, match="into the object"):
        SimWorld(Scenario.from_dict(inside), camera=False)
