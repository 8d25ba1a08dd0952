"""The object to bag as rigid geometry: MJCF geoms from the scenario's shape, and the convex parts
the ground truth measures penetration against.

A shape's geoms sit in one static body (the object is held still, as in the experiments, by a thin
rod from above that takes no contacts). With only V in the scenario, V is extruded along its
upward normal by `ObjectSpec.effective_height()` into a convex mesh. The object's ArUco marker, when
the scenario gives one, is a thin printed card (a box textured with OpenCV's marker image and a
white quiet zone) stuck on at its pose; the rod then comes down beside the card, not through it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull

from bagit.common.geometry import make_transform
from bagit.common.scenario import MARKER_THICKNESS_M, MarkerSpec, ObjectSpec
from bagit.common.shapes import Box, Bundle, Cylinder, Prism, Sphere

OBJECT_RGBA = "0.85 0.65 0.25 1"
ROD_LENGTH_M = 0.6
ROD_RADIUS_M = 0.003
MARKER_PX_PER_CELL = 16  # texture resolution of the printed marker


@dataclass
class ConvexPart:
    """One convex piece of the object, world frame, with an exact inside-depth for its kind.

    points: (k, 3) on its boundary (the hull, for display); faces: (f, 3) triangles into points,
    counter-clockwise seen from outside;
    halfspaces: (f', 4) rows [n, d], n.p + d <= 0 inside (unit outward n). A sphere or cylinder also
    keeps its centre, axis, radius and half-height, so its depth is exact rather than a polygon's.
    """

    points: np.ndarray
    halfspaces: np.ndarray
    faces: np.ndarray
    kind: str = "polytope"  # or "sphere", "cylinder"
    center: np.ndarray | None = None
    axis: np.ndarray | None = None
    radius: float = 0.0
    half_height: float = 0.0

    @classmethod
    def from_points(cls, points: np.ndarray, **round_shape) -> ConvexPart:
        hull = ConvexHull(points)
        tri = hull.simplices.copy()
        p = points[tri]
        inward = np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), hull.equations[:, :3]) < 0
        tri[inward] = tri[inward][:, ::-1]  # counter-clockwise seen from outside
        return cls(points[hull.vertices], hull.equations, _reindex(tri, hull.vertices), **round_shape)

    def depth(self, p: np.ndarray) -> np.ndarray:
        """(n,) how deep each of `p (n, 3)` lies inside (> 0); <= 0 outside (minus a distance bound)."""
        if self.kind == "sphere":
            return self.radius - np.linalg.norm(p - self.center, axis=1)
        if self.kind == "cylinder":
            rel = p - self.center
            along = rel @ self.axis
            radial = np.linalg.norm(rel - along[:, None] * self.axis, axis=1)
            return np.minimum(self.radius - radial, self.half_height - np.abs(along))
        return -(p @ self.halfspaces[:, :3].T + self.halfspaces[:, 3]).max(axis=1)


def _reindex(simplices: np.ndarray, kept: np.ndarray) -> np.ndarray:
    lut = np.full(kept.max() + 1, -1)
    lut[kept] = np.arange(len(kept))
    return lut[simplices]


def _v(x) -> str:
    return " ".join(f"{float(c):.6g}" for c in np.ravel(x))


def _pose_attrs(position, rpy) -> str:
    # A quaternion, not MJCF's euler (intrinsic by default) for the scenario's extrinsic roll-pitch-yaw.
    return f'pos="{_v(position)}" quat="{_v(_quat(rpy))}"'


def _quat(rpy) -> np.ndarray:
    """MuJoCo quaternion (w, x, y, z) of roll-pitch-yaw (extrinsic x, y, z, as in URDF and common.geometry)."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_euler("xyz", np.asarray(rpy, dtype=float)).as_quat()
    return np.array([w, x, y, z])


def _shape_geoms(shape, name: str, contact: str, cylinder_as_mesh: bool = False) -> tuple[str, list[str]]:
    """Geoms (XML) of a scenario shape in its parent frame, and the mesh assets they need."""
    attrs = f'rgba="{OBJECT_RGBA}" {contact}'
    pose = _pose_attrs(shape.position, shape.rpy)
    if isinstance(shape, Cylinder) and cylinder_as_mesh:
        pts = np.vstack([_ring(shape.radius, -shape.height / 2, 48), _ring(shape.radius, shape.height / 2, 48)])
        return f'<geom name="{name}" type="mesh" mesh="{name}_mesh" {pose} {attrs}/>', [f'<mesh name="{name}_mesh" vertex="{_v(pts)}"/>']
    if isinstance(shape, Box):
        return f'<geom name="{name}" type="box" size="{_v(np.asarray(shape.size) / 2)}" {pose} {attrs}/>', []
    if isinstance(shape, Cylinder):
        return f'<geom name="{name}" type="cylinder" size="{shape.radius:.6g} {shape.height / 2:.6g}" {pose} {attrs}/>', []
    if isinstance(shape, Sphere):
        return f'<geom name="{name}" type="sphere" size="{shape.radius:.6g}" {pose} {attrs}/>', []
    if isinstance(shape, Prism):
        asset = f'<mesh name="{name}_mesh" vertex="{_v(shape.local_hull_points())}"/>'
        return f'<geom name="{name}" type="mesh" mesh="{name}_mesh" {pose} {attrs}/>', [asset]
    if isinstance(shape, Bundle):
        parts, assets = [], []
        for k, p in enumerate(shape.parts):
            g, a = _shape_geoms(p, f"{name}_{k}", contact, cylinder_as_mesh)
            parts.append(g)
            assets += a
        return f'<body name="{name}_bundle" {pose}>{"".join(parts)}</body>', assets
    raise ValueError(f"unknown shape {type(shape).__name__}")


def _extruded_points(obj: ObjectSpec) -> np.ndarray:
    """V `(n_v, 3)` and V moved up by the object's height along V's upward normal: `(2 n_v, 3)`."""
    v = obj.bottom_vertices()
    c = v.mean(axis=0)
    _, _, vt = np.linalg.svd(v - c)
    up = vt[2] * (1.0 if vt[2][2] >= 0 else -1.0)
    return np.vstack([v, v + obj.effective_height() * up])


def _parts(shape, T_parent: np.ndarray) -> list[ConvexPart]:
    T = T_parent @ shape.pose()
    if isinstance(shape, Bundle):
        return [part for p in shape.parts for part in _parts(p, T)]
    world = lambda local: local @ T[:3, :3].T + T[:3, 3]  # noqa: E731
    if isinstance(shape, Sphere):
        r = shape.radius
        rings = [_ring(r * np.cos(a), r * np.sin(a), 32) for a in np.linspace(-np.pi / 2, np.pi / 2, 13)]
        return [ConvexPart.from_points(world(np.vstack(rings)), kind="sphere", center=T[:3, 3].copy(), radius=r)]
    if isinstance(shape, Cylinder):
        local = np.vstack([_ring(shape.radius, -shape.height / 2, 48), _ring(shape.radius, shape.height / 2, 48)])
        return [
            ConvexPart.from_points(
                world(local), kind="cylinder", center=T[:3, 3].copy(), axis=T[:3, 2].copy(), radius=shape.radius, half_height=shape.height / 2
            )
        ]
    return [ConvexPart.from_points(world(shape.local_hull_points()))]


def _ring(radius: float, z: float, n: int) -> np.ndarray:
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full(n, z)], 1)


