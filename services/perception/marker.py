"""Which object, and where: find the object's ArUco marker in the colour image, estimate the marker's
pose, look the object up by marker id in the object library, and place its bottom outline V in the world.

As in the paper the marker names the object; its bottom outline V, height and marker pose (in the
object's bottom frame, `ObjectSpec.bottom_frame`) come from the object library, built from the
scenario files' object descriptions (never from where a scenario puts the object).

Corners: OpenCV's detector finds the marker; its corner refinements, on a marker only 20-30 pixels
wide (40-60 mm at the rig's ~0.8 m, a border cell 4 pixels), are pulled by the inner bits by up to a
pixel (measured on the simulator's renders: 1.6 deg of in-plane rotation). So each side of the black
square is re-fitted as a straight line through its edge points (the black-to-white crossing across the
side, sampled along its middle) and the corners are the lines' crossings: ~0.1 px.

Pose: OpenCV's IPPE_SQUARE solution from the four corners. A tenth of a pixel of corner error is
still several mm in range and a degree in tilt; so when the aligned depth covers the marker, the marker plane
fitted to its depth pixels fixes the tilt (of the two IPPE solutions, the one closer to it, turned
onto it) and the range (the ray through the marker's centre, where the image diagonals cross, meets
that plane). The in-plane rotation stays the corners'.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from scipy.ndimage import map_coordinates

from bagit.common.errors import BadScenario, MarkerNotFound
from bagit.common.geometry import invert_transform, make_transform, transform_points
from bagit.common.messages import CameraInfo, ObjectDetection, RgbdFrame
from bagit.common.scenario import MarkerSpec, Scenario

MIN_DEPTH_PIXELS = 30  # fewer valid depth pixels on the marker: keep the corners-only pose
DEPTH_INNER_FRACTION = 0.8  # use depth pixels inside the marker shrunk by this much (away from its edges)
SAME_GEOMETRY_TOL_M = 1e-6


@dataclass(frozen=True)
class LibraryObject:
    """One object of the library. vertices: (n_v, 3) V in the object's bottom frame."""

    name: str
    marker: MarkerSpec
    vertices: np.ndarray
    height: float
    source: str

    def T_bottom_marker(self) -> np.ndarray:
        return self.marker.T_bottom_marker()


class ObjectLibrary:
    """Objects by marker id. Two scenario files may describe the same object under one id (the same
    coffee box with and without obstacles); one id for two different objects is an error."""

    def __init__(self, objects: Iterable[LibraryObject] = ()):
        self._by_id: dict[int, LibraryObject] = {}
        for obj in objects:
            self.add(obj)

    def add(self, obj: LibraryObject) -> None:
        old = self._by_id.get(obj.marker.id)
        if old is not None:
            same = (
                old.marker.size == obj.marker.size
                and old.marker.dictionary == obj.marker.dictionary
                and old.vertices.shape == obj.vertices.shape
                and np.allclose(old.vertices, obj.vertices, atol=SAME_GEOMETRY_TOL_M)
                and np.allclose(old.T_bottom_marker(), obj.T_bottom_marker(), atol=SAME_GEOMETRY_TOL_M)
            )
            if not same:
                raise BadScenario(
                    f"marker id {obj.marker.id} names two different objects: {old.name} ({old.source}) and {obj.name} ({obj.source})"
                )
            return
        self._by_id[obj.marker.id] = obj

    @classmethod
    def from_scenarios(cls, paths: Iterable[str | Path] | None = None) -> ObjectLibrary:
        """The library of every object with a marker in these scenario files (default: the bundled ones)."""
        if paths is None:
            from bagit.scenarios import list_scenarios

            paths = list_scenarios()
        lib = cls()
        for p in paths:
            s = Scenario.from_file(p)
            o = s.object
            if o.marker is None:
                continue
            lib.add(LibraryObject(o.name or s.name, o.marker, o.local_vertices(), float(o.effective_height()), str(p)))
        return lib

    def __len__(self) -> int:
        return len(self._by_id)

    def __contains__(self, marker_id: int) -> bool:
        return marker_id in self._by_id

    def ids(self) -> list[int]:
        return sorted(self._by_id)

    def get(self, marker_id: int) -> LibraryObject:
        try:
            return self._by_id[marker_id]
        except KeyError:
            raise MarkerNotFound(f"marker id {marker_id} is not in the object library (ids {self.ids()})") from None

    def dictionaries(self) -> list[str]:
        return sorted({o.marker.dictionary for o in self._by_id.values()})


