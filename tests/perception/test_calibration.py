"""`bagit calibrate`: the camera's pose from a simulated ChArUco board, against the pose it was rendered from."""

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from bagit.cli import main
from bagit.common.board import BoardSpec
from bagit.common.errors import BadScenario, MarkerNotFound
from bagit.common.geometry import pose_to_matrix
from bagit.common.messages import RgbdFrame
from bagit.common.rig import RigConfig
from bagit.services.perception.calibration import calibrate_extrinsics
from bagit.services.perception.rs_recording import write_recording
from bagit.services.sim.board import render_board


def errors(T, T_true):
    return float(np.linalg.norm(T[:3, 3] - T_true[:3, 3])), float(np.degrees(Rotation.from_matrix(T[:3, :3].T @ T_true[:3, :3]).magnitude()))


def moved_rig(rig: RigConfig, dp, drpy) -> tuple[RigConfig, np.ndarray]:
    """The rig with its camera moved by (dp, drpy) in its own frame: where the camera really is."""
    T = rig.camera.T_world_camera() @ pose_to_matrix(dp, drpy)
    return rig.model_copy(update={"camera": rig.camera.with_pose(T)}), T


@pytest.mark.parametrize("dp, drpy", [((0.0, 0.0, 0.0), (0.0, 0.0, 0.0)), ((0.03, -0.02, 0.04), (0.02, -0.03, 0.05)),
                                      ((-0.05, 0.04, -0.03), (-0.04, 0.02, -0.06))])
def test_board_recovers_the_camera_pose(dp, drpy):
    rig = RigConfig()
    truth, T_true = moved_rig(rig, dp, drpy)
    frame = render_board(truth, seed=1)
    cal = calibrate_extrinsics([frame], rig.board)  # knows only the board's pose, not the camera's
    pos, ang = errors(cal.T_world_camera, T_true)
    assert pos < 0.005 and ang < 0.3
    assert cal.corners >= 15 and cal.reprojection_px < 0.5


def test_calibrate_command_from_a_recording_writes_the_rig(tmp_path, capsys):
    rig = RigConfig()
    truth, T_true = moved_rig(rig, (0.02, 0.01, -0.02), (0.03, 0.0, -0.02))
    frames = [render_board(truth, seed=s).model_copy(update={"seq": s, "stamp": s / 30}) for s in range(3)]
    write_recording(frames, tmp_path / "board.db3", real_time=False)
    (tmp_path / "rig.yaml").write_text(rig.to_yaml())
    out = tmp_path / "calibrated.yaml"
    code = main(["calibrate", "--rig-config", str(tmp_path / "rig.yaml"), "--file", str(tmp_path / "board.db3"), "--frames", "3",
                 "--write", str(out), "--json"])
    assert code == 0
    written = RigConfig.from_file(out)
    pos, ang = errors(written.camera.T_world_camera(), T_true)
    assert pos < 0.005 and ang < 0.3
    assert written.camera.serial == "BAGIT-SIM" and written.arms == rig.arms and written.board == rig.board


def test_calibrate_command_from_an_image(tmp_path, capsys):
    rig = RigConfig()
    truth, T_true = moved_rig(rig, (0.0, 0.02, 0.0), (0.0, 0.02, 0.0))
    png = tmp_path / "board.png"
    cv2.imwrite(str(png), cv2.cvtColor(render_board(truth).color, cv2.COLOR_RGB2BGR))
    assert main(["calibrate", "--image", str(png)]) == 0
    assert "written" not in capsys.readouterr().out
    assert main(["calibrate", "--image", str(tmp_path / "missing.png")]) == 2
    assert "cannot read image" in capsys.readouterr().err


def test_no_board_in_view_is_a_clear_error(tmp_path, capsys):
    blank = RgbdFrame(color=np.full((480, 640, 3), 200, np.uint8), depth=np.zeros((480, 640), np.uint16))
    with pytest.raises(MarkerNotFound, match=r"calibration board \(7x5 ChArUco, DICT_4X4_50\) not found"):
        calibrate_extrinsics([blank], RigConfig().board)
    png = tmp_path / "blank.png"
    cv2.imwrite(str(png), blank.color)
    assert main(["calibrate", "--image", str(png)]) == 2
    assert "board" in capsys.readouterr().err


def test_board_spec_validation(tmp_path):
    with pytest.raises(ValueError, match="smaller than its square"):
        BoardSpec(square_length=0.03, marker_length=0.04)
    with pytest.raises(ValueError, match="too few markers"):
        BoardSpec(squares_x=12, squares_y=10)
    with pytest.raises(ValueError, match="unknown ArUco dictionary 'DICT_9X9_1'"):
        BoardSpec(dictionary="DICT_9X9_1")
    assert BoardSpec(dictionary="DICT_5X5_100", squares_x=14, squares_y=14).dictionary == "DICT_5X5_100"
    (tmp_path / "r.yaml").write_text("board: {squares_x: 2}\n")
    with pytest.raises(BadScenario, match="board.squares_x"):
        RigConfig.from_file(tmp_path / "r.yaml")
    assert main(["calibrate", "--print-board", str(tmp_path / "b.png")]) == 0
    img = cv2.imread(str(tmp_path / "b.png"), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (6 * 120, 8 * 120)  # 7x5 squares of 120 px and half a square of margin each side