def object_parts(obj: ObjectSpec) -> list[ConvexPart]:
    """The object's convex pieces in the world frame (one per primitive; a bundle's parts apart)."""
    if obj.shape is None:
        return [ConvexPart.from_points(_extruded_points(obj))]
    return _parts(obj.shape, np.eye(4))


def object_slice(parts: list[ConvexPart], origin: np.ndarray, up: np.ndarray, height: float) -> np.ndarray:
    """(k, 3) points whose convex hulls (one per part) are the object's cross-section `height` above
    `origin` along the unit `up`; (0, 3) when the plane misses every part."""
    out = [np.zeros((0, 3))]
    for part in parts:
        s = (part.points - origin) @ up - height  # signed height of each hull point over the plane
        i, j = np.nonzero((s[:, None] < 0.0) & (s[None, :] >= 0.0))  # point pairs that straddle it
        t = s[i] / (s[i] - s[j])
        out.append(part.points[i] + t[:, None] * (part.points[j] - part.points[i]))
    return np.vstack(out)


def object_pose(obj: ObjectSpec) -> np.ndarray:
    """(4, 4) world <- object: the shape's pose, or V's centroid (axes of the world) when only V is known."""
    if obj.shape is not None:
        return obj.shape.pose()
    return make_transform(None, obj.bottom_vertices().mean(axis=0))


