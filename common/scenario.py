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
from bagit.common.bag import RIM_PERIMETER_M, FabricSpec, RimSpec, SimSpec
from bagit.common.errors import BadScenario
from bagit.common.geometry import closed_polyline_length, make_transform, pca, pose_to_matrix, resample_closed
from bagit.common.names import MAX_N_X, MIN_N_X
from bagit.common.params import DEFAULT_LAMBDA_D_M, MethodParams
from bagit.common.shapes import MAX_ANGLE_RAD, MAX_SIZE_M, Angles, Length, Position, Shape, Size3, check_coordinates

# Height assumed for collision checks when only V is known: the object is extruded this far up.
DEFAULT_OBJECT_HEIGHT_M = 0.10

# What a scenario document may be, checked before it is validated: the bundled ones are ~2.5 kB, 7
# levels deep (object.shape.parts[i].outline[j][k]) and under 1000 values. The limits stop a file that
# would exhaust the parser's stack (a YAML nested 100k deep), memory (a 10 GB file, or aliases that
# expand a few lines into 10^9 values) or time, with a one-line BadScenario instead.
MAX_SCENARIO_BYTES = 4 << 20  # room for a rim of ~100k points
MAX_SCENARIO_DEPTH = 32
MAX_SCENARIO_VALUES = 250_000  # scalars and containers, aliases counted each time they are used


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
    check_coordinates(a, what)
    return a.tolist()


MAX_MARKER_ID = 999  # ids of every OpenCV predefined dictionary are below 1000 (the largest has 1000)
MARKER_THICKNESS_M = 0.001  # a printed card: the marker's face stands this far off the surface it is stuck on


