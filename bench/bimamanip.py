"""`bagit bench bimamanip`: the BimaManip baseline's learned SOI dynamics (services/controller/soi_gnn.py),
its training data made in the simulator, its training, and its error on held-out transitions.

    bagit bench bimamanip            # the versioned model's one-step error on freshly simulated held-out episodes
    bagit bench bimamanip --train    # generate the data, train, and write the weights and their record
    bagit bench bimamanip --quick    # a tiny data set and a few epochs, written under bench/results/quick/

Data: episodes in `SimWorld` (exp01's bag and object, no camera, no arms: the mounts are moved
directly, at most C7 per tick) from the bag's hung start. A transition is (x_t, grippers_t, u_t,
x_{t+1}) over one model step (MODEL_TICKS ticks): x the true rim resampled to the scenario's n_x points,
what perception's SOI estimates (~5 mm from it, mostly the binding's radius: an offset that changes
little between frames, bench/results/camera-modes.md), without rendering a frame per step (rendering
and perception cost many times the physics); the training jitters x by 0.5 mm instead. The mounts follow a random look-alike of the task:
beside the object at the start height, then under it, then up round it (the goal shapes BimaManip is
asked for), at random speeds with independent noise on each arm and random changes of their
separation within C6, so that the data covers the motions the MPC can choose. Held-out episodes come
from another seed. The data is not kept: its generation parameters and seed rebuild it bit for bit.
"""

from __future__ import annotations

import logging
import os
import socket
import time
from dataclasses import asdict, dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.common import RESULTS_DIR
from bagit.common.errors import SimulationFailed
from bagit.common.results import provenance
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.controller.servo import MIN_SEPARATION_M, SEPARATION_MARGIN

log = logging.getLogger("bagit.bench.bimamanip")


@dataclass(frozen=True)
class DataSpec:
    """How the transitions are simulated (all recorded beside the weights)."""

    scenario: str = "exp01"
    episodes: int = 36
    heldout_episodes: int = 8
    steps: int = 60  # model steps per episode (10 s simulated)
    seed: int = 0  # the training episodes'; the held-out ones use seed + HELDOUT_SEED_OFFSET
    speed_range: tuple[float, float] = (0.3, 1.0)  # the mounts' drift towards a waypoint, a share of C7
    noise: float = 0.3  # each arm's own motion noise (AR(1), a share of C7 per axis)
    lateral_m: tuple[float, float] = (-0.03, 0.18)  # waypoints beside the object: x from its centre
    below_m: tuple[float, float] = (0.015, 0.06)  # ... this far below its bottom
    lift_m: tuple[float, float] = (0.0, 0.10)  # the lift: this far above its bottom, on its axis (within AXIS_M)
    lift_share: float = 0.6  # the share of episodes that go under the object and lift


HELDOUT_SEED_OFFSET = 1000
AXIS_M = 0.02
REACHED_M = 0.01


@dataclass(frozen=True)
class TrainSpec:
    seed: int = 0
    epochs: int = 40
    batch: int = 64
    lr: float = 2e-3
    noise_m: float = 5e-4  # perception-like jitter on the input SOI


QUICK_DATA = DataSpec(episodes=3, heldout_episodes=1, steps=12)
QUICK_TRAIN = TrainSpec(epochs=2)


def step_limit(sc: Scenario) -> float:
    """The largest translation of a mount per axis over one model step (m): C7 over MODEL_TICKS ticks."""
    from bagit.services.controller.soi_gnn import MODEL_TICKS

    c = sc.params.controller
    return MODEL_TICKS * c.max_linear_speed_mps / c.control_rate_hz


def _waypoints(rng: np.random.Generator, spec: DataSpec, centre: np.ndarray, bottom: float) -> list[np.ndarray]:
    """Where the mounts' midpoint goes in one episode: beside (and below) the object, then perhaps under it and up."""
    def beside() -> np.ndarray:
        return np.array([centre[0] + rng.uniform(*spec.lateral_m), centre[1] + rng.uniform(-0.04, 0.04), bottom - rng.uniform(*spec.below_m)])

    pts = [beside()]
    if rng.random() < spec.lift_share:
        under = np.array([centre[0] + rng.uniform(-AXIS_M, AXIS_M), centre[1] + rng.uniform(-AXIS_M, AXIS_M), bottom - rng.uniform(*spec.below_m)])
        pts += [under, np.array([under[0], under[1], bottom + rng.uniform(*spec.lift_m)])]
    else:
        pts.append(beside())
    return pts


