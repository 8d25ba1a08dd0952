"""The scenario: the object to bag, the bag, the obstacles and the method parameters.

Read with `Scenario.from_file(path)` (YAML or JSON). Later issues add fields; files written for
earlier versions keep reading.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from bagit.common.aruco import ARUCO_DICTIONARIES, ArucoDictionary
from bagit.common.errors import BadScenario
from bagit.common.geometry import closed_polyline_length, make_transform, pca, pose_to_matrix, resample_closed
from bagit.common.params import DEFAULT_LAMBDA_D_M, MethodParams
from bagit.common.shapes import Shape, Vec3

# Height assumed for collision checks when only V is known: the object is extruded this far up.
DEFAULT_OBJECT_HEIGHT_M = 0.10


def _finite_points(v: list[list[float]] | None, what: str, min_points: int) -> list[list[float]] | None:
    if v is None:
        return v
    a = np.asarray(v, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ValueError(f"{what} must be a list of [x, y, z] points")
    if len(a) < min_points:
        raise ValueError(f"{what} needs at least {min_points} points, got {len(a)}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{what} has NaN or infinite coordinates")
    return a.tolist()


MARKER_THICKNESS_M = 0.001  # a printed card: the marker's face stands this far off the surface it is stuck on


class MarkerSpec(BaseModel):
    """The ArUco marker stuck on the object, which tells perception which object it sees (as in the paper).

    Its pose is given in the object's bottom frame (`ObjectSpec.bottom_frame`), with OpenCV's marker
    axes: x to the right and y up on the printed marker, z out of its face. Without `position` the
    marker lies centred on the object's top (the bottom frame moved up by the object's height).
    """

    model_config = ConfigDict(extra="forbid")

    id: int = Field(..., ge=0, le=999)
    size: float = Field(0.05, gt=0.005, lt=0.5, description="side of the marker's black square (m)")
    dictionary: ArucoDictionary = Field("DICT_4X4_50", description="OpenCV predefined dictionary, e.g. DICT_4X4_50")
    position: Vec3 | None = Field(None, description="marker centre in the bottom frame (m)")
    rpy: Vec3 = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _id_in_dictionary(self) -> "MarkerSpec":
        if self.id >= ARUCO_DICTIONARIES[self.dictionary]:
            raise ValueError(f"marker id {self.id} is not in {self.dictionary} (ids 0..{ARUCO_DICTIONARIES[self.dictionary] - 1})")
        return self

    def T_bottom_marker(self) -> np.ndarray:
        """4x4 object bottom frame <- marker (needs `position`, which ObjectSpec fills in)."""
        if self.position is None:
            raise ValueError("the marker's position is resolved by its ObjectSpec")
        return pose_to_matrix(self.position, self.rpy)


class ObjectSpec(BaseModel):
    """The object to bag: its bottom outline V (given, or derived from `shape`), its height, and the
    ArUco marker that identifies it."""

    model_config = ConfigDict(extra="forbid")

    name: str | None = None
    vertices: list[list[float]] | None = Field(None, description="bottom outline V, world frame (m)")
    height: float | None = Field(None, gt=0, lt=5, description="how far the object reaches above its bottom (m)")
    shape: Shape | None = None
    marker_id: int | None = Field(None, ge=0, description="shorthand for `marker: {id: ...}` (a default marker on top)")
    marker: MarkerSpec | None = None

    @field_validator("vertices")
    @classmethod
    def _vertices(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _finite_points(v, "object.vertices", 3)

    @model_validator(mode="after")
    def _derive(self) -> "ObjectSpec":
        if self.vertices is None and self.shape is None:
            raise ValueError("object needs `vertices` or a `shape` to derive them from")
        if self.vertices is None and self.shape is not None:
            self.vertices = self.shape.bottom_vertices().tolist()
        if self.height is None and self.shape is not None:
            self.height = self.shape.local_height()
        if self.marker_id is not None:
            if self.marker is None:
                self.marker = MarkerSpec(id=self.marker_id)
            elif self.marker.id != self.marker_id:
                raise ValueError(f"object.marker_id {self.marker_id} disagrees with object.marker.id {self.marker.id}")
        if self.marker is not None:
            self.marker_id = self.marker.id
            if self.marker.position is None:
                self.marker.position = (0.0, 0.0, float(self.effective_height()) + MARKER_THICKNESS_M)
        return self

    def bottom_frame(self) -> np.ndarray:
        """4x4 world <- the object's bottom frame: on the bottom face, z up out of the object.

        With a shape: the shape's own axes, moved down to its bottom outline (origin straight under
        the shape's origin). With V only: origin at V's centroid, z normal to V (upward), x along
        V's principal axis. Markers and the object library (perception) are placed in this frame.
        """
        if self.shape is not None:
            zb = float(self.shape.local_bottom()[:, 2].min())
            return self.shape.pose() @ make_transform(None, np.array([0.0, 0.0, zb]))
        centroid, _, axes = pca(self.bottom_vertices())
        z = axes[2] if axes[2][2] >= 0 else -axes[2]
        x = axes[0] - np.dot(axes[0], z) * z
        x /= np.linalg.norm(x)
        return make_transform(np.column_stack([x, np.cross(z, x), z]), centroid)

    def local_vertices(self) -> np.ndarray:
        """V `(n_v, 3)` in the object's bottom frame: the object's outline wherever it is placed."""
        T = self.bottom_frame()
        return (self.bottom_vertices() - T[:3, 3]) @ T[:3, :3]

    def T_world_marker(self) -> np.ndarray | None:
        """4x4 world <- marker, or None without a marker (where the scenario puts the marker)."""
        if self.marker is None:
            return None
        return self.bottom_frame() @ self.marker.T_bottom_marker()

    def bottom_vertices(self) -> np.ndarray:
        """V `(n_v, 3)`, world frame."""
        return np.asarray(self.vertices, dtype=float)

    def effective_height(self) -> float:
        """The object's height, or DEFAULT_OBJECT_HEIGHT_M when only V is known."""
        return self.height if self.height is not None else DEFAULT_OBJECT_HEIGHT_M


