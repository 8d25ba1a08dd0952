"""Geometry shared by several services.

Conventions: points are float64 arrays `(n, 3)` in metres, world frame unless named otherwise;
a rim (SOI) is a closed polyline through its `(n_x, 3)` points in order; transforms are 4x4
homogeneous matrices named `T_a_b` (frame b expressed in frame a, i.e. a <- b).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.spatial import cKDTree

from bagit.common.errors import NumericalFailure
from bagit.common.so3 import matrix_to_rpy, rpy_to_matrix  # noqa: F401  (part of this module's API)


def as_points(obj: object, error: type[Exception], what: str) -> np.ndarray:
    """`obj` as a float64 `(n, 3)` array, or `error` naming `what` is wrong (not numeric, wrong shape).

    Finiteness and counts are left to the caller, whose messages know what the points are for.
    """
    try:
        a = np.asarray(obj, dtype=float)
    except (TypeError, ValueError) as e:
        raise error(f"{what} is not numeric: {e}") from None
    if a.ndim != 2 or a.shape[1] != 3:
        raise error(f"{what} must have shape (n, 3), got {a.shape}")
    return a


def farthest_point_sampling(points: np.ndarray, k: int, start: int = 0) -> np.ndarray:
    """Indices `(k,)` of `k` points of `points (n, d)` chosen greedily farthest from those already chosen.

    FPS keeps the shape of a dense curve when it is thinned, which uniform index striding
    does not when the curve's sampling is uneven.
    """
    pts = np.asarray(points, dtype=float)
    n = len(pts)
    if not 0 < k <= n:
        raise ValueError(f"farthest_point_sampling: need 0 < k <= {n}, got k={k}")
    chosen = np.empty(k, dtype=np.int64)
    chosen[0] = start % n
    d2 = np.sum((pts - pts[chosen[0]]) ** 2, axis=1)
    for i in range(1, k):
        j = int(np.argmax(d2))
        chosen[i] = j
        d2 = np.minimum(d2, np.sum((pts - pts[j]) ** 2, axis=1))
    return chosen


def pca(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid `(d,)`, variances `(d,)` (descending) and axes `(d, d)` (rows) of `points (n, d)`."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise NumericalFailure(f"PCA needs finite points (n, d), got {'non-finite values' if pts.size else 'none'} in shape {pts.shape}")
    centroid = pts.mean(axis=0)
    try:
        _, s, vt = np.linalg.svd(pts - centroid, full_matrices=False)
    except np.linalg.LinAlgError as e:  # LAPACK can still fail on badly scaled data
        raise NumericalFailure(f"PCA failed: {e}") from None
    var = s**2 / max(len(pts) - 1, 1)
    return centroid, var, vt


def pca_axis(points: np.ndarray) -> np.ndarray:
    """The unit principal axis `(d,)` of `points (n, d)`: the direction of largest spread."""
    return pca(points)[2][0]


def ramanujan_perimeter(a: np.ndarray | float, b: np.ndarray | float) -> np.ndarray | float:
    """Perimeter of an ellipse with semi-axes a, b by Ramanujan's second approximation.

    Relative error below 1e-6 up to a 5:1 aspect ratio (1e-4 at 20:1), and cheap enough to sit
    inside an optimiser's objective.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    s = a + b
    h = np.where(s > 0, ((a - b) / np.where(s > 0, s, 1.0)) ** 2, 0.0)
    out = np.pi * s * (1.0 + 3.0 * h / (10.0 + np.sqrt(4.0 - 3.0 * h)))
    return float(out) if out.ndim == 0 else out