def object_mjcf(obj: ObjectSpec, contact: str = 'condim="3" friction="0.6"', round_as_mesh: bool = False) -> tuple[str, list[str], list[str]]:
    """(body XML, assets XML, names of the geoms that make up the object) for a static, rod-held object.
    `round_as_mesh`: cylinders as fine convex meshes (for contact modes that take meshes, not cylinders).
    A marker's texture file is in `object_files(obj)`, to be handed to MuJoCo with the XML."""
    if obj.shape is not None:
        geoms, assets = _shape_geoms(obj.shape, "object", contact, round_as_mesh)
        names = _geom_names(obj.shape, "object")
    else:
        pts = _extruded_points(obj)
        assets = [f'<mesh name="object_mesh" vertex="{_v(pts)}"/>']
        geoms = f'<geom name="object" type="mesh" mesh="object_mesh" rgba="{OBJECT_RGBA}" {contact}/>'
        names = ["object"]
    parts = object_parts(obj)
    card = ""
    T_world_marker = obj.T_world_marker()  # None without a marker
    if obj.marker is not None and T_world_marker is not None:
        card, card_assets = _marker_card(obj.marker, T_world_marker)
        assets = assets + card_assets
    base = _rod_foot(parts, T_world_marker, _card_side(obj.marker) if obj.marker is not None else 0.0)
    # The rod comes straight down onto the top of the object, beside the marker if there is one.
    rod = (
        f'<geom name="object_rod" type="cylinder" fromto="{_v(base - [0, 0, 0.01])} {_v(base + [0, 0, ROD_LENGTH_M])}" '
        f'size="{ROD_RADIUS_M}" contype="0" conaffinity="0" rgba="0.6 0.6 0.62 1"/>'
    )
    return f'<body name="object_body">{geoms}{card}{rod}</body>', assets, names


def marker_image(marker: MarkerSpec, px_per_cell: int = MARKER_PX_PER_CELL) -> np.ndarray:
    """The printed card `(n, n)` uint8: OpenCV's marker image with one white cell of quiet zone around it."""
    import cv2

    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, marker.dictionary))
    cells = dictionary.markerSize + 2  # data bits plus the black border
    img = cv2.aruco.generateImageMarker(dictionary, marker.id, cells * px_per_cell, borderBits=1)
    return cv2.copyMakeBorder(img, px_per_cell, px_per_cell, px_per_cell, px_per_cell, cv2.BORDER_CONSTANT, value=255)


def _card_side(marker: MarkerSpec) -> float:
    """Side (m) of the card: the black square plus a white cell on each side."""
    import cv2

    cells = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, marker.dictionary)).markerSize + 2
    return marker.size * (cells + 2) / cells


def _marker_file(marker: MarkerSpec) -> str:
    return f"aruco_{marker.dictionary.lower()}_{marker.id}.png"


def object_files(obj: ObjectSpec) -> dict[str, bytes]:
    """Files the object's MJCF refers to (the marker's texture PNG), for `MjModel.from_xml_string(assets=...)`."""
    if obj.marker is None:
        return {}
    import cv2

    ok, png = cv2.imencode(".png", marker_image(obj.marker))
    if not ok:  # pragma: no cover - encoding a small grey image does not fail
        raise RuntimeError("cannot encode the marker texture")
    return {_marker_file(obj.marker): png.tobytes()}


