"""The rig config: defaults like the paper's set-up, YAML round trip, camera pose."""


import numpy as np
import pytest
from suite_support import ROOT

from bagit.common.errors import BadScenario
from bagit.common.rig import RigConfig


def test_committed_sim_rig_is_the_default():
    r = RigConfig.from_file(ROOT / "deploy" / "rig-sim.yaml")
    d = RigConfig()
    assert r.model_dump() == d.model_dump()
    # the arms face each other across the object, the camera looks at it from above
    assert r.arms["left"].base_position[1] < 0 < r.arms["right"].base_position[1]
    T = r.camera.T_world_camera()
    assert T[2, 3] > 1.0 and T[:3, 2][2] < -0.5
    assert np.allclose(T[:3, :3].T @ T[:3, :3], np.eye(3))


def test_bad_rig_file(tmp_path):
    p = tmp_path / "rig.yaml"
    p.write_text("name: 'two words'\n")
    with pytest.raises(BadScenario):
        RigConfig.from_file(p)
    with pytest.raises(BadScenario):
        RigConfig.from_file(tmp_path / "missing.yaml")


def test_a_watchdog_shorter_than_four_servo_periods_is_refused():
    """It halts after a gap of watchdog_s less a servo period: under 4 periods a late command would halt the arms."""
    from bagit.common.rig import SafetyLimits

    assert SafetyLimits(watchdog_s=0.12, servo_period_s=0.03).halt_gap_s == pytest.approx(0.09)
    with pytest.raises(ValueError, match="at least 4 servo periods"):
        SafetyLimits(watchdog_s=0.1, servo_period_s=0.03)
