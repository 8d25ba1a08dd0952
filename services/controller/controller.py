"""The controllers behind one interface, selectable by name: `mpc` (the paper's), `ibvs` and `ssvs`
(its shape-servoing baselines), `autobag` and `shakingbot` (the action-primitive methods of Table I) and
`bimamanip` (Table I's MPC through a learned SOI model; JAX is loaded when its run starts).

    c = make_controller("mpc", params, n_x)
    c.reset(x0, path, gripper_poses, goal=goal)  # path: messages.Path, or nodes with dagger_index=; goal: messages.Goal
    out = c.step(x_t, now, gripper_poses)      # every tick; out.u (12,) within C7
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

import numpy as np

from bagit.common.dual_arm import Poses
from bagit.common.errors import BadControlInput
from bagit.common.params import MethodParams
from bagit.services.controller.baselines import IbvsController, SsvsController
from bagit.services.controller.bimamanip import BimaManipController
from bagit.services.controller.mpc import MpcController
from bagit.services.controller.primitives import AutoBagController, ShakingBotController
from bagit.services.controller.servo import ControlOutput

CONTROLLERS: dict[str, Callable[..., Controller]] = {
    "mpc": MpcController, "ibvs": IbvsController, "ssvs": SsvsController, "autobag": AutoBagController, "shakingbot": ShakingBotController,
    "bimamanip": BimaManipController,
}


class Controller(Protocol):
    """What a host (`ServoSession`, the benchmarks) drives; `ServoBase` and its laws satisfy it
    (`make_controller`'s return is checked against it by the type checker)."""

    name: str
    u_max: np.ndarray  # (12,) C7 per tick
    dt: float
    ticks: int

    def reset(
        self,
        x0: np.ndarray | None,
        path: Any,
        gripper_poses: Poses | None,
        dagger_index: int | None = None,
        perimeter: float | None = None,
        goal: Any = None,
    ) -> None: ...

    def step(
        self, x: np.ndarray | None, now: float, gripper_poses: Poses, source_stamp: float | None = None,
        pending: np.ndarray | None = None, slowed: bool = False,
    ) -> ControlOutput: ...


def make_controller(name: str, params: MethodParams, n_x: int, **kwargs: Any) -> Controller:
    """A fresh controller by name (CONTROLLER_NAMES); call `reset` before the first `step`."""
    if name not in CONTROLLERS:
        raise BadControlInput(f"unknown controller {name!r}; choose from {', '.join(CONTROLLERS)}")
    return CONTROLLERS[name](params, n_x, **kwargs)


def ShapeServo(  # noqa: N802
    kind: str, params: MethodParams, path: np.ndarray, dagger_index: int, perimeter: float,
) -> Controller:
    """A controller already reset on `path (n_nodes, n_x, 3)`: the one-call form of make_controller + reset."""
    nodes = np.asarray(path, dtype=float)
    if nodes.ndim != 3:
        raise BadControlInput(f"path must have shape (n_nodes, n_x, 3), got {nodes.shape}")
    c = make_controller(kind, params, nodes.shape[1])
    c.reset(None, nodes, None, dagger_index=dagger_index, perimeter=perimeter)
    return c
