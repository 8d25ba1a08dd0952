"""Object shapes of a scenario and the bottom outline V they imply.

Each shape lives in its own local frame: centred at `position`, turned by `rpy`, with its bottom
face at local z = -height/2 (a sphere's "bottom" is its widest cross-section, at local z = 0).
A bundle's parts are placed in the bundle's frame, as bound objects are strapped together.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator
from scipy.spatial import ConvexHull, QhullError

from bagit.common.geometry import pose_to_matrix, transform_points

CIRCLE_VERTICES = 24  # polygon vertices used for a round bottom (cylinder, sphere)


# Bounds on what a scenario may say, for a table-top rig: two CR5s (reach 0.9 m) either side of the
# object. Every bundled scenario lies well inside them (coordinates within 0.7 m of the origin, sizes
# at most 0.32 m, angles at most 0.4 rad); they are there so that a typo or a hostile file (an object
# at 1e308) is refused where it is read, instead of overflowing an SVD or a hull later on.
MAX_COORDINATE_M = 10.0  # |x|, |y|, |z| of any point or position (m): ten times the arms' reach
MAX_SIZE_M = 2.0  # any extent of an object or obstacle: a size, a height, a diameter (m)
MAX_ANGLE_RAD = 2 * np.pi  # |roll|, |pitch|, |yaw|: a whole turn either way names every orientation


def _finite_vec(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not np.all(np.isfinite(v)):
        raise ValueError("must be finite")
    return v


def check_coordinates(v: object, what: str = "coordinates") -> None:
    """ValueError unless every number in `v` is finite and within MAX_COORDINATE_M of 0."""
    a = np.asarray(v, dtype=float)
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be finite")
    if a.size and np.abs(a).max() > MAX_COORDINATE_M:
        raise ValueError(f"{what} must lie within {MAX_COORDINATE_M:g} m of the origin, got {np.abs(a).max():.4g} m")


def _position(v: tuple[float, float, float]) -> tuple[float, float, float]:
    check_coordinates(v, "a position")
    return v


def _angles(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not all(np.isfinite(x) and abs(x) <= MAX_ANGLE_RAD for x in v):
        raise ValueError(f"angles must be finite and within ±2π rad, got {v}")
    return v


def _sizes(v: tuple[float, ...]) -> tuple[float, ...]:
    if not all(np.isfinite(x) and 0 < x <= MAX_SIZE_M for x in v):
        raise ValueError(f"sizes must be finite, positive and at most {MAX_SIZE_M:g} m, got {v}")
    return v


Vec3 = Annotated[tuple[float, float, float], AfterValidator(_finite_vec)]  # a finite vector (the rig's own poses)
Position = Annotated[tuple[float, float, float], AfterValidator(_position)]  # a scenario's position (m)
Angles = Annotated[tuple[float, float, float], AfterValidator(_angles)]  # roll, pitch, yaw (rad)
Size3 = Annotated[tuple[float, float, float], AfterValidator(_sizes)]  # full extents (m)
Length = Annotated[float, Field(gt=0, le=MAX_SIZE_M)]  # a height (m)
Radius = Annotated[float, Field(gt=0, le=MAX_SIZE_M / 2)]  # a radius: its diameter is an extent (m)


def _circle(radius: float, z: float, n: int = CIRCLE_VERTICES) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full(n, z)], axis=1)


class _ShapeBase(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    position: Position = (0.0, 0.0, 0.0)
    rpy: Angles = (0.0, 0.0, 0.0)

    def pose(self) -> np.ndarray:
        """4x4 transform parent <- shape."""
        return pose_to_matrix(self.position, self.rpy)

    def local_bottom(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def local_hull_points(self) -> np.ndarray:  # pragma: no cover - overridden
        raise NotImplementedError

    def local_height(self) -> float:
        """How far the shape reaches above its bottom outline (along its local z)."""
        pts = self.local_hull_points()
        return float(pts[:, 2].max() - self.local_bottom()[:, 2].min())

    def bottom_vertices(self) -> np.ndarray:
        """The bottom outline V `(n_v, 3)` in the parent (world) frame."""
        return transform_points(self.pose(), self.local_bottom())

    def hull_points(self) -> np.ndarray:
        """Points `(m, 3)` whose convex hull bounds the shape, in the parent frame."""
        return transform_points(self.pose(), self.local_hull_points())


class Box(_ShapeBase):
    type: Literal["box"] = "box"
    size: Size3 = Field(..., description="full extents (m)")

    def local_bottom(self) -> np.ndarray:
        sx, sy, sz = (s / 2 for s in self.size)
        return np.array([[sx, sy, -sz], [-sx, sy, -sz], [-sx, -sy, -sz], [sx, -sy, -sz]])

    def local_hull_points(self) -> np.ndarray:
        b = self.local_bottom()
        return np.vstack([b, b * [1, 1, -1]])


class Cylinder(_ShapeBase):
    type: Literal["cylinder"] = "cylinder"
    radius: Radius
    height: Length

    def local_bottom(self) -> np.ndarray:
        return _circle(self.radius, -self.height / 2)

    def local_hull_points(self) -> np.ndarray:
        return np.vstack([_circle(self.radius, -self.height / 2), _circle(self.radius, self.height / 2)])


class Sphere(_ShapeBase):
    type: Literal["sphere"] = "sphere"
    radius: Radius

    def local_bottom(self) -> np.ndarray:
        return _circle(self.radius, 0.0)

    def local_hull_points(self) -> np.ndarray:
        r = self.radius
        rings = [_circle(r * np.cos(a), r * np.sin(a)) for a in np.linspace(-np.pi / 2, np.pi / 2, 9)]
        return np.vstack(rings)


class Prism(_ShapeBase):
    type: Literal["prism"] = "prism"
    outline: list[tuple[float, float]] = Field(..., min_length=3, description="2-D polygon of the cross-section (m)")
    height: Length

    @field_validator("outline")
    @classmethod
    def _polygon(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
        a = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(a)) or np.abs(a).max() > MAX_SIZE_M:
            raise ValueError(f"prism outline must be finite and within {MAX_SIZE_M:g} m of the prism's axis")
        x, y = a[:, 0], a[:, 1]
        area = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
        if area < 1e-6:
            raise ValueError("prism outline encloses no area")
        return v

    def local_bottom(self) -> np.ndarray:
        a = np.asarray(self.outline, dtype=float)
        return np.column_stack([a, np.full(len(a), -self.height / 2)])

    def local_hull_points(self) -> np.ndarray:
        b = self.local_bottom()
        return np.vstack([b, b * [1, 1, -1]])


class Bundle(_ShapeBase):
    """Several shapes bound together; V is the outline around the parts' bottoms."""

    type: Literal["bundle"] = "bundle"
    parts: list[Annotated[Box | Cylinder | Sphere | Prism, Field(discriminator="type")]] = Field(..., min_length=1)

    def local_bottom(self) -> np.ndarray:
        bottoms = np.vstack([p.bottom_vertices() for p in self.parts])
        z0 = min(p.hull_points()[:, 2].min() for p in self.parts)
        z0 = min(z0, bottoms[:, 2].min())
        xy = bottoms[:, :2]
        try:
            hull = ConvexHull(xy)
        except QhullError:  # a ValueError, so the scenario's validation names it
            raise ValueError("the bundle's parts outline no bottom face (they are too small or in a line)") from None
        ring = xy[hull.vertices]  # counter-clockwise
        return np.column_stack([ring, np.full(len(ring), z0)])

    def local_hull_points(self) -> np.ndarray:
        return np.vstack([p.hull_points() for p in self.parts])


Shape = Annotated[Box | Cylinder | Sphere | Prism | Bundle, Field(discriminator="type")]
