"""Frame after frame, the rim as `n_x` ordered points: warm from the last SOI, cold when that fails.

The per-frame rule perception applies wherever it runs (the `bagit perception` node, `bagit run`'s
in-process loop): the rim cloud from the bag's colour, then the SOI by EM started from the last
one (keeping the point order, so the controller sees the same points move); a warm fit that fails
or jumps further than `max_jump_m` is redone cold, seeded near `hint` (the left gripper), which
fixes where the ordering starts. A frame numbered below the last SOI's is of a new stream (a
simulator numbers its frames per world) and is fitted cold too: the bag may be anywhere in it.

    tr = RimTracker(n_x=32, kind="red-edged")
    rim, cloud = tr.update(frame, hint=left_gripper_xyz)    # BagItError when the frame shows no rim
    soi, cloud = frame_soi(tr, frame, start_hint(left_state, age_s, max_age_s), stamp)  # the message both hosts send
"""

from __future__ import annotations

import time

import numpy as np

from bagit.common.errors import BagItError
from bagit.common.geometry import points_to_polyline_distance
from bagit.common.messages import ArmState, RgbdFrame, SoiState
from bagit.services.perception.rgbd import Segmenter, red_rim_mask, rim_cloud, rim_color_segmenter, solid_rim_segmenter
from bagit.services.perception.soi import DEFAULT_PARAMS, SoiParams, extract_soi

MAX_JUMP_M = 0.05  # a warm SOI further than this from the last one: refit cold


def segmenter_for(kind: str, color: tuple[float, float, float] | None = None,
                  rim_color: tuple[float, float, float] | None = None) -> Segmenter:
    """The rim's segmenter for a bag: its binding's colour (`rim_color`, RGB 0..1; None: red), or the
    solid bag's own colour (`color`)."""
    if kind == "red-edged":
        return red_rim_mask if rim_color is None else rim_color_segmenter(rim_color)
    return solid_rim_segmenter(color if color is not None else (0.15, 0.35, 0.75))


class RimTracker:
    """One camera's SOI over time (see the module docstring)."""

    def __init__(self, n_x: int, kind: str = "red-edged", color: tuple[float, float, float] | None = None,
                 params: SoiParams | None = None, max_jump_m: float = MAX_JUMP_M,
                 rim_color: tuple[float, float, float] | None = None):
        self.n_x = int(n_x)
        self.segmenter = segmenter_for(kind, color, rim_color)
        self.params = params if params is not None else DEFAULT_PARAMS
        self.max_jump_m = float(max_jump_m)
        self.prev: np.ndarray | None = None  # (n_x, 3), the last SOI
        self.prev_seq = -1  # its frame's number
        self.cold = 0  # cold fits so far

    def reset(self) -> None:
        """Forget the last SOI (a new run, a new world): the next frame is fitted cold."""
        self.prev, self.prev_seq = None, -1

    def update(self, frame: RgbdFrame, hint: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The SOI `(n_x, 3)` and the rim cloud `(m, 3)` it came from; BagItError (and the next frame
        cold) when the frame shows no usable rim."""
        try:
            cloud = rim_cloud(frame, self.segmenter)
        except BagItError:
            self.prev = None
            raise
        same_stream = frame.seq >= self.prev_seq
        prev = self.prev if self.prev is not None and self.prev.shape == (self.n_x, 3) and same_stream else None
        rim = None
        if prev is not None:
            try:
                rim = extract_soi(cloud, self.n_x, init=prev, params=self.params)
                if float(np.linalg.norm(rim - prev, axis=1).max()) > self.max_jump_m:
                    rim = None  # jumped: start again cold
            except BagItError:
                rim = None
        if rim is None:
            self.cold += 1
            try:
                rim = extract_soi(cloud, self.n_x, start_hint=hint, params=self.params)
            except BagItError:
                self.prev = None
                raise
        self.prev, self.prev_seq = rim, frame.seq
        return rim, cloud


def start_hint(left: ArmState | None, age_s: float, max_age_s: float) -> np.ndarray | None:
    """Where a cold fit starts, `(3,)`: the left gripper's position from its state `age_s` old; None when
    there is none, it is older than `max_age_s` or not finite."""
    if left is None or age_s > max_age_s:
        return None
    p = np.asarray(left.tool_pose[:3], dtype=float)
    return p if np.all(np.isfinite(p)) else None


def frame_soi(tracker: RimTracker, frame: RgbdFrame, hint: np.ndarray | None, stamp: float,
              inlier_m: float | None = None) -> tuple[SoiState, np.ndarray]:
    """A frame's SOI as the message both hosts hand on (`bagit run` to its coordinator, the node on
    perception/soi), with the rim cloud `(m, 3)` it came from: source_stamp is the frame's, `stamp` when it
    was made (the host's clock); with `inlier_m`, the share of cloud points that close to the SOI (a
    display figure, skipped when None). BagItError when the frame shows no usable rim."""
    t0 = time.perf_counter()
    rim, cloud = tracker.update(frame, hint=hint)
    inl = 1.0
    if inlier_m is not None:
        inl = float(np.mean(points_to_polyline_distance(cloud, rim) <= inlier_m)) if len(cloud) else 0.0
    ms = (time.perf_counter() - t0) * 1000.0
    return SoiState(seq=frame.seq, stamp=stamp, source_stamp=frame.stamp, rim=rim, n_points=len(cloud), inlier_fraction=inl,
                    solve_ms=ms), cloud