def with_run_object(lib: ObjectLibrary, scenario: Scenario) -> ObjectLibrary:
    """`lib` with the run's own object added when its marker id is new (a scenario document started from
    the dashboard), as a new library (the old one stays whole for whoever reads it); BadScenario when
    one id would name two different objects."""
    o = scenario.object
    if o.marker is None or o.marker.id in lib:
        return lib
    out = ObjectLibrary(lib.get(i) for i in lib.ids())
    out.add(LibraryObject(o.name or scenario.name, o.marker, o.local_vertices(), float(o.effective_height()), "run/state"))
    return out


@dataclass
class MarkerPose:
    """One detected marker. corners: (4, 2) pixels (OpenCV order: the printed marker's top-left first,
    clockwise); T_camera_marker: (4, 4); reprojection_px: RMS corner error of the final pose."""

    id: int
    corners: np.ndarray
    T_camera_marker: np.ndarray
    reprojection_px: float
    depth_pixels: int = 0
    depth_rms_m: float = float("nan")


@dataclass
class ObjectEstimate:
    """An identified object placed in the world. vertices: (n_v, 3) V, world frame."""

    marker_id: int
    name: str
    T_world_marker: np.ndarray
    T_world_bottom: np.ndarray
    vertices: np.ndarray
    height: float
    marker: MarkerPose
    others: list[int] = field(default_factory=list)  # ids seen but not in the library


def _detector(dictionary: str) -> cv2.aruco.ArucoDetector:
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)), params)


def detect_markers(color: np.ndarray, dictionary: str = "DICT_4X4_50", refine: bool = True) -> list[tuple[int, np.ndarray]]:
    """(id, corners (4, 2) float64 pixels) of every marker of `dictionary` in `color (H, W, 3)` RGB uint8
    (or `(H, W)` grey); `refine`: corners from the sides' edge lines (`refine_corners_by_edges`)."""
    img = np.asarray(color)
    if img.ndim == 3 and img.shape[2] == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(img, dtype=np.uint8), cv2.COLOR_RGB2GRAY)
    elif img.ndim == 2:
        gray = np.ascontiguousarray(img, dtype=np.uint8)
    else:
        raise ValueError(f"colour image must be (H, W, 3) or grey (H, W), got {img.shape}")
    det = _detector(dictionary)
    corners, ids, _ = det.detectMarkers(gray)
    if ids is None:
        return []
    cells = det.getDictionary().markerSize + 2
    out = []
    for i, c in zip(ids.ravel(), corners, strict=False):
        c = np.asarray(c, dtype=float).reshape(4, 2)
        out.append((int(i), refine_corners_by_edges(gray, c, cells) if refine else c))
    return out


