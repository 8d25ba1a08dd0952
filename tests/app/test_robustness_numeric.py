"""Never a crash on bad numbers: NaN or degenerate data in every stage ends in a clear error or a held
tick with a reason (issue 5), and an unstable simulation raises SimulationFailed, which a run reports."""

from __future__ import annotations

import numpy as np
import pytest

from bagit.common.errors import BadCloud, BagItError, NumericalFailure, SimulationFailed
from bagit.common.geometry import pca
from bagit.common.params import MethodParams
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.controller import make_controller
from bagit.services.controller.baselines import servo_law
from bagit.services.controller.broyden import jacobian_from_exploration
from bagit.services.controller.mpc import MpcSolver
from bagit.services.perception import extract_soi
from bagit.services.planner import plan_scenario
from bagit.services.planner import space as space_mod


def _ring(n=32, r=0.1):
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.stack([r * np.cos(t), r * np.sin(t), np.full(n, 0.4)], 1)


def test_pca_turns_nan_and_lapack_failures_into_a_named_error(monkeypatch):
    with pytest.raises(NumericalFailure, match="finite"):
        pca(np.array([[0.0, 0, 0], [1, np.nan, 0], [0, 1, 0]]))
    with pytest.raises(NumericalFailure):
        pca(np.zeros((0, 3)))

    def no_convergence(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(np.linalg, "svd", no_convergence)
    with pytest.raises(NumericalFailure, match="SVD did not converge"):
        pca(_ring())
    assert issubclass(NumericalFailure, BagItError)


def test_soi_extraction_reports_a_failing_svd_as_a_bad_cloud(monkeypatch):
    """Whatever fails inside EM / the curve fit, extract_soi says BadCloud (the pipeline holds on it)."""
    rng = np.random.default_rng(0)
    cloud = np.repeat(_ring(64), 40, axis=0) + rng.normal(0, 0.002, (64 * 40, 3))
    assert extract_soi(cloud, 32).shape == (32, 3)

    def no_convergence(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(np.linalg, "svd", no_convergence)
    with pytest.raises(BadCloud, match="numerically"):
        extract_soi(cloud, 32)


def test_exploration_jacobian_and_servo_law_refuse_non_finite_data():
    U = np.eye(12)
    S = np.ones((12, 96))
    S[3, 5] = np.nan
    with pytest.raises(NumericalFailure, match="non-finite"):
        jacobian_from_exploration(U, S)
    J = np.ones((96, 12))
    J[0, 0] = np.inf
    with pytest.raises(NumericalFailure):
        servo_law(J, np.zeros(96), np.zeros(96), 0.5, np.full(12, 0.01))


def test_mpc_fails_a_tick_on_bad_data_and_recovers():
    solver = MpcSolver(horizon=5, q=1.0, r=1e-3)
    u_max = np.full(12, 0.005)
    J = np.random.default_rng(1).normal(size=(96, 12)) * 0.1
    for bad in (np.full((96, 12), np.nan), J * 1e200):  # NaN, and J finite but JᵀJ overflowing to inf
        sol = solver.solve(bad, np.zeros(96), np.ones(96) * 0.01, u_max)
        assert not sol.ok and np.all(sol.u == 0)
    ok = solver.solve(J, np.zeros(96), np.ones(96) * 0.01, u_max)
    assert ok.ok and np.all(np.abs(ok.u) <= u_max + 1e-12)


@pytest.mark.parametrize("name", ["mpc", "ibvs", "ssvs"])
def test_controller_holds_with_a_reason_when_its_numerics_fail(name, monkeypatch):
    p = MethodParams()
    x0 = _ring()
    path = np.stack([x0 + [0, 0, 0.01 * k] for k in range(4)])
    poses = {"left": np.eye(4), "right": np.eye(4)}
    poses["left"][:3, 3] = [0, -0.1, 0.4]
    poses["right"][:3, 3] = [0, 0.1, 0.4]
    c = make_controller(name, p, 32)
    c.reset(x0, path, poses, dagger_index=2)

    def broken(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")

    # The exploration's least squares fails: the controller holds and says so, every tick after.
    monkeypatch.setattr("bagit.services.controller.broyden.np.linalg.lstsq", broken)
    t, out = 0.0, None
    for _ in range(c.exploration.total_ticks + 3):
        out = c.step(x0, t, poses, source_stamp=t)
        t += c.dt
        assert np.all(np.isfinite(out.u)) and np.all(np.abs(out.u) <= c.u_max + 1e-12)
    assert out.mode == "hold" and "Jacobian" in out.reason and "SVD did not converge" in out.reason
    assert np.all(out.u == 0)
    # With J learnt, a law that fails numerically holds too.
    monkeypatch.undo()
    c.reset(x0, path, poses, dagger_index=2)
    for _ in range(c.exploration.total_ticks + 1):
        out = c.step(x0, t, poses, source_stamp=t)
        t += c.dt
    monkeypatch.setattr(type(c), "_law", broken)
    out = c.step(x0, t, poses, source_stamp=t)
    assert out.mode == "hold" and f"the {name} law failed numerically" in out.reason and np.all(out.u == 0)


def test_planner_regularisation_rejects_degenerate_samples_and_the_plan_fails_with_a_reason(monkeypatch):
    with pytest.raises(NumericalFailure):
        space_mod.regularize(np.full((32, 3), np.nan), 0.002, 0.021)
    with pytest.raises(NumericalFailure):
        space_mod.regularize(np.zeros((32, 3)), 0.002, 0.021)  # all points at one place
    s = Scenario.from_file(find_scenario("exp02"))

    def broken(*a, **k):
        raise np.linalg.LinAlgError("SVD did not converge")

    monkeypatch.setattr(space_mod, "regularize", broken)
    r = plan_scenario(s, "cbirrt", 0)
    assert not r.success and "numerically" in r.reason and "SVD did not converge" in r.reason


@pytest.fixture(scope="module")
def coffee():
    return Scenario.from_file(find_scenario("exp01-coffee-box"))


@pytest.mark.slow
def test_sim_raises_simulation_failed_when_the_state_goes_non_finite(coffee):
    from bagit.services.sim.world import SimWorld

    w = SimWorld(coffee, camera=False)
    w.step(0.02)
    saved = w.save_state()
    w.data.qvel[:] = np.nan
    with pytest.raises(SimulationFailed, match="unstable"):
        w.step(0.02)
    assert w.failure and "BADQVEL" in w.failure
    with pytest.raises(SimulationFailed, match="failed earlier"):  # no stepping on from a broken world
        w.step(0.02)
    w.restore_state(saved)
    w.step(0.02)  # a snapshot from before is fine again
    assert np.all(np.isfinite(w.bag_vertices()))
    # a fabric flung off (finite but absurd: MuJoCo's own checks start at 1e10)
    w.data.qvel[:] = 0.0
    w.data.qpos[:] += 30.0  # every vertex 30 m off: the clamps yank it back and the solver overflows
    with pytest.raises(SimulationFailed):
        w.step(0.02)
    assert any(k in w.failure for k in ("away", "MuJoCo warned", "MuJoCo: mj_stackAlloc")), w.failure
    w.close()


@pytest.mark.slow
def test_a_run_reports_a_simulator_failure_with_stage_and_reason(monkeypatch):
    """The real run, with the physics made to blow up a few ticks into servoing: a result, not a crash."""
    from bagit.inprocess import RunOptions, run_inprocess
    from bagit.services.sim.world import SimWorld

    real_step = SimWorld.step

    def step(self, dt):
        if self.time > 1.2:  # settled (1 s), planned, then a few control ticks
            self.data.qvel[:] = np.nan
        return real_step(self, dt)

    monkeypatch.setattr(SimWorld, "step", step)
    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_inprocess(RunOptions(scenario=s, seed=0, time_limit_s=5.0))
    assert not r.success
    assert r.stage_reached == "pre-bagging" and r.reason.startswith("simulator: ") and "unstable" in r.reason
    assert 3 <= r.ticks <= 8 and r.truth is not None


@pytest.mark.slow
def test_a_run_that_takes_too_long_in_wall_time_is_stopped():
    from bagit.inprocess import RunOptions, run_inprocess

    s = Scenario.from_file(find_scenario("exp02-canned-pineapple"))
    r = run_inprocess(RunOptions(scenario=s, seed=0, time_limit_s=5.0, wall_limit_s=1e-6))
    # the limit is checked at every physics step: it passes inside the bag's first settling step, before any tick
    assert not r.success and r.ticks == 0 and r.stage_reached == "perceiving"
    assert r.reason.startswith("simulator: too slow") and "for 0.00 s simulated" in r.reason and "limit 1e-06 s" in r.reason


def test_the_wall_deadline_stops_a_long_step_at_its_first_physics_step(coffee):
    """A host's wall limit must not wait out a whole long step (MuJoCo's contact solver can crawl for seconds
    a physics step on a bunched-up stiff bag): past the deadline, step() stops at the physics step it is in."""
    import time

    from bagit.common.errors import WallLimitReached
    from bagit.services.sim.scene import TIMESTEP
    from bagit.services.sim.world import SimWorld

    w = SimWorld(coffee, seed=0, camera=False)
    w.step(2 * TIMESTEP)
    w.wall_deadline = time.perf_counter() - 1.0
    with pytest.raises(WallLimitReached, match="wall-time limit passed at t = 0.012 s"):
        w.step(1.0)
    assert w.time == pytest.approx(3 * TIMESTEP) and w.failure is None  # one physics step, and the world is not broken
    w.wall_deadline = None
    w.step(TIMESTEP)
    assert w.time == pytest.approx(4 * TIMESTEP)


def test_a_mujoco_fatal_error_is_a_simulation_failure(coffee, monkeypatch):
    """As seen on obstacles-a seed 4: `mj_stackAlloc: out of memory` from the IPC contact solver."""
    import mujoco

    from bagit.services.sim import world as world_mod

    w = world_mod.SimWorld(coffee, camera=False)

    def overflow(m, d):
        raise mujoco.FatalError("mj_stackAlloc: out of memory, stack overflow at ipc_efcPublish, line 536\n  max = 1")

    monkeypatch.setattr(world_mod.mujoco, "mj_step", overflow)
    with pytest.raises(SimulationFailed, match="mj_stackAlloc: out of memory"):
        w.step(0.02)
    assert "\n" not in w.failure
    w.close()


def test_a_flung_off_fabric_is_a_simulation_failure(coffee, monkeypatch):
    from bagit.services.sim import world as world_mod

    w = world_mod.SimWorld(coffee, camera=False)
    monkeypatch.setattr(world_mod, "FAR_M", 0.05)  # the start rim itself is farther than this from the origin
    with pytest.raises(SimulationFailed, match="flew"):
        w.step(0.004)
    w.close()
