"""The run coordinator's state machine, driven with a fake clock and real planning (no Zenoh)."""

from __future__ import annotations

import numpy as np
import pytest

from bagit.common.messages import ControllerStatus, Goal, RunControl, SoiState
from bagit.common.results import RunResult
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.planner.coordinator import Coordinator, CoordinatorConfig, PlanOutcome, compute_plan

T0 = 1_000_000.0


def sample_g0(sc: Scenario) -> np.ndarray:
    """A level rim beside the object, the size of the scenario's bag (what perception would see)."""
    R = sc.bag.rim_perimeter or 0.68
    c = sc.object.bottom_vertices().mean(axis=0)
    r = R / (2 * np.pi)
    t = np.linspace(0, 2 * np.pi, sc.bag.n_x, endpoint=False)
    return np.column_stack([c[0] + 0.0 + r * np.cos(t), c[1] + r * np.sin(t), np.full_like(t, c[2] - 0.12)])


def started(cfg: CoordinatorConfig | None = None, scenario: str = "exp02", **kw) -> Coordinator:
    c = Coordinator(cfg or CoordinatorConfig(settle_s=0.5), now=T0)
    c.on_liveliness("controller", True, T0)
    c.on_liveliness("arm-driver", True, T0)
    c.on_liveliness("perception", True, T0)
    rep = c.start(RunControl(action="start", scenario=scenario, **kw), T0)
    assert rep.accepted, rep.reason
    return c


def soi(rim: np.ndarray, frame_t: float) -> SoiState:
    return SoiState(rim=rim, source_stamp=frame_t, stamp=frame_t + 0.02)


def servoing(c: Coordinator, t: float = T0 + 2.0) -> None:
    """Push the run to pre-bagging with a real goal and path computed from a sampled g0."""
    sc = c.run.scenario
    (eff,) = c.on_soi(soi(sample_g0(sc), t - 0.1), t)
    goals: list[Goal] = []
    out = compute_plan(eff.job, on_goal=goals.append)
    assert out.path is not None, out.reason
    assert [e.kind for e in c.on_goal(goals[0], t)] == ["publish_goal"]
    assert c.state.stage == "planning"
    effects = c.on_plan(out, t + 0.5)
    assert [e.kind for e in effects] == ["publish_path"]
    assert c.state.stage == "pre-bagging"


def status(c: Coordinator, **kw) -> ControllerStatus:
    return ControllerStatus(run_id=c.state.run_id, **kw)


def test_start_publishes_what_the_run_was_started_with():
    c = started(controller="ibvs", planner="ffg-rrt", seed=3, params={"horizon": 5})
    s = c.state
    assert s.stage == "perceiving" and s.run_id and s.scenario == "exp02-canned-pineapple"
    assert (s.controller, s.planner, s.seed, s.params) == ("ibvs", "ffg-rrt", 3, {"horizon": 5})
    sc = Scenario.from_dict(s.scenario_doc)  # services rebuild the scenario from run/state alone
    assert sc.params.controller.horizon == 5 and sc.name == Scenario.from_file(find_scenario("exp02")).name


def test_a_start_while_running_is_refused_with_the_reason():
    c = started()
    rep = c.start(RunControl(action="start", scenario="exp01"), T0 + 1)
    assert not rep.accepted and "in progress" in rep.reason and c.state.run_id in rep.reason
    assert c.state.scenario == "exp02-canned-pineapple"


@pytest.mark.parametrize(
    "req, words",
    [
        (dict(scenario="no-such-scenario"), "no scenario"),
        (dict(), "needs a scenario"),
        (dict(scenario="exp02", params={"horizon": -1}), "horizon"),
        (dict(scenario="exp02", params={"nonsense": 1}), "nonsense"),
        (dict(scenario="exp02", controller="pid"), "unknown controller"),
        (dict(scenario="exp02", planner="astar"), "unknown planner"),
        (dict(scenario_doc={"name": "x"}), "object"),
    ],
)
def test_bad_starts_are_refused_and_leave_the_coordinator_idle(req, words):
    c = Coordinator(now=T0)
    rep = c.start(RunControl(action="start", **req), T0)
    assert not rep.accepted and words in rep.reason
    assert c.state.stage == "idle" and c.run is None


