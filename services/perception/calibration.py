"""Camera-to-world extrinsics from a view of the ChArUco board lying at a known world pose.

The board's chessboard corners (found through its ArUco markers, refined to subpixel on the
chessboard's saddle points, which unlike a marker's corners no inner bit pulls) and the board's
geometry give the board's pose in the camera (PnP, then Levenberg-Marquardt refinement). With the
board's pose in the world from the rig config: T_world_camera = T_world_board T_board_camera.
Several frames: the poses are averaged (rotations by their quaternion mean).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.spatial.transform import Rotation

from bagit.common.board import BoardSpec
from bagit.common.errors import MarkerNotFound
from bagit.common.geometry import invert_transform, make_transform
from bagit.common.messages import RgbdFrame

MIN_CORNERS = 6


@dataclass
class BoardView:
    """The board seen in one frame. T_camera_board: (4, 4); corners: how many chessboard corners."""

    T_camera_board: np.ndarray
    corners: int
    reprojection_px: float


@dataclass
class Calibration:
    """The estimated extrinsics. T_world_camera: (4, 4); spread_*: how much the frames disagree."""

    T_world_camera: np.ndarray
    frames: int
    corners: int
    reprojection_px: float
    spread_m: float
    spread_deg: float


def find_board(frame: RgbdFrame, board: BoardSpec) -> BoardView:
    """The board's pose in the camera from one frame's colour image, or MarkerNotFound."""
    cv_board = board.cv_board()
    gray = cv2.cvtColor(np.ascontiguousarray(frame.color, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    det = cv2.aruco.CharucoDetector(cv_board)
    ch_corners, ch_ids, _, marker_ids = det.detectBoard(gray)
    n = 0 if ch_ids is None else len(ch_ids)
    if n < MIN_CORNERS:
        seen = 0 if marker_ids is None else len(marker_ids)
        raise MarkerNotFound(
            f"calibration board ({board.squares_x}x{board.squares_y} ChArUco, {board.dictionary}) not found: "
            f"{seen} of its markers and {n} chessboard corners seen (need {MIN_CORNERS})"
        )
    obj, img = cv_board.matchImagePoints(ch_corners, ch_ids)
    K = frame.camera.K()
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, None, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise MarkerNotFound("no board pose from its corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, None, rvec, tvec)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, None)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img.reshape(-1, 2)) ** 2, axis=1))))
    return BoardView(make_transform(cv2.Rodrigues(rvec)[0], tvec.ravel()), n, err)


def calibrate_extrinsics(frames: Iterable[RgbdFrame], board: BoardSpec) -> Calibration:
    """T_world_camera from frames of the board at `board`'s world pose (frames without it are skipped;
    none with it: MarkerNotFound)."""
    Ts, views, last_err = [], [], None
    T_wb = board.T_world_board()
    for f in frames:
        try:
            v = find_board(f, board)
        except MarkerNotFound as e:
            last_err = e
            continue
        views.append(v)
        Ts.append(T_wb @ invert_transform(v.T_camera_board))
    if not Ts:
        raise last_err or MarkerNotFound("no frames to calibrate from")
    rots = Rotation.from_matrix(np.stack([T[:3, :3] for T in Ts]))
    R = rots.mean().as_matrix()
    p = np.mean([T[:3, 3] for T in Ts], axis=0)
    spread_m = float(max(np.linalg.norm(T[:3, 3] - p) for T in Ts))
    spread_deg = float(max(np.degrees((Rotation.from_matrix(T[:3, :3]) * Rotation.from_matrix(R).inv()).magnitude()) for T in Ts))
    return Calibration(make_transform(R, p), len(Ts), int(np.mean([v.corners for v in views])),
                       float(np.mean([v.reprojection_px for v in views])), spread_m, spread_deg)
