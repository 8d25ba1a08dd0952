"""Method parameters, split by stage (goal, planner, controller), with the paper's values as defaults.

    MethodParams(goal=GoalParams(...), planner=PlannerParams(...), controller=ControllerParams(...))

Each stage's model holds the paper's parameters of that stage and, in its `experimental` sub-model,
what this project added that the paper does not have (kept because measured to pay; the account is
in docs/experiments.md, with the experiments that did not pay and were removed).

Overrides go on top of the defaults (a scenario's `params:` block), then on top of those (a run's,
e.g. `bagit run --params`, the dashboard's panel). A parameter has one name, its field's, whatever
its stage (`{"twist_weight": 0}`, `{"step_m": 0.02}`; `PARAM_PATHS` maps each to its place), and that
name is what overrides, records, panels and a dumped scenario use. The nested form
(`{"controller": {...}}`) and the old planner names with a `planner_` prefix are refused with the
name to write instead; unknown keys are rejected, naming the key, so a typo never silently falls
back to a default.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_serializer, model_validator

from bagit.common.errors import BadScenario

# lambda_d when only V is known (no object height): a 4 cm lift of the rim along the object.
DEFAULT_LAMBDA_D_M = 0.04

_STRICT = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # NaN passes no bound check
RigidTurns = Literal["measured", "all"]  # the pair's turns J's rigid model sets (ControllerExperimental.rigid_pair_turns)


# ---- goal: the bagging ellipse g† and the goal SOI g* (paper section V) --------------------------


class GoalExperimental(BaseModel):
    """The goal's additions to the paper (docs/experiments.md: g† depth, the bagging ellipse's shape)."""

    model_config = _STRICT

    # g† a little below the bottom plane, so the rim encircles the object's bottom before it rises
    # past it (a rim brought in level with the bottom can slide under a corner the camera cannot
    # see); g* stays lambda_d above the bottom plane. 0: the paper's g†.
    dagger_depth_m: float = Field(0.02, ge=0.0, le=0.1, description="g† this far below the object's bottom (m)")
    # Which of the ellipses that minimise |L - R|² under C1 is the bagging ellipse (the paper's objective
    # has a whole family of minimisers, L = R exactly). 'bag': the one closest in shape to the bag's
    # own opening g0 that keeps dagger_margin_share of the margin round V the 'tight' one has; the
    # bag's orientation replaces C3. 'tight': the smallest C1-C3 ellipse scaled up to R (C3 kept).
    dagger_shape: Literal["bag", "tight"] = Field("bag", description="bagging ellipse: nearest the bag's opening, or the tight one scaled up")
    dagger_margin_share: float = Field(0.8, ge=0.0, le=1.0, description="'bag' keeps this share of the tight ellipse's margin round V")


class GoalParams(BaseModel):
    """The bagging ellipse (eq. 7-10) and the goal SOI (eq. 11)."""

    model_config = _STRICT

    lambda_1: float = Field(0.912, gt=0.0, lt=1.0, description="C1: max F_e of any vertex (< 1)")
    lambda_2: float = Field(0.007, ge=0.0, le=0.2, description="C2: max ellipse-centre offset (m)")
    lambda_3: float = Field(0.9943, ge=0.0, le=1.0, description="C3: min |d_e . d_v|")
    # None: half the object height, or DEFAULT_LAMBDA_D_M when only V is known.
    lambda_d: float | None = Field(None, gt=0.0, le=1.0, description="g* = g_dagger + lambda_d a_z (m)")
    experimental: GoalExperimental = GoalExperimental()


# ---- planner: CBiRRT over SOIs (paper section VI-A) -------------------------------------------


class PlannerParams(BaseModel):
    """The SOI path search, with the regularisation of its nodes (eq. 13-15)."""

    model_config = _STRICT

    lambda_4: float = Field(0.002, ge=0.0, le=0.5, description="C4: max |R_x/R_y - 1|")
    lambda_5: float = Field(0.021, ge=0.0, le=0.5, description="C5: max ellipse-centre offset (m)")
    max_iterations: int = Field(4000, ge=10, le=1_000_000)
    step_m: float = Field(0.03, gt=0.0, le=0.05, description="max rim-point move per tree step (m)")
    connect_eps_m: float = Field(0.03, gt=0.0, le=0.05, description="tree-connection distance (m)")
    perimeter_tol: float = Field(0.05, gt=0.0, le=0.5, description="node perimeter within this of R")
    clearance_m: float = Field(0.01, ge=0.0, le=0.2, description="rim clearance to object and obstacles")


# ---- controller: MPC shape servoing with a Broyden Jacobian (paper section VI-B) -------------------


class ControllerExperimental(BaseModel):
    """The controller's additions to the paper (docs/experiments.md: twist weight, settle at g†, the lift round V)."""

    model_config = _STRICT

    # A choice of the paper's R (which it leaves open): the cost of the two grippers turning
    # differently, |ω_L - ω_R|² per tick (rad²). Each mount clamps a rigid stretch of the rim, so a
    # differential turn only creases the fabric between them. 0: R is the plain diagonal.
    twist_weight: float = Field(1000.0, ge=0.0, le=1e6, description="MPC cost of the grippers turning differently (per rad²)")
    # The cloth lags the grippers, most of all its leading edge, on the far side of the object from
    # the camera; the grippers keep still at g† for a moment so it catches up before the lift.
    dagger_settle_s: float = Field(1.0, ge=0.0, le=10.0, description="grippers still at g† this long before the lift (s)")
    # J's response to the two grippers moving as one rigid body (translating together, turning about
    # their midpoint) is the rim moving as that body, from the grippers' and the SOI's positions each
    # tick, not measured: the exploration measures those directions mostly as the bag's own motion.
    rigid_pair: bool = Field(True, description="J's rigid motions of the gripper pair from the rigid model (False: measured, the paper)")
    # Which of the pair's rigid turns the model sets. A turn about an axis across the grippers' line
    # moves them round their midpoint, and Broyden, learning what the executed turns of both grippers in
    # place did, shares most of that direction with it: pinned every tick, it undoes what Broyden learnt
    # of a hem that does not follow those turns (envelope -90 and -94: docs/experiments.md). About the
    # line itself the rigid turn is the turn in place, and the clamps carry the rim with it. "measured"
    # (the default): the line's turn always, the two across it until Broyden has seen a step's worth of
    # them (`broyden.TURN_SEEN`): the rigid model guides the start, what was measured of the hem then
    # stays; the CR5 sweep 120/120 (0.38 cm), the core zoo 100/100 (0.33), the envelope 95/100. "all": the
    # three turns every tick (the default before; 120/120 at 0.41 cm, 100/100 at 0.36, 94/100).
    rigid_pair_turns: RigidTurns = Field("measured", description="the pair's turns the rigid model pins: about the grippers' line "
                                         "always and across it until measured, or all three axes every tick")
    # g† is the paper's bagging ellipse because it goes round V (C1): the SOI within the RMS tolerance
    # of g† can still leave a corner of V outside it, and a lift from there catches the corner.
    dagger_round_v: bool = Field(True, description="the lift starts only once the SOI at the settle's end goes round V; else servo to g† again (bounded)")
    # J's rigid model of the pair has the whole rim turn with a turn of both grippers, which a hem with
    # little bending stiffness of its own barely follows: the MPC then turns them on, past 100° from where
    # they started, and the twisted rim stalls far from its subgoal or is lost (docs/experiments.md, "the
    # floppy hem's turns"). Off by default: at 45° it bags envelope -90 and -94, but bags that bag
    # unbounded turn up to 83° too and would change (not re-run yet).
    max_turn_deg: float = Field(0.0, ge=0.0, le=180.0, description="each gripper turns at most this far from its pose at the first tick (deg); 0: unbounded")


