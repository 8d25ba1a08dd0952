"""The ChArUco calibration board: what it looks like and where it is placed in the world.

`bagit calibrate` finds the camera-to-world extrinsics from one view of the board lying at a
known pose (`RigConfig.board`); the simulator renders the same board to test it. The board's
frame is OpenCV's: origin at the printed board's top-left corner, x along its top edge, y down
its left edge, z into the board (so a board lying face up has z pointing down).
"""

from __future__ import annotations

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bagit.common.aruco import ARUCO_DICTIONARIES, ArucoDictionary
from bagit.common.geometry import pose_to_matrix
from bagit.common.shapes import Vec3

SQUARE_PX = 120  # printed resolution of one square (board_image)


class BoardSpec(BaseModel):
    """A ChArUco board (chessboard squares with ArUco markers in the white ones) and its world pose."""

    model_config = ConfigDict(extra="forbid")

    squares_x: int = Field(7, ge=3, le=30)
    squares_y: int = Field(5, ge=3, le=30)
    square_length: float = Field(0.06, gt=0.005, lt=0.5, description="side of a chessboard square (m)")
    marker_length: float = Field(0.045, gt=0.002, lt=0.5, description="side of a marker's black square (m)")
    dictionary: ArucoDictionary = "DICT_4X4_50"
    # default: face up on a stand in the work area, centred at (0, 0, 0.45), its top edge towards +y
    position: Vec3 = Field((-0.21, 0.15, 0.45), description="world position of the board origin (m)")
    rpy: Vec3 = Field((np.pi, 0.0, 0.0), description="world orientation of the board frame")

    @model_validator(mode="after")
    def _fits(self) -> BoardSpec:
        if self.marker_length >= self.square_length:
            raise ValueError("a marker must be smaller than its square")
        if (self.squares_x * self.squares_y) // 2 > ARUCO_DICTIONARIES[self.dictionary]:
            raise ValueError(f"{self.dictionary} has too few markers for a {self.squares_x}x{self.squares_y} board")
        return self

    def size(self) -> tuple[float, float]:
        """(width, height) of the squares (m)."""
        return self.squares_x * self.square_length, self.squares_y * self.square_length

    def T_world_board(self) -> np.ndarray:
        """4x4 world <- board."""
        return pose_to_matrix(self.position, self.rpy)

    def cv_board(self):
        """The OpenCV CharucoBoard."""
        import cv2

        d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_length, self.marker_length, d)

    def image(self, square_px: int = SQUARE_PX, margin_squares: float = 0.5) -> np.ndarray:
        """The printable board `(h, w)` uint8, with a white margin of `margin_squares` squares round it."""
        import cv2

        img = self.cv_board().generateImage((self.squares_x * square_px, self.squares_y * square_px), marginSize=0)
        m = int(round(margin_squares * square_px))
        return cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
