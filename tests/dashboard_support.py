"""Helpers of the dashboard tests: a recording RunLink and synthetic rig messages built from a real
plan of a paper scenario. The browser side (Debian's headless Chromium opened on any dashboard
URL) is bagit.dashboard.browser, so the same checks run against an in-process Dashboard now and
against `bagit up` later."""

from __future__ import annotations

import functools
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from bus_support import wait_until  # noqa: F401  (re-exported for the dashboard tests)
from suite_support import ROOT

from bagit.common import cr5
from bagit.common.geometry import matrix_to_rpy
from bagit.common.messages import (
    ArmState,
    Command,
    ControllerStatus,
    PointCloud,
    RunControlReply,
    RunState,
    SoiState,
)
from bagit.common.rig import RigConfig

ARTIFACTS = ROOT / "artifacts"
CLOUD_RGB = (0, 200, 0)  # the synthetic cloud's colour, so a screenshot can find it
HOME_Q = np.radians([0.0, -20.0, -100.0, 30.0, 90.0, 0.0])




@dataclass
class FakeRunLink:
    """Records every call with its monotonic time; start replies as told."""

    accept: bool = True
    reason: str | None = None
    delay_s: float = 0.0
    calls: list[tuple[Any, ...]] = field(default_factory=list)
    runs: int = 0
    fail_with: Exception | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def _record(self, *call: Any) -> None:
        with self.lock:
            self.calls.append((*call, time.monotonic()))

    def start(self, scenario: str | dict[str, Any], params: dict[str, Any], controller: str | None = None) -> RunControlReply:
        self._record("start", scenario, params, controller)
        if self.delay_s:
            time.sleep(self.delay_s)
        if self.fail_with is not None:
            raise self.fail_with
        if not self.accept:
            return RunControlReply(accepted=False, reason=self.reason)
        self.runs += 1
        return RunControlReply(accepted=True, run_id=f"run-{self.runs:03d}")

    def stop(self) -> RunControlReply:
        self._record("stop")
        if self.delay_s:
            time.sleep(self.delay_s)
        return RunControlReply(accepted=True)

    def reset(self) -> RunControlReply:
        self._record("reset")
        return RunControlReply(accepted=True)

    def estop(self, reason: str) -> None:
        self._record("estop", reason)

    def release_estop(self, reason: str) -> None:
        self._record("release", reason)

    def named(self, name: str) -> list[tuple[Any, ...]]:
        with self.lock:
            return [c for c in self.calls if c[0] == name]


@functools.lru_cache(maxsize=1)
def planned_exp01() -> Any:
    """A real CBiRRT plan of the paper's Exp. 1 (seeded, ~0.3 s), cached for the session."""
    from bagit.services.planner import plan

    r = plan("exp01", seed=0)
    assert r.success and r.goal is not None
    return r


def synthetic_cloud(rim: np.ndarray, n: int = 6000, seed: int = 0) -> PointCloud:
    """Points on a bag hanging below `rim (n_x, 3)`, in CLOUD_RGB."""
    rng = np.random.default_rng(seed)
    t = rng.uniform(0.0, 1.0, n)
    k = rng.integers(0, len(rim), n)
    c = rim.mean(axis=0)
    pts = c + (rim[k] - c) * (1 - 0.5 * t[:, None]) - np.array([0.0, 0.0, 0.25]) * t[:, None]
    pts += rng.normal(scale=0.002, size=pts.shape)
    return PointCloud(points=pts.astype(np.float32), colors=np.tile(np.array(CLOUD_RGB, np.uint8), (n, 1)))


def arm_state(arm: str, q: np.ndarray = HOME_Q, qd: np.ndarray | None = None, rig: RigConfig | None = None) -> ArmState:
    rig = rig or RigConfig()
    T = rig.arms[arm].T_world_base() @ cr5.fk(q)
    pose = np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])
    return ArmState(arm=arm, q=q, qd=np.zeros(6) if qd is None else qd, tool_pose=pose, enabled=True)


def scene_messages(run_id: str = "run-001") -> dict[str, Any]:
    """One of each scene message for Exp. 1."""
    r = planned_exp01()
    g0 = r.path[0]
    return {
        "cloud": synthetic_cloud(g0),
        "soi": SoiState(rim=g0, seq=1),
        "goal": r.goal.to_message(run_id, 0.15),
        "path": r.to_message(run_id),
        "left": arm_state("left"),
        "right": arm_state("right"),
    }


def feed_scene(dash: Any, run_id: str = "run-001") -> dict[str, Any]:
    m = scene_messages(run_id)
    dash.on_cloud(m["cloud"])
    dash.on_soi(m["soi"])
    dash.on_goal(m["goal"])
    dash.on_path(m["path"])
    dash.on_arm_state(m["left"])
    dash.on_arm_state(m["right"])
    return m


def feed_run(dash: Any, run_id: str, scenario: str, stage: str, progress: float, n_status: int = 10, t0: float = 1000.0) -> None:
    """A run's state with controller ticks and commands, as the services would publish them."""
    for i in range(n_status):
        t = t0 + i / 30
        dash.on_controller_status(ControllerStatus(stamp=t, run_id=run_id, subgoal_index=min(i, 10), progress=progress,
                                                   error_to_subgoal=0.01, error_to_goal=0.05 - 0.001 * i, solve_ms=2.5))
        dash.on_command(Command(stamp=t, run_id=run_id, u=np.r_[0.001, 0, 0, 0, 0, 0.002, -0.001, 0, 0, 0, 0, 0]))
    dash.on_run_state(RunState(run_id=run_id, scenario=scenario, stage=stage, progress=progress, elapsed_s=3.0))
