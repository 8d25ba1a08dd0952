"""The dashboard on Zenoh (loopback peers): it receives the rig's keys, its buttons reach
run/control and estop, liveliness shows in its health panel; and `bagit dashboard` itself."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from dashboard_support import scene_messages, wait_until

from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, declare_alive, locators, open_session, serve_run_control
from bagit.common.messages import ArmState, ControllerStatus, EStop, PointCloud, RunControl, RunControlReply, RunState, SoiState
from bagit.common.names import ESTOP_RELEASE_SOURCES, ESTOP_SOURCE_DASHBOARD
from bagit.dashboard.node import DashboardNode
from bagit.dashboard.server import DashboardConfig


@pytest.fixture
def rig_peer(request):
    rig = "d" + "".join(c for c in request.node.name if c.isalnum())[-40:]
    s = open_session(BusConfig(rig=rig, adminspace=True))
    try:
        yield rig, s
    finally:
        s.close()


def test_node_feeds_the_dashboard_and_drives_the_rig(rig_peer):
    rig, peer = rig_peer
    keys = Keys(rig)
    requests: list[RunControl] = []

    def coordinator(req: RunControl) -> RunControlReply:
        requests.append(req)
        return RunControlReply(accepted=True, run_id="run-42" if req.action == "start" else None)

    server = serve_run_control(peer, keys, coordinator)
    estops: list[EStop] = []
    estop_sub = Subscriber(peer, keys.estop, EStop, estops.append)
    node = DashboardNode(BusConfig(rig=rig, connect=locators(peer)), DashboardConfig(port=0, draw_without_viewers=True), query_timeout_s=3.0)
    try:
        d = node.dashboard
        assert wait_until(lambda: len(list(peer.info.peers_zid())) == 1)
        # the dashboard announces itself
        assert wait_until(lambda: d.health.is_up("dashboard") is True)
        m = scene_messages()
        pubs = {
            "soi": Publisher(peer, keys.perception_soi, SoiState),
            "arm": Publisher(peer, keys.arm_state("left"), ArmState),
            "status": Publisher(peer, keys.controller_status, ControllerStatus),
            "run": Publisher(peer, keys.run_state, RunState),
            "cloud": Publisher(peer, keys.perception_cloud, PointCloud),  # drawn without viewers: watched
        }
        assert wait_until(lambda: all(p.matched for p in pubs.values()))
        pubs["soi"].put(m["soi"])
        pubs["arm"].put(m["left"])
        pubs["status"].put(ControllerStatus(run_id="run-42", subgoal_index=2, error_to_subgoal=0.01, error_to_goal=0.02))
        pubs["run"].put(RunState(run_id="run-42", scenario="exp01-coffee-box", stage="bagging", progress=0.5))
        assert wait_until(lambda: "soi" in d.scene.summary and "arm:left" in d.scene.summary)
        assert np.allclose(d.scene.node("/soi/points").points, m["soi"].rim, atol=1e-6)
        assert wait_until(lambda: "bagging" in d.panel.status_md.content)
        assert len(d.errors) == 1
        # Start, Stop and Reset are run/control queries; E-STOP is a put on estop
        reply = d.panel.press_start()
        assert reply.accepted and reply.run_id == "run-42"
        assert requests[-1].action == "start" and requests[-1].scenario == d.panel.picker.value
        d.panel.press_stop()
        d.panel.press_reset()
        assert [r.action for r in requests] == ["start", "stop", "reset"]
        d.panel.press_estop()
        assert wait_until(lambda: len(estops) == 1)
        assert estops[0].engage and estops[0].source == ESTOP_SOURCE_DASHBOARD  # a name the arm driver takes a release from
        assert ESTOP_SOURCE_DASHBOARD in ESTOP_RELEASE_SOURCES
        # its own e-stop comes back on the bus and is shown
        assert wait_until(lambda: "E-STOP ENGAGED" in d.panel.status_markdown())
        # liveliness: a service appears, then dies
        token = declare_alive(peer, keys, "perception")
        assert wait_until(lambda: d.health.is_up("perception") is True)
        token.undeclare()
        assert wait_until(lambda: d.health.is_up("perception") is False)
        assert any("perception went away" in w for w in d.health.warnings())
        for p in pubs.values():
            p.close()
    finally:
        node.close()
        estop_sub.close()
        server.close()


def test_start_without_a_coordinator_says_so_and_nobody_watching_takes_only_the_plots_streams(rig_peer):
    rig, peer = rig_peer
    keys = Keys(rig)
    node = DashboardNode(BusConfig(rig=rig, connect=locators(peer)), DashboardConfig(port=0), query_timeout_s=0.5)
    watched = [Publisher(peer, keys.perception_soi, SoiState), Publisher(peer, keys.perception_cloud, PointCloud),
               Publisher(peer, keys.arm_state("right"), ArmState)]
    followed = [Publisher(peer, keys.controller_status, ControllerStatus), Publisher(peer, keys.run_state, RunState)]
    try:
        assert node.dashboard.panel.press_start() is None
        assert "nobody serves it" in node.dashboard.panel.message_md.content
        # with no browser connected the dashboard follows the plots' and the run's streams, but takes neither the
        # SOI, the arms' states nor the display cloud (so perception makes none)
        assert wait_until(lambda: all(p.matched for p in followed))
        assert not any(p.matched for p in watched)
        node.dashboard.config.draw_without_viewers = True  # as a browser connecting does
        node._follow_viewers()
        assert wait_until(lambda: all(p.matched for p in watched))
        node.dashboard.config.draw_without_viewers = False  # and as its leaving does
        node._follow_viewers()
        assert wait_until(lambda: not any(p.matched for p in watched))
    finally:
        for p in watched + followed:
            p.close()
        node.close()


@pytest.mark.slow
@pytest.mark.processes
def test_cli_serves_on_loopback_and_stops(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "bagit.cli", "dashboard", "--port", "0", "--duration", "1.5", "--rig", "clitest", "--json"],
        capture_output=True, text=True, timeout=60,
    )
    assert out.returncode == 0, out.stderr
    r = json.loads(out.stdout)  # viser's banner does not pollute --json
    assert r["success"] and r["url"].startswith("http://127.0.0.1:") and r["rig"] == "clitest"


@pytest.mark.slow
@pytest.mark.processes
@pytest.mark.parametrize(
    "args,msg",
    [(["--port", "70000"], "--port"), (["--duration", "-1"], "--duration"), (["--rig", "bad rig"], "rig name"),
     (["--rig-config", "/nonexistent.yaml"], "cannot read rig config")],
)
def test_cli_rejects_bad_flags_in_one_line(args, msg):
    out = subprocess.run([sys.executable, "-m", "bagit.cli", "dashboard", *args], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert msg in out.stderr and out.stderr.strip().count("\n") == 0, out.stderr