def refine_corners_by_edges(gray: np.ndarray, corners: np.ndarray, cells: int = 6, samples: int = 12) -> np.ndarray:
    """Corners `(4, 2)` of a dark square on a light surround as the crossings of its four sides, each a
    line fitted to where the grey level crosses half-way between dark and light across the side
    (sampled over the middle 60% of the side, away from the corners); the input corners if that fails."""
    c = np.asarray(corners, dtype=float)
    centre = c.mean(axis=0)
    side = float(np.mean(np.linalg.norm(c - np.roll(c, -1, axis=0), axis=1)))
    reach = float(np.clip(0.8 * side / cells, 1.0, 3.0))  # stay within the border cell and the quiet zone
    s = np.linspace(-reach, reach, 61)
    g = np.asarray(gray, dtype=float)
    lines = []
    for i in range(4):
        a, b = c[i], c[(i + 1) % 4]
        d = (b - a) / np.linalg.norm(b - a)
        n = np.array([d[1], -d[0]])
        if n @ (a - centre) < 0:
            n = -n  # outward: from the black border to the white surround
        pts = []
        for t in np.linspace(0.2, 0.8, samples):
            q = (a + t * (b - a))[None] + s[:, None] * n[None]
            prof = map_coordinates(g, [q[:, 1], q[:, 0]], order=1, mode="nearest")
            lo, hi = np.percentile(prof, 10), np.percentile(prof, 90)
            if hi - lo < 20:  # no contrast here (occluded, blurred away)
                continue
            mid = (lo + hi) / 2
            k = np.nonzero((prof[:-1] < mid) & (prof[1:] >= mid))[0]
            if len(k) == 0:
                continue
            k = k[np.argmin(np.abs(s[k]))]
            f = (mid - prof[k]) / (prof[k + 1] - prof[k])
            pts.append(q[k] + f * (q[k + 1] - q[k]))
        if len(pts) < 4:
            return c
        P = np.asarray(pts)
        m = P.mean(axis=0)
        _, _, vt = np.linalg.svd(P - m)
        lines.append((m, vt[0]))
    out = np.empty((4, 2))
    for i in range(4):
        (p1, d1), (p2, d2) = lines[(i - 1) % 4], lines[i]
        A = np.column_stack([d1, -d2])
        if abs(np.linalg.det(A)) < 1e-6:
            return c
        out[i] = p1 + np.linalg.solve(A, p2 - p1)[0] * d1
    if np.max(np.linalg.norm(out - c, axis=1)) > max(1.5, 0.1 * side):  # not the same square: keep OpenCV's
        return c
    return out


def marker_object_points(size: float) -> np.ndarray:
    """(4, 3) the marker's corners in its own frame, in OpenCV's detection order."""
    h = size / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


def _diagonal_crossing(corners: np.ndarray) -> np.ndarray:
    """(2,) where the quad's diagonals cross: the image of the square's centre under any perspective."""
    p0, p1, p2, p3 = corners
    d1, d2 = p2 - p0, p3 - p1
    A = np.column_stack([d1, -d2])
    s, _ = np.linalg.solve(A, p1 - p0)
    return p0 + s * d1