class ControllerParams(BaseModel):
    """The MPC (horizon, Q, R), the Broyden update, C7's speed limits and the path tolerances."""

    model_config = _STRICT

    horizon: int = Field(10, ge=1, le=100, description="MPC horizon T")
    control_rate_hz: float = Field(30.0, gt=0.0, le=500.0)
    epsilon: float = Field(0.3, gt=0.0, le=1.0, description="Broyden update rate")
    q_weight: float = Field(1.0, gt=0.0, le=1e6)
    r_weight: float = Field(0.05, ge=0.0, le=1e6)
    max_linear_speed_mps: float = Field(0.05, gt=0.0, le=0.25, description="C7: gripper speed (m/s)")
    max_angular_speed_rps: float = Field(0.3, gt=0.0, le=2.0, description="C7: gripper angular speed (rad/s)")
    subgoal_tol_m: float = Field(0.02, gt=0.0, le=0.2, description="advance along the path below this RMS error")
    goal_tol_m: float = Field(0.008, gt=0.0, le=0.2, description="the run is at g* below this RMS error")
    # The paper's claim is that the online update adapts J to a bag it has no model of; "frozen" keeps
    # the exploration's initial estimate for the whole run, the ablation that measures the claim.
    jacobian_update: Literal["broyden", "frozen"] = Field(
        "broyden", description="broyden: J updated online (the paper); frozen: J kept at its initial estimate (an ablation)")
    experimental: ControllerExperimental = ControllerExperimental()


