"""The Dashboard's scene fed with messages in-process: what gets drawn, where, and what is refused."""

from __future__ import annotations

import numpy as np
import pytest
from dashboard_support import FakeRunLink, arm_state, feed_scene, planned_exp01, synthetic_cloud, wait_until

from bagit.common.messages import ArmState, CameraInfo, Command, ControllerStatus, Path, PointCloud, SoiState
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario
from bagit.dashboard import Dashboard, DashboardConfig, style
from bagit.dashboard.scene import LAYERS, MAX_FAN_RIMS
from bagit.scenarios import find_scenario


@pytest.fixture
def dash():
    d = Dashboard(FakeRunLink(), DashboardConfig(port=0, max_cloud_points=2000), start=False)
    try:
        yield d
    finally:
        d.close()


def test_binds_loopback_by_default(dash):
    assert DashboardConfig().host == "127.0.0.1"
    assert dash.server.get_host() == "127.0.0.1"
    assert dash.url.startswith("http://127.0.0.1:")


def test_cloud_soi_goal_path_and_arms_are_drawn(dash):
    m = feed_scene(dash)
    dash.flush()
    sc = dash.scene
    # the cloud, down-sampled to the cap, in its own colours
    cloud = sc.node("/cloud/points")
    assert len(cloud.points) == 2000 and sc.summary["cloud"]["n_received"] == 6000
    assert np.all(cloud.colors == np.array((0, 200, 0), np.uint8))
    # the SOI as points and a closed curve through them
    soi = sc.node("/soi/points")
    assert np.allclose(soi.points, m["soi"].rim, atol=1e-6)
    curve = sc.node("/soi/curve").points
    assert curve.shape == (32, 2, 3) and np.allclose(curve[-1, 1], m["soi"].rim[0], atol=1e-6)
    # the bagging ellipse lies in F_m's xy plane around g†'s centre
    goal = m["goal"]
    ell = sc.node("/goal/ellipse").points[:, 0].astype(float)
    local = (ell - goal.frame[:3, 3]) @ goal.frame[:3, :3]
    assert np.allclose(local[:, 2], 0.0, atol=1e-5)
    assert np.allclose(sc.node("/goal/g_star").points[:, 0], goal.g_star, atol=1e-6)
    # the path fan: every rim closed, orange first, red last, all faded toward white
    path = m["path"]
    fan = sc.node("/path/fan")
    n_nodes, n_x = path.nodes.shape[:2]
    assert fan.points.shape == (min(n_nodes, MAX_FAN_RIMS) * n_x, 2, 3)
    first, last = fan.colors[0, 0].astype(int), fan.colors[-1, 0].astype(int)
    assert np.array_equal(first, style.fade(style.ORANGE[None], 0.45)[0])
    assert np.array_equal(last, style.fade(style.RED[None], 0.45)[0])
    # V and the object's meshes (the picker shows the first bundled scenario, exp01)
    assert sc.node("/object/V") is not None and len(sc.node("/object/V").points) == 4
    assert sc.summary["scenario"]["name"] == "coffee-box"
    # both arms, from their joint angles: the last link ends at the measured gripper frame
    rig = RigConfig()
    for arm in ("left", "right"):
        end = sc.summary[f"arm:{arm}"]["flange"]
        assert np.allclose(end, m[arm].tool_pose[:3], atol=1e-9)
        assert np.allclose(sc.node(f"/grippers/{arm}/measured").position, m[arm].tool_pose[:3])
        assert sc.node(f"/arms/{arm}/link0").visible
        assert np.allclose(sc.node(f"/arms/{arm}/joint0").position, rig.arms[arm].base_position)


