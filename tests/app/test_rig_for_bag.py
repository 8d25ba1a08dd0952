"""The arms keep to the run's bag: `bagit run` and `bagit up` give the arm driver the rig holding the scenario's
bag, whose separation limit follows the rim (`RigConfig.for_bag`), so a large bag's start is inside it."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from bagit.common.rig import RigConfig, SafetyLimits
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.rig_sim import SimRig
from bagit.sim_arms import Cr5Arms


def _bag(perimeter: float) -> Scenario:
    doc = yaml.safe_load(find_scenario("exp02").read_text())
    doc["bag"]["rim_perimeter"] = perimeter
    return Scenario.from_dict(doc)


def _start_fault(sc: Scenario, rig: RigConfig) -> tuple[str | None, float]:
    """The fault starting the CR5s where the simulator hangs `sc`'s bag (None: started), and the mounts' distance."""
    sim = SimRig(sc, rig, camera=False)
    try:
        arms = Cr5Arms.of(sim)
        arms.start()
        poses = sim.world.mount_home_poses()
        return arms.fault, float(np.linalg.norm(poses["right"][:3, 3] - poses["left"][:3, 3]))
    finally:
        sim.close()


def test_a_large_bag_starts_inside_its_own_limit_and_a_rig_ceiling_still_refuses_it():
    """A 1.2 m rim starts with its mounts 0.37 m apart: inside its own 0.58 m, outside the 0.32 m every bag
    had before (the envelope zoo's 12 refused starts), which a rig that sets that ceiling still keeps."""
    sc = _bag(1.2)
    fault, d = _start_fault(sc, RigConfig().for_bag(sc.bag.perimeter_m()))
    assert fault is None and 0.32 < d < 0.58
    fault, _ = _start_fault(sc, RigConfig(safety=SafetyLimits(max_flange_distance_m=0.32)).for_bag(1.2))
    assert fault is not None and "max_distance" in fault and "> 320 mm" in fault


def test_bagit_up_writes_the_simulated_bags_rim_into_the_rig_config(tmp_path):
    from bagit.up import Up, UpOptions

    f = tmp_path / "large.yaml"
    f.write_text(_bag(1.2).to_yaml())
    for scenario, limit in (("exp08", 0.26), (str(f), 0.58)):
        _, rpath = Up(UpOptions(scenario=scenario, workdir=tmp_path / "up"))._write_configs()
        assert RigConfig.from_file(rpath).safety.max_separation_m == pytest.approx(limit)
