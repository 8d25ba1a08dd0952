"""From an RGB-D frame to the rim cloud: segment the rim band, back-project it, move it to the world.

Segmentation is a hook: any `Segmenter` (a callable `frame -> (H, W) bool mask`) can replace the
red-rim colour threshold -- a solid-colour bag's local top, a learned segmenter, ...
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import cv2
import numpy as np
from scipy.ndimage import maximum_filter

from bagit.common.errors import BadCloud
from bagit.common.geometry import transform_points
from bagit.common.messages import CameraInfo, RgbdFrame

# Red wraps round hue 0 in OpenCV's 0-179 hue scale: two bands.
RED_HUE_BANDS: tuple[tuple[int, int], ...] = ((0, 10), (170, 179))
RIM_HUE_TOL = 10  # a binding's pixels lie within this of its hue (OpenCV's 0-179 scale), as the red bands do round 0
MIN_SATURATION = 110
MIN_VALUE = 50


class Segmenter(Protocol):
    """Picks the rim band's pixels: `(H, W)` boolean mask (anything numpy reads as one) of a frame."""

    def __call__(self, frame: RgbdFrame) -> np.ndarray: ...


def hsv_segmenter(
    hue_bands: Sequence[tuple[int, int]], min_saturation: int = MIN_SATURATION, min_value: int = MIN_VALUE
) -> Segmenter:
    """A segmenter keeping pixels whose OpenCV hue (0-179) lies in any of `hue_bands` (inclusive),
    with at least the given saturation and value (0-255)."""
    bands = [(int(lo), int(hi)) for lo, hi in hue_bands]
    for lo, hi in bands:
        if not 0 <= lo <= hi <= 179:
            raise BadCloud(f"hue band ({lo}, {hi}) is not within 0..179 with lo <= hi")

    def mask(frame: RgbdFrame) -> np.ndarray:
        hsv = cv2.cvtColor(np.ascontiguousarray(frame.color), cv2.COLOR_RGB2HSV)
        out = np.zeros(hsv.shape[:2], dtype=np.uint8)
        for lo, hi in bands:
            out |= cv2.inRange(hsv, (lo, min_saturation, min_value), (hi, 255, 255))
        return out.astype(bool)

    return mask


_red = hsv_segmenter(RED_HUE_BANDS)


def opencv_hue(color_rgb: tuple[float, float, float]) -> int:
    """OpenCV's hue (0-179) of an RGB colour (each in [0, 1])."""
    rgb = np.array([[[int(c * 255) for c in color_rgb]]], dtype=np.uint8)
    return int(cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)[0, 0, 0])


def hue_bands(color_rgb: tuple[float, float, float], tol: int = RIM_HUE_TOL) -> tuple[tuple[int, int], ...]:
    """The inclusive OpenCV hue bands within `tol` of `color_rgb`'s hue: one band, or two where it wraps
    round 0/179 (red's: RED_HUE_BANDS)."""
    h = opencv_hue(color_rgb)
    lo, hi = h - tol, h + tol
    if lo < 0:
        return ((0, hi), (180 + lo, 179))
    if hi > 179:
        return ((0, hi - 180), (lo, 179))
    return ((lo, hi),)


def rim_color_segmenter(color_rgb: tuple[float, float, float]) -> Segmenter:
    """The segmenter of a binding of colour `color_rgb` (RGB 0..1): its hue's band at red_rim_mask's
    saturation and value (the same mask as red_rim_mask's for the default red binding)."""
    return hsv_segmenter(hue_bands(color_rgb))


def red_rim_mask(frame: RgbdFrame) -> np.ndarray:
    """(H, W) bool: pixels of the bag's red edge (HSV threshold on the RGB image; red wraps hue 0/180).

    No morphological opening: at 1 m a rim band is only 2-4 pixels wide and would be erased;
    isolated red specks are left to the SOI extractor's outlier handling.
    """
    return _red(frame)


def back_project(depth_m: np.ndarray, camera: CameraInfo, mask: np.ndarray | None = None) -> np.ndarray:
    """Camera-frame points `(n, 3)` of the pixels with valid depth (and in `mask`). depth_m: (H, W) metres.

    Pinhole model: x = (u - cx) z / fx, y = (v - cy) z / fy (OpenCV/RealSense axes: x right, y down,
    z forward); zero, negative or non-finite depth means no measurement.
    """
    with np.errstate(invalid="ignore"):
        valid = np.isfinite(depth_m) & (depth_m > 0)
    if mask is not None:
        valid &= mask
    v, u = np.nonzero(valid)
    return _pinhole(v, u, depth_m[v, u], camera)


def _pinhole(v: np.ndarray, u: np.ndarray, z: np.ndarray, camera: CameraInfo) -> np.ndarray:
    """Camera-frame points `(n, 3)` of pixels (row `v (n,)`, column `u (n,)`) at depths `z (n,)` metres."""
    x = (u - camera.cx) * z / camera.fx
    y = (v - camera.cy) * z / camera.fy
    return np.column_stack([x, y, z])