STAGE_MODELS: dict[str, type[BaseModel]] = {"goal": GoalParams, "planner": PlannerParams, "controller": ControllerParams}


def _paths() -> dict[str, tuple[str, ...]]:
    """Every leaf's name -> its path in MethodParams (its stage, `experimental` for an addition, the
    field); names are unique across the stages, so a name alone says which parameter."""
    out: dict[str, tuple[str, ...]] = {}
    for stage, model in STAGE_MODELS.items():
        for name, info in model.model_fields.items():
            subs = info.annotation.model_fields if name == "experimental" else {name: None}  # type: ignore[union-attr]
            for sub in subs:
                path = (stage, "experimental", sub) if name == "experimental" else (stage, name)
                if sub in out:
                    raise AssertionError(f"parameter {sub} is in two places: {out[sub]} and {path}; give one another name")
                out[sub] = path
    return out


PARAM_PATHS: dict[str, tuple[str, ...]] = _paths()
_NAMES: dict[tuple[str, ...], str] = {path: name for name, path in PARAM_PATHS.items()}

# Experiments removed from the code (they did not pay; docs/experiments.md has their records): a
# key naming one is refused with this pointer rather than as a typo.
REMOVED_PARAMS: dict[str, str] = {
    "enclose_margin_m": "the enclosure rule",
    "enclose_timeout_s": "the enclosure rule",
    "enclose_push_m": "the enclosure rule",
    "max_pitch_deg": "the pitch bound",
    "du_weight": "move suppression",
}
# Old spellings, refused with the one to write: the planner's fields once had a `planner_` prefix.
RENAMED_PARAMS: dict[str, str] = {f"planner_{name}": name for name in PlannerParams.model_fields if not name.startswith("lambda_")}


def _leaf_names(value: Mapping[str, Any], path: tuple[str, ...]) -> list[str]:
    """The parameter names of a nested mapping's leaves under `path` (those that name one)."""
    out: list[str] = []
    for k, v in value.items():
        sub = (*path, str(k))
        out += _leaf_names(v, sub) if isinstance(v, Mapping) else [_NAMES[sub]] if sub in _NAMES else []
    return out