def chamfer_distance(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer distance between point sets `a (n, d)` and `b (m, d)`.

    The mean nearest-neighbour distance from a to b plus that from b to a; works for sets of
    different sizes, which is why the paper fits ellipses with it.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    da, _ = cKDTree(b).query(a)
    db, _ = cKDTree(a).query(b)
    return float(da.mean() + db.mean())


def closed_polyline_length(points: np.ndarray) -> float:
    """Length of the closed polyline through `points (n, d)` (the rim perimeter R for a SOI)."""
    p = np.asarray(points, dtype=float)
    return float(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum())


def resample_closed(points: np.ndarray, n: int) -> np.ndarray:
    """`(n, d)` points evenly spaced by arc length along the closed polyline through `points`."""
    p = np.asarray(points, dtype=float)
    seg = np.roll(p, -1, axis=0) - p
    seg_len = np.linalg.norm(seg, axis=1)
    cum = np.concatenate([[0.0], np.cumsum(seg_len)])
    total = cum[-1]
    if total <= 0:
        raise ValueError("resample_closed: the polyline has zero length")
    s = np.arange(n) * (total / n)
    idx = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(p) - 1)
    frac = (s - cum[idx]) / np.where(seg_len[idx] > 0, seg_len[idx], 1.0)
    return p[idx] + frac[:, None] * seg[idx]