def simulate(spec: DataSpec, seed: int, episodes: int) -> Any:
    """`episodes` episodes of transitions (soi_gnn.Transitions) from the scenario's hung bag, drawn with `seed`."""
    from bagit.services.controller.soi_gnn import MODEL_TICKS, Transitions
    from bagit.services.sim.rig_sim import SETTLE_S
    from bagit.services.sim.world import SimWorld

    sc = Scenario.from_file(find_scenario(spec.scenario))
    params = sc.params.controller
    dt = MODEL_TICKS / params.control_rate_hz
    a_max = step_limit(sc)
    V = sc.object.bottom_vertices()
    centre, bottom = V.mean(axis=0), float(V[:, 2].min())
    rng = np.random.default_rng(seed)
    world = SimWorld(sc, seed=0, camera=False)
    world.step(SETTLE_S)
    start = world.save_state()
    perimeter = float(np.sum(np.linalg.norm(np.diff(np.vstack([world.true_rim(), world.true_rim()[:1]]), axis=0), axis=1)))
    sep_band = (MIN_SEPARATION_M, SEPARATION_MARGIN * perimeter / 2)
    xs, gs, us, xn = [], [], [], []
    for ep in range(episodes):
        world.restore_state(start)
        poses = world.mount_poses()
        sep0 = float(np.linalg.norm(poses["right"][:3, 3] - poses["left"][:3, 3]))
        sep_goal = float(np.clip(sep0 * rng.uniform(0.8, 1.15), *sep_band))
        speed = rng.uniform(*spec.speed_range) * a_max
        route = _waypoints(rng, spec, centre, bottom)
        noise = np.zeros((2, 3))
        kept = 0
        for _ in range(spec.steps):
            poses = world.mount_poses()
            pl, pr = poses["left"][:3, 3], poses["right"][:3, 3]
            mid, sep = 0.5 * (pl + pr), float(np.linalg.norm(pr - pl))
            if len(route) > 1 and np.linalg.norm(route[0] - mid) < REACHED_M:
                route.pop(0)
            drift = route[0] - mid
            drift *= min(1.0, speed / max(float(np.abs(drift).max()), 1e-9))
            axis = (pr - pl) / max(sep, 1e-9)
            spread = 0.5 * float(np.clip(sep_goal - sep, -speed, speed)) * axis
            noise = 0.6 * noise + 0.8 * rng.normal(0.0, spec.noise * a_max, (2, 3))
            a = np.clip(np.stack([drift - spread, drift + spread]) + noise, -a_max, a_max)
            x0 = world.true_rim(sc.bag.n_x)
            targets = {k: T.copy() for k, T in poses.items()}
            targets["left"][:3, 3] += a[0]
            targets["right"][:3, 3] += a[1]
            world.set_mount_targets(targets)
            try:
                world.step(dt)
            except SimulationFailed as e:
                log.warning("episode %d: %s; its last step dropped", ep, e)
                break
            after = world.mount_poses()
            u = np.zeros(12)
            u[0:3], u[6:9] = after["left"][:3, 3] - pl, after["right"][:3, 3] - pr
            xs.append(x0)
            gs.append(np.stack([pl, pr]))
            us.append(u)
            xn.append(world.true_rim(sc.bag.n_x))
            kept += 1
        log.info("episode %d/%d: %d transitions", ep + 1, episodes, kept)
    world.close()
    return Transitions(np.array(xs), np.array(gs), np.array(us), np.array(xn))


def run(train: bool = False, quick: bool = False, out_dir: Path | None = None) -> dict[str, Any]:
    """Train (`train`) or evaluate the model; see the module docstring. Returns the record."""
    from bagit.services.controller import soi_gnn

    data_spec, train_spec = (QUICK_DATA, QUICK_TRAIN) if quick else (DataSpec(), TrainSpec())
    t0 = time.perf_counter()
    heldout = simulate(data_spec, data_spec.seed + HELDOUT_SEED_OFFSET, data_spec.heldout_episodes)
    if not train:
        model = soi_gnn.load()
        err = soi_gnn.prediction_error_mm(model, heldout)
        return {"kind": "bimamanip-eval", "heldout_transitions": len(heldout.x), "heldout_error": err,
                "weights": str(soi_gnn.WEIGHTS_FILE), "wall_s": round(time.perf_counter() - t0, 1)}
    data = simulate(data_spec, data_spec.seed, data_spec.episodes)
    t_data = time.perf_counter() - t0
    log.info("%d training and %d held-out transitions in %.0f s; training ...", len(data.x), len(heldout.x), t_data)
    t1 = time.perf_counter()
    model, losses = soi_gnn.train(data, seed=train_spec.seed, epochs=train_spec.epochs, batch=train_spec.batch,
                                  lr=train_spec.lr, noise_m=train_spec.noise_m, log=log)
    t_train = time.perf_counter() - t1
    prov = provenance()
    record: dict[str, Any] = {
        "kind": "bimamanip-train",
        "model": "SOI graph network (soi_gnn.SoiGnn): rim points and the two grippers as nodes, ring and gripper edges",
        "data": {**asdict(data_spec), "transitions": len(data.x), "heldout_transitions": len(heldout.x),
                 "model_ticks": soi_gnn.MODEL_TICKS, "soi": "the true rim resampled to n_x (SimWorld.true_rim)"},
        "training": {**asdict(train_spec), "losses_cm2": [round(v, 5) for v in losses]},
        "train_error": soi_gnn.prediction_error_mm(model, data),
        "heldout_error": soi_gnn.prediction_error_mm(model, heldout),
        "wall_s": {"data": round(t_data, 1), "train": round(t_train, 1)},
        "commit": prov.commit, "dirty": prov.dirty, "host": socket.gethostname(), "date": prov.date,
        "libraries": {k: version(k) for k in ("jax", "jaxlib", "equinox", "optax", "mujoco", "numpy")},
        "load": [round(v, 2) for v in os.getloadavg()],
    }
    if quick:
        folder = (out_dir or RESULTS_DIR) / "quick"
        soi_gnn.save(model, record, folder / "bimamanip.eqx", folder / "bimamanip.json")
        record["files"] = [str(folder / "bimamanip.eqx"), str(folder / "bimamanip.json")]
    else:
        soi_gnn.save(model, record)
        record["files"] = [str(soi_gnn.WEIGHTS_FILE), str(soi_gnn.RECORD_FILE)]
    return record

