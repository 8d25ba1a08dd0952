"""Method parameters have one spelling, their field's name: overrides, scenario files, dumped
scenario documents and records all use it, and the old spellings are refused naming the new one."""

from __future__ import annotations

import pytest

from bagit.cli import main
from bagit.common.errors import BadScenario
from bagit.common.params import PARAM_PATHS, ControllerParams, MethodParams, merge_params
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario


def test_a_parameters_name_is_its_fields_name():
    assert all(name == path[-1] for name, path in PARAM_PATHS.items())
    assert PARAM_PATHS["step_m"] == ("planner", "step_m") and PARAM_PATHS["twist_weight"] == ("controller", "experimental", "twist_weight")


def test_overrides_by_name_go_over_the_base_and_only_what_was_set_is_kept():
    base = MethodParams(twist_weight=0, step_m=0.02)
    merged = merge_params(base, {"control_rate_hz": 15, "step_m": 0.01})
    assert merged.controller.control_rate_hz == 15 and merged.planner.step_m == 0.01 and merged.controller.experimental.twist_weight == 0
    assert merged.overrides() == {"step_m": 0.01, "control_rate_hz": 15.0, "twist_weight": 0.0}
    assert MethodParams(controller=ControllerParams(horizon=5)).overrides() == {"horizon": 5}  # Python construction by stage model


@pytest.mark.parametrize("overrides, says", [
    ({"planner_step_m": 0.02}, "params.planner_step_m: renamed step_m"),
    ({"planner_max_iterations": 100}, "params.planner_max_iterations: renamed max_iterations"),
    ({"controller": {"experimental": {"twist_weight": 0}}},
     'params.controller: parameters are not nested under their stage; give each by its name ("twist_weight")'),
    ({"planner": {"step_m": 0.02, "lambda_4": 0.01}}, 'give each by its name ("step_m", "lambda_4")'),
    ({"enclose_margin_m": 0.0}, "the enclosure rule was an experiment removed"),
    ({"step": 0.02}, "params.step: unknown parameter"),
])
def test_old_spellings_are_refused_naming_the_new_one(overrides, says):
    with pytest.raises(BadScenario) as e:
        merge_params(MethodParams(), overrides)
    assert says in str(e.value)


def test_a_scenario_file_with_an_old_spelling_is_refused_naming_the_new_one():
    text = find_scenario("exp01").read_text() + "params: {planner_step_m: 0.02}\n"
    with pytest.raises(BadScenario, match="params: .*renamed step_m"):
        Scenario.from_text(text)


def test_a_dumped_scenario_writes_its_parameters_by_name_and_reads_back_the_same():
    """What `bagit run` puts in run/state (scenario_doc) and `to_yaml` writes is read again as it was."""
    sc = Scenario.from_file(find_scenario("exp01"))
    sc = sc.model_copy(update={"params": merge_params(sc.params, {"step_m": 0.02, "twist_weight": 0})})
    doc = sc.model_dump(mode="json", exclude_none=True)
    assert doc["params"] == {"step_m": 0.02, "twist_weight": 0.0}
    assert Scenario.model_validate(doc) == sc and Scenario.from_text(sc.to_yaml()) == sc


def test_bagit_run_refuses_an_old_spelling_in_one_line(capsys):
    assert main(["run", "exp01", "--params", '{"planner_step_m": 0.02}']) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "planner_step_m: renamed step_m" in err[0]