def test_subgoal_highlight_follows_the_controller(dash):
    m = feed_scene(dash)
    for i in (3, 7):
        dash.on_controller_status(ControllerStatus(subgoal_index=i, error_to_subgoal=0.01, error_to_goal=0.03))
        dash.flush()
        hl = dash.scene.node("/path/subgoal")
        assert np.allclose(hl.points[:, 0], m["path"].nodes[i], atol=1e-6)
        assert np.all(hl.colors == np.array(style.SUBGOAL, np.uint8))
    # an index past the end clamps to g*
    dash.on_controller_status(ControllerStatus(subgoal_index=10_000))
    dash.flush()
    assert np.allclose(dash.scene.node("/path/subgoal").points[:, 0], m["path"].nodes[-1], atol=1e-6)
    # a failed plan clears the fan and the highlight
    dash.on_path(Path(success=False, nodes=np.zeros((0, 1, 3)), dagger_index=0))
    dash.flush()
    assert not dash.scene.node("/path/fan").visible and not dash.scene.node("/path/subgoal").visible


def test_commanded_frames_are_the_measured_poses_moved_by_u(dash):
    left = arm_state("left")
    dash.on_arm_state(left)
    dash.on_command(Command(u=np.r_[0.01, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.02, 0.0, 0.0, 0.0, 0.0]))
    dash.flush()
    assert np.allclose(dash.scene.node("/grippers/left/commanded").position, left.tool_pose[:3] + [0.01, 0, 0])
    assert dash.scene.summary["command"]["arms"] == ["left"]  # the right arm has no measured pose yet
    assert not dash.scene.node("/grippers/right/commanded").visible


def test_layers_toggle_and_the_view_resets(dash):
    for layer in LAYERS:
        dash.panel.layer_boxes[layer].value = False
        assert dash.scene.layers[layer].visible is False
        dash.panel.layer_boxes[layer].value = True
        assert dash.scene.layers[layer].visible is True
    dash.scene.reset_view()
    assert np.allclose(dash.server.initial_camera.look_at, (0.1, 0.0, 0.4))


def test_bad_input_is_dropped_not_drawn(dash):
    # non-finite cloud points are dropped; an empty cloud hides the layer
    pts = np.array([[0, 0, 0.5], [np.nan, 0, 0], [0.1, np.inf, 0.2]], dtype=np.float32)
    dash.on_cloud(PointCloud(points=pts, colors=np.zeros((3, 3), np.uint8)))
    dash.flush()
    assert len(dash.scene.node("/cloud/points").points) == 1
    assert dash.scene.summary["cloud"]["dropped_nonfinite"] == 2
    dash.on_cloud(PointCloud(points=np.zeros((0, 3), np.float32)))
    dash.flush()
    assert not dash.scene.node("/cloud/points").visible
    # colours of the wrong length fall back to the height ramp
    dash.on_cloud(PointCloud(points=np.zeros((5, 3), np.float32), colors=np.zeros((2, 3), np.uint8)))
    dash.flush()
    assert len(dash.scene.node("/cloud/points").colors) == 5
    # a NaN joint angle is refused (counted), the previous pose stays
    dash.on_arm_state(arm_state("left"))
    dash.flush()
    before = np.array(dash.scene.node("/arms/left/joint6").position)
    dash.on_arm_state(ArmState(arm="left", q=np.full(6, np.nan), qd=np.zeros(6), tool_pose=np.zeros(6)))
    dash.flush()
    assert dash.stats()["render_errors"]["arm:left"] == 1
    assert np.allclose(dash.scene.node("/arms/left/joint6").position, before)
    # a path of NaNs is not drawn
    dash.on_path(Path(nodes=np.full((3, 8, 3), np.nan), dagger_index=1))
    dash.flush()
    assert dash.scene.summary["path"]["n_nodes"] == 0


