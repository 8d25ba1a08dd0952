"""Object shapes of a scenario and the bottom outline V they imply.

Each shape lives in its own local frame: centred at `position`, turned by `rpy`, with its bottom
face at local z = -height/2 (a sphere's "bottom" is its widest cross-section, at local z = 0).
A bundle's parts are placed in the bundle's frame, as bound objects are strapped together.
"""

from __future__ import annotations

from typing import Annotated, Literal, Union

import numpy as np
from pydantic import AfterValidator, BaseModel, ConfigDict, Field, field_validator
from scipy.spatial import ConvexHull

from bagit.common.geometry import pose_to_matrix, transform_points

CIRCLE_VERTICES = 24  # polygon vertices used for a round bottom (cylinder, sphere)


def _finite_vec(v: tuple[float, float, float]) -> tuple[float, float, float]:
    if not np.all(np.isfinite(v)):
        raise ValueError("must be finite")
    return v


Vec3 = Annotated[tuple[float, float, float], AfterValidator(_finite_vec)]  # a finite position or rpy


def _circle(radius: float, z: float, n: int = CIRCLE_VERTICES) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.stack([radius * np.cos(t), radius * np.sin(t), np.full(n, z)], axis=1)


class _ShapeBase(BaseModel):
    model_config = ConfigDict(extra="forbid")

    position: Vec3 = (0.0, 0.0, 0.0)
    rpy: Vec3 = (0.0, 0.0, 0.0)

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
    size: tuple[float, float, float] = Field(..., description="full extents (m)")

    @field_validator("size")
    @classmethod
    def _positive(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(np.isfinite(x) and 0 < x < 5 for x in v):
            raise ValueError("box size must be finite, positive and under 5 m")
        return v

    def local_bottom(self) -> np.ndarray:
        sx, sy, sz = (s / 2 for s in self.size)
        return np.array([[sx, sy, -sz], [-sx, sy, -sz], [-sx, -sy, -sz], [sx, -sy, -sz]])

    def local_hull_points(self) -> np.ndarray:
        b = self.local_bottom()
        return np.vstack([b, b * [1, 1, -1]])


class Cylinder(_ShapeBase):
    type: Literal["cylinder"] = "cylinder"
    radius: float = Field(..., gt=0, lt=2.5)
    height: float = Field(..., gt=0, lt=5)

    def local_bottom(self) -> np.ndarray:
        return _circle(self.radius, -self.height / 2)

    def local_hull_points(self) -> np.ndarray:
        return np.vstack([_circle(self.radius, -self.height / 2), _circle(self.radius, self.height / 2)])


class Sphere(_ShapeBase):
    type: Literal["sphere"] = "sphere"
    radius: float = Field(..., gt=0, lt=2.5)

    def local_bottom(self) -> np.ndarray:
        return _circle(self.radius, 0.0)

    def local_hull_points(self) -> np.ndarray:
        r = self.radius
        rings = [_circle(r * np.cos(a), r * np.sin(a)) for a in np.linspace(-np.pi / 2, np.pi / 2, 9)]
        return np.vstack(rings)


class Prism(_ShapeBase):
    type: Literal["prism"] = "prism"
    outline: list[tuple[float, float]] = Field(..., min_length=3, description="2-D polygon of the cross-section (m)")
    height: float = Field(..., gt=0, lt=5)

    @field_validator("outline")
    @classmethod
    def _polygon(cls, v: list[tuple[float, float]]) -> list[tuple[float, float]]:
        a = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(a)):
            raise ValueError("prism outline must be finite")
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
    parts: list[Annotated[Union[Box, Cylinder, Sphere, Prism], Field(discriminator="type")]] = Field(..., min_length=1)

    def local_bottom(self) -> np.ndarray:
        bottoms = np.vstack([p.bottom_vertices() for p in self.parts])
        z0 = min(p.hull_points()[:, 2].min() for p in self.parts)
        z0 = min(z0, bottoms[:, 2].min())
        xy = bottoms[:, :2]
        hull = ConvexHull(xy)
        ring = xy[hull.vertices]  # counter-clockwise
        return np.column_stack([ring, np.full(len(ring), z0)])

    def local_hull_points(self) -> np.ndarray:
        return np.vstack([p.hull_points() for p in self.parts])


Shape = Annotated[Union[Box, Cylinder, Sphere, Prism, Bundle], Field(discriminator="type")]
