"""Triangle meshes of a scenario's object and obstacles, built with numpy (no trimesh).

A mesh is `(vertices (n, 3) float, faces (m, 3) int)` with counter-clockwise faces seen from
outside. Shapes are meshed in their local frame (see bagit.common.shapes: centred, bottom face at
local z = -height/2) and moved by their pose; a bundle's parts by the bundle's pose too.
"""

from __future__ import annotations

import numpy as np

from bagit.common.errors import BadVertices
from bagit.common.geometry import make_transform, rpy_to_matrix, transform_points
from bagit.common.scenario import Obstacle
from bagit.common.shapes import Box, Bundle, Cylinder, Prism, Sphere

Mesh = tuple[np.ndarray, np.ndarray]

ROUND_SEGMENTS = 32


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _inside_triangle(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Which of `p (k, 2)` lie inside or on the counter-clockwise triangle a, b, c."""

    def cross(o: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return (u[0] - o[0]) * (v[..., 1] - o[1]) - (u[1] - o[1]) * (v[..., 0] - o[0])

    return (cross(a, b, p) >= 0) & (cross(b, c, p) >= 0) & (cross(c, a, p) >= 0)


def triangulate_polygon(xy: np.ndarray) -> np.ndarray:
    """Faces `(n - 2, 3)` of a simple polygon `xy (n, 2)` by ear clipping, counter-clockwise.

    Works for concave outlines (an L-shaped prism), which a fan from the centroid does not.
    """
    xy = np.asarray(xy, dtype=float)
    n = len(xy)
    if n < 3 or abs(_signed_area(xy)) < 1e-12:
        raise BadVertices(f"cannot triangulate a polygon of {n} points with no area")
    order = list(range(n)) if _signed_area(xy) > 0 else list(range(n - 1, -1, -1))
    faces: list[tuple[int, int, int]] = []
    guard = 0
    while len(order) > 3 and guard < 10 * n * n:
        guard += 1
        m = len(order)
        for k in range(m):
            i, j, n = order[k - 1], order[k], order[(k + 1) % m]
            a, b, c = xy[i], xy[j], xy[n]
            if (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]) <= 1e-15:
                continue  # reflex or degenerate corner: not an ear
            others = [o for o in order if o not in (i, j, n)]
            if others and np.any(_inside_triangle(xy[others], a, b, c)):
                continue
            faces.append((i, j, n))
            order.pop(k)
            break
        else:  # no ear found (self-intersecting input): close with a fan rather than loop forever
            faces.extend((order[0], order[q], order[q + 1]) for q in range(1, len(order) - 1))
            order = order[:3]
            break
    if len(order) == 3:
        faces.append((order[0], order[1], order[2]))
    return np.asarray(faces, dtype=np.int32)


def extrude_polygon(xy: np.ndarray, z0: float, z1: float) -> Mesh:
    """A closed prism over the polygon `xy (n, 2)` from z0 up to z1 (z1 > z0)."""
    xy = np.asarray(xy, dtype=float)
    if _signed_area(xy) < 0:
        xy = xy[::-1]
    n = len(xy)
    cap = triangulate_polygon(xy)
    verts = np.vstack([np.column_stack([xy, np.full(n, z0)]), np.column_stack([xy, np.full(n, z1)])])
    bottom = cap[:, ::-1]  # facing down
    top = cap + n
    i = np.arange(n)
    j = (i + 1) % n
    sides = np.vstack([np.column_stack([i, j, j + n]), np.column_stack([i, j + n, i + n])])
    return verts, np.vstack([bottom, top, sides]).astype(np.int32)


def box_mesh(size: tuple[float, float, float] | np.ndarray) -> Mesh:
    """A box of full extents `size`, centred at the origin."""
    sx, sy, sz = (float(s) / 2 for s in size)
    square = np.array([[sx, sy], [-sx, sy], [-sx, -sy], [sx, -sy]])
    return extrude_polygon(square, -sz, sz)


def cylinder_mesh(radius: float, height: float, segments: int = ROUND_SEGMENTS) -> Mesh:
    """A closed cylinder along z, centred at the origin."""
    t = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    return extrude_polygon(radius * np.column_stack([np.cos(t), np.sin(t)]), -height / 2, height / 2)


def sphere_mesh(radius: float, rings: int = 12, segments: int = ROUND_SEGMENTS) -> Mesh:
    """A UV sphere centred at the origin: two poles and `rings - 1` latitude circles."""
    lat = np.linspace(0.0, np.pi, rings + 1)[1:-1]
    lon = np.linspace(0.0, 2 * np.pi, segments, endpoint=False)
    ring_pts = np.stack(
        [np.outer(np.sin(lat), np.cos(lon)), np.outer(np.sin(lat), np.sin(lon)), np.repeat(np.cos(lat)[:, None], segments, 1)],
        axis=-1,
    ).reshape(-1, 3)
    verts = radius * np.vstack([[0.0, 0.0, 1.0], ring_pts, [0.0, 0.0, -1.0]])
    top, bottom = 0, len(verts) - 1
    faces: list[np.ndarray] = []
    s = np.arange(segments)
    s1 = (s + 1) % segments
    faces.append(np.column_stack([np.full(segments, top), 1 + s, 1 + s1]))
    for r in range(rings - 2):
        a, b = 1 + r * segments, 1 + (r + 1) * segments
        faces.append(np.column_stack([a + s, b + s, b + s1]))
        faces.append(np.column_stack([a + s, b + s1, a + s1]))
    last = 1 + (rings - 2) * segments
    faces.append(np.column_stack([np.full(segments, bottom), last + s1, last + s]))
    return verts, np.vstack(faces).astype(np.int32)


def _local_mesh(shape: Box | Cylinder | Sphere | Prism) -> Mesh:
    if isinstance(shape, Box):
        return box_mesh(shape.size)
    if isinstance(shape, Cylinder):
        return cylinder_mesh(shape.radius, shape.height)
    if isinstance(shape, Sphere):
        return sphere_mesh(shape.radius)
    if isinstance(shape, Prism):
        return extrude_polygon(np.asarray(shape.outline, dtype=float), -shape.height / 2, shape.height / 2)
    raise BadVertices(f"no mesh for shape type {type(shape).__name__}")


def shape_meshes(shape: Box | Cylinder | Sphere | Prism | Bundle, T_world_parent: np.ndarray | None = None) -> list[Mesh]:
    """The meshes of a scenario shape in the world frame (one per part of a bundle)."""
    T = (np.eye(4) if T_world_parent is None else np.asarray(T_world_parent, dtype=float)) @ shape.pose()
    if isinstance(shape, Bundle):
        return [m for part in shape.parts for m in shape_meshes(part, T)]
    verts, faces = _local_mesh(shape)
    return [(transform_points(T, verts), faces)]


def obstacle_mesh(obstacle: Obstacle) -> Mesh:
    """A scenario's cuboid obstacle in the world frame."""
    verts, faces = box_mesh(obstacle.size)
    T = make_transform(rpy_to_matrix([0.0, 0.0, obstacle.yaw]), np.asarray(obstacle.center, dtype=float))
    return transform_points(T, verts), faces


def outline_prism(vertices: np.ndarray, up: np.ndarray, height: float) -> Mesh:
    """The object when only its bottom outline V `(n_v, 3)` is known: V extruded by `height` along `up (3,)`."""
    V = np.asarray(vertices, dtype=float)
    if V.ndim != 2 or V.shape[1] != 3 or len(V) < 3 or not np.all(np.isfinite(V)):
        raise BadVertices(f"V must be at least 3 finite points of shape (n, 3), got {V.shape}")
    z = np.asarray(up, dtype=float)
    z = z / np.linalg.norm(z)
    x = V[0] - V.mean(axis=0)
    x -= z * np.dot(x, z)
    if np.linalg.norm(x) < 1e-9:
        raise BadVertices("V has no extent across its up axis")
    x /= np.linalg.norm(x)
    R = np.column_stack([x, np.cross(z, x), z])
    T = make_transform(R, V.mean(axis=0))
    local = (V - V.mean(axis=0)) @ R
    verts, faces = extrude_polygon(local[:, :2], 0.0, float(height))
    return transform_points(T, verts), faces


def mesh_volume(verts: np.ndarray, faces: np.ndarray) -> float:
    """Signed volume of a closed mesh (positive when its faces turn outward); a check of orientation."""
    a, b, c = verts[faces[:, 0]], verts[faces[:, 1]], verts[faces[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