def _nest(data: Mapping[str, Any]) -> dict[str, Any]:
    """`data` (parameters by name) moved to their nested place; a stage's model (Python construction,
    `MethodParams(controller=ControllerParams(...))`) is taken as it is. ValueError naming a nested
    mapping, an old or removed name, or an unknown key."""
    out: dict[str, Any] = {}
    for key, value in data.items():
        if key in STAGE_MODELS and isinstance(value, BaseModel):
            _deep_set(out, (key,), value.model_dump(exclude_unset=True))
        elif key in STAGE_MODELS:
            names = _leaf_names(value, (key,)) if isinstance(value, Mapping) else []
            example = ", ".join(f'"{n}"' for n in names) or '"twist_weight"'
            raise ValueError(f"{key}: parameters are not nested under their stage; give each by its name ({example})")
        elif key in PARAM_PATHS:
            _deep_set(out, PARAM_PATHS[key], value)
        elif key in RENAMED_PARAMS:
            raise ValueError(f"{key}: renamed {RENAMED_PARAMS[key]}")
        elif key in REMOVED_PARAMS:
            raise ValueError(f"{key}: {REMOVED_PARAMS[key]} was an experiment removed from the code (docs/experiments.md)")
        else:
            raise ValueError(f"{key}: unknown parameter; known: {', '.join(sorted(PARAM_PATHS))}")
    return out


def _deep_set(out: dict[str, Any], path: tuple[str, ...], value: Any) -> None:
    """Set `value` at `path` in `out`, merging mappings into what is already there."""
    node = out
    for k in path[:-1]:
        node = node.setdefault(k, {})
    last = path[-1]
    if isinstance(value, Mapping) and isinstance(node.get(last), dict):
        for k, v in value.items():
            _deep_set(node[last], (k,), v)
    else:
        node[last] = dict(value) if isinstance(value, Mapping) else value


class MethodParams(BaseModel):
    """Parameters of the BagIt method (sections V and VI of the paper), one sub-model per stage."""

    model_config = _STRICT

    goal: GoalParams = GoalParams()
    planner: PlannerParams = PlannerParams()
    controller: ControllerParams = ControllerParams()

    @model_validator(mode="before")
    @classmethod
    def _by_name(cls, data: Any) -> Any:
        return _nest(data) if isinstance(data, Mapping) else data

    @model_serializer(mode="plain")
    def _dump_by_name(self) -> dict[str, Any]:
        """Dumped (e.g. in a scenario document) as it is written: the set parameters by name."""
        return self.overrides()

    def flat(self) -> dict[str, Any]:
        """Every parameter by name (`PARAM_PATHS`): what a panel or a record's table shows."""
        return {name: self.get(name) for name in PARAM_PATHS}

    def get(self, name: str) -> Any:
        """One parameter by its name."""
        node: Any = self
        for k in PARAM_PATHS[name]:
            node = getattr(node, k)
        return node

    def overrides(self) -> dict[str, Any]:
        """The parameters set explicitly, by name, e.g. a scenario's: what later overrides go on top of."""
        return {_NAMES[path]: value for path, value in _set_leaves(self, ())}


def _set_leaves(model: BaseModel, path: tuple[str, ...]) -> list[tuple[tuple[str, ...], Any]]:
    """(path, value) of every field set explicitly in `model` and its sub-models, in field order."""
    out: list[tuple[tuple[str, ...], Any]] = []
    for name in type(model).model_fields:
        if name in model.model_fields_set:
            value = getattr(model, name)
            out += _set_leaves(value, (*path, name)) if isinstance(value, BaseModel) else [((*path, name), value)]
    return out


def merge_params(base: MethodParams, overrides: Mapping[str, Any] | None) -> MethodParams:
    """`base`'s explicitly set parameters with `overrides` (a run's, e.g. `bagit run --params`; by
    name) on top; BadScenario naming the first bad one."""
    try:
        _nest(overrides or {})  # refuse a bad key before merging, naming it
        return MethodParams.model_validate({**base.overrides(), **(overrides or {})})
    except ValueError as e:  # ValidationError is a ValueError; _nest raises a plain one for an unknown key
        raise BadScenario(params_error(e)) from None


def params_error(e: ValueError) -> str:
    """One line naming the first bad parameter of a failed validation (by its name when it has one)."""
    if isinstance(e, ValidationError):
        first = e.errors()[0]
        path = tuple(map(str, first["loc"]))
        loc = _NAMES.get(path, ".".join(path))
        return f"params.{loc}: {first['msg'].removeprefix('Value error, ')}" if loc else f"params: {first['msg'].removeprefix('Value error, ')}"
    return f"params.{e}"
