"""`bagit run`'s arm side: the arm driver's motion rules streaming to two simulated CR5s in process.

Near the wrist singularity a small tilt of the mount asks J4 and J6 for large turns. Sent as is, the
controller alarms on its joint speed and the run stops; the arm side must instead let the rotation lag
what the joints can follow (the mount's position sent whole), count it, and get there; a step out of
the arms' reach is slowed.
"""

import numpy as np

from bagit.common import cr5
from bagit.common.messages import Command
from bagit.common.rig import ARMS, RigConfig
from bagit.common.so3 import rotvec_between
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.sim_arms import Cr5Arms

Q_NEAR_SINGULAR = np.radians([10.0, -20.0, 100.0, -80.0, 1.5, 30.0])  # J5 near 0: J4 and J6 nearly parallel
Q_EASY = np.radians([-10.0, -20.0, 100.0, -80.0, 60.0, 30.0])
CONTROL_DT = 1 / 30


def _arms(q_left: np.ndarray, q_right: np.ndarray) -> tuple[Cr5Arms, dict[str, SimulatedCR5]]:
    """Two CR5s where the test puts them; the workspace and separation limits opened (not what is tested here)."""
    rig = RigConfig()
    rig = rig.model_copy(update={
        "arms": {a: rig.arms[a].model_copy(update={"workspace_min": (-2.0, -2.0, -2.0), "workspace_max": (2.0, 2.0, 2.0)}) for a in ARMS},
        "safety": rig.safety.model_copy(update={"min_flange_distance_m": 0.0, "rim_perimeter_m": 9.9}),
    })
    robots = {"left": SimulatedCR5(rig.arms["left"], q0=q_left, name="left"), "right": SimulatedCR5(rig.arms["right"], q0=q_right, name="right")}

    def step(dt: float) -> None:
        for r in robots.values():
            r.step(dt)

    arms = Cr5Arms(rig, robots, step)
    arms.start()
    return arms, robots


def _drive(arms: Cr5Arms, u_per_tick: np.ndarray, ticks: int, settle_ticks: int) -> None:
    """`ticks` control ticks of `u_per_tick`, then zero increments (the stream kept alive) while the arms catch up;
    servo periods and control ticks interleaved on one simulated clock, as `bagit run` does."""
    t, next_servo, next_tick, k = 0.0, 0.0, 0.0, 0
    while k < ticks + settle_ticks:
        if t >= next_servo - 1e-9:
            arms.servo(t)
            next_servo += arms.period
        if t >= next_tick - 1e-9:
            arms.submit(Command(u=u_per_tick if k < ticks else np.zeros(12), dt=CONTROL_DT), t)
            next_tick += CONTROL_DT
            k += 1
        dt = min(next_servo, next_tick) - t
        arms.step(dt)
        t += dt


def test_a_tilt_through_a_wrist_singularity_lags_and_completes_without_an_alarm():
    arms, robots = _arms(Q_NEAR_SINGULAR, Q_EASY)
    start = robots["left"].mount_pose_world()
    # tilt the left mount 3 deg about its flange's y axis (the turn the near-singular wrist cannot make directly)
    axis = robots["left"].flange_pose_world()[:3, 1]
    u = np.zeros(12)
    u[3:6] = np.radians(0.3) * axis
    _drive(arms, u, ticks=10, settle_ticks=150)
    ev = arms.events()
    assert ev["lagged"] > 0 and ev["slowed"] == 0, ev  # the joints set the rotation's pace, the mount stays put ...
    assert ev["faults"] == 0 and ev["alarms"] == 0 and ev["rejected"] == 0, (ev, arms.fault)  # ... and nothing stopped
    assert not robots["left"].alarms() and not robots["right"].alarms()
    end = robots["left"].mount_pose_world()
    turned = np.degrees(np.linalg.norm(rotvec_between(start[:3, :3], end[:3, :3])))
    assert abs(turned - 3.0) < 0.05, turned  # it got there
    assert np.linalg.norm(end[:3, 3] - start[:3, 3]) < 5e-4
    assert np.max(np.abs(robots["left"].qd)) < cr5.JOINT_SPEED_LIMIT


def test_a_fault_stops_streaming_refuses_commands_and_shows_in_the_arm_states():
    arms, robots = _arms(Q_EASY, Q_EASY)
    robots["right"].raise_alarm(18)  # a controller in error (a joint limit)
    _drive(arms, np.r_[0.001, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0], ticks=5, settle_ticks=0)
    ev = arms.events()
    assert arms.fault is not None and "right" in arms.fault and "18" in arms.fault
    assert ev["faults"] == 1 and ev["alarms"] == 1 and ev["rejected"] >= 4
    states = arms.states()
    assert states["left"].error and states["left"].error_reason.startswith("driver fault")


def test_the_arm_states_report_the_motion_still_in_flight_and_a_lagged_step_is_not_slowed():
    """What the controller predicts from: target_pose (where the arm side is taking each mount) less
    tool_pose is the motion taken and not yet made; slowed says the joints set the pace of the mounts, which a
    rotation lagging at the wrist singularity does not (the positions are sent whole)."""
    arms, robots = _arms(Q_NEAR_SINGULAR, Q_EASY)
    start = {a: robots[a].mount_pose_world() for a in ARMS}
    axis = robots["left"].flange_pose_world()[:3, 1]
    u = np.zeros(12)
    u[3:6] = np.radians(0.3) * axis  # the tilt the near-singular wrist must lag
    u[6] = 0.001  # and the right mount 1 mm per tick along x
    _drive(arms, u, ticks=10, settle_ticks=0)
    states = arms.states()
    lagged_then = arms.events()["lagged"] > 0 and not states["left"].slowed and not states["right"].slowed
    aim = {a: states[a].target_pose for a in ARMS}
    assert np.allclose(aim["right"][:3], start["right"][:3, 3] + [0.010, 0, 0], atol=1e-6)  # all ten ticks taken ...
    assert aim["right"][0] - states["right"].tool_pose[0] > 0.002  # ... and not all made yet
    _drive(arms, np.zeros(12), ticks=0, settle_ticks=150)
    states = arms.states()
    assert lagged_then and not states["left"].slowed
    for a in ARMS:  # once the arms caught up, nothing is in flight
        assert np.allclose(states[a].target_pose[:3], states[a].tool_pose[:3], atol=5e-4), a
