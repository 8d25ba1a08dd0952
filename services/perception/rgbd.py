"""From an RGB-D frame to the rim cloud: segment the rim band, back-project it, move it to the world.

Segmentation is a hook: any callable `frame -> (H, W) bool mask` can replace the red-rim colour
threshold (for a solid-colour bag, a learned segmenter, ...).
"""

from __future__ import annotations

from typing import Callable

import cv2
import numpy as np

from bagit.common.errors import BadCloud
from bagit.common.geometry import transform_points
from bagit.common.messages import CameraInfo, RgbdFrame

Segmenter = Callable[[RgbdFrame], np.ndarray]

# Red wraps round hue 0 in OpenCV's 0-179 hue scale: two bands.
RED_HUE_BANDS = ((0, 10), (170, 179))
MIN_SATURATION = 110
MIN_VALUE = 50


def red_rim_mask(frame: RgbdFrame) -> np.ndarray:
    """(H, W) bool: pixels of the bag's red edge (HSV threshold on the RGB image)."""
    hsv = cv2.cvtColor(frame.color, cv2.COLOR_RGB2HSV)
    mask = np.zeros(hsv.shape[:2], dtype=np.uint8)
    for lo, hi in RED_HUE_BANDS:
        mask |= cv2.inRange(hsv, (lo, MIN_SATURATION, MIN_VALUE), (hi, 255, 255))
    # No morphological opening: at 1 m a rim band is only 2-4 pixels wide and would be erased;
    # isolated red specks are left to EM's outlier term.
    return mask.astype(bool)


def back_project(depth_m: np.ndarray, camera: CameraInfo, mask: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points `(n, 3)` of the pixels with valid depth (and in `mask`). depth_m: (H, W) metres."""
    valid = depth_m > 0
    if mask is not None:
        valid &= mask
    v, u = np.nonzero(valid)
    z = depth_m[v, u]
    x = (u - camera.cx) * z / camera.fx
    y = (v - camera.cy) * z / camera.fy
    return np.column_stack([x, y, z])


def rim_cloud(
    frame: RgbdFrame,
    segmenter: Segmenter = red_rim_mask,
    depth_range: tuple[float, float] = (0.2, 3.0),
) -> np.ndarray:
    """World-frame points `(n, 3)` of the rim band seen in `frame`."""
    h, w = frame.depth.shape
    if frame.color.shape[:2] != (h, w):
        raise BadCloud(f"colour {frame.color.shape[:2]} and depth {(h, w)} images differ in size")
    depth_m = frame.depth.astype(np.float64) * frame.camera.depth_scale
    in_range = (depth_m >= depth_range[0]) & (depth_m <= depth_range[1])
    mask = segmenter(frame)
    if mask.shape != (h, w):
        raise BadCloud(f"segmenter returned a mask of shape {mask.shape}, expected {(h, w)}")
    pts_cam = back_project(depth_m, frame.camera, mask & in_range)
    return transform_points(frame.camera.extrinsics(), pts_cam)


def solid_rim_segmenter(color_rgb: tuple[float, float, float], band_m: float = 0.015, hue_tol: int = 12) -> Segmenter:
    """A segmenter for a solid-colour bag (no red edge): the bag's pixels by hue, then only its top
    band (within `band_m` of the highest bag point, measured along world z), where the rim is."""
    rgb = np.uint8([[[int(c * 255) for c in color_rgb]]])
    hue = int(cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)[0, 0, 0])

    def mask(frame: RgbdFrame) -> np.ndarray:
        hsv = cv2.cvtColor(frame.color, cv2.COLOR_RGB2HSV)
        h = hsv[..., 0].astype(int)
        dh = np.minimum(np.abs(h - hue), 180 - np.abs(h - hue))
        bag = (dh <= hue_tol) & (hsv[..., 1] >= 60) & (hsv[..., 2] >= 30) & (frame.depth > 0)
        if not bag.any():
            return bag
        depth_m = frame.depth.astype(np.float64) * frame.camera.depth_scale
        v, u = np.nonzero(bag)
        pts = transform_points(frame.camera.extrinsics(), back_project(depth_m, frame.camera, bag))
        top = np.percentile(pts[:, 2], 99)
        keep = pts[:, 2] >= top - band_m
        out = np.zeros_like(bag)
        out[v[keep], u[keep]] = True
        return out

    return mask