def nearest_on_polyline(points: np.ndarray, polyline: np.ndarray, closed: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """For each of `points (n, d)`: the nearest point `(n, d)` on the polyline through `polyline (m, d)`
    and its distance `(n,)`; any dimension d (3-D rims, or their 2-D projections)."""
    q = np.asarray(points, dtype=float)
    a = np.asarray(polyline, dtype=float)
    b = np.roll(a, -1, axis=0) if closed else a[1:]
    if not closed:
        a = a[:-1]
    ab = b - a  # (m, d)
    denom = np.einsum("ij,ij->i", ab, ab)
    denom = np.where(denom > 0, denom, 1.0)
    t = np.einsum("nmj,mj->nm", q[:, None, :] - a[None], ab) / denom
    np.clip(t, 0.0, 1.0, out=t)
    # The projections and distances one coordinate at a time, as (n, m) arrays: the same float
    # operations in the same order as a + t ab and norm over (n, m, d) arrays (bit for bit), at half
    # the cost (the perception node runs this on every frame's cloud for its inlier fraction).
    proj = []
    for c in range(q.shape[1]):
        p = t * ab[:, c]
        p += a[:, c]
        proj.append(p)
    r = [q[:, c, None] - p for c, p in enumerate(proj)]
    sq = r[0] * r[0]
    for rc in r[1:]:
        sq += rc * rc
    dist = np.sqrt(sq)
    j = dist.argmin(axis=1)
    rows = np.arange(len(q))
    return np.stack([p[rows, j] for p in proj], axis=1), dist[rows, j]


def points_to_polyline_distance(points: np.ndarray, polyline: np.ndarray, closed: bool = True) -> np.ndarray:
    """Distance `(n,)` from each of `points (n, 3)` to the polyline through `polyline (m, 3)`."""
    return nearest_on_polyline(points, polyline, closed)[1]


def enclosure(rim: np.ndarray, points: np.ndarray, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How well the closed `rim (n, 3)`, seen along the z axis of `frame` (4x4, world <- F), goes round
    each of `points (m, 3)`: its signed distance `(m,)` (m, > 0 inside) from the rim's outline, and
    the unit world direction `(m, 3)`, in F's xy plane, in which the rim's edge nearest it must move
    to take it in further.

    Why: an SOI can match a subgoal to within its RMS tolerance and still leave an object's corner
    outside, which the lift then catches."""
    r = np.asarray(rim, dtype=float)
    q = np.asarray(points, dtype=float)
    T = np.asarray(frame, dtype=float)
    if r.ndim != 2 or r.shape[1] != 3 or len(r) < 3 or q.ndim != 2 or q.shape[1] != 3 or len(q) < 1 or T.shape != (4, 4):
        raise ValueError(f"enclosure: need rim (n >= 3, 3), points (m >= 1, 3), frame (4, 4); got {r.shape}, {q.shape}, {T.shape}")
    if not (np.all(np.isfinite(r)) and np.all(np.isfinite(q)) and np.all(np.isfinite(T))):
        raise ValueError("enclosure: non-finite input")
    import cv2  # only here: the rest of this module does not need OpenCV

    axes = T[:3, :2]  # F's x and y axes in the world
    r2 = (r - T[:3, 3]) @ axes  # (n, 2)
    q2 = (q - T[:3, 3]) @ axes  # (m, 2)
    near, d = nearest_on_polyline(q2, r2)
    contour = r2.astype(np.float32).reshape(-1, 1, 2)
    inside = np.array([cv2.pointPolygonTest(contour, (float(x), float(y)), False) >= 0 for x, y in q2])
    out2 = np.where(inside[:, None], near - q2, q2 - near)  # towards where the edge must go
    on_edge = d < 1e-9
    out2[on_edge] = q2[on_edge] - r2.mean(axis=0)  # on the outline: away from the rim's centre
    norm = np.linalg.norm(out2, axis=1, keepdims=True)
    out2 = np.divide(out2, norm, out=np.zeros_like(out2), where=norm > 1e-12)
    return np.where(inside, d, -d), out2 @ axes.T


def align_cyclic(rim: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """`rim (n, 3)` re-indexed (best cyclic shift and direction) so point i lies nearest reference point i.

    The controller compares SOIs point by point, so every SOI of a run must share one indexing.
    """
    r = np.asarray(rim, dtype=float)
    ref = np.asarray(reference, dtype=float)
    if r.shape != ref.shape:
        raise ValueError(f"align_cyclic: shapes differ {r.shape} vs {ref.shape}")
    n = len(r)
    idx = (np.arange(n)[None, :] + np.arange(n)[:, None]) % n  # (shift, i)
    best, best_cost = r, np.inf
    for cand in (r, r[::-1]):
        cost = np.sum((cand[idx] - ref[None]) ** 2, axis=(1, 2))
        k = int(np.argmin(cost))
        if cost[k] < best_cost:
            best_cost, best = cost[k], cand[idx[k]]
    return best.copy()


def fit_plane(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Centroid `(3,)`, unit normal `(3,)` and RMS out-of-plane residual of `points (n, 3)`."""
    centroid, var, axes = pca(points)
    normal = axes[2]
    rms = float(np.sqrt(np.mean(((np.asarray(points) - centroid) @ normal) ** 2)))
    return centroid, normal, rms


def ellipse_points_2d(
    center: np.ndarray, a: np.ndarray | float, b: np.ndarray | float, alpha: np.ndarray | float, theta: np.ndarray
) -> np.ndarray:
    """Points `(len(theta), 2)` of the ellipse centred at `center (2,)`, semi-axes a, b, rotated by alpha
    (arrays of them broadcast against theta: points of several ellipses at once)."""
    c, s = np.cos(alpha), np.sin(alpha)
    ct, st = np.cos(theta), np.sin(theta)
    x = center[0] + a * ct * c - b * st * s
    y = center[1] + a * ct * s + b * st * c
    return np.stack([x, y], axis=-1)


def make_transform(R: np.ndarray | None = None, t: np.ndarray | None = None) -> np.ndarray:
    """4x4 homogeneous transform from a rotation `(3, 3)` and a translation `(3,)`."""
    T = np.eye(4)
    if R is not None:
        T[:3, :3] = R
    if t is not None:
        T[:3, 3] = t
    return T


def pose_to_matrix(position: np.ndarray | Sequence[float], rpy: np.ndarray | Sequence[float]) -> np.ndarray:
    """4x4 transform of a pose given as position `(3,)` and roll-pitch-yaw `(3,)`."""
    return make_transform(rpy_to_matrix(rpy), np.asarray(position, dtype=float))


def invert_transform(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform, without a general matrix inverse."""
    R = T[:3, :3]
    return make_transform(R.T, -R.T @ T[:3, 3])


def transform_points(T: np.ndarray, points: np.ndarray) -> np.ndarray:
    """`points (n, 3)` mapped through the 4x4 transform `T` (returns `(n, 3)`)."""
    p = np.asarray(points, dtype=float)
    return p @ T[:3, :3].T + T[:3, 3]