def test_scenarios_with_obstacles_and_without_shape(dash):
    s = Scenario.from_file(find_scenario("obstacles-a-coffee-box"))
    dash.show_scenario(s)
    dash.flush()
    assert dash.scene.summary["scenario"]["n_obstacles"] == len(s.obstacles) >= 1
    assert dash.scene.layers["obstacles"] is not None
    # only V known: V is extruded by the default height
    bare = Scenario.from_text("name: bare\nobject: {vertices: [[0,0,0.5],[0.1,0,0.5],[0.1,0.1,0.5],[0,0.1,0.5]]}")
    dash.show_scenario(bare)
    dash.flush()
    assert dash.scene.summary["scenario"] == {"name": "bare", "n_obstacles": 0, "n_v": 4}
    assert len(dash.scene._object_nodes) == 1  # the old meshes were removed


def test_running_scenario_is_shown_by_name(dash):
    from bagit.common.messages import RunState

    dash.on_run_state(RunState(run_id="x", scenario="grapefruit", stage="planning"))  # the `name:`, not the file
    dash.flush()
    assert dash.scene.summary["scenario"]["name"] == "grapefruit"
    dash.on_run_state(RunState(run_id="y", scenario="exp02-canned-pineapple", stage="planning"))
    dash.flush()
    assert dash.scene.summary["scenario"]["name"] == "canned-pineapple"
    # a preview picked during the run is not overwritten by the run's periodic states
    dash.panel.select_scenario("exp05-tea-caddy")
    dash.on_run_state(RunState(run_id="y", scenario="exp02-canned-pineapple", stage="bagging"))
    dash.flush()
    assert dash.scene.summary["scenario"]["name"] == "tea-caddy"


def test_camera_frustum_from_camera_info(dash):
    T = np.eye(4)
    T[:3, 3] = [0.2, 0.3, 1.5]
    dash.on_camera_info(CameraInfo(width=640, height=480, fy=400.0, T_world_camera=T.tolist()))
    dash.flush()
    assert dash.scene.summary["camera"]["position"] == [0.2, 0.3, 1.5]
    assert dash.scene.summary["camera"]["fov"] == pytest.approx(2 * np.arctan(240 / 400))


def test_render_thread_rate_limits_a_burst(dash):
    """A burst of 300 SOIs in one go is drawn a few times, latest last, and nothing queues up."""
    rim = planned_exp01().path[0]
    dash.config.draw_without_viewers = True  # no browser here: the live layers would wait for one
    dash.start()
    for i in range(300):
        dash.on_soi(SoiState(rim=rim + [0, 0, 0.0001 * i], seq=i))
    assert wait_until(lambda: dash.scene.summary.get("soi", {}).get("seq") == 299)
    st = dash.stats()["slots"]["soi"]
    assert st["received"] == 300 and st["taken"] < 30 and st["coalesced"] >= 270
    dash.on_cloud(synthetic_cloud(rim, 100_000))
    assert wait_until(lambda: dash.scene.summary.get("cloud", {}).get("n_received") == 100_000)  # how fast: bench/dashboard.py


def test_with_no_browser_the_live_layers_wait_and_the_first_browser_gets_the_newest(dash):
    """No viewer: the cloud, SOI, arms and command stay in their latest-wins slots (no CPU spent on
    them), the plan is drawn; once a browser is connected the newest live messages are drawn."""
    m = feed_scene(dash)
    assert not dash.server.get_clients()
    dash.render_once()
    sc = dash.scene
    assert sc.node("/cloud/points") is None and sc.node("/soi/points") is None and "arm:left" not in sc.summary
    assert sc.node("/path/fan") is not None  # the plan is drawn whoever watches
    dash._held = lambda: ()  # a browser connected (what get_clients() would say)
    dash.render_once()
    assert np.allclose(sc.node("/soi/points").points, m["soi"].rim, atol=1e-6) and "arm:left" in sc.summary


def test_draw_without_viewers_draws_the_live_layers_anyway():
    d = Dashboard(FakeRunLink(), DashboardConfig(port=0, max_cloud_points=2000, draw_without_viewers=True), start=False)
    try:
        m = feed_scene(d)
        d.render_once()
        assert np.allclose(d.scene.node("/soi/points").points, m["soi"].rim, atol=1e-6)
    finally:
        d.close()
