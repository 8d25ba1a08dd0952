"""Collision checks for rims: the closed polyline through the SOI points against convex polytopes.

The object is V's convex hull extruded along its up axis by its height; each obstacle is a yawed
cuboid. Both are convex polytopes {p : A p <= b}, so a rim segment hits one exactly when
Cyrus-Beck clipping leaves part of it inside. Everything is vectorised over segments and states.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from bagit.common.geometry import rpy_to_matrix
from bagit.common.scenario import Obstacle


@dataclass(frozen=True)
class Polytope:
    """{p : A p <= b + margin}. A: (m, 3) unit normals, b: (m,)."""

    A: np.ndarray
    b: np.ndarray
    name: str = ""


def prism_polytope(vertices: np.ndarray, up: np.ndarray, height: float, name: str = "object") -> Polytope:
    """The convex hull of V `(n_v, 3)` and V + height * up, as half-spaces."""
    pts = np.vstack([vertices, vertices + height * up])
    hull = ConvexHull(pts)
    eq = hull.equations  # (m, 4): n . p + d <= 0 inside
    return Polytope(eq[:, :3], -eq[:, 3], name)


def box_polytope(ob: Obstacle, name: str = "obstacle") -> Polytope:
    """A yawed cuboid as six half-spaces."""
    R = rpy_to_matrix([0.0, 0.0, ob.yaw])
    c = np.asarray(ob.center, dtype=float)
    half = np.asarray(ob.size, dtype=float) / 2
    A = np.vstack([R.T, -R.T])  # rows: the box's axes in the world, both signs
    b = np.concatenate([R.T @ c + half, -(R.T @ c) + half])
    return Polytope(A, b, name)


def segments_hit(p0: np.ndarray, p1: np.ndarray, poly: Polytope, margin: float = 0.0) -> np.ndarray:
    """Which segments p0[i] -> p1[i] (arrays `(..., 3)`) pass within the polytope inflated by `margin`."""
    d = p1 - p0
    num = (poly.b + margin) - p0 @ poly.A.T  # (..., m): inside while t * den <= num
    den = d @ poly.A.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = num / den
    t_enter = np.max(np.where(den < 0, t, 0.0), axis=-1)
    t_exit = np.min(np.where(den > 0, t, 1.0), axis=-1)
    parallel_out = np.any((den == 0) & (num < 0), axis=-1)
    return (t_enter <= t_exit) & (t_enter <= 1.0) & (t_exit >= 0.0) & ~parallel_out


GAP_SAMPLES_PER_SEGMENT = 8  # points per rim segment where `rim_gap` measures


def rim_gap(rim: np.ndarray, poly: Polytope) -> float:
    """How far the closed polyline `rim (n_x, 3)` stays outside `poly` (>= 0 outside, < 0 inside), by the
    planes' own measure: min over points on the rim of max_k (A_k p - b_k), a point being within a margin
    m exactly when this is <= m (as `segments_hit` inflates). Sampled along the segments: a lower bound of
    the Euclidean distance, exact at faces."""
    s = np.linspace(0, 1, GAP_SAMPLES_PER_SEGMENT, endpoint=False)[:, None, None]
    dense = (rim[None] + s * (np.roll(rim, -1, axis=0) - rim)[None]).reshape(-1, 3)
    return float((dense @ poly.A.T - poly.b).max(axis=1).min())


class RimCollision:
    """Checks rims (closed polylines) against the object and the obstacles."""

    def __init__(self, polytopes: list[Polytope], margins: list[float]):
        self.polytopes = polytopes
        self.margins = margins

    def rims_hit(self, rims: np.ndarray) -> np.ndarray:
        """`rims (k, n_x, 3)` -> `(k,)` bool: does any segment of each rim touch anything."""
        p0 = rims
        p1 = np.roll(rims, -1, axis=1)
        hit = np.zeros(rims.shape[0], dtype=bool)
        for poly, m in zip(self.polytopes, self.margins, strict=False):
            hit |= segments_hit(p0, p1, poly, m).any(axis=-1)
        return hit

    def touched(self, rim: np.ndarray, margins: bool = True) -> list[int]:
        """Indices of the polytopes a single rim `(n_x, 3)` touches, within their margins or (False) themselves."""
        seg = (rim, np.roll(rim, -1, axis=0))
        return [k for k, (poly, m) in enumerate(zip(self.polytopes, self.margins, strict=True))
                if segments_hit(*seg, poly, m if margins else 0.0).any()]

    def first_hit(self, rim: np.ndarray) -> str | None:
        """Name of the first thing a single rim `(n_x, 3)` touches, or None."""
        hit = self.touched(rim)
        return self.polytopes[hit[0]].name if hit else None
