"""The simulator node on a loopback bus: wall-stamped frames on camera/rgbd, ground truth on
sim/truth, and the world reset to a new run's scenario as run/state announces it."""

from __future__ import annotations

import threading
import time

import numpy as np
from bus_support import wait_until

from bagit.common.bus import Keys, LatestCache, Publisher
from bagit.common.messages import RgbdFrame, RunState, SimTruth
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.sim.node import SimNode, SimNodeConfig
from bagit.services.sim.rig_sim import SimRig


def test_frames_truth_and_reset_between_runs(pair):
    a, b = pair
    keys = Keys("simnode")
    first = Scenario.from_file(find_scenario("exp02"))
    second = Scenario.from_file(find_scenario("exp01"))
    said: list[str] = []
    with SimRig(first, with_servers=False) as rig:
        q_before = {n: arm.q for n, arm in rig.arms.items()}
        node = SimNode(a, keys, rig, SimNodeConfig(fps=10, speed=1.0, settle_s=0.3, truth_hz=5), first.name, say=said.append)
        frames = LatestCache(b, keys.camera_rgbd, RgbdFrame)
        truth = LatestCache(b, keys.sim_truth, SimTruth)
        stop = threading.Event()
        th = threading.Thread(target=node.run, args=(stop,), daemon=True)
        th.start()
        try:
            f = frames.wait(20)
            assert f is not None and f.color.shape == (480, 640, 3) and f.depth.shape == (480, 640)
            assert abs(f.stamp - time.time()) < 3600  # wall clock, not simulated time
            assert wait_until(lambda: truth.get() is not None and truth.get().scenario == first.name, 10)
            state_pub = Publisher(b, keys.run_state, RunState)
            doc = second.model_dump(mode="json", exclude_none=True)
            t_sent = time.time()
            state_pub.put(RunState(run_id="run-2", stage="perceiving", scenario="exp01", scenario_doc=doc, seed=1))
            assert wait_until(lambda: node.stats.resets == 1, 20), said
            assert node.run_id == "run-2"
            # every frame from now on shows the new world: stamped after the reset announcement
            f2 = frames.wait(20, newer_than=time.monotonic())
            assert f2 is not None and f2.stamp > t_sent
            assert wait_until(lambda: truth.get().run_id == "run-2" and truth.get().scenario == "exp01", 10)
            assert not np.allclose(truth.get().rim.mean(0), 0)
            # the arms were re-placed at the new world's start, and the same state again resets nothing
            moved = any(not np.allclose(q_before[n], arm.q) for n, arm in rig.arms.items())
            assert moved or np.allclose(first.object.bottom_vertices(), second.object.bottom_vertices())
            state_pub.put(RunState(run_id="run-2", stage="perceiving", scenario="exp01", scenario_doc=doc, seed=1))
            time.sleep(0.3)
            assert node.stats.resets == 1
            # a scenario the world cannot be built from pauses the camera with the reason
            bad = dict(doc, bag={**doc.get("bag", {}), "depth": 1.9})  # hangs through the table
            state_pub.put(RunState(run_id="run-3", stage="perceiving", scenario="bad", scenario_doc=bad))
            assert wait_until(lambda: any("cannot build" in s for s in said), 20), said
            n = node.stats.frames
            time.sleep(0.5)
            assert node.stats.frames == n
        finally:
            stop.set()
            th.join(10)
            node.close()
    assert any("world reset to exp01" in s for s in said)