def _rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(3, 3) the smallest rotation taking unit vector a onto unit vector b."""
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    s = float(np.linalg.norm(v))
    if s < 1e-12:
        return np.eye(3)
    k = v / s
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    ang = np.arctan2(s, c)
    return np.eye(3) + np.sin(ang) * Kx + (1 - np.cos(ang)) * Kx @ Kx


def _marker_plane(corners: np.ndarray, depth: np.ndarray, info: CameraInfo) -> tuple[np.ndarray, np.ndarray, int, float] | None:
    """(point (3,), unit normal (3,) towards the camera, pixel count, RMS residual m) of the plane fitted
    to the depth pixels inside the marker (shrunk away from its edges), camera frame; None if too few."""
    c = _diagonal_crossing(corners)
    inner = c + DEPTH_INNER_FRACTION * (corners - c)
    h, w = depth.shape
    x0, y0 = np.floor(inner.min(axis=0)).astype(int)
    x1, y1 = np.ceil(inner.max(axis=0)).astype(int)
    x0, y0, x1, y1 = max(x0, 0), max(y0, 0), min(x1, w - 1), min(y1, h - 1)
    if x1 <= x0 or y1 <= y0:
        return None
    mask = np.zeros((y1 - y0 + 1, x1 - x0 + 1), dtype=np.uint8)
    cv2.fillConvexPoly(mask, np.round((inner - [x0, y0]) * 16).astype(np.int32), 1, shift=4)
    d = depth[y0 : y1 + 1, x0 : x1 + 1]
    vv, uu = np.nonzero((mask > 0) & (d > 0))
    if len(uu) < MIN_DEPTH_PIXELS:
        return None
    z = d[vv, uu].astype(float) * info.depth_scale
    u, v = uu + x0, vv + y0
    pts = np.column_stack([(u - info.cx) / info.fx * z, (v - info.cy) / info.fy * z, z])
    keep = np.ones(len(pts), dtype=bool)
    for _ in range(3):  # plane fit, dropping outliers (flying pixels, the card's edge) by the residual's MAD
        centroid = pts[keep].mean(axis=0)
        _, _, vt = np.linalg.svd(pts[keep] - centroid, full_matrices=False)
        n = vt[2]
        r = (pts - centroid) @ n
        mad = np.median(np.abs(r[keep] - np.median(r[keep]))) + 1e-6
        new = np.abs(r) < 4.0 * 1.4826 * mad
        if new.sum() < MIN_DEPTH_PIXELS or np.array_equal(new, keep):
            break
        keep = new
    centroid = pts[keep].mean(axis=0)
    if n @ centroid > 0:  # the face looks back at the camera
        n = -n
    rms = float(np.sqrt(np.mean(((pts[keep] - centroid) @ n) ** 2)))
    return centroid, n, int(keep.sum()), rms


def estimate_marker_pose(
    marker_id: int, corners: np.ndarray, size: float, info: CameraInfo, depth: np.ndarray | None = None
) -> MarkerPose:
    """The marker's pose in the camera frame from its corners `(4, 2)` (IPPE_SQUARE), refined by the
    aligned depth `(H, W)` uint16 (in info.depth_scale units) when it covers the marker."""
    K = info.K()
    obj = marker_object_points(size)
    img = np.ascontiguousarray(corners, dtype=np.float64).reshape(4, 1, 2)
    n_sol, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, K, None, flags=cv2.SOLVEPNP_IPPE_SQUARE)
    if n_sol == 0:
        raise MarkerNotFound(f"no pose for marker {marker_id} from its corners")
    cands = [make_transform(cv2.Rodrigues(r)[0], np.ravel(t)) for r, t in zip(rvecs, tvecs, strict=False)]
    plane = _marker_plane(np.asarray(corners, dtype=float), depth, info) if depth is not None else None
    if plane is None:
        T = cands[0]  # IPPE's best by reprojection error
        n_px, rms = 0, float("nan")
    else:
        p0, n, n_px, rms = plane
        T = max(cands, key=lambda c: float(c[:3, 2] @ n))  # the solution whose face normal agrees with depth
        R = _rotation_between(T[:3, 2], n) @ T[:3, :3]
        uv = _diagonal_crossing(np.asarray(corners, dtype=float))
        ray = np.array([(uv[0] - info.cx) / info.fx, (uv[1] - info.cy) / info.fy, 1.0])
        t = ray * float(n @ p0) / float(n @ ray)
        T = make_transform(R, t)
    proj, _ = cv2.projectPoints(obj, cv2.Rodrigues(T[:3, :3])[0], T[:3, 3], K, None)
    err = float(np.sqrt(np.mean(np.sum((proj.reshape(4, 2) - np.asarray(corners)) ** 2, axis=1))))
    return MarkerPose(marker_id, np.asarray(corners, dtype=float), T, err, n_px, rms)


def locate_objects(frame: RgbdFrame, library: ObjectLibrary, use_depth: bool = True) -> list[ObjectEstimate]:
    """Every library object whose marker is in view, placed in the world through the frame's
    camera-to-world extrinsics (one estimate per id: the marker seen largest)."""
    info = frame.camera
    T_wc = info.extrinsics()
    seen: dict[int, np.ndarray] = {}
    unknown: list[int] = []
    for dictionary in library.dictionaries():
        for mid, corners in detect_markers(frame.color, dictionary):
            if mid not in library or library.get(mid).marker.dictionary != dictionary:
                unknown.append(mid)
                continue
            if mid not in seen or cv2.contourArea(corners.astype(np.float32)) > cv2.contourArea(seen[mid].astype(np.float32)):
                seen[mid] = corners
    out = []
    for mid, corners in sorted(seen.items()):
        obj = library.get(mid)
        pose = estimate_marker_pose(mid, corners, obj.marker.size, info, frame.depth if use_depth else None)
        T_wm = T_wc @ pose.T_camera_marker
        T_wb = T_wm @ invert_transform(obj.T_bottom_marker())
        out.append(ObjectEstimate(mid, obj.name, T_wm, T_wb, transform_points(T_wb, obj.vertices), obj.height, pose, sorted(set(unknown))))
    return out


def locate_object(frame: RgbdFrame, library: ObjectLibrary, use_depth: bool = True) -> ObjectEstimate:
    """The one object in view (the largest marker if several), or MarkerNotFound saying what was seen."""
    found = locate_objects(frame, library, use_depth)
    if not found:
        seen = sorted({mid for d in library.dictionaries() for mid, _ in detect_markers(frame.color, d)})
        what = f"markers {seen} are not in the library" if seen else "no ArUco marker in the image"
        raise MarkerNotFound(f"no known object in view: {what} (library ids {library.ids()}, dictionaries {library.dictionaries()})")
    return max(found, key=lambda e: cv2.contourArea(e.marker.corners.astype(np.float32)))


def detect_object(frame: RgbdFrame, library: ObjectLibrary, run_id: str | None = None) -> ObjectDetection:
    """`locate_object` as a perception/object message: the object found, or ok=False with the reason
    (no marker, an id not in the library, no pose). Never raises for what the image holds."""
    t0 = time.perf_counter()
    common = dict(seq=frame.seq, source_stamp=frame.stamp, run_id=run_id)
    try:
        est = locate_object(frame, library)
        return ObjectDetection(
            ok=True, marker_id=est.marker_id, name=est.name, vertices=est.vertices, T_world_object=est.T_world_bottom,
            T_world_marker=est.T_world_marker, height=est.height, reprojection_px=est.marker.reprojection_px,
            depth_pixels=est.marker.depth_pixels, others=est.others, detect_ms=(time.perf_counter() - t0) * 1000.0, **common,
        )
    except (MarkerNotFound, cv2.error, np.linalg.LinAlgError, ValueError) as e:  # ValueError: also a non-finite pose
        return ObjectDetection(ok=False, error=str(e).splitlines()[0] or type(e).__name__,
                               detect_ms=(time.perf_counter() - t0) * 1000.0, **common)
    except Exception as e:  # noqa: BLE001 - a detector bug is a failed detection too, never a dead host (node or `bagit run`)
        return ObjectDetection(ok=False, error=f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}",
                               detect_ms=(time.perf_counter() - t0) * 1000.0, **common)


MARKER_RATE_HZ = 1.0  # marker detection at most this often (on the frames' stamps)
MARKER_SETTLE_S = 0.5  # a new run's first detection: on its first frame this much newer than its start


class MarkerSchedule:
    """Which frames also go to the marker detector, written once for both hosts (`bagit run`'s loop and the
    perception node, lockstep or wall): a new run's first settled frame (`settle_s` after its start: the
    coordinator takes no detection of an earlier one), then at most `rate_hz`, counted on the frames' stamps
    (the camera's clock) so a busy machine skips none. Between runs (no start told) frames go at `rate_hz`.
    Pure: the host tells it the starts and asks about each frame.

        s = MarkerSchedule(); s.run_started(t_start)
        if s.due(frame.stamp): detect_object(frame, library, run_id)
    """

    def __init__(self, rate_hz: float = MARKER_RATE_HZ, settle_s: float = MARKER_SETTLE_S) -> None:
        self.period = 1.0 / rate_hz
        self.settle_s = settle_s
        self._after: float | None = None  # a new run's start + settle: nothing before it, then its first detection
        self._last = -float("inf")  # the stamp of the last frame detected on

    def run_started(self, t_start: float) -> None:
        """A run began at `t_start` (the rig's clock)."""
        self._after = t_start + self.settle_s

    def due(self, stamp: float) -> bool:
        """The frame stamped `stamp` goes to the detector (and counts as the last one that did)."""
        if self._after is not None:
            if stamp < self._after:
                return False
            self._after = None
        elif stamp - self._last < self.period:
            return False
        self._last = stamp
        return True
