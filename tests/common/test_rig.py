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


def test_the_separation_limit_follows_the_bags_rim_under_the_rigs_own_ceiling():
    """Half the rim less the margin; the paper's 0.68 m bag keeps the 0.32 m every earlier run had, to the bit;
    a ceiling the rig sets still caps it; a bag too small to hold the tools apart is a one-line error."""
    from bagit.common.rig import RIM_SEPARATION_MARGIN_M, SafetyLimits, rim_separation_limit_m

    assert RigConfig().safety.max_separation_m == 0.32 == rim_separation_limit_m(0.68)
    assert RigConfig().for_bag(1.3).safety.max_separation_m == pytest.approx(0.65 - RIM_SEPARATION_MARGIN_M)
    assert RigConfig().for_bag(0.56).safety.max_separation_m == pytest.approx(0.26)
    capped = RigConfig(safety=SafetyLimits(max_flange_distance_m=0.4))
    assert capped.for_bag(1.3).safety.max_separation_m == 0.4
    assert capped.for_bag(0.56).safety.max_separation_m == pytest.approx(0.26)
    with pytest.raises(BadScenario, match="too small for the tools"):
        RigConfig().for_bag(0.19)  # 75 mm < the tools' 80 mm
    with pytest.raises(ValueError, match="the rig's ceiling"):
        SafetyLimits(max_flange_distance_m=0.05)


def test_no_two_means_of_disjoint_stretches_of_a_closed_rim_are_more_than_half_its_perimeter_apart():
    """The derivation of `rim_separation_limit_m`: mounts clamping two stretches of any rim of perimeter P
    have centres at most P/2 apart (on random rims, however crumpled or stretched out), and a rim pulled
    into a thin slot between them nears it, so no bound below P/2 holds for every pair of mounts."""
    from bagit.common.geometry import closed_polyline_length

    rng = np.random.default_rng(0)
    worst = 0.0
    for k in range(300):
        n = int(rng.integers(6, 40))
        pts = rng.normal(size=(n, 3)) * (rng.uniform(0.1, 1.0, size=3) if k % 2 else [1.0, 0.02, 0.02])
        pts = pts[np.argsort(np.arctan2(pts[:, 1], pts[:, 0]))] if k % 3 else pts  # some round-ish, some crumpled
        P = closed_polyline_length(pts)
        a, b = sorted(rng.choice(n, size=2, replace=False))
        la, lb = int(rng.integers(1, max(2, (b - a) // 2 + 1))), int(rng.integers(1, max(2, (n - b + a) // 2 + 1)))
        ca, cb = pts[a : a + la].mean(axis=0), pts[[(b + j) % n for j in range(lb)]].mean(axis=0)
        worst = max(worst, float(np.linalg.norm(cb - ca)) / P)
    assert worst <= 0.5
    slot = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1e-3, 0.0], [0.0, 1e-3, 0.0]])  # a rim pulled flat
    assert np.linalg.norm(slot[1:3].mean(axis=0) - slot[[3, 0]].mean(axis=0)) / closed_polyline_length(slot) > 0.499