def test_g0_only_from_an_soi_of_a_frame_after_the_start_and_of_the_right_size():
    c = started()
    n_x = c.run.scenario.bag.n_x
    g0 = sample_g0(c.run.scenario)
    assert c.on_soi(soi(g0, T0 - 1.0), T0 + 0.1) == []  # a frame of before the start
    assert c.on_soi(soi(g0, T0 + 0.2), T0 + 0.3) == []  # within the settle time (the sim resets)
    assert c.on_soi(soi(g0[: n_x // 2], T0 + 1.0), T0 + 1.1) == []  # perception still on another n_x
    assert c.state.stage == "perceiving"
    (eff,) = c.on_soi(soi(g0, T0 + 1.0), T0 + 1.1)
    assert eff.kind == "plan" and eff.job.run_id == c.state.run_id and np.allclose(eff.job.g0, g0)
    assert c.state.stage == "goal"


def test_a_full_run_follows_the_controller_to_done_with_a_result():
    c = started()
    servoing(c)
    c.on_status(status(c, stage="pre-bagging", progress=0.2), T0 + 3)
    assert c.state.progress == pytest.approx(0.2)
    c.on_status(status(c, stage="bagging", progress=0.7, error_to_goal=0.02), T0 + 4)
    assert c.state.stage == "bagging"
    c.on_status(ControllerStatus(run_id="another", stage="bagging", done=True), T0 + 4.5)  # not this run
    assert c.state.stage == "bagging"
    c.on_status(status(c, stage="bagging", progress=1.0, done=True, error_to_goal=0.006, seq=130, ticks=120), T0 + 5)
    s = c.state
    assert s.stage == "done" and s.progress == 1.0 and s.reason is None
    r = s.result
    assert r["success"] and r["error_to_goal_m"] == pytest.approx(0.006) and r["ticks"] == 120
    assert r["duration_s"] == pytest.approx(2.5) and r["path_nodes"] > 2 and r["planning_time_s"] > 0
    res = RunResult.model_validate(r)  # one result model, whoever hosts the coordinator
    assert res.stage_reached == "done" and res.object_from == "scenario" and len(res.object_vertices) >= 3
    assert res.final_rim is not None and res.perceived_error_cm is not None  # the rig's own view of the end
    # the next run may start
    assert c.start(RunControl(action="start", scenario="exp01"), T0 + 6).accepted


def test_an_infeasible_goal_fails_the_run_with_the_planners_reason():
    c = started()
    sc = c.run.scenario
    small = sample_g0(sc) * 0.0 + sample_g0(sc).mean(0) + (sample_g0(sc) - sample_g0(sc).mean(0)) * 0.3
    (eff,) = c.on_soi(soi(small, T0 + 1), T0 + 1.1)
    # scenario with a rim perimeter too small for the object
    job = eff.job
    job.scenario = sc.model_copy(update={"bag": sc.bag.model_copy(update={"rim_perimeter": 0.1})})
    out = compute_plan(job)
    assert out.failed_stage == "goal" and "too large for the bag" in out.reason
    c.on_plan(out, T0 + 1.2)
    assert c.state.stage == "failed" and "too large for the bag" in c.state.reason
    assert c.state.result["stage_reached"] == "goal" and c.state.result["success"] is False


def test_a_failed_planning_fails_the_run_in_planning():
    c = started(scenario="obstacles-b")  # the sampled g0 runs through this layout's obstacle
    g0 = sample_g0(c.run.scenario)
    (eff,) = c.on_soi(soi(g0, T0 + 1), T0 + 1.1)
    out = compute_plan(eff.job)
    assert out.failed_stage == "planning" and out.goal is not None
    effects = c.on_plan(out, T0 + 2)
    assert [e.kind for e in effects] == ["publish_goal"]
    assert c.state.stage == "failed" and c.state.reason.startswith("planning:") and "obstacle" in c.state.reason
    assert c.state.result["stage_reached"] == "planning"


def test_malformed_g0_is_a_reason_not_a_crash():
    c = started()
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1), T0 + 1.1)
    eff.job.g0 = np.full((32, 3), np.nan)
    out = compute_plan(eff.job)
    assert out.failed_stage == "goal" and "finite" in out.reason


def test_controller_gone_while_servoing_fails_the_run_with_the_reason():
    c = started()
    servoing(c)
    c.on_status(status(c, stage="pre-bagging", progress=0.1), T0 + 3)
    c.on_liveliness("controller", False, T0 + 3.5)
    assert c.state.stage == "failed" and "controller service is gone" in c.state.reason


def test_silent_controller_and_no_first_status_fail_the_run():
    cfg = CoordinatorConfig(settle_s=0.5, status_timeout_s=2.0, first_status_timeout_s=5.0)
    c = started(cfg)
    servoing(c)  # path at T0 + 2.5
    c.tick(T0 + 7.0)
    assert c.state.stage == "pre-bagging"
    c.tick(T0 + 8.0)
    assert c.state.stage == "failed" and "no controller status" in c.state.reason
    c = started(cfg)
    servoing(c)
    c.on_status(status(c, stage="pre-bagging", progress=0.1), T0 + 3)
    c.tick(T0 + 4.9)
    assert c.state.stage == "pre-bagging"
    c.tick(T0 + 5.1)
    assert c.state.stage == "failed" and "silent" in c.state.reason


def test_a_rim_lost_while_servoing_fails_the_run_with_that_reason():
    """The controller holds on a stale SOI, so nothing brings a lost rim back: the run fails, in bounded time."""
    c = started(CoordinatorConfig(settle_s=0.5, status_timeout_s=60, soi_lost_s=4.0))
    servoing(c)  # path at T0 + 2.5
    rim = c.run.last_rim
    c.on_soi(soi(rim, T0 + 5.0), T0 + 5.0)
    c.tick(T0 + 8.9)
    assert c.state.stage == "pre-bagging"  # 3.9 s since the last SOI
    c.on_soi(soi(rim, T0 + 9.0), T0 + 9.0)
    c.tick(T0 + 12.9)
    assert c.state.stage == "pre-bagging"
    c.tick(T0 + 13.1)
    assert c.state.stage == "failed" and "perception lost the rim: no SOI for 4.1 s in pre-bagging" in c.state.reason


def test_perception_may_come_back_within_its_grace_time():
    c = started(CoordinatorConfig(settle_s=0.5, perception_grace_s=3.0, status_timeout_s=60, soi_lost_s=60))
    servoing(c)
    c.on_liveliness("perception", False, T0 + 3)
    c.tick(T0 + 5)
    c.on_liveliness("perception", True, T0 + 5.5)
    c.tick(T0 + 9)
    assert c.state.stage == "pre-bagging"
    c.on_liveliness("perception", False, T0 + 10)
    c.tick(T0 + 13.5)
    assert c.state.stage == "failed" and "perception service is gone" in c.state.reason


def test_no_fresh_soi_in_time_fails_and_says_perception_is_down():
    c = started(CoordinatorConfig(perceive_timeout_s=10, perception_grace_s=60))
    c.on_liveliness("perception", False, T0 + 1)
    c.tick(T0 + 9)
    assert c.state.stage == "perceiving"
    c.tick(T0 + 11)
    assert c.state.stage == "failed" and "no fresh SOI" in c.state.reason and "not up" in c.state.reason


def test_stop_aborts_and_a_late_plan_is_ignored_then_reset_goes_idle():
    c = started()
    (eff,) = c.on_soi(soi(sample_g0(c.run.scenario), T0 + 1), T0 + 1.1)
    assert c.stop(T0 + 1.5).accepted
    assert c.state.stage == "aborted" and "operator" in c.state.reason
    assert c.on_plan(PlanOutcome(eff.job.run_id, path=None, failed_stage="planning", reason="x"), T0 + 2) == []
    assert c.state.stage == "aborted"
    assert not c.stop(T0 + 3).accepted
    assert c.reset(T0 + 4).accepted and c.state.stage == "idle" and c.state.run_id is None


def test_controller_reporting_failure_fails_the_run_and_time_limit_applies():
    c = started(CoordinatorConfig(settle_s=0.5, run_time_limit_s=20, status_timeout_s=60))
    servoing(c)
    c.on_status(status(c, stage="failed", reason="SOI lost"), T0 + 3)
    assert c.state.stage == "failed" and c.state.reason == "controller: SOI lost"
    c = started(CoordinatorConfig(settle_s=0.5, run_time_limit_s=20, status_timeout_s=60))
    servoing(c)
    c.on_status(status(c, stage="bagging", progress=0.5), T0 + 22)
    c.tick(T0 + 23)
    assert c.state.stage == "failed" and "time limit" in c.state.reason


def test_tick_state_advances_elapsed_only_while_active():
    c = started()
    assert c.tick_state(T0 + 4).elapsed_s == pytest.approx(4)
    c.stop(T0 + 5)
    assert c.tick_state(T0 + 9).elapsed_s == pytest.approx(5)


def test_an_estop_aborts_the_run_and_refuses_starts_until_released():
    c = started()
    servoing(c)
    c.on_estop(True, "dashboard", "E-STOP pressed", T0 + 3.0)
    s = c.state
    assert s.stage == "aborted" and "emergency stop" in s.reason and "dashboard" in s.reason
    assert s.result["success"] is False and s.result["stage_reached"] == "pre-bagging"
    rep = c.start(RunControl(action="start", scenario="exp02"), T0 + 4.0)
    assert not rep.accepted and "e-stop is engaged" in rep.reason and "release it first" in rep.reason
    assert c.state.stage == "aborted"
    c.on_estop(False, "dashboard", None, T0 + 5.0)
    assert c.start(RunControl(action="start", scenario="exp02"), T0 + 6.0).accepted
    # an e-stop while idle only latches
    c.reset(T0 + 7.0)
    c.on_estop(True, "pendant", None, T0 + 8.0)
    assert c.state.stage == "idle"
    assert not c.start(RunControl(action="start", scenario="exp02"), T0 + 9.0).accepted


def test_a_run_never_goes_back_from_bagging_to_pre_bagging():
    """A late or a hold status saying pre-bagging once the lift has begun does not flip the run/state back."""
    c = started()
    servoing(c)
    c.on_status(status(c, stage="bagging", progress=0.7), T0 + 3)
    c.on_status(status(c, stage="pre-bagging", progress=0.7, mode="hold"), T0 + 3.1)
    assert c.state.stage == "bagging"


def test_only_the_dashboard_or_the_cli_release_the_coordinators_estop_latch():
    c = started()
    c.on_estop(True, "arm_driver", "watchdog", T0 + 1.0)
    assert c.state.stage == "aborted" and c.estop
    c.on_estop(False, "some-process", None, T0 + 2.0)
    assert c.estop and not c.start(RunControl(action="start", scenario="exp01"), T0 + 3.0).accepted
    c.on_estop(False, "cli", None, T0 + 4.0)
    assert c.estop is None and c.start(RunControl(action="start", scenario="exp01"), T0 + 5.0).accepted
