"""Shared helpers of the bus tests: two connected in-process peers on loopback and one valid
example of every message kind."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest
from suite_support import wait_until  # noqa: F401 - re-exported for the bus tests

from bagit.common.messages import MESSAGE_TYPES, CameraInfo, Message
from bagit.harness import session_pair  # noqa: F401 - re-exported for the bus tests


@pytest.fixture
def pair(request) -> Iterator[tuple]:
    rig = "t" + "".join(c for c in request.node.name if c.isalnum())[-40:]
    yield from session_pair(rig)


def example_message(kind: str, rng: np.random.Generator | None = None) -> Message:
    """A valid message of `kind` with non-trivial content."""
    rng = rng or np.random.default_rng(7)
    rim = rng.normal(size=(32, 3))
    ex = {
        "rgbd": dict(
            seq=3,
            camera=CameraInfo(width=20, height=12),
            color=rng.integers(0, 255, size=(12, 20, 3), dtype=np.uint8),
            depth=rng.integers(0, 4000, size=(12, 20), dtype=np.uint16),
        ),
        "cloud": dict(points=rng.normal(size=(100, 3)).astype(np.float32), colors=rng.integers(0, 255, (100, 3), dtype=np.uint8)),
        "soi": dict(seq=9, source_stamp=12.5, rim=rim, n_points=1234, inlier_fraction=0.9, solve_ms=4.2),
        "goal": dict(
            run_id="r1", g_dagger=rim, g_star=rim + 0.1, frame=np.eye(4),
            ellipse={"center": (0.01, -0.02), "a": 0.12, "b": 0.09, "alpha": 0.3},
            perimeter=0.68, c1=0.8, c2=0.01, c3=0.9, vertices=rng.normal(size=(4, 3)), object_height=0.15,
        ),
        "path": dict(run_id="r1", nodes=np.stack([rim, rim + 0.01, rim + 0.02]), dagger_index=1, time_s=0.4, iterations=77),
        "cmd": dict(run_id="r1", seq=41, u=rng.normal(scale=1e-3, size=12), dt=1 / 30),
        "controller_status": dict(run_id="r1", seq=41, mode="servo", error_to_subgoal=0.004, error_to_goal=0.03, solve_ms=3.1, progress=0.4),
        "arm_state": dict(arm="right", robot_mode=5, q=rng.normal(size=6), qd=np.zeros(6), tool_pose=rng.normal(size=6), enabled=True),
        "run_state": dict(run_id="r1", scenario="exp01", stage="bagging", progress=0.5, elapsed_s=12.0),
        "run_control": dict(action="start", scenario="exp01", params={"n_x": 32}, seed=3),
        "run_control_reply": dict(accepted=False, reason="a run is in progress"),
        "estop": dict(engage=True, source="dashboard", reason="operator"),
        "object": dict(seq=4, source_stamp=12.4, run_id="r1", marker_id=1, name="coffee box", vertices=rng.normal(size=(4, 3)),
                       T_world_object=np.eye(4), T_world_marker=np.eye(4), height=0.15, reprojection_px=0.1, depth_pixels=300,
                       others=[7], detect_ms=18.0),
        "sim_truth": dict(run_id="r1", scenario="exp01", sim_time=3.5, realtime_factor=0.8, frames=35, rim=rim, clearance_m=0.02),
        "clock": dict(t=1073741825.5, servo_tick=3, run_id="r1"),
        "ack": dict(service="arm-driver", tick=3, servo_sent={"left": 1, "right": 1}),
        "recorder_status": dict(started=1795765055.5, messages=1200, lost=30, overflow=2, errors=3, error="disk full (ENOSPC) on x.mcap",
                                last_error="disk full (ENOSPC) on x.mcap", file=None),
    }
    if kind not in ex:
        raise KeyError(f"no bus test example for message kind {kind!r}; add one to tests/bus_support.py")
    return MESSAGE_TYPES[kind](**ex[kind])


def assert_same_message(a: Message, b: Message) -> None:
    assert type(a) is type(b)
    for name in type(a).model_fields:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape and np.array_equal(x, y), name
        else:
            assert x == y, name
