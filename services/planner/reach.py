"""Can both CR5s hold the bag's rim where the goal puts it? Checked on the goal, before anything moves.

Without this check an object 3 m from the rig got a goal and a path, and the run servoed for
minutes towards it (the arm driver clipping every command to the workspace), ending far away.

The approximation (a pure function of the goal and the rig, no search): the mounts clamp the rim's
two ends along the mounts' axis (world y laid into the rim's plane, `bagit.common.mounts`). For g†
and g*, each mount is taken at the rim point furthest along its side, turned as the mounts are at the
start (tool axis along the mounts' axis into the bag, `mount_rotation` in the rim's own frame). The
real mount centre is the middle of the stretch it clamps, a few centimetres inside that end, and the
controller may turn the mounts a little on the way; so this refuses a goal that is out of reach by
far (a wrong position, an object beside the rig instead of between the arms), and leaves the last
centimetres to the arm driver's own reach rules while it servoes. A mount pose is within reach when
its centre and its tool flange lie in the arm's workspace box (`ArmConfig.workspace_min/max`, world
frame, as the arm driver's safety gate checks them) and the CR5's inverse kinematics reaches the
flange within the joint limits, the elbow at least `ELBOW_MARGIN_RAD` from straight.
"""

from __future__ import annotations

import numpy as np

from bagit.common import cr5
from bagit.common.dual_arm import Poses
from bagit.common.geometry import invert_transform, make_transform, pca
from bagit.common.mounts import mount_rotation, rim_frame
from bagit.common.rig import ARMS, ArmConfig, RigConfig


def rim_mount_poses(rim: np.ndarray) -> Poses:
    """Where the mounts hold `rim (n, 3)` (world): each at the rim's end on its side of the mounts'
    axis, turned as `mount_rotation` turns it in the rim's frame (see the module doc)."""
    rim = np.asarray(rim, dtype=float)
    centre, _, axes = pca(rim)
    frame = rim_frame(centre, axes[2])
    along = (rim - centre) @ frame[:3, 1]  # e_y: from the left mount's side to the right's
    ends = {"left": rim[int(np.argmin(along))], "right": rim[int(np.argmax(along))]}
    return {a: make_transform(mount_rotation(frame, a), ends[a]) for a in ARMS}


def _box(arm: ArmConfig) -> str:
    lo, hi = arm.workspace_min, arm.workspace_max
    return " x ".join(f"[{a:g}, {b:g}]" for a, b in zip(lo, hi, strict=False)) + " m"


def mount_reach_problem(arm_name: str, arm: ArmConfig, T_world_mount: np.ndarray) -> str | None:
    """Why `arm` cannot put its mount at `T_world_mount (4, 4)`, or None when it can."""
    T_world_flange = T_world_mount @ invert_transform(arm.T_flange_mount())
    lo, hi = np.asarray(arm.workspace_min, dtype=float), np.asarray(arm.workspace_max, dtype=float)
    for what, p in (("mount", T_world_mount[:3, 3]), ("tool flange", T_world_flange[:3, 3])):
        if np.any(p < lo) or np.any(p > hi):
            where = ", ".join(f"{v:.3f}" for v in p)
            return f"the {arm_name} {what} would be at ({where}) m, outside the {arm_name} arm's workspace box {_box(arm)}"
    q = cr5.ik(invert_transform(arm.T_world_base()) @ T_world_flange, np.zeros(6))
    if q is None or abs(q[2]) < cr5.ELBOW_MARGIN_RAD:
        where = ", ".join(f"{v:.3f}" for v in T_world_mount[:3, 3])
        return f"the {arm_name} CR5 cannot reach its mount's pose at ({where}) m (no joint solution within its limits)"
    return None


def reach_problem(rims: dict[str, np.ndarray], rig: RigConfig | None = None) -> str | None:
    """Why both arms cannot hold each of `rims` (name -> (n, 3) world, e.g. {'g†': ..., 'g*': ...}), or None."""
    rig = rig or RigConfig()
    for name, rim in rims.items():
        poses = rim_mount_poses(rim)
        for a in ARMS:
            why = mount_reach_problem(a, rig.arms[a], poses[a])
            if why is not None:
                return f"{name} is out of the arms' reach: {why}"
    return None
