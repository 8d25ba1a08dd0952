"""The rim as a ring: its plane, a cold ordering of the cloud around it, and the SOI's order convention.

A bag rim seen from above is a closed, roughly star-shaped loop (ellipses, pinched 'lens' rims,
wavy or sagging 3D rims all project to one), so the angle around a centre inside it orders the
cloud along the rim. That order only seeds EM; EM and the chain prior do the fitting.
"""

from __future__ import annotations

import numpy as np

from bagit.common.errors import BadCloud
from bagit.common.geometry import pca, resample_closed

MIN_SPREAD_M = 0.005  # a cloud thinner than this across its second axis is a line or a point, not a rim


def rim_plane(cloud: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid `(3,)` and unit normal `(3,)` (z >= 0) of the plane that fits `cloud (n, 3)` best.

    Raises BadCloud when the cloud is degenerate (all on a line or at a point).
    """
    if len(cloud) < 3:
        raise BadCloud(f"cloud is degenerate: its points sit at {len(cloud)} place(s), not around a rim")
    centroid, var, axes = pca(cloud)
    if not np.all(np.isfinite(var)) or var[1] < MIN_SPREAD_M**2:
        raise BadCloud("cloud is degenerate: its points lie on a line or a point, not around a rim")
    normal = axes[2]
    return centroid, (-normal if normal[2] < 0 else normal)


def plane_basis(normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors `(3,)`, `(3,)` spanning the plane of `normal`: the first as close to world +x as
    the plane allows, the second completing a right-handed frame with the normal (so angles grow
    counter-clockwise seen from the normal's side, i.e. from above)."""
    x = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
    if np.linalg.norm(x) < 1e-6:
        x = np.array([0.0, 1.0, 0.0]) - normal[1] * normal
    x /= np.linalg.norm(x)
    return x, np.cross(normal, x)


def plane_angles(points: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Angle `(n,)` in (-pi, pi] of each of `points (n, 3)` around `centre` in the plane of `normal`,
    measured from the direction nearest world +x, counter-clockwise seen from above."""
    ex, ey = plane_basis(normal)
    rel = points - centre
    return np.arctan2(rel @ ey, rel @ ex)


def ring_init(cloud: np.ndarray, k: int, centroid: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """k points `(k, 3)` evenly spaced by arc length along the rim, counter-clockwise, for EM to start from.

    The cloud is binned by angle around a robust centre (the median in the rim plane), and the
    trimmed mean of each bin is a point of a rough rim polyline, which is resampled at equal arc
    length (angle bins alone would crowd components where the rim passes close to the centre).
    Bins that hold only a clump of outliers are dropped -- too few points, or a radius far from
    that of the neighbouring bins -- as are empty ones (e.g. behind a gripper): the polyline
    crosses such a stretch by a chord, and EM takes it from there.
    """
    ex, ey = plane_basis(normal)
    rel = cloud - centroid
    uv = np.column_stack([rel @ ex, rel @ ey])
    centre = centroid + np.median(uv[:, 0]) * ex + np.median(uv[:, 1]) * ey
    ang = plane_angles(cloud, centre, normal)
    n_bins = 2 * k
    bins = np.minimum(((ang + np.pi) / (2 * np.pi) * n_bins).astype(np.int64), n_bins - 1)
    mean = _bin_means(cloud, bins, n_bins, np.ones(len(cloud)))
    # One trimming pass: points far from their bin's mean (stray outliers) are left out.
    d = np.linalg.norm(cloud - mean[bins], axis=1)
    near = d <= np.median(d) * 3.0 + 1e-4
    mean = _bin_means(cloud, bins, n_bins, near.astype(float))
    count = np.bincount(bins[near], minlength=n_bins)
    ok = count >= max(2.0, 0.25 * np.median(count[count > 0])) if count.any() else count > 0
    if ok.sum() >= 5:
        radius = np.linalg.norm(np.cross(mean[ok] - centre, normal), axis=1)
        window = np.stack([np.roll(radius, s) for s in range(-2, 3)])  # the bin and 2 valid ones each side
        typical = np.median(window, axis=0)
        ok[np.flatnonzero(ok)] = np.abs(radius - typical) <= 0.25 * typical + 0.01
    if ok.sum() < 3:
        raise BadCloud("cloud does not go around a rim: fewer than 3 angular sectors hold points")
    return resample_closed(mean[ok], k)


def _bin_means(cloud: np.ndarray, bins: np.ndarray, n_bins: int, w: np.ndarray) -> np.ndarray:
    """Weighted mean `(n_bins, 3)` of the points in each bin; NaN rows for empty bins."""
    total = np.bincount(bins, weights=w, minlength=n_bins)
    sums = np.stack([np.bincount(bins, weights=w * cloud[:, j], minlength=n_bins) for j in range(3)], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(total[:, None] > 0, sums / np.where(total > 0, total, 1.0)[:, None], np.nan)


def is_counter_clockwise(rim: np.ndarray, normal: np.ndarray) -> bool:
    """Whether the closed polyline `rim (n, 3)` turns counter-clockwise about `normal` (seen from its tip)."""
    c = rim.mean(axis=0)
    return float(np.einsum("ij,j->", np.cross(rim - c, np.roll(rim, -1, axis=0) - c), normal)) >= 0.0
