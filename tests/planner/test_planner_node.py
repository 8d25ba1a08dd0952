"""The planner service on a loopback bus: run/control, run/state, goal and path, liveliness.

Perception and the controller are stood in for by a second in-process peer that publishes SOIs
and controller status; the planning itself is the real one.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from bus_support import wait_until
from test_planner_coordinator import sample_g0

from bagit.common.bus import Keys, LatestCache, Publisher, declare_alive, request_run_control
from bagit.common.messages import ClockTick, ControllerStatus, Goal, Path, RunControl, RunState, SoiState
from bagit.common.names import NO_SIM_CLOCK_YET
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.planner.coordinator import CoordinatorConfig
from bagit.services.planner.node import PlannerNode, PlannerServiceConfig


def _rig(pair_) -> Keys:
    a, _ = pair_
    return Keys(f"pn{abs(hash(str(a.zid()))) % 10**8}")


def test_a_run_over_the_bus_from_start_to_done(pair):
    a, b = pair
    keys = _rig(pair)
    states: list[RunState] = []
    lock = threading.Lock()
    cfg = PlannerServiceConfig(coordinator=CoordinatorConfig(settle_s=0.2, status_timeout_s=10), publish_hz=5)
    with PlannerNode(a, keys, cfg) as node:
        watch = LatestCache(b, keys.run_state, RunState, on_update=lambda s: (lock.acquire(), states.append(s), lock.release()))
        goal = LatestCache(b, keys.planner_goal, Goal)
        path = LatestCache(b, keys.planner_path, Path)
        tokens = [declare_alive(b, keys, s) for s in ("controller", "arm-driver", "perception")]
        soi_pub = Publisher(b, keys.perception_soi, SoiState)
        st_pub = Publisher(b, keys.controller_status, ControllerStatus)
        assert wait_until(lambda: watch.get() is not None), "no periodic run/state"
        rep = request_run_control(b, keys, RunControl(action="start", scenario="exp02", seed=1))
        assert rep.accepted and rep.run_id
        again = request_run_control(b, keys, RunControl(action="start", scenario="exp01"))
        assert not again.accepted and "in progress" in again.reason
        assert wait_until(lambda: (s := watch.get()) is not None and s.run_id == rep.run_id and s.stage == "perceiving")
        assert Scenario.from_dict(watch.get().scenario_doc).name == Scenario.from_file(find_scenario("exp02")).name
        g0 = sample_g0(Scenario.from_file(find_scenario("exp02")))
        # SOIs keep coming, as perception publishes them; the first fresh one becomes g0
        stop = threading.Event()

        def perceive() -> None:
            while not stop.wait(0.05):
                t = time.time()
                soi_pub.put(SoiState(rim=g0, source_stamp=t - 0.01))

        th = threading.Thread(target=perceive, daemon=True)
        th.start()
        try:
            assert wait_until(lambda: watch.get().stage == "pre-bagging"), watch.get()
            # goal and path were put before that state, but each key is called back on its own thread
            assert wait_until(lambda: goal.get() is not None and path.get() is not None)
            assert goal.get().run_id == rep.run_id
            p = path.get()
            assert p is not None and p.run_id == rep.run_id and p.nodes.shape[1:] == g0.shape
            assert np.allclose(p.nodes[0], g0)
            st_pub.put(ControllerStatus(run_id=rep.run_id, stage="bagging", progress=0.6))
            assert wait_until(lambda: watch.get().stage == "bagging" and watch.get().progress == pytest.approx(0.6))
            st_pub.put(ControllerStatus(run_id=rep.run_id, stage="bagging", progress=1.0, done=True, error_to_goal=0.005, seq=90, ticks=77))
            assert wait_until(lambda: watch.get().stage == "done")
        finally:
            stop.set()
            th.join()
        res = watch.get().result
        assert res["success"] and res["ticks"] == 77 and res["path_nodes"] == len(p.nodes)
        with lock:
            seen = [s.stage for s in states if s.run_id == rep.run_id]
        order = ["perceiving", "goal", "planning", "pre-bagging", "bagging", "done"]
        firsts = [seen.index(x) for x in order if x in seen]
        assert firsts == sorted(firsts) and {"perceiving", "pre-bagging", "bagging", "done"} <= set(seen)
        assert node.state.stage == "done"
        for t in tokens:
            t.undeclare()


def test_controller_death_fails_the_run_with_the_reason(pair):
    a, b = pair
    keys = _rig(pair)
    cfg = PlannerServiceConfig(coordinator=CoordinatorConfig(settle_s=0.0, status_timeout_s=30, perception_grace_s=60))
    with PlannerNode(a, keys, cfg):
        watch = LatestCache(b, keys.run_state, RunState)
        ctl = declare_alive(b, keys, "controller")
        drv = declare_alive(b, keys, "arm-driver")
        soi_pub = Publisher(b, keys.perception_soi, SoiState)
        rep = request_run_control(b, keys, RunControl(action="start", scenario="exp02"))
        assert rep.accepted
        g0 = sample_g0(Scenario.from_file(find_scenario("exp02")))
        assert wait_until(lambda: (soi_pub.put(SoiState(rim=g0)), watch.get() is not None and watch.get().stage == "pre-bagging")[1])
        ctl.undeclare()
        assert wait_until(lambda: watch.get().stage == "failed")
        assert "controller service is gone" in watch.get().reason
        drv.undeclare()
        # a stop with nothing running is refused; reset goes idle
        assert not request_run_control(b, keys, RunControl(action="stop")).accepted
        assert request_run_control(b, keys, RunControl(action="reset")).accepted
        assert wait_until(lambda: watch.get().stage == "idle")


def test_malformed_run_control_is_refused_not_fatal(pair):
    a, b = pair
    keys = _rig(pair)
    with PlannerNode(a, keys):
        rep = request_run_control(b, keys, RunControl(action="start", scenario_doc={"name": "bad", "object": {}}))
        assert not rep.accepted and "scenario_doc" in rep.reason
        replies = list(b.get(keys.run_control, payload=b"\x00garbage", timeout=3))
        assert replies and replies[0].ok is not None  # answered with a refusal, the node lives on
        assert request_run_control(b, keys, RunControl(action="reset")).accepted


def test_in_lockstep_a_start_before_the_simulators_first_tick_is_refused_then_accepted_after_it(pair):
    # A run started on a clock never heard would start at 0 and time out at the first tick (2**30 s on).
    a, b = pair
    keys = _rig(pair)
    with PlannerNode(a, keys, clock="sim") as node:
        tokens = [declare_alive(b, keys, s) for s in ("controller", "arm-driver", "perception", "sim")]
        rep = request_run_control(b, keys, RunControl(action="start", scenario="exp02"))
        assert not rep.accepted and rep.reason.startswith(NO_SIM_CLOCK_YET)
        with Publisher(b, keys.sim_clock, ClockTick) as clock:
            assert wait_until(lambda: clock.matched)
            clock.put(ClockTick(t=2.0**30, stamp=2.0**30))
            assert wait_until(lambda: node.clock() == 2.0**30)
            rep = request_run_control(b, keys, RunControl(action="start", scenario="exp02"))
            assert rep.accepted, rep.reason
        for t in tokens:
            t.undeclare()


def test_no_run_state_says_pre_bagging_before_the_path_is_out(pair):
    """The periodic run/state once went out between the plan's state change and the path's put (its
    encoding takes a while). Here the path's put is slowed on purpose and run/state republished
    often; the order is checked where it is made, at the publishers (a subscriber cannot see it:
    Zenoh calls each subscription back on its own thread)."""
    a, b = pair
    keys = _rig(pair)
    cfg = PlannerServiceConfig(coordinator=CoordinatorConfig(settle_s=0.0, status_timeout_s=10), publish_hz=50)
    sent: list[str] = []
    with PlannerNode(a, keys, cfg) as node:
        put_state, put_path = node._state_pub.put, node._path_pub.put

        def state(msg: RunState) -> int:
            sent.append(msg.stage)
            return put_state(msg)

        def slow_path(msg: Path) -> int:
            time.sleep(0.3)
            sent.append("path")
            return put_path(msg)

        node._state_pub.put, node._path_pub.put = state, slow_path
        tokens = [declare_alive(b, keys, s) for s in ("controller", "arm-driver", "perception")]
        soi_pub = Publisher(b, keys.perception_soi, SoiState)
        assert request_run_control(b, keys, RunControl(action="start", scenario="exp02", seed=1)).accepted
        g0 = sample_g0(Scenario.from_file(find_scenario("exp02")))
        assert wait_until(lambda: (soi_pub.put(SoiState(rim=g0, source_stamp=time.time())), "pre-bagging" in sent)[1])
        assert "path" in sent and sent.index("path") < sent.index("pre-bagging"), sent
        for t in tokens:
            t.undeclare()