def masked_points(
    frame: RgbdFrame, mask: np.ndarray, depth_range: tuple[float, float] | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rows `v (n,)`, columns `u (n,)` and camera-frame points `(n, 3)` of the pixels in `mask (H, W)`
    (anything numpy reads as booleans) with valid depth, inside `depth_range` (metres) if given.

    The mask is applied first and only its pixels' depths are converted, so a frame costs in
    proportion to the rim band, not to the image: the same numbers as `back_project` on the whole
    image in metres, in the same (row-major) order, without a float64 copy of the depth image.
    """
    v, u = _nonzero(mask)
    z = frame.depth[v, u].astype(np.float64) * frame.camera.depth_scale
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(z) & (z > 0)
        if depth_range is not None:
            ok &= (z >= depth_range[0]) & (z <= depth_range[1])
    if not ok.all():
        v, u, z = v[ok], u[ok], z[ok]
    return v, u, _pinhole(v, u, z, frame.camera)


def _nonzero(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows `(n,)` and columns `(n,)` of the nonzero pixels of `mask (H, W)` in row-major order, as
    np.nonzero gives them; OpenCV's scan is 4x faster on a 640x480 bool or uint8 mask."""
    if mask.ndim != 2 or mask.dtype not in (np.bool_, np.uint8):
        return np.nonzero(mask)  # type: ignore[return-value]
    xy = cv2.findNonZero(np.ascontiguousarray(mask).view(np.uint8))
    if xy is None:  # OpenCV gives None for an all-zero mask
        return np.zeros(0, np.intp), np.zeros(0, np.intp)
    xy = xy.reshape(-1, 2).astype(np.intp)
    return xy[:, 1], xy[:, 0]


def rim_cloud(
    frame: RgbdFrame,
    segmenter: Segmenter = red_rim_mask,
    depth_range: tuple[float, float] = (0.2, 3.0),
) -> np.ndarray:
    """World-frame points `(n, 3)` of the rim band seen in `frame` (empty `(0, 3)` if none).

    Pixels the segmenter picks, with a depth inside `depth_range` (metres; the D455 is unreliable
    nearer than 0.2 m and noisy beyond 3 m), back-projected with the frame's intrinsics and moved
    to the world with its extrinsics (world <- camera).
    """
    h, w = frame.depth.shape
    if frame.color.ndim != 3 or frame.color.shape[:2] != (h, w) or frame.color.shape[2] != 3:
        raise BadCloud(f"colour image {frame.color.shape} does not match the depth image {(h, w)} (need (H, W, 3))")
    if (frame.camera.height, frame.camera.width) != (h, w):
        raise BadCloud(
            f"images are {w}x{h} but the camera info says {frame.camera.width}x{frame.camera.height}"
        )
    lo, hi = (float(v) for v in depth_range)
    if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 <= lo < hi):
        raise BadCloud(f"depth_range must be finite with 0 <= near < far, got {depth_range}")
    T = frame.camera.extrinsics()
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise BadCloud("camera extrinsics are not a finite 4x4 transform")
    mask = np.asarray(segmenter(frame))
    if mask.shape != (h, w):
        raise BadCloud(f"segmenter returned a mask of shape {mask.shape}, expected {(h, w)}")
    return transform_points(T, masked_points(frame, mask, (lo, hi))[2])


def solid_rim_segmenter(
    color_rgb: tuple[float, float, float],
    band_m: float = 0.015,
    hue_tol: int = 12,
    reach_m: float = 0.03,
    depth_m: float = 0.10,
) -> Segmenter:
    """A segmenter for a solid-colour bag (no red edge): the bag's pixels by hue, then the rim, the
    bag's local top: a bag point within `band_m` of the highest bag point within `reach_m` of it
    horizontally (the fabric hangs down from the rim, so next to the rim nothing of the bag is higher),
    and within `depth_m` of the bag's highest point (the bag's bottom, seen through its opening, is a
    local top too, but far lower). A single global top band would keep only the upper arc of a rim
    tilted by more than `band_m`, as it is whenever the grippers lift it round an object."""
    hue = opencv_hue(color_rgb)

    def mask(frame: RgbdFrame) -> np.ndarray:
        hsv = cv2.cvtColor(np.ascontiguousarray(frame.color), cv2.COLOR_RGB2HSV)
        h = hsv[..., 0].astype(int)
        dh = np.minimum(np.abs(h - hue), 180 - np.abs(h - hue))
        bag = (dh <= hue_tol) & (hsv[..., 1] >= 60) & (hsv[..., 2] >= 30) & (frame.depth > 0)
        if not bag.any():
            return bag
        v, u, pts_cam = masked_points(frame, bag)
        pts = transform_points(frame.camera.extrinsics(), pts_cam)
        keep = pts[:, 2] >= np.percentile(pts[:, 2], 99) - depth_m
        keep &= pts[:, 2] >= local_top(pts[:, :2], pts[:, 2], reach_m) - band_m
        out = np.zeros_like(bag)
        out[v[keep], u[keep]] = True
        return out

    return mask


def local_top(xy: np.ndarray, z: np.ndarray, reach_m: float, support: int = 3) -> np.ndarray:
    """(n,) the highest z within about `reach_m` horizontally of each point `xy (n, 2)`: per grid cell
    of reach_m / 2 the `support`-th highest z (so that a few flying pixels, the colour of the bag
    with the depth of what is in front of it at a silhouette, cannot raise the top), then the maximum
    over the cells around (a square of +-reach_m). A cell with fewer points gives no top."""
    cell = reach_m / 2
    ij = np.floor((xy - xy.min(axis=0)) / cell).astype(int)
    shape = ij.max(axis=0) + 1
    flat = ij[:, 0] * shape[1] + ij[:, 1]
    order = np.lexsort((-z, flat))  # by cell, highest first within each
    flat_sorted = flat[order]
    first = np.searchsorted(flat_sorted, flat_sorted, side="left")
    rank = np.arange(len(order)) - first
    pick = order[rank == support - 1]
    grid = np.full(shape, -np.inf)
    grid[ij[pick, 0], ij[pick, 1]] = z[pick]
    grid = maximum_filter(grid, size=5, mode="constant", cval=-np.inf)
    return grid[ij[:, 0], ij[:, 1]]