class MarkerSpec(BaseModel):
    """The ArUco marker stuck on the object, which tells perception which object it sees (as in the paper).

    Its pose is given in the object's bottom frame (`ObjectSpec.bottom_frame`), with OpenCV's marker
    axes: x to the right and y up on the printed marker, z out of its face. Without `position` the
    marker lies centred on the object's top (the bottom frame moved up by the object's height).
    """

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    id: int = Field(..., ge=0, le=MAX_MARKER_ID)
    size: float = Field(0.05, gt=0.005, lt=0.5, description="side of the marker's black square (m)")
    dictionary: ArucoDictionary = Field("DICT_4X4_50", description="OpenCV predefined dictionary, e.g. DICT_4X4_50")
    position: Position | None = Field(None, description="marker centre in the bottom frame (m)")
    rpy: Angles = (0.0, 0.0, 0.0)

    @model_validator(mode="after")
    def _id_in_dictionary(self) -> MarkerSpec:
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

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str | None = None
    vertices: list[list[float]] | None = Field(None, description="bottom outline V, world frame (m)")
    height: Length | None = Field(None, description="how far the object reaches above its bottom (m)")
    shape: Shape | None = None
    marker_id: int | None = Field(None, ge=0, le=MAX_MARKER_ID, description="shorthand for `marker: {id: ...}` (a default marker on top)")
    marker: MarkerSpec | None = None

    @field_validator("vertices")
    @classmethod
    def _vertices(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _finite_points(v, "object.vertices", 3)

    @model_validator(mode="after")
    def _derive(self) -> ObjectSpec:
        if self.vertices is None and self.shape is None:
            raise ValueError("object needs `vertices` or a `shape` to derive them from")
        if self.vertices is None and self.shape is not None:
            self.vertices = self.shape.bottom_vertices().tolist()
        if self.height is None and self.shape is not None:
            self.height = self.shape.local_height()
        # a shape's parts are bounded one by one; where they put the object must be bounded as a whole
        check_coordinates(self.vertices, "object's bottom outline")
        if self.height is not None and not self.height <= MAX_SIZE_M:
            raise ValueError(f"object height {self.height:.4g} m is over {MAX_SIZE_M:g} m")
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

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    rim_perimeter: float | None = Field(None, gt=0.05, lt=10.0, description="R (m); measured from initial_rim when absent")
    n_x: int = Field(32, ge=MIN_N_X, le=MAX_N_X)
    initial_rim: list[list[float]] | None = Field(None, description="g0 (m); when absent perception gives it")
    kind: Literal["red-edged", "solid"] = "red-edged"
    depth: float = Field(0.30, gt=0.02, lt=2.0, description="bag depth (m), for the simulator")
    color: tuple[float, float, float] = Field((0.15, 0.35, 0.75), description="RGB of the fabric, each in [0, 1]")
    fabric: FabricSpec = Field(default_factory=FabricSpec, description="the fabric's physics (simulator; defaults: the bag of every earlier run)")
    rim: RimSpec = Field(default_factory=RimSpec, description="the binding's bending stiffness and colour")

    @field_validator("color")
    @classmethod
    def _color(cls, v: tuple[float, float, float]) -> tuple[float, float, float]:
        if not all(0.0 <= c <= 1.0 for c in v):
            raise ValueError(f"bag color components must be in [0, 1], got {v}")
        return v

    @field_validator("initial_rim")
    @classmethod
    def _rim(cls, v: list[list[float]] | None) -> list[list[float]] | None:
        return _finite_points(v, "bag.initial_rim", 4)

    @model_validator(mode="after")
    def _perimeter(self) -> BagSpec:
        if self.rim_perimeter is None and self.initial_rim is not None:
            self.rim_perimeter = closed_polyline_length(np.asarray(self.initial_rim))
        return self

    def perimeter_m(self) -> float:
        """The rim's perimeter the simulator builds and the arms hold: R (given or measured from g0), else the paper's bag's."""
        return self.rim_perimeter or RIM_PERIMETER_M

    def g0(self) -> np.ndarray | None:
        """The initial SOI `(n_x, 3)` resampled to n_x points, or None when perception must give it."""
        if self.initial_rim is None:
            return None
        rim = np.asarray(self.initial_rim, dtype=float)
        return rim if len(rim) == self.n_x else resample_closed(rim, self.n_x)


class Obstacle(BaseModel):
    """A static cuboid: centre, full extents, yaw about world z."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    center: Position
    size: Size3
    yaw: float = Field(0.0, ge=-MAX_ANGLE_RAD, le=MAX_ANGLE_RAD)


def check_document(data: Any, source: str = "scenario") -> None:
    """BadScenario when a parsed document is deeper than MAX_SCENARIO_DEPTH or holds more than
    MAX_SCENARIO_VALUES values (aliases counted at each use). Iterative, so a self-referencing or
    deeply nested document cannot exhaust the stack, and it stops at the first limit it passes."""
    stack: list[tuple[Any, int]] = [(data, 1)]
    seen = 1
    while stack:
        node, depth = stack.pop()
        if not isinstance(node, (dict, list, tuple)):
            continue
        if depth > MAX_SCENARIO_DEPTH:
            raise BadScenario(f"{source}: nested more than {MAX_SCENARIO_DEPTH} levels deep")
        seen += len(node)
        if seen > MAX_SCENARIO_VALUES:
            raise BadScenario(f"{source}: more than {MAX_SCENARIO_VALUES} values (a scenario has a few thousand)")
        stack.extend((c, depth + 1) for c in (node.values() if isinstance(node, dict) else node))


def _yaml_reason(e: yaml.YAMLError) -> str:
    """One line from a YAML error: its problem (e.g. libyaml's 'exceeded maximum nesting depth'), the
    context it arose in and where, rather than only the context that str(e) starts with."""
    problem, context, mark = (getattr(e, k, None) for k in ("problem", "context", "problem_mark"))
    if not problem:
        return str(e).splitlines()[0] if str(e) else type(e).__name__
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    return f"{problem}{' ' + context if context else ''}{where}"


# libyaml's safe loader parses the bundled scenarios (rims of hundreds of points) about 10x faster
_YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


class Scenario(BaseModel):
    """One bagging task."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    name: str = Field(..., min_length=1, max_length=200)
    description: str | None = None
    object: ObjectSpec
    bag: BagSpec = BagSpec()
    obstacles: list[Obstacle] = []
    params: MethodParams = MethodParams()
    sim: SimSpec = Field(default_factory=SimSpec, description="the simulator's light and camera noise (a real rig ignores it)")

    def lambda_d(self) -> float:
        """The goal lift λd: the parameter when set, else half the object's height."""
        if self.params.goal.lambda_d is not None:
            return self.params.goal.lambda_d
        if self.object.height is not None:
            return self.object.height / 2
        return DEFAULT_LAMBDA_D_M

    @classmethod
    def from_dict(cls, data: Any, source: str = "scenario") -> Scenario:
        """Validate a parsed document; errors become one-line `BadScenario`."""
        if not isinstance(data, dict):
            raise BadScenario(f"{source}: expected a mapping at the top level, got {type(data).__name__}")
        check_document(data, source)
        try:
            return cls.model_validate(data)
        except ValidationError as e:
            first = e.errors()[0]
            loc = ".".join(str(p) for p in first["loc"])
            more = f" (+{e.error_count() - 1} more)" if e.error_count() > 1 else ""
            msg = first["msg"].removeprefix("Value error, ")
            if first["type"] == "finite_number":
                msg = f"NaN or infinite number ({first['input']!r}): numbers must be finite"
            raise BadScenario(f"{source}: {loc}: {msg}{more}") from None
        except (ValueError, TypeError, ArithmeticError) as e:  # raised while deriving V from a shape
            raise BadScenario(f"{source}: {e}") from None

    @classmethod
    def from_text(cls, text: str, source: str = "scenario") -> Scenario:
        """Parse YAML (a superset of JSON) and validate; a document over MAX_SCENARIO_BYTES is refused unread."""
        if len(text) > MAX_SCENARIO_BYTES:
            raise BadScenario(f"{source}: {len(text)} characters, over the {MAX_SCENARIO_BYTES >> 20} MiB a scenario may have")
        try:
            data = yaml.load(text, Loader=_YAML_LOADER)  # noqa: S506 - a safe loader (libyaml's when built in)
        except yaml.YAMLError as e:
            raise BadScenario(f"{source}: not valid YAML/JSON: {_yaml_reason(e)}") from None
        except RecursionError:  # the pure-Python loader composes nested nodes recursively
            raise BadScenario(f"{source}: nested too deeply (a scenario is at most {MAX_SCENARIO_DEPTH} levels deep)") from None
        except MemoryError:
            raise BadScenario(f"{source}: too large to parse") from None
        return cls.from_dict(data, source)

    @classmethod
    def from_file(cls, path: str | Path) -> Scenario:
        """Read a `.yaml`, `.yml` or `.json` scenario file."""
        p = Path(path)
        try:
            with open(p, "rb") as f:  # read at most one byte over the limit: /dev/zero or a 10 GB file is not read whole
                raw = f.read(MAX_SCENARIO_BYTES + 1)
            if len(raw) > MAX_SCENARIO_BYTES:
                raise BadScenario(f"scenario {p} is over the {MAX_SCENARIO_BYTES >> 20} MiB a scenario may have")
            text = raw.decode("utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise BadScenario(f"cannot read scenario {p}: {e}") from None
        return cls.from_text(text, str(p))

    def to_yaml(self) -> str:
        return yaml.safe_dump(json.loads(self.model_dump_json(exclude_none=True)), sort_keys=False)
