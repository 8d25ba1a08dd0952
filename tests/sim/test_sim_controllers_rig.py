"""The rig: two simulated CR5s bolted to the bag's mounts in the physics world, driven in Python and over TCP."""

import socket
import threading

import numpy as np
import pytest

from bagit.common import cr5, dobot
from bagit.common.errors import BadScenario
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.rig_sim import SimRig, natural_ik


@pytest.fixture(scope="module")
def scenario():
    return Scenario.from_file(find_scenario("exp01-coffee-box"))


def servo_both(rig: SimRig, offsets_mm: dict, seconds: float, period: float = 0.03) -> None:
    """Move each flange by `offsets_mm[name]` (its base frame, mm) with a smooth ServoP stream."""
    start = {name: arm.get_pose6() for name, arm in rig.arms.items()}
    n = int(round(seconds / period))
    for k in range(1, n + 1):
        s = 0.5 - 0.5 * np.cos(np.pi * k / n)
        for name, arm in rig.arms.items():
            p = start[name].copy()
            p[:3] += s * np.asarray(offsets_mm[name], dtype=float)
            assert arm.servo_p(p, t=period) == 0, arm.alarms()
        rig.step(period)


def rim_extent(rig: SimRig) -> np.ndarray:
    rim = rig.ground_truth().rim
    return rim.max(axis=0) - rim.min(axis=0)


def test_arms_start_holding_the_mounts_where_the_world_put_them(scenario):
    with SimRig(scenario, seed=0, camera=False) as rig:
        homes = rig.world.mount_home_poses()
        for name, arm in rig.arms.items():
            assert np.allclose(arm.mount_pose_world(), homes[name], atol=1e-9)
            assert arm.robot_mode() == dobot.RobotMode.DISABLED
            assert cr5.within_limits(arm.q) and not cr5.self_collision(arm.q)
        rig.step(0.2)  # disabled arms hold still, so do the mounts
        for name, T in rig.world.mount_poses().items():
            assert np.allclose(T[:3, 3], homes[name][:3, 3], atol=1e-9)


def test_moving_the_arms_apart_and_together_opens_and_closes_the_rim(scenario):
    with SimRig(scenario, seed=0, camera=False) as rig:
        for arm in rig.arms.values():
            assert arm.enable() == 0
        rig.step(0.4)
        e0 = rim_extent(rig)
        # each base's x axis points at the object: -x pulls the handles apart
        servo_both(rig, {"left": [-30, 0, 0], "right": [-30, 0, 0]}, 0.6)
        rig.step(0.3)
        apart = rim_extent(rig)
        mounts = rig.world.mount_poses()
        assert np.linalg.norm(mounts["left"][:3, 3] - mounts["right"][:3, 3]) == pytest.approx(0.212 + 0.06, abs=0.003)
        servo_both(rig, {"left": [70, 0, 0], "right": [70, 0, 0]}, 0.8)
        rig.step(0.3)
        together = rim_extent(rig)
        gt = rig.ground_truth()
        assert apart[1] > e0[1] + 0.02 and together[1] < e0[1] - 0.04  # along the handles
        assert apart[0] < e0[0]  # a fabric rim pulled long gets narrow
        assert together[2] > e0[2] + 0.01  # pushed together, its free stretches sag
        assert not gt.passed_through and np.all(np.isfinite(gt.rim))
        assert all(arm.alarms() == [] for arm in rig.arms.values())


def test_same_seed_and_commands_give_the_same_run(scenario):
    rims = []
    for _ in range(2):
        with SimRig(scenario, seed=3, camera=False) as rig:
            for arm in rig.arms.values():
                arm.enable()
            servo_both(rig, {"left": [-20, 10, 30], "right": [10, -10, 20]}, 0.45)
            rims.append(rig.ground_truth().rim)
    assert np.array_equal(rims[0], rims[1])


def test_the_arms_over_tcp_move_the_mounts(scenario):
    with SimRig(scenario, seed=0, camera=False, with_servers=True, ephemeral_ports=True) as rig:
        ports = rig.ports()
        assert len({p for pair in ports.values() for p in pair}) == 4
        stop = threading.Event()
        loop = threading.Thread(target=rig.run_realtime, kwargs={"speed": 1.0, "stop": stop})
        loop.start()
        try:
            dash = socket.create_connection(("127.0.0.1", ports["left"][0]), timeout=3.0)

            def ask(text: str) -> dobot.Reply:
                dash.sendall(text.encode())
                buf = b""
                while not buf.endswith(b";"):
                    buf += dash.recv(4096)
                return dobot.parse_reply(buf.decode())

            assert ask("EnableRobot(0.3)").ok
            z0 = rig.world.mount_poses()["left"][2, 3]
            pose = np.array(ask("GetPose()").values)
            for k in range(1, 11):
                p = pose + [0, 0, 2.0 * k, 0, 0, 0]
                assert ask(dobot.format_command("ServoP", *p, t=0.03)).ok
                stop.wait(0.03)
            stop.wait(0.4)
            fb = socket.create_connection(("127.0.0.1", ports["left"][1]), timeout=3.0)
            data = b""
            while len(data) < 1440:
                data += fb.recv(1440 - len(data))
            packet = dobot.parse_feedback(data)
            fb.close()
            dash.close()
        finally:
            stop.set()
            loop.join(timeout=10)
        assert rig.world.mount_poses()["left"][2, 3] - z0 == pytest.approx(0.020, abs=0.001)
        assert packet["ToolVectorActual"][2] - pose[2] == pytest.approx(20.0, abs=1.0)
        assert rig.world.mount_poses()["right"][2, 3] == pytest.approx(z0, abs=1e-9)  # the other arm never moved


