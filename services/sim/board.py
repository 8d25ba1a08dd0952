"""A calibration scene: the rig's table and camera with only the ChArUco board (`RigConfig.board`) in
view, to test `bagit calibrate` against a camera whose pose the test knows.

The board is a thin textured box whose top face carries the printed board (MuJoCo maps the image's
columns along the box's x and its rows down its -y). The board frame (OpenCV's: origin at the
printed top-left corner, x right, y down, z into the board) sits on that face.
"""

from __future__ import annotations

import cv2
import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common.board import BoardSpec
from bagit.common.messages import RgbdFrame
from bagit.common.rig import RigConfig
from bagit.services.sim.camera import DepthNoise, RgbdRenderer, add_depth_noise
from bagit.services.sim.scene import TABLE_RGBA, camera_mjcf

BOARD_THICKNESS_M = 0.003
MARGIN_SQUARES = 0.5


def _v(x) -> str:
    return " ".join(f"{float(c):.9g}" for c in np.ravel(x))


def board_mjcf(board: BoardSpec, rig: RigConfig) -> tuple[str, dict[str, bytes]]:
    """(MJCF, texture files) of the table, the board at its pose and the rig's camera."""
    w, h = board.size()
    m = MARGIN_SQUARES * board.square_length
    # box <- board: the printed top-left corner of the squares, on the top face, y and z flipped
    T_box_board = np.array([[1.0, 0, 0, -w / 2], [0, -1.0, 0, h / 2], [0, 0, -1.0, BOARD_THICKNESS_M / 2], [0, 0, 0, 1]])
    T = board.T_world_board() @ np.linalg.inv(T_box_board)
    x, y, z, qw = Rotation.from_matrix(T[:3, :3]).as_quat()
    ok, png = cv2.imencode(".png", board.image(margin_squares=MARGIN_SQUARES))
    cam = rig.camera
    xml = f"""<mujoco model="bagit-calibration">
  <visual><global offwidth="{max(cam.width, 640)}" offheight="{max(cam.height, 480)}"/><map znear="0.01" zfar="5"/>
    <quality shadowsize="0" offsamples="0"/></visual>
  <statistic extent="2" center="0 0 0.4"/>
  <asset><texture name="board_tex" type="2d" file="board.png"/>
    <material name="board_mat" texture="board_tex" specular="0" shininess="0" reflectance="0"/></asset>
  <worldbody>
    <light pos="0 0 2.5" dir="0 0 -1" diffuse="0.8 0.8 0.8"/>
    <light pos="1 1 2" dir="-0.5 -0.5 -1" diffuse="0.4 0.4 0.4"/>
    <geom name="table" type="plane" size="3 3 0.05" pos="0 0 {rig.table_height}" rgba="{TABLE_RGBA}"/>
    <geom name="board" type="box" size="{w / 2 + m:.9g} {h / 2 + m:.9g} {BOARD_THICKNESS_M / 2:.9g}" pos="{_v(T[:3, 3])}"
      quat="{_v([qw, x, y, z])}" material="board_mat" contype="0" conaffinity="0"/>
    {camera_mjcf(cam, cam.T_world_camera())}
  </worldbody>
</mujoco>"""
    return xml, {"board.png": png.tobytes()}


def render_board(rig: RigConfig, seed: int = 0, noise: DepthNoise | None = None) -> RgbdFrame:
    """One RGB-D frame of the board from the rig's camera (depth with the D455-like noise by default)."""
    xml, files = board_mjcf(rig.board, rig)
    model = mujoco.MjModel.from_xml_string(xml, assets=files)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    renderer = RgbdRenderer(model, rig.camera)
    try:
        color, z = renderer.render(data)
        z = add_depth_noise(z, noise or DepthNoise(), np.random.default_rng(seed), renderer.rays)
    finally:
        renderer.close()
    info = rig.camera.info()
    units = np.round(z / np.float32(info.depth_scale))
    return RgbdFrame(camera=info, color=color, depth=np.where(units <= 65535, units, 0).astype(np.uint16))
