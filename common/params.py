"""Method parameters, with the paper's values as defaults.

One model for every stage so a scenario's `params:` block (and the dashboard's parameter panel)
is validated in one place; unknown keys are rejected so a typo never silently falls back to a default.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError

from bagit.common.errors import BadScenario

# lambda_d when only V is known (no object height): a 4 cm lift of the rim along the object.
DEFAULT_LAMBDA_D_M = 0.04


class MethodParams(BaseModel):
    """Parameters of the BagIt method (sections V and VI of the paper)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN passes no bound check

    # Bagging ellipse (eq. 7-10): C1 inside margin, C2 concentricity (m), C3 parallelism.
    lambda_1: float = Field(0.912, gt=0.0, lt=1.0, description="C1: max F_e of any vertex (< 1)")
    lambda_2: float = Field(0.007, ge=0.0, le=0.2, description="C2: max ellipse-centre offset (m)")
    lambda_3: float = Field(0.9943, ge=0.0, le=1.0, description="C3: min |d_e . d_v|")
    # Regularisation (eq. 13-15): C4 perimeter ratio, C5 concentricity (m).
    lambda_4: float = Field(0.002, ge=0.0, le=0.5, description="C4: max |R_x/R_y - 1|")
    lambda_5: float = Field(0.021, ge=0.0, le=0.5, description="C5: max ellipse-centre offset (m)")
    # Goal SOI (eq. 11): lift of g_dagger along the object; None = half the object height.
    lambda_d: float | None = Field(None, gt=0.0, le=1.0, description="g* = g_dagger + lambda_d a_z (m)")
    # Not in the paper: g† a little below the bottom plane, so the rim encircles the object's bottom
    # before it rises past it (a rim brought in level with the bottom can slide under a corner the
    # camera cannot see); g* stays lambda_d above the bottom plane.
    dagger_depth_m: float = Field(0.02, ge=0.0, le=0.1, description="g† this far below the object's bottom (m)")
    # Not in the paper either: the cloth lags the grippers, most of all its leading edge, which is on
    # the far side of the object from the camera (perception bridges it); the grippers keep still
    # at g† for a moment so it catches up before the lift, instead of being pinned under the bottom.
    dagger_settle_s: float = Field(1.0, ge=0.0, le=10.0, description="grippers still at g† this long before the lift (s)")
    # Which of the ellipses that minimise |L - R|² under C1 is the bagging ellipse (the paper's objective
    # has a whole family of minimisers, L = R exactly). 'bag' (not in the paper's text, which only asks
    # the opening to stay close to Q0's): the one closest in shape to the bag's own opening g0 that keeps
    # dagger_margin_share of the margin round V the 'tight' one has; the bag's orientation replaces C3.
    # 'tight': the smallest C1-C3 ellipse scaled up to R (the largest margin, C3 kept).
    dagger_shape: Literal["bag", "tight"] = Field("bag", description="bagging ellipse: nearest the bag's opening, or the tight one scaled up")
    dagger_margin_share: float = Field(0.8, ge=0.0, le=1.0, description="'bag' keeps this share of the tight ellipse's margin round V")
    # Not in the paper either: an SOI within the RMS tolerance of g† can still leave a corner of the
    # object outside the rim, and the lift then catches it where the camera cannot see. With a value,
    # the rim must go round V (seen along the object's axis) by this much before the lift and at the
    # end, and the subgoal may be pushed outwards where it does not. None (the default, the paper's
    # rule): measured over the whole sweep, the rule did not pay (it costs time, and runs ran out of it).
    enclose_margin_m: float | None = Field(None, ge=0.0, le=0.1, description="the rim goes round V by this much before the lift and at g* (m)")
    enclose_timeout_s: float = Field(5.0, ge=0.0, le=60.0, description="lift or finish anyway after the enclosure rule held this long (s)")
    enclose_push_m: float = Field(0.0, ge=0.0, le=0.1, description="the enclosure rule moves a subgoal outwards at most this far (m)")
    # Planner.
    planner_max_iterations: int = Field(4000, ge=10, le=1_000_000)
    planner_step_m: float = Field(0.03, gt=0.0, le=0.05, description="max rim-point move per tree step (m)")
    planner_connect_eps_m: float = Field(0.03, gt=0.0, le=0.05, description="tree-connection distance (m)")
    planner_perimeter_tol: float = Field(0.05, gt=0.0, le=0.5, description="node perimeter within this of R")
    planner_clearance_m: float = Field(0.01, ge=0.0, le=0.2, description="rim clearance to object and obstacles")
    # Controller (section VI-B).
    horizon: int = Field(10, ge=1, le=100, description="MPC horizon T")
    control_rate_hz: float = Field(30.0, gt=0.0, le=500.0)
    epsilon: float = Field(0.3, gt=0.0, le=1.0, description="Broyden update rate")
    q_weight: float = Field(1.0, gt=0.0, le=1e6)
    r_weight: float = Field(0.05, ge=0.0, le=1e6)
    # Not in the paper: how far each gripper may turn about the line between the grippers (from its
    # start); None: no bound (the default: measured, the bound did not pay).
    max_pitch_deg: float | None = Field(None, ge=0.0, le=180.0, description="grippers turn at most this far about their common axis (deg)")
    # Not in the paper: the cost of changing the input from one tick to the next (move suppression);
    # 0 (the paper's cost) is the default: measured, 100 did not pay.
    du_weight: float = Field(0.0, ge=0.0, le=1e4, description="MPC cost of the input's change per tick")
    # A choice of the paper's R: the cost of the two grippers turning differently, |ω_L - ω_R|² per tick
    # (rad²). Each mount clamps a rigid stretch of the rim, so a differential turn only creases the
    # fabric between them; with it the rim moves as a body (measured: the fold that caught the
    # object's bottom during the lift is gone). 0: R is the plain diagonal.
    twist_weight: float = Field(1000.0, ge=0.0, le=1e6, description="MPC cost of the grippers turning differently (per rad²)")
    max_linear_speed_mps: float = Field(0.05, gt=0.0, le=0.25, description="C7: gripper speed (m/s)")
    max_angular_speed_rps: float = Field(0.3, gt=0.0, le=2.0, description="C7: gripper angular speed (rad/s)")
    subgoal_tol_m: float = Field(0.02, gt=0.0, le=0.2, description="advance along the path below this RMS error")
    goal_tol_m: float = Field(0.008, gt=0.0, le=0.2, description="the run is at g* below this RMS error")


def merge_params(base: MethodParams, overrides: Mapping[str, Any] | None) -> MethodParams:
    """`base`'s explicitly set parameters with `overrides` (a run's, e.g. `bagit run --params`) on top;
    BadScenario naming the first bad one."""
    try:
        return MethodParams.model_validate({**base.model_dump(exclude_unset=True), **(overrides or {})})
    except ValidationError as e:
        first = e.errors()[0]
        raise BadScenario(f"params.{'.'.join(map(str, first['loc']))}: {first['msg']}") from None