class _FarWorld:
    """A stand-in world whose mounts start far beyond the arms' reach."""

    time = 0.0

    def mount_home_poses(self):
        T = np.eye(4)
        T[:3, 3] = [3.0, 0.0, 0.5]
        return {"left": T, "right": T}

    def close(self):
        self.closed = True


def test_mounts_out_of_reach_are_a_bad_scenario():
    w = _FarWorld()
    with pytest.raises(BadScenario, match="out of the arm's reach"):
        SimRig(world=w)
    assert w.closed


def test_natural_ik_faces_the_target_with_the_elbow_up():
    T = cr5.fk(np.radians([0, -44, -73, -153, 90, 1]))
    q = natural_ik(T)
    assert q is not None and np.allclose(cr5.fk(q), T, atol=1e-6)
    F = cr5.link_frames(q)
    assert F[2][2, 3] > cr5.D1  # elbow above the shoulder
    assert np.dot(F[2][:2, 3], T[:2, 3]) > 0  # upper arm leans toward the target
    far = np.eye(4)
    far[:3, 3] = [2.0, 0, 0]
    assert natural_ik(far) is None


def test_between_runs_the_world_rests_until_an_arm_moves_and_for_a_while_after(scenario):
    """`idle` (lockstep between runs): a world just built is at rest (its clock runs, its bag stays put);
    an arm's motion steps the physics, and REST_AFTER_S of stillness after it rests it again."""
    from bagit.services.sim.rig_sim import REST_AFTER_S

    with SimRig(scenario, seed=0, camera=False) as rig:
        v0, t0 = rig.world.bag_vertices().copy(), rig.time
        rig.idle(0.5)
        assert rig.time == pytest.approx(t0 + 0.5)
        assert np.array_equal(rig.world.bag_vertices(), v0)  # at rest: nothing stepped
        for arm in rig.arms.values():
            assert arm.enable() == 0
        pose = rig.arms["left"].get_pose6()
        pose[2] += 10.0
        assert rig.arms["left"].servo_p(pose, t=0.3) == 0
        rig.idle(0.3)  # the arm moves: the physics steps
        moved = rig.world.bag_vertices().copy()
        assert not np.array_equal(moved, v0)
        rig.idle(REST_AFTER_S / 2)  # still swinging after the arm stopped
        swung = rig.world.bag_vertices().copy()
        assert not np.array_equal(swung, moved)
        rig.idle(1.5 + REST_AFTER_S)  # the arm's joints settle to the last bit within ~1.5 s
        settled, t1 = rig.world.bag_vertices().copy(), rig.time
        rig.idle(0.2)
        assert np.array_equal(rig.world.bag_vertices(), settled) and rig.time == pytest.approx(t1 + 0.2)


def _world_state(rig: SimRig) -> tuple[np.ndarray, ...]:
    d = rig.world.data  # type: ignore[attr-defined]
    return d.qpos.copy(), d.qvel.copy(), d.qacc_warmstart.copy(), d.mocap_pos.copy(), d.mocap_quat.copy(), np.array([d.time])


def _after_settle(rig: SimRig) -> tuple[np.ndarray, ...]:
    """The world after a reset's settle and a second of a stream, and how the arms' stamps read the rig's clock."""
    stamps = [robot.time + robot.clock_offset - rig.clock_s for robot in rig.arms.values()]
    state = _world_state(rig)
    for arm in rig.arms.values():
        assert arm.enable() == 0
    servo_both(rig, {"left": [0, -40, 20], "right": [0, 40, 20]}, 1.0)
    return (*state, np.array(stamps), _world_state(rig)[0], np.array([rig.clock_s - rig.epoch]))


def test_a_world_settled_at_start_stands_in_for_a_reset_to_it_bit_for_bit(scenario):
    """`bagit up SCENARIO`'s simulator settles the world it starts with while the services start; the run's
    reset to that scenario and seed then takes it as it is (`resettle`): the same world as a reset and settle."""
    other = Scenario.from_file(find_scenario("exp02"))
    with SimRig(other, seed=3, camera=False) as fresh, SimRig(scenario, seed=3, camera=False) as reused:
        fresh.stamp_feedback()
        reused.stamp_feedback()
        fresh.idle(0.4)  # the services start: the world rests, its clock runs
        fresh.reset(scenario, 3)  # the run's world, built when the run asks for it
        fresh.settle(1.0)
        pushed: list[float] = []
        reused.settle(1.0, between=lambda: pushed.append(reused.time))  # the run's world at start, settled before the run asks for it
        assert len(pushed) == 25 and pushed[-1] == reused.time  # every 10 steps of 4 ms
        reused.idle(0.7)
        assert not reused.resettle(scenario, 4, 1.0) and not reused.resettle(scenario, 3, 0.5)  # another seed, another settle
        assert reused.resettle(scenario, 3, 1.0)
        assert not reused.resettle(scenario, 3, 1.0)  # once: it is now the run's
        for a, b in zip(_after_settle(fresh), _after_settle(reused), strict=True):
            assert np.array_equal(a, b)


def test_a_settled_world_that_stepped_since_is_built_again(scenario):
    with SimRig(scenario, seed=0, camera=False) as rig:
        rig.settle(1.0)
        for arm in rig.arms.values():
            assert arm.enable() == 0
        pose = rig.arms["left"].get_pose6()
        pose[2] += 5.0
        assert rig.arms["left"].servo_p(pose, t=0.3) == 0
        rig.idle(0.3)  # between runs an arm moved: the physics stepped
        assert not rig.resettle(scenario, 0, 1.0)
    with SimRig(scenario, seed=0, camera=False) as rig:
        rig.idle(0.3)
        rig.settle(1.0)  # not right after it was built: its clock ran
        assert not rig.resettle(scenario, 0, 1.0)
