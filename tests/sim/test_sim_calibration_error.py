"""The camera's calibration error (sim.camera.calibration_error): the simulator renders from the true pose,
perception back-projects with the believed one, so what it sees is displaced as on a miscalibrated rig."""

import numpy as np
import yaml
from scipy.spatial.transform import Rotation

from bagit.common.bag import CalibrationError
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception.rgbd import red_rim_mask, rim_cloud
from bagit.services.sim.world import SimWorld


def test_the_true_pose_is_the_believed_one_moved_and_turned_about_the_camera():
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [150, 5, 80], degrees=True).as_matrix()
    T[:3, 3] = [0.55, 0.0, 1.25]
    assert CalibrationError().true_pose(T) is T  # no error: the very pose, so older runs are unchanged
    e = CalibrationError(offset_m=(0.01, -0.02, 0.005), turn_deg=(0.0, 1.5, 0.0))
    Tt = e.true_pose(T)
    assert np.allclose(Tt[:3, 3], T[:3, 3] + [0.01, -0.02, 0.005])
    turn = Rotation.from_matrix(Tt[:3, :3] @ T[:3, :3].T)
    assert np.allclose(turn.as_rotvec(degrees=True), [0.0, 1.5, 0.0])
    assert np.allclose(e.size(), (np.linalg.norm([0.01, -0.02, 0.005]), 1.5))


def _rim_cloud_mean(offset) -> tuple[np.ndarray, np.ndarray, list[float]]:
    doc = yaml.safe_load(find_scenario("exp02").read_text())
    doc["sim"] = {"camera": {"calibration_error": {"offset_m": offset}, "depth_noise": 0.0}}
    with SimWorld(Scenario.from_dict(doc), seed=0) as w:
        w.step(0.3)
        frame = w.render_rgbd(0)
        return rim_cloud(frame, red_rim_mask).mean(axis=0), w.true_rim().mean(axis=0), frame.camera.T_world_camera


def test_a_camera_really_2cm_off_shows_the_rim_2cm_off_the_other_way():
    seen0, true0, T0 = _rim_cloud_mean([0.0, 0.0, 0.0])
    seen, true, T = _rim_cloud_mean([0.02, 0.0, 0.0])
    assert np.allclose(true, true0) and T == T0  # the same bag; the frame carries the believed pose
    assert np.allclose(seen - seen0, [-0.02, 0.0, 0.0], atol=0.002)