def _marker_card(marker: MarkerSpec, T_world_marker: np.ndarray) -> tuple[str, list[str]]:
    """A thin textured box whose top face is the marker (MuJoCo maps a 2-D texture onto a box's +z face
    with the image's columns along the box's x and its rows down its -y: OpenCV's marker axes).
    The card lies under the marker's face, so a marker placed on a surface stands its thickness proud of it."""
    half = _card_side(marker) / 2
    centre = T_world_marker[:3, 3] - T_world_marker[:3, 2] * (MARKER_THICKNESS_M / 2)
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(T_world_marker[:3, :3]).as_quat()
    name = f"marker_{marker.id}"
    assets = [
        f'<texture name="{name}_tex" type="2d" file="{_marker_file(marker)}"/>',
        f'<material name="{name}_mat" texture="{name}_tex" specular="0" shininess="0" reflectance="0"/>',
    ]
    geom = (
        f'<geom name="{name}" type="box" size="{half:.6g} {half:.6g} {MARKER_THICKNESS_M / 2:.6g}" pos="{_v(centre)}" '
        f'quat="{_v([w, x, y, z])}" material="{name}_mat" contype="0" conaffinity="0"/>'
    )
    return geom, assets


def _top_at(parts: list[ConvexPart], xy: np.ndarray) -> float | None:
    """The highest z where the vertical line through `xy (2,)` leaves one of the parts, or None if it misses them all."""
    best = None
    for part in parts:
        h = part.halfspaces
        rhs = -(h[:, 3] + h[:, 0] * xy[0] + h[:, 1] * xy[1])  # n_z z <= rhs
        up, down, flat = h[:, 2] > 1e-9, h[:, 2] < -1e-9, np.abs(h[:, 2]) <= 1e-9
        if np.any(rhs[flat] < 0):
            continue
        z_hi = np.min(rhs[up] / h[up, 2])
        z_lo = np.max(rhs[down] / h[down, 2]) if down.any() else -np.inf
        if z_lo <= z_hi and (best is None or z_hi > best):
            best = float(z_hi)
    return best


def _rod_foot(parts: list[ConvexPart], T_world_marker: np.ndarray | None = None, card_side: float = 0.0) -> np.ndarray:
    """(3,) where the holding rod meets the object's top: above the highest part's centroid, or, when
    that would pierce the marker card, just beside the card on its side away from the camera (-x), so
    that the rod, seen from the rig's camera, rises away from the marker."""
    part = max(parts, key=lambda p: p.points[:, 2].max())
    c = part.points.mean(axis=0)
    foot = np.array([c[0], c[1], _top_at([part], c[:2])])
    if T_world_marker is None:
        return foot
    half = card_side / 2 + ROD_RADIUS_M + 0.002
    local = (foot - T_world_marker[:3, 3]) @ T_world_marker[:3, :3]
    if np.max(np.abs(local[:2])) > half + ROD_RADIUS_M:
        return foot
    # candidates on a square ring just outside the card, in the marker's plane
    s = np.linspace(-half, half, 9)
    ring = np.vstack([np.column_stack([s, np.full(9, half)]), np.column_stack([s, np.full(9, -half)]),
                      np.column_stack([np.full(9, half), s]), np.column_stack([np.full(9, -half), s])])
    pts = np.column_stack([ring, np.zeros(len(ring))]) @ T_world_marker[:3, :3].T + T_world_marker[:3, 3]
    best = None
    for p in pts:
        z = _top_at(parts, p[:2])
        if z is None or z < T_world_marker[2, 3] - 0.03:  # off the object or far down its side
            continue
        if best is None or p[0] < best[0]:
            best = np.array([p[0], p[1], z])
    return best if best is not None else foot


def _geom_names(shape, name: str) -> list[str]:
    if isinstance(shape, Bundle):
        return [n for k, p in enumerate(shape.parts) for n in _geom_names(p, f"{name}_{k}")]
    return [name]


def object_mesh(obj: ObjectSpec) -> tuple[np.ndarray, np.ndarray]:
    """Vertices `(n, 3)` (world) and triangles `(m, 3)` of the object's convex parts, for display."""
    verts, faces, off = [], [], 0
    for p in object_parts(obj):
        verts.append(p.points)
        faces.append(p.faces + off)
        off += len(p.points)
    return np.vstack(verts), np.vstack(faces)