class BagSpec(BaseModel):
    """The bag: its rim perimeter R, how many SOI points, and optionally its initial rim g0."""

    model_config = ConfigDict(extra="forbid")

    rim_perimeter: float | None = Field(None, gt=0.05, lt=10.0, description="R (m); measured from initial_rim when absent")
    n_x: int = Field(32, ge=4, le=512)
    initial_rim: list[list[float]] | None = Field(None, description="g0 (m); when absent perception gives it")
    kind: Literal["red-edged", "solid"] = "red-edged"
    depth: float = Field(0.30, gt=0.02, lt=2.0, description="bag depth (m), for the simulator")
    color: tuple[float, float, float] = (0.15, 0.35, 0.75)

    @field_validator("initial_rim")
    @classmethod
    def _rim(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _finite_points(v, "bag.initial_rim", 4)

    @model_validator(mode="after")
    def _perimeter(self) -> "BagSpec":
        if self.rim_perimeter is None and self.initial_rim is not None:
            self.rim_perimeter = closed_polyline_length(np.asarray(self.initial_rim))
        return self

    def g0(self) -> np.ndarray | None:
        """The initial SOI `(n_x, 3)` resampled to n_x points, or None when perception must give it."""
        if self.initial_rim is None:
            return None
        rim = np.asarray(self.initial_rim, dtype=float)
        return rim if len(rim) == self.n_x else resample_closed(rim, self.n_x)


class Obstacle(BaseModel):
    """A static cuboid: centre, full extents, yaw about world z."""

    model_config = ConfigDict(extra="forbid")

    center: tuple[float, float, float]
    size: tuple[float, float, float]
    yaw: float = 0.0

    @field_validator("size")
    @classmethod
    def _size(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(np.isfinite(x) and x > 0 for x in v):
            raise ValueError("obstacle size must be finite and positive")
        return v

    @field_validator("center")
    @classmethod
    def _center(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not np.all(np.isfinite(v)):
            raise ValueError("obstacle center must be finite")
        return v


# libyaml's safe loader parses the bundled scenarios (rims of hundreds of points) about 10x faster
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class Scenario(BaseModel):
    """One bagging task."""

    model_config = ConfigDict(extra="forbid")

    name: str = Field(..., min_length=1, max_length=200)
    description: str | None = None
    object: ObjectSpec
    bag: BagSpec = BagSpec()
    obstacles: list[Obstacle] = []
    params: MethodParams = MethodParams()

    def lambda_d(self) -> float:
        """The goal lift λd: the parameter when set, else half the object's height."""
        if self.params.lambda_d is not None:
            return self.params.lambda_d
        if self.object.height is not None:
            return self.object.height / 2
        return DEFAULT_LAMBDA_D_M

    @classmethod
    def from_dict(cls, data: Any, source: str = "scenario") -> "Scenario":
        """Validate a parsed document; errors become one-line `BadScenario`."""
        if not isinstance(data, dict):
            raise BadScenario(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
        try:
            return cls.model_validate(data)
        except ValidationError as e:
            first = e.errors()[0]
            loc = ".".join(str(p) for p in first["loc"])
            more = f" (+{e.error_count() - 1} more)" if e.error_count() > 1 else ""
            raise BadScenario(f"{source}: {loc}: {first['msg']}{more}") from None
        except (ValueError, TypeError) as e:  # raised while deriving V from a shape
            raise BadScenario(f"{source}: {e}") from None

    @classmethod
    def from_text(cls, text: str, source: str = "scenario") -> "Scenario":
        """Parse YAML (a superset of JSON) and validate."""
        try:
            data = yaml.load(text, Loader=_YAML_LOADER)  # noqa: S506 - a safe loader (libyaml's when built in)
        except yaml.YAMLError as e:
            raise BadScenario(f"{source}: not valid YAML/JSON: {str(e).splitlines()[0]}") from None
        return cls.from_dict(data, source)

    @classmethod
    def from_file(cls, path: str | Path) -> "Scenario":
        """Read a `.yaml`, `.yml` or `.json` scenario file."""
        p = Path(path)
        try:
            text = p.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise BadScenario(f"cannot read scenario {p}: {e}") from None
        return cls.from_text(text, str(p))

    def to_yaml(self) -> str:
        return yaml.safe_dump(json.loads(self.model_dump_json(exclude_none=True)), sort_keys=False)
