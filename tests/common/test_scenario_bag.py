"""The bag's physics and looks in a scenario (bag.fabric, bag.rim) and the simulator's light and
depth noise (sim): optional, today's values by default, absurd values a one-line error (exit 2)."""

import math

import pytest
import yaml

from bagit.cli import main
from bagit.common.bag import RIM_BENDING_NM2, RIM_COLOR, RIM_TUBE_RADIUS_M, RIM_YOUNG_PA
from bagit.common.errors import BadScenario
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario


def _doc(**bag_or_sim) -> dict:
    doc = yaml.safe_load(find_scenario("exp02").read_text())
    for where, value in bag_or_sim.items():
        section, _, key = where.partition("__")
        target = doc.setdefault(section, {})
        for part in key.split("__")[:-1]:
            target = target.setdefault(part, {})
        target[key.split("__")[-1]] = value
    return doc


def test_without_the_fields_the_bag_is_the_one_every_run_used():
    s = Scenario.from_file(find_scenario("exp02"))
    f, r = s.bag.fabric, s.bag.rim
    assert (f.stretch_n_per_m, f.mass_kg, f.damping_s, f.friction) == (8000.0, 0.08, 0.002, 0.5)
    assert r.color == RIM_COLOR and math.isclose(r.bending_nm2, 1.0179e-4, rel_tol=1e-4)
    assert math.isclose(4 * RIM_BENDING_NM2 / (math.pi * RIM_TUBE_RADIUS_M**4), RIM_YOUNG_PA, rel_tol=1e-12)
    assert s.sim.light.intensity == 1.0 and s.sim.light.direction == (0.0, 0.0, -1.0) and s.sim.camera.depth_noise == 1.0


def test_the_fields_read_as_named():
    doc = _doc(bag__fabric__stretch_n_per_m=64000, bag__fabric__mass_kg=0.3, bag__fabric__damping_s=0.008, bag__fabric__friction=0.9,
               bag__rim__bending_nm2=1e-3, bag__rim__color=[0.1, 0.8, 0.2], sim__light__intensity=0.5,
               sim__light__direction=[0.3, 0.0, -1.0], sim__camera__depth_noise=2.0)
    s = Scenario.from_dict(doc)
    assert s.bag.fabric.stretch_n_per_m == 64000 and s.bag.fabric.mass_kg == 0.3 and s.bag.rim.color == (0.1, 0.8, 0.2)
    assert s.sim.light.intensity == 0.5 and s.sim.camera.depth_noise == 2.0
    assert Scenario.from_text(s.to_yaml()).bag.rim.bending_nm2 == 1e-3  # written and read back


@pytest.mark.parametrize("where, value, says", [
    ("bag__fabric__stretch_n_per_m", -8000, "bag.fabric.stretch_n_per_m"),
    ("bag__fabric__stretch_n_per_m", 1e12, "bag.fabric.stretch_n_per_m"),
    ("bag__fabric__mass_kg", 0, "bag.fabric.mass_kg"),
    ("bag__fabric__mass_kg", 1000, "bag.fabric.mass_kg"),
    ("bag__fabric__damping_s", -0.1, "bag.fabric.damping_s"),
    ("bag__fabric__friction", 5, "bag.fabric.friction"),
    ("bag__rim__bending_nm2", -1e-4, "bag.rim.bending_nm2"),
    ("bag__rim__bending_nm2", 10.0, "bag.rim.bending_nm2"),
    ("bag__rim__color", [1.5, 0, 0], "bag.rim.color"),
    ("bag__rim__color", [0.5, 0.5], "bag.rim.color"),
    ("bag__fabric__colour", 1, "bag.fabric.colour"),  # a misspelt field is refused, not ignored
    ("sim__light__intensity", 0, "sim.light.intensity"),
    ("sim__light__direction", [0, 0, 1], "point down"),
    ("sim__light__direction", [0, 0, 0], "non-zero"),
    ("sim__camera__depth_noise", -1, "sim.camera.depth_noise"),
    ("sim__camera__calibration_error__offset_m", [0.5, 0, 0], "calibration_error.offset_m"),
    ("sim__camera__calibration_error__turn_deg", [0, 0, 45], "calibration_error.turn_deg"),
    ("sim__camera__calibration_error__turn_deg", [0, "nan", 0], "sim.camera.calibration_error.turn_deg"),
])
def test_absurd_values_are_one_line_errors(where, value, says):
    with pytest.raises(BadScenario) as e:
        Scenario.from_dict(_doc(**{where: value}), "bag.yaml")
    msg = str(e.value)
    assert says in msg and len(msg.splitlines()) == 1 and msg.startswith("bag.yaml: ")


@pytest.mark.parametrize("where, value", [("bag__fabric__stretch_n_per_m", -1), ("bag__fabric__stretch_n_per_m", 1e9),
                                          ("bag__fabric__mass_kg", -0.1), ("bag__fabric__mass_kg", 500), ("bag__rim__color", [2, 0, 0]),
                                          ("bag__color", [0.2, -1, 0.5])])
def test_bagit_run_exits_2_on_an_absurd_stiffness_mass_or_colour(tmp_path, capsys, where, value):
    f = tmp_path / "bad-bag.yaml"
    f.write_text(yaml.safe_dump(_doc(**{where: value})))
    assert main(["run", str(f), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and where.replace("__", ".") in err[0]
