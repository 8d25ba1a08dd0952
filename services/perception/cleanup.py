"""Cloud clean-up before EM: validation, voxel down-sampling and sparse-outlier removal (open3d)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
from scipy.spatial import cKDTree

from bagit.common.errors import BadCloud
from bagit.common.geometry import as_points

MAX_POINTS = 2_000_000  # refuse clouds beyond this (a 640x480 frame has 307,200 pixels)
VOXEL_M = 0.004  # voxel size for down-sampling: well under the rim band's width and the 2 mm accuracy goal
MIN_NEIGHBOURS = 3  # a point needs this many others within OUTLIER_RADIUS_M to be kept
OUTLIER_RADIUS_M = 0.012
SUBSAMPLE_POINTS = 40_000
GATE_M = 0.04  # warm start: keep points within this of the previous rim


def validate_cloud(points: object, n_x: int) -> np.ndarray:
    """`points` as a finite float64 `(n, 3)` array, or BadCloud saying what is wrong."""
    if not isinstance(n_x, (int, np.integer)) or isinstance(n_x, bool) or n_x < 4:
        raise BadCloud(f"n_x must be an integer >= 4, got {n_x!r}")
    a = as_points(points, BadCloud, "cloud")
    if len(a) == 0:
        raise BadCloud("cloud is empty")
    if len(a) > MAX_POINTS:
        raise BadCloud(f"cloud has {len(a)} points, more than the {MAX_POINTS} accepted")
    if not np.all(np.isfinite(a)):
        bad = int((~np.isfinite(a)).any(axis=1).sum())
        raise BadCloud(f"cloud has {bad} points with NaN or infinite coordinates")
    if np.abs(a).max() > 1e4:
        raise BadCloud("cloud coordinates beyond 10 km: not metres from a depth camera")
    if len(a) < n_x:
        raise BadCloud(f"cloud has {len(a)} points, fewer than n_x = {n_x}")
    return a


def gate_near(points: np.ndarray, rim: np.ndarray, radius: float = GATE_M) -> np.ndarray:
    """Points `(m, 3)` of `points (n, 3)` within `radius` of the previous rim `(n_x, 3)` (warm start).

    Measured to the rim's points, so the radius must exceed half the rim spacing plus the motion
    expected between two frames.
    """
    d, _ = cKDTree(rim).query(points, distance_upper_bound=radius)
    return points[np.isfinite(d)]


def voxel_down(points: np.ndarray, voxel: float = VOXEL_M) -> np.ndarray:
    """`points (n, 3)` thinned to one per voxel (open3d), so dense stretches don't dominate the fit.

    Clouds above SUBSAMPLE_POINTS are first thinned at random (seeded): it bounds the time, and it
    keeps scattered outliers as sparse as in a normal frame so the radius test still removes them.
    """
    if len(points) > SUBSAMPLE_POINTS:
        keep = np.random.default_rng(0).choice(len(points), SUBSAMPLE_POINTS, replace=False)
        points = points[np.sort(keep)]
    if len(points) <= 2000:
        return points
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    return np.asarray(pc.voxel_down_sample(voxel).points)


def clean_cloud(points: np.ndarray, voxel: float = VOXEL_M) -> np.ndarray:
    """Down-sample on a voxel grid and drop isolated points. `points (n, 3)` -> `(m, 3)`.

    Outliers spread through the scene are sparse, the rim band is dense: a radius count
    separates them cheaply. If cleaning would leave too little, the down-sampled cloud is kept.
    """
    down = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(voxel_down(points, voxel)))
    kept, _ = down.remove_radius_outlier(nb_points=MIN_NEIGHBOURS, radius=OUTLIER_RADIUS_M)
    out = np.asarray(kept.points)
    return out if len(out) >= 0.05 * len(down.points) and len(out) >= 16 else np.asarray(down.points)
