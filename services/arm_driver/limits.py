"""The safety envelope every outgoing arm command must lie in, and the one gate that enforces it.

Poses here are the bag mounts' (the tool centre points the controller commands) as 4x4 world <-
mount transforms, one per arm, in a dict keyed 'left' / 'right'. The envelope, from the rig config:

- finite: a NaN or inf anywhere rejects the whole command (both arms hold; nothing is guessed);
- workspace: each arm's mount centre and tool flange stay inside that arm's box (world frame,
  `ArmConfig.workspace_min/max`); a pose outside is translated back in;
- separation: the two mount centres stay between `min_flange_distance_m` (the tools must not
  meet) and `max_separation_m` (the bag cannot stretch further than its rim: half its perimeter less a
  margin, `bagit.common.rig.rim_separation_limit_m`, under the rig's own ceiling if any). Both limits are
  measured between the mounts, which hold the rim: with the default rig the flanges sit 6 cm further
  out each, 0.33 m apart at the start, so measuring at the flanges would refuse the rig's own start;
- speed: from one command to the next (`dt` apart) a mount moves at most `max_tcp_speed_mps * dt`
  (250 mm/s by default, the usual collaborative reduced speed) and turns at most
  `max_angular_speed_rps * dt`; a longer step is shortened along its direction.

`check_and_clip(target, previous, dt, env)` is the only way out of the driver: it returns the
clipped command and the violations it found. If clipping cannot give a command inside the whole
envelope it falls back to `previous` (hold), and to None (send nothing) if even that is outside;
the final check uses the same predicate as `violations`, so what leaves is inside by construction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common.rig import ARMS, RigConfig, SafetyLimits
from bagit.common.so3 import so3_exp, so3_log
from bagit.services.arm_driver.frames import Poses, arrays_to_poses, poses_to_arrays

# Slack on the final check: clipping lands exactly on a limit and floating point may miss by ulps.
TOL_M = 1e-9
TOL_RAD = 1e-9
# A measured pose may sit this far past a limit its commands kept: targets clipped onto a limit are
# reached with the servo's following error, and the feedback rounds to 1 um. Within it, the arms are
# where they were sent, and the next target is clipped inside again; beyond it, they are not.
MEASURED_TOL_M = 0.002
_MAX_PASSES = 8  # alternating box / separation projections before giving up


@dataclass(frozen=True)
class Violation:
    """One limit a command broke: which arm ('left', 'right' or 'both'), which limit, and by how much."""

    arm: str
    kind: str  # non_finite | workspace | min_distance | max_distance | speed | angular_speed | lead | unsafe_hold
    detail: str

    def __str__(self) -> str:
        return f"{self.arm}: {self.kind}: {self.detail}"


@dataclass(frozen=True)
class Envelope:
    """The limits of both arms, in the form the checks use.

    `box_min/box_max (2, 3)` per arm (rows in ARMS order, world frame); `mount_to_flange (2, 3)` the
    flange centre in each mount's frame.
    """

    box_min: np.ndarray
    box_max: np.ndarray
    mount_to_flange: np.ndarray
    limits: SafetyLimits

    @classmethod
    def from_rig(cls, rig: RigConfig) -> Envelope:
        lo = np.array([rig.arms[a].workspace_min for a in ARMS], dtype=float)
        hi = np.array([rig.arms[a].workspace_max for a in ARMS], dtype=float)
        if np.any(lo >= hi):
            raise ValueError("every workspace box needs min < max on each axis")
        off = np.array([-np.asarray(rig.arms[a].mount_offset, dtype=float) for a in ARMS])
        return cls(lo, hi, off, rig.safety)

    def max_step_m(self, dt: float) -> float:
        return self.limits.max_tcp_speed_mps * dt

    def max_turn_rad(self, dt: float) -> float:
        return self.limits.max_angular_speed_rps * dt


def _is_pose(T: object) -> bool:
    """A finite 4x4 rigid transform (rotation orthonormal with det +1, last row 0 0 0 1)."""
    if not isinstance(T, np.ndarray) or T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.abs(R @ R.T - np.eye(3)).max() < 1e-6 and np.linalg.det(R) > 0 and np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0])
    )


def _tool_points(p: np.ndarray, R: np.ndarray, env: Envelope) -> np.ndarray:
    """`(2, 2, 3)`: per arm, its mount centre and its flange centre (world)."""
    flange = p + np.einsum("aij,aj->ai", R, env.mount_to_flange)
    return np.stack([p, flange], axis=1)


def static_violations(p: np.ndarray, R: np.ndarray, env: Envelope, tol: float = TOL_M) -> list[Violation]:
    """Workspace and separation limits broken by mount positions `p (2, 3)` with rotations `R (2, 3, 3)`."""
    out = []
    pts = _tool_points(p, R, env)
    for i, a in enumerate(ARMS):
        below = env.box_min[i] - pts[i].min(axis=0)
        above = pts[i].max(axis=0) - env.box_max[i]
        worst = float(max(below.max(), above.max()))
        if worst > tol:
            out.append(Violation(a, "workspace", f"tool {worst * 1000:.1f} mm outside its box"))
    d = float(np.linalg.norm(p[1] - p[0]))
    lim = env.limits
    if d < lim.min_flange_distance_m - tol:
        out.append(Violation("both", "min_distance", f"mounts {d * 1000:.1f} mm apart < {lim.min_flange_distance_m * 1000:.0f} mm"))
    if d > lim.max_separation_m + tol:
        out.append(Violation("both", "max_distance", f"mounts {d * 1000:.1f} mm apart > {lim.max_separation_m * 1000:.0f} mm"))
    return out


def _turn_angles(R_from: np.ndarray, R_to: np.ndarray) -> np.ndarray:
    """`(2,)` rotation angle from each `R_from[i]` to `R_to[i]` (radians)."""
    rel = np.einsum("aij,akj->aik", R_to, R_from)  # R_to @ R_from^T
    c = (np.trace(rel, axis1=1, axis2=2) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))


def speed_violations(p: np.ndarray, R: np.ndarray, p_prev: np.ndarray, R_prev: np.ndarray, dt: float, env: Envelope) -> list[Violation]:
    """Cartesian speed limits broken going from the previous command to this one, `dt` seconds later."""
    out = []
    step = np.linalg.norm(p - p_prev, axis=1)
    turn = _turn_angles(R_prev, R)
    for i, a in enumerate(ARMS):
        if step[i] > env.max_step_m(dt) + TOL_M:
            out.append(Violation(a, "speed", f"{step[i] / dt:.3f} m/s > {env.limits.max_tcp_speed_mps:.3f} m/s"))
        if turn[i] > env.max_turn_rad(dt) + TOL_RAD:
            out.append(Violation(a, "angular_speed", f"{turn[i] / dt:.3f} rad/s > {env.limits.max_angular_speed_rps:.3f} rad/s"))
    return out


def violations(target: Poses, previous: Poses | None, dt: float, env: Envelope, tol: float = TOL_M) -> list[Violation]:
    """Every limit `target` breaks (speed only when `previous` is given); empty means it may be sent.
    `tol`: slack on the static limits (MEASURED_TOL_M for the arms' measured poses)."""
    if any(not _is_pose(target.get(a)) for a in ARMS):
        return [Violation("both", "non_finite", "a pose is missing, non-finite or not a rigid transform")]
    p, R = poses_to_arrays(target)
    out = static_violations(p, R, env, tol)
    if previous is not None:
        pp, Rp = poses_to_arrays(previous)
        out += speed_violations(p, R, pp, Rp, dt, env)
    return out


def clip_static(p: np.ndarray, R: np.ndarray, env: Envelope, previous_p: np.ndarray | None = None) -> np.ndarray:
    """Mount positions `(2, 3)` moved (orientation kept) into the boxes and the separation band.

    Alternates the two projections a few times; the caller checks the result. `previous_p (2, 3)`
    gives the direction to push apart two mounts that coincide.
    """
    p = np.array(p, dtype=float)
    lim = env.limits
    for _ in range(_MAX_PASSES):
        # workspace: shift each arm's tool (mount and flange together) into its box
        pts = _tool_points(p, R, env)
        for i in range(2):
            lo_shift = env.box_min[i] - pts[i].min(axis=0)
            hi_shift = env.box_max[i] - pts[i].max(axis=0)
            shift = np.where(lo_shift <= hi_shift, np.clip(0.0, lo_shift, hi_shift), (lo_shift + hi_shift) / 2)
            p[i] += shift
        # separation: move both mounts symmetrically along the line between them
        d = p[1] - p[0]
        n = float(np.linalg.norm(d))
        if n > lim.max_separation_m:
            u = d / n
            excess = (n - lim.max_separation_m) / 2
            p[0] += excess * u
            p[1] -= excess * u
        elif n < lim.min_flange_distance_m:
            if n > 1e-9:
                u = d / n
            elif previous_p is not None and np.linalg.norm(previous_p[1] - previous_p[0]) > 1e-9:
                u = (previous_p[1] - previous_p[0]) / np.linalg.norm(previous_p[1] - previous_p[0])
            else:
                u = np.array([0.0, 1.0, 0.0])  # the rig's arms face each other along world y
            deficit = (lim.min_flange_distance_m - n) / 2
            p[0] -= deficit * u
            p[1] += deficit * u
        if not static_violations(p, R, env):
            break
    return p


def clip_speed(p: np.ndarray, R: np.ndarray, p_prev: np.ndarray, R_prev: np.ndarray, dt: float, env: Envelope) -> tuple[np.ndarray, np.ndarray]:
    """`(p, R)` with each arm's step from the previous command shortened to the speed limits."""
    p, R = np.array(p, dtype=float), np.array(R, dtype=float)
    max_step, max_turn = env.max_step_m(dt), env.max_turn_rad(dt)
    for i in range(2):
        step = p[i] - p_prev[i]
        n = float(np.linalg.norm(step))
        if n > max_step:
            p[i] = p_prev[i] + step * (max_step / n) * (1 - 1e-12)
        rv = so3_log(R[i] @ R_prev[i].T)
        ang = float(np.linalg.norm(rv))
        if ang > max_turn:
            R[i] = so3_exp(rv * (max_turn / ang) * (1 - 1e-12)) @ R_prev[i]
    return p, R


def clip_target(target: Poses, env: Envelope, previous: Poses | None = None) -> tuple[Poses, list[Violation]]:
    """A streaming target pulled into the static envelope (no speed limit: the trajectory sees to that)."""
    p, R = poses_to_arrays(target)
    found = static_violations(p, R, env)
    if not found:
        return target, []
    prev_p = poses_to_arrays(previous)[0] if previous is not None else None
    return arrays_to_poses(clip_static(p, R, env, prev_p), R), found


def check_and_clip(target: Poses, previous: Poses | None, dt: float, env: Envelope) -> tuple[Poses | None, list[Violation]]:
    """The command to send for `target`, and every violation found on the way.

    Returns `target` itself when it is inside; a clipped copy when it was outside; `previous` (hold)
    when it was non-finite or could not be clipped inside; None when not even `previous` is safe to
    send. `previous` is the last command sent (or the measured pose when a stream starts); `dt` the
    time between the two commands.
    """
    if not dt > 0 or not np.isfinite(dt):
        raise ValueError(f"dt must be a positive number of seconds, got {dt}")
    if previous is not None and any(not _is_pose(previous.get(a)) for a in ARMS):
        raise ValueError("previous must hold a rigid 4x4 pose per arm")
    found = violations(target, previous, dt, env)
    if not found:
        return target, []
    if found[0].kind == "non_finite":
        return _hold(previous, env, found)
    p, R = poses_to_arrays(target)
    if previous is None:
        p = clip_static(p, R, env, None)
    else:
        prev_p, prev_R = poses_to_arrays(previous)
        p = clip_static(p, R, env, prev_p)
        p, R = clip_speed(p, R, prev_p, prev_R, dt, env)
    out = arrays_to_poses(p, R)
    if violations(out, previous, dt, env):
        return _hold(previous, env, found)
    return out, found


def _hold(previous: Poses | None, env: Envelope, found: list[Violation]) -> tuple[Poses | None, list[Violation]]:
    if previous is not None and not violations(previous, None, 1.0, env):
        return previous, found
    return None, found + [Violation("both", "unsafe_hold", "the last command is outside the envelope too; nothing is sent")]
