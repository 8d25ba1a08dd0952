"""The 3-D scene: cloud, SOI, goal, planned path, object, obstacles, arms, grippers, camera, grid.

Every layer lives under its own top-level frame (`/cloud`, `/soi`, ...) so a checkbox can hide it
by that frame's visibility. Nodes are created once and then updated in place (same array sizes:
property updates; new sizes: the node is replaced under the same name), so a long run does not
accumulate nodes in the server or the browser. Call the draw methods from one thread only (the
dashboard's render thread): they do the geometry and the viser calls.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
import viser

from bagit.common.errors import SafetyViolation
from bagit.common.geometry import ellipse_points_2d, transform_points
from bagit.common.messages import ArmState, CameraInfo, Command, Goal, Path, PointCloud, SoiState
from bagit.common.rig import ARMS, RigConfig
from bagit.common.scenario import DEFAULT_OBJECT_HEIGHT_M, Scenario
from bagit.dashboard import style
from bagit.dashboard.arms import command_speeds, commanded_matrix, link_lengths, link_segments, segment_pose, tool_matrix, wxyz
from bagit.dashboard.meshes import obstacle_mesh, outline_prism, shape_meshes

LAYERS: tuple[str, ...] = ("cloud", "soi", "goal", "path", "object", "obstacles", "arms", "grippers", "camera", "grid")
LAYER_LABELS = {
    "cloud": "point cloud",
    "soi": "SOI (live rim)",
    "goal": "ellipse, g†, g*",
    "path": "planned path",
    "object": "object and V",
    "obstacles": "obstacles",
    "arms": "arms",
    "grippers": "gripper frames",
    "camera": "camera frustum",
    "grid": "ground grid",
}
MAX_FAN_RIMS = 60  # rims drawn from a long path (g0, g†, g* always among them)
FAN_FADE = 0.45
LINK_RADII = (0.055, 0.045, 0.04, 0.035, 0.035, 0.03)
JOINT_RADIUS = 0.045
DEFAULT_VIEW = {"position": (1.25, -1.1, 1.15), "look_at": (0.1, 0.0, 0.4), "up": (0.0, 0.0, 1.0)}


def closed_segments(points: np.ndarray) -> np.ndarray:
    """`(n, 2, 3)` segments joining `points (n, 3)` in order and back to the first."""
    p = np.asarray(points, dtype=float)
    return np.stack([p, np.roll(p, -1, axis=0)], axis=1)


def _seg_colors(colors: np.ndarray | tuple[int, int, int], n: int) -> np.ndarray:
    c = np.asarray(colors, dtype=np.uint8)
    if c.ndim == 1:
        c = np.broadcast_to(c, (n, 3))
    return np.ascontiguousarray(np.repeat(c[:, None, :], 2, axis=1))


def fan_indices(n_nodes: int, dagger_index: int, max_rims: int = MAX_FAN_RIMS) -> np.ndarray:
    """Which rims of a path to draw: all of a short path, else an even subset that keeps g0, g† and g*."""
    if n_nodes <= max_rims:
        return np.arange(n_nodes)
    idx = np.round(np.linspace(0, n_nodes - 1, max_rims)).astype(int)
    return np.unique(np.concatenate([idx, [0, int(np.clip(dagger_index, 0, n_nodes - 1)), n_nodes - 1]]))


class SceneView:
    """Owns the scene nodes of one ViserServer."""

    def __init__(self, server: viser.ViserServer, rig: RigConfig | None = None, max_cloud_points: int = 20000) -> None:
        self.server = server
        self.rig = rig or RigConfig()
        self.max_cloud_points = max_cloud_points
        self.summary: dict[str, dict[str, Any]] = {}
        self._nodes: dict[str, Any] = {}
        self._object_nodes: list[Any] = []
        self._path_nodes: np.ndarray | None = None
        self._path_run: str | None = None
        self._subgoal: int | None = None
        self._measured: dict[str, np.ndarray] = {}
        self._has_scenario_object = False
        scene = server.scene
        scene.set_up_direction("+z")
        self.layers = {name: scene.add_frame(f"/{name}", show_axes=False) for name in LAYERS}
        table = self.rig.table_height
        self._nodes["/grid/plane"] = scene.add_grid(
            "/grid/plane", width=2.0, height=2.0, plane="xy", cell_size=0.1, section_size=0.5, position=(0.0, 0.0, table)
        )
        self._world_axes = scene.add_frame("/grid/world", axes_length=0.15, axes_radius=0.005)
        self.draw_camera(self.rig.camera.info())
        self._make_arms()

    # --- helpers -------------------------------------------------------------------------------

    def node(self, name: str) -> Any:
        """The viser handle drawn under `name` (e.g. "/cloud/points"), or None."""
        return self._nodes.get(name)

    def _refresh(self, name: str, points: np.ndarray, colors: np.ndarray) -> bool:
        """Update an existing node's points and colours in place (no re-creation); False if it must be added."""
        h = self._nodes.get(name)
        if h is None or len(h.points) != len(points):
            return False
        with self.server.atomic():
            h.points = points
            h.colors = colors
            h.visible = True
        return True

    def _points(self, name: str, points: np.ndarray, colors: np.ndarray, size: float, precision: Literal["float16", "float32"] = "float32") -> None:
        """Clouds go as float16 (half the bytes; 0.5 mm steps at 1 m), rims and outlines as float32."""
        pts = np.ascontiguousarray(points, dtype=np.float32)
        cols = np.ascontiguousarray(colors, dtype=np.uint8)
        if not self._refresh(name, pts, cols):
            self._nodes[name] = self.server.scene.add_point_cloud(
                name, pts, cols, point_size=size, point_shape="circle", precision=precision
            )

    def _segments(self, name: str, segments: np.ndarray, colors: np.ndarray, px: float) -> None:
        segs = np.ascontiguousarray(segments, dtype=np.float32)
        cols = np.ascontiguousarray(colors, dtype=np.uint8)
        if not self._refresh(name, segs, cols):
            self._nodes[name] = self.server.scene.add_line_segments(name, segs, cols, thickness=px, thickness_units="screen")

    def _hide(self, *names: str) -> None:
        for n in names:
            h = self._nodes.get(n)
            if h is not None:
                h.visible = False

    def _label(self, name: str, text: str, at: np.ndarray) -> None:
        h = self._nodes.get(name)
        x, y, z = (float(v) for v in at)
        if h is None:
            self._nodes[name] = self.server.scene.add_label(name, text, position=(x, y, z))
        else:
            h.position = (x, y, z)
            h.visible = True

    def set_layer_visible(self, layer: str, visible: bool) -> None:
        self.layers[layer].visible = bool(visible)

    def reset_view(self) -> None:
        """Point every connected browser (and any that connects later) at the workspace."""
        ic = self.server.initial_camera
        ic.position, ic.look_at, ic.up = DEFAULT_VIEW["position"], DEFAULT_VIEW["look_at"], DEFAULT_VIEW["up"]
        for client in self.server.get_clients().values():
            with client.atomic():
                client.camera.position = DEFAULT_VIEW["position"]
                client.camera.look_at = DEFAULT_VIEW["look_at"]
                client.camera.up_direction = DEFAULT_VIEW["up"]

    # --- perception ----------------------------------------------------------------------------

    def draw_cloud(self, msg: PointCloud) -> None:
        """The cloud, down-sampled by an even stride (stable between frames, no flicker), non-finite points dropped."""
        pts = np.asarray(msg.points, dtype=np.float32).reshape(-1, 3) if msg.points.size % 3 == 0 else np.zeros((0, 3), np.float32)
        cols = msg.colors
        ok = np.all(np.isfinite(pts), axis=1)
        if cols is not None and (cols.ndim != 2 or cols.shape != (len(pts), 3)):
            cols = None
        pts = pts[ok]
        cols = None if cols is None else cols[ok]
        n_in = len(pts)
        if n_in > self.max_cloud_points:
            idx = np.linspace(0, n_in - 1, self.max_cloud_points).astype(np.int64)
            pts = pts[idx]
            cols = None if cols is None else cols[idx]
        if len(pts) == 0:
            self._hide("/cloud/points")
        else:
            self._points("/cloud/points", pts, cols if cols is not None else style.height_colors(pts[:, 2]), 0.004, "float16")
        self.summary["cloud"] = {"n_received": int(msg.points.size // 3), "n_drawn": len(pts), "dropped_nonfinite": int((~ok).sum()), "seq": msg.seq}

    def draw_soi(self, msg: SoiState) -> None:
        rim = np.asarray(msg.rim, dtype=float)
        n = len(rim)
        self._points("/soi/points", rim, np.tile(np.array(style.SOI, np.uint8), (n, 1)), 0.012)
        self._segments("/soi/curve", closed_segments(rim), _seg_colors(style.SOI, n), 4.0)
        self.summary["soi"] = {"n_x": n, "seq": msg.seq, "centroid": rim.mean(axis=0).tolist()}

    # --- planner -------------------------------------------------------------------------------

    def draw_goal(self, msg: Goal) -> None:
        """Bagging ellipse (in F_m), g†, g* and the object's bottom outline V."""
        e = msg.ellipse
        theta = np.linspace(0.0, 2 * np.pi, 96, endpoint=False)
        xy = ellipse_points_2d(np.asarray(e.center, dtype=float), e.a, e.b, e.alpha, theta)
        ellipse = transform_points(np.asarray(msg.frame, dtype=float), np.column_stack([xy, np.zeros(len(xy))]))
        self._segments("/goal/ellipse", closed_segments(ellipse), _seg_colors(style.ELLIPSE, len(ellipse)), 3.0)
        for name, rim, color, text in (
            ("g_dagger", msg.g_dagger, style.BLUE, "g†"),
            ("g_star", msg.g_star, style.RED, "g*"),
        ):
            rim = np.asarray(rim, dtype=float)
            c = color.astype(np.uint8)
            self._segments(f"/goal/{name}", closed_segments(rim), _seg_colors(c, len(rim)), 3.0)
            self._points(f"/goal/{name}_points", rim, np.tile(c, (len(rim), 1)), 0.008)
            self._label(f"/goal/{name}_label", text, rim[np.argmax(rim[:, 0])] + np.array([0.02, 0.0, 0.0]))
        V = np.asarray(msg.vertices, dtype=float)
        if V.ndim == 2 and V.shape[1] == 3 and len(V) >= 3:
            self._draw_outline(V)
            if not self._has_scenario_object:
                height = msg.object_height if msg.object_height > 0 else DEFAULT_OBJECT_HEIGHT_M
                verts, faces = outline_prism(V, np.asarray(msg.frame)[:3, 2], height)
                self._clear_object()
                self._object_nodes.append(
                    self.server.scene.add_mesh_simple("/object/prism", verts, faces, color=style.OBJECT, opacity=0.6, flat_shading=True)
                )
        self.summary["goal"] = {"run_id": msg.run_id, "perimeter": msg.perimeter, "n_x": len(msg.g_star), "n_v": len(V)}

    def _draw_outline(self, V: np.ndarray) -> None:
        self._points("/object/V", V, np.tile(np.array(style.VERTICES, np.uint8), (len(V), 1)), 0.012)
        self._segments("/object/V_outline", closed_segments(V), _seg_colors(style.VERTICES, len(V)), 2.0)

    def draw_path(self, msg: Path) -> None:
        """The fan of rims g0 ... g† ... g*, faded, orange -> blue -> red (Fig. 7(c))."""
        nodes = np.asarray(msg.nodes, dtype=float)
        if not msg.success or nodes.ndim != 3 or nodes.shape[0] == 0 or nodes.shape[2] != 3 or not np.all(np.isfinite(nodes)):
            self._path_nodes = None
            self._hide("/path/fan", "/path/subgoal")
            self.summary["path"] = {"n_nodes": 0, "success": msg.success, "run_id": msg.run_id}
            return
        n_nodes, n_x = nodes.shape[:2]
        idx = fan_indices(n_nodes, msg.dagger_index)
        colors = style.fade(style.fan_colors(n_nodes, msg.dagger_index)[idx], FAN_FADE)
        segs = np.concatenate([closed_segments(nodes[i]) for i in idx])
        seg_cols = np.concatenate([_seg_colors(c, n_x) for c in colors])
        self._segments("/path/fan", segs, seg_cols, 1.5)
        self._path_nodes = nodes
        self._path_run = msg.run_id
        self.summary["path"] = {
            "n_nodes": n_nodes, "n_drawn": len(idx), "dagger_index": msg.dagger_index, "success": True, "run_id": msg.run_id,
        }
        if self._subgoal is not None:
            self.set_subgoal(self._subgoal)

    def set_subgoal(self, index: int) -> None:
        """Highlight the path node the controller is servoing toward."""
        self._subgoal = int(index)
        if self._path_nodes is None:
            return
        i = int(np.clip(index, 0, len(self._path_nodes) - 1))
        rim = self._path_nodes[i]
        self._segments("/path/subgoal", closed_segments(rim), _seg_colors(style.SUBGOAL, len(rim)), 4.0)
        self.summary["subgoal"] = {"index": i}

    # --- object and obstacles --------------------------------------------------------------------

    def _clear_object(self) -> None:
        for h in self._object_nodes:
            h.remove()
        self._object_nodes = []

    def draw_scenario(self, scenario: Scenario) -> None:
        """The object's meshes (or V extruded when it has no shape), its outline V, and the obstacles."""
        self._clear_object()
        scene = self.server.scene
        V = scenario.object.bottom_vertices()
        if scenario.object.shape is not None:
            for i, (verts, faces) in enumerate(shape_meshes(scenario.object.shape)):
                self._object_nodes.append(
                    scene.add_mesh_simple(f"/object/part{i}", verts, faces, color=style.OBJECT, opacity=0.85, flat_shading=True)
                )
            self._has_scenario_object = True
        else:
            verts, faces = outline_prism(V, np.array([0.0, 0.0, 1.0]), scenario.object.effective_height())
            self._object_nodes.append(scene.add_mesh_simple("/object/prism", verts, faces, color=style.OBJECT, opacity=0.6, flat_shading=True))
            self._has_scenario_object = False
        self._draw_outline(V)
        for i, ob in enumerate(scenario.obstacles):
            verts, faces = obstacle_mesh(ob)
            self._object_nodes.append(scene.add_mesh_simple(f"/obstacles/box{i}", verts, faces, color=style.OBSTACLE, flat_shading=True))
        self.summary["scenario"] = {"name": scenario.name, "n_obstacles": len(scenario.obstacles), "n_v": len(V)}

    # --- arms ----------------------------------------------------------------------------------

    def _make_arms(self) -> None:
        scene = self.server.scene
        lengths = link_lengths()
        for arm in ARMS:
            for i in range(6):
                self._nodes[f"/arms/{arm}/link{i}"] = scene.add_cylinder(
                    f"/arms/{arm}/link{i}", radius=LINK_RADII[i], height=float(lengths[i]), color=style.ARM_LINK, visible=False
                )
            for j in range(7):
                r = JOINT_RADIUS * (1.4 if j == 0 else 1.0)
                self._nodes[f"/arms/{arm}/joint{j}"] = scene.add_icosphere(
                    f"/arms/{arm}/joint{j}", radius=r, color=style.ARM_JOINT, subdivisions=2, visible=False
                )
            self._nodes[f"/grippers/{arm}/measured"] = scene.add_frame(
                f"/grippers/{arm}/measured", axes_length=0.09, axes_radius=0.006, visible=False
            )
            self._nodes[f"/grippers/{arm}/commanded"] = scene.add_frame(
                f"/grippers/{arm}/commanded", axes_length=0.06, axes_radius=0.003, origin_color=style.SUBGOAL, visible=False
            )

    def draw_arm(self, msg: ArmState) -> None:
        """One arm from its measured joint angles; its measured gripper pose as a frame."""
        arm = msg.arm
        cfg = self.rig.arms.get(arm)
        if cfg is None:
            return
        segs = link_segments(cfg.T_world_base(), msg.q)  # SafetyViolation on non-finite q: caller counts it
        joints = np.vstack([segs[:, 0], segs[-1:, 1]])
        color = (220, 60, 60) if msg.error else style.ARM_LINK
        with self.server.atomic():
            for i in range(6):
                pos, q = segment_pose(segs[i, 0], segs[i, 1])
                h = self._nodes[f"/arms/{arm}/link{i}"]
                h.position, h.wxyz, h.visible = pos, q, True
                if tuple(h.color) != tuple(color):
                    h.color = color
            for j in range(7):
                h = self._nodes[f"/arms/{arm}/joint{j}"]
                h.position, h.visible = joints[j], True
            try:
                T = tool_matrix(msg.tool_pose)
            except SafetyViolation:
                T = None
            if T is not None:
                self._measured[arm] = T
                h = self._nodes[f"/grippers/{arm}/measured"]
                h.position, h.wxyz, h.visible = T[:3, 3], wxyz(T[:3, :3]), True
        speed = float(np.max(np.abs(msg.qd))) if np.all(np.isfinite(msg.qd)) else float("nan")
        self.summary[f"arm:{arm}"] = {"q": np.asarray(msg.q).tolist(), "flange": segs[-1, 1].tolist(), "max_qd": speed, "error": msg.error}

    def draw_command(self, msg: Command) -> None:
        """The commanded gripper poses: each measured pose moved by this tick's increment."""
        u = np.asarray(msg.u, dtype=float).reshape(2, 6)
        drawn = []
        for k, arm in enumerate(ARMS):
            T = self._measured.get(arm)
            if T is None:
                continue
            C = commanded_matrix(T, u[k])
            h = self._nodes[f"/grippers/{arm}/commanded"]
            h.position, h.wxyz, h.visible = C[:3, 3], wxyz(C[:3, :3]), True
            drawn.append(arm)
        ll, rl, _, _ = command_speeds(msg.u, msg.dt)
        self.summary["command"] = {"seq": msg.seq, "arms": drawn, "linear_mps": (ll, rl), "mode": msg.mode}

    # --- camera --------------------------------------------------------------------------------

    def draw_camera(self, info: CameraInfo) -> None:
        """The camera's frustum at its extrinsics (OpenCV axes, as viser's frustums)."""
        T = info.extrinsics()
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return
        fov = 2 * np.arctan2(info.height / 2, info.fy)
        self._nodes["/camera/frustum"] = self.server.scene.add_camera_frustum(
            "/camera/frustum", fov=float(fov), aspect=info.width / info.height, scale=0.12, thickness=2.0,
            thickness_units="screen", color=style.CAMERA, wxyz=wxyz(T[:3, :3]), position=T[:3, 3],
        )
        self.summary["camera"] = {"position": T[:3, 3].tolist(), "fov": float(fov)}
