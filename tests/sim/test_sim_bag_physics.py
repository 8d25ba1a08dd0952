"""The scenario's bag physics and looks, light and depth noise reach the simulated world."""

import numpy as np
import yaml

from bagit.common.bag import RIM_BENDING_NM2
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.world import SimWorld


def _world(**sections) -> SimWorld:
    doc = yaml.safe_load(find_scenario("exp02").read_text())
    for k, v in sections.items():
        doc.setdefault(k, {}).update(v)
    return SimWorld(Scenario.from_dict(doc), camera=False)


def _flex(w: SimWorld, name: str) -> int:
    import mujoco

    return mujoco.mj_name2id(w.model, mujoco.mjtObj.mjOBJ_FLEX, name)


def _elasticity(w: SimWorld) -> tuple[np.ndarray, np.ndarray]:
    """The compiled elasticity: the fabric shell's membrane stiffness (the only flex with `flex_stiffness`),
    linear in Young's modulus, and the binding rod's `flex_bending` (the only flex with one)."""
    m = w.model
    assert m.flex_stiffnessadr[_flex(w, "rim")] == -1 and m.flex_bendingadr[_flex(w, "bag")] == -1
    return np.ravel(m.flex_stiffness).copy(), np.ravel(m.flex_bending).copy()


def test_defaults_are_the_constants_of_every_earlier_run():
    w = _world()
    m, bag, rim = w.model, _flex(w, "bag"), _flex(w, "rim")
    assert m.flex_damping[bag] == 0.002 and m.flex_friction[bag][0] == 0.5
    assert np.allclose(m.flex_rgba[rim], [0.85, 0.05, 0.05, 1.0])
    assert np.isclose(m.body_mass[m.flex_vertbodyid[m.flex_vertadr[bag]:m.flex_vertadr[bag] + m.flex_vertnum[bag]]].sum(), 0.08)
    assert np.allclose(m.light_pos[0], [0, 0, 2.5]) and np.allclose(m.light_diffuse[:, 0], [0.8, 0.4])
    assert w.noise.sigma_at_1m == 0.0015
    w.close()


def test_a_stiff_heavy_green_bound_bag_under_dim_side_light():
    w0 = _world()
    membrane0, bending0 = _elasticity(w0)
    w0.close()
    w = _world(bag={"fabric": {"stretch_n_per_m": 64000, "mass_kg": 0.3, "damping_s": 0.008, "friction": 0.9},
                    "rim": {"bending_nm2": 1e-3, "color": [0.1, 0.8, 0.2]}},
               sim={"light": {"intensity": 0.5, "direction": [1.0, 0.0, -1.0]}, "camera": {"depth_noise": 2.0}})
    m, bag, rim = w.model, _flex(w, "bag"), _flex(w, "rim")
    assert m.flex_damping[bag] == 0.008 and m.flex_friction[bag][0] == 0.9
    membrane, bending = _elasticity(w)
    on = membrane0 != 0
    assert on.any() and np.allclose(membrane[on] / membrane0[on], 8.0) and not membrane[~on].any()  # 64 kN/m against 8
    moved = ~np.isclose(bending, bending0)  # flex_bending holds the rod's topology and geometry too: what changed is its stiffness
    assert moved.any() and np.allclose(bending[moved] / bending0[moved], 1e-3 / RIM_BENDING_NM2)
    assert np.allclose(m.flex_rgba[rim], [0.1, 0.8, 0.2, 1.0])
    assert np.isclose(m.body_mass[m.flex_vertbodyid[m.flex_vertadr[bag]:m.flex_vertadr[bag] + m.flex_vertnum[bag]]].sum(), 0.3)
    assert np.allclose(m.light_dir[0], np.array([1.0, 0.0, -1.0]) / np.sqrt(2))
    assert np.allclose(m.light_pos[0], -2.5 * np.array([1.0, 0.0, -1.0]) / np.sqrt(2))
    assert np.allclose(m.light_diffuse[:, 0], [0.4, 0.2]) and np.allclose(m.vis.headlight.diffuse, 0.2)
    assert w.noise.sigma_at_1m == 0.003
    w.close()
