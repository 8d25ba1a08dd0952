"""The parameter form: which MethodParams fields (by flat name, `PARAM_PATHS`) the panel edits, and how
edits become overrides.

The next run is started with the scenario's own parameters plus the fields the operator changed
(RunControl.params holds only those), so a scenario's tuned values are never silently replaced by
defaults. Every edit is validated by MethodParams itself; the error names the field.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bagit.common.errors import BadScenario
from bagit.common.params import DEFAULT_LAMBDA_D_M, PARAM_PATHS, MethodParams, merge_params


@dataclass(frozen=True)
class FieldSpec:
    name: str
    label: str
    step: float
    hint: str


# λ1-λ5, λd, g†'s depth and margin share, the MPC's horizon and weights (R and its twist term), the speed
# limits (C7), the tolerances and the settle at g†.
FIELDS: tuple[FieldSpec, ...] = (
    FieldSpec("lambda_1", "λ1 C1 margin", 0.001, "max F_e of any vertex inside the ellipse (< 1)"),
    FieldSpec("lambda_2", "λ2 C2 centre (m)", 0.001, "max ellipse-centre offset from V's centroid"),
    FieldSpec("lambda_3", "λ3 C3 parallel", 0.0001, "min |d_e · d_v|"),
    FieldSpec("lambda_4", "λ4 C4 perimeter", 0.001, "max |R_x/R_y - 1| of a path node"),
    FieldSpec("lambda_5", "λ5 C5 centre (m)", 0.001, "max regularised-ellipse centre offset"),
    FieldSpec("lambda_d", "λd lift (m)", 0.005, "g* = g† + λd a_z; tick 'λd auto' for half the object height"),
    FieldSpec("dagger_depth_m", "g† depth (m)", 0.005, "g† this far below the object's bottom; g* stays λd above it"),
    FieldSpec("dagger_margin_share", "g† margin share", 0.05, "the bag-shaped g† keeps this share of the tight ellipse's margin round V"),
    FieldSpec("horizon", "MPC horizon T", 1, "steps the MPC looks ahead"),
    FieldSpec("q_weight", "MPC Q weight", 0.05, "weight of the SOI error"),
    FieldSpec("r_weight", "MPC R weight", 0.01, "weight of the command size"),
    FieldSpec("twist_weight", "MPC twist weight", 10.0, "weight of the two grippers turning differently"),
    FieldSpec("epsilon", "Broyden ε", 0.05, "Jacobian update rate"),
    FieldSpec("control_rate_hz", "control rate (Hz)", 1, "controller ticks per second"),
    FieldSpec("max_linear_speed_mps", "max speed (m/s)", 0.005, "C7: gripper linear speed limit"),
    FieldSpec("max_angular_speed_rps", "max ang. speed (rad/s)", 0.05, "C7: gripper angular speed limit"),
    FieldSpec("subgoal_tol_m", "subgoal tol (m)", 0.001, "advance along the path below this RMS error"),
    FieldSpec("goal_tol_m", "goal tol (m)", 0.001, "the run reaches g* below this RMS error"),
    FieldSpec("dagger_settle_s", "g† settle (s)", 0.1, "grippers still at g† this long before the lift"),
)
FIELD_NAMES = tuple(f.name for f in FIELDS)
LAMBDA_D_AUTO_VALUE = DEFAULT_LAMBDA_D_M  # what the λd box shows while λd is automatic


def validate_params(base: MethodParams, values: dict[str, Any]) -> MethodParams:
    """`base` with `values` (flat names) applied, validated; BadScenario naming the first bad field otherwise."""
    unknown = sorted(set(values) - set(PARAM_PATHS))
    if unknown:
        raise BadScenario(f"params: unknown parameter {unknown[0]!r}")
    return merge_params(base, values)


def overrides(base: MethodParams, values: dict[str, Any]) -> dict[str, Any]:
    """The validated fields of `values` that differ from `base`: what RunControl.params carries."""
    merged = validate_params(base, values)
    out: dict[str, Any] = {}
    for name in values:
        new, old = merged.get(name), base.get(name)
        if new != old and not (isinstance(new, float) and isinstance(old, float) and abs(new - old) <= 1e-12 * max(1.0, abs(old))):
            out[name] = new
    return out
