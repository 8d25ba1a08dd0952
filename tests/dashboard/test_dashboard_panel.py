"""The panel's behaviour with a recording RunLink: start/stop/reset, E-STOP, uploads, parameters,
run state, plots, health and history."""

from __future__ import annotations

import asyncio
import threading

import numpy as np
import pytest
from dashboard_support import FakeRunLink, arm_state, feed_run, wait_until
from suite_support import HANG_S

from bagit.common.errors import BusError
from bagit.common.messages import ControllerStatus, EStop, RunControlReply, RunState
from bagit.dashboard import Dashboard, DashboardConfig
from bagit.dashboard.panel import ESTOP_REASON, UPLOAD_PREFIX
from bagit.scenarios import find_scenario


@pytest.fixture
def link():
    return FakeRunLink()


@pytest.fixture
def dash(link):
    d = Dashboard(link, DashboardConfig(port=0), start=False)
    try:
        yield d
    finally:
        d.close()


def test_start_sends_the_picked_scenario_with_only_the_changed_params(dash, link):
    p = dash.panel
    p.select_scenario("exp03-grapefruit")
    assert p.picker.value == "exp03-grapefruit"
    reply = p.press_start()
    assert reply.accepted and link.named("start")[-1][1:3] == ("exp03-grapefruit", {})
    p.param_inputs["horizon"].value = 14
    p.param_inputs["lambda_1"].value = 0.9
    assert "horizon = 14" in p.params_md.content
    p.press_start()
    assert link.named("start")[-1][2] == {"horizon": 14, "lambda_1": 0.9}
    # the run's record shows the parameters it was started with
    rec = dash.history.get("run-002")
    assert rec.params == {"horizon": 14, "lambda_1": 0.9} and rec.scenario == "exp03-grapefruit"
    dash.flush()
    assert "horizon=14" in p.history_md.content and "run-002" in p.history_md.content
    # back to the scenario's values: nothing is overridden
    p._fill_params(p._base)
    p.press_start()
    assert link.named("start")[-1][2] == {}
    assert link.named("start")[-1][3] is None  # the controller left to the rig ...
    p.controller_pick.value = "autobag"
    p.press_start()
    assert link.named("start")[-1][3] == "autobag"  # ... or the one picked


def test_invalid_params_block_start_with_the_reason(dash, link):
    p = dash.panel
    p.param_inputs["lambda_1"].value = 1.2
    assert "lambda_1" in p.params_md.content and "Invalid" in p.params_md.content
    assert p.press_start() is None
    assert link.named("start") == []
    assert "lambda_1" in p.message_md.content
    p.param_inputs["lambda_1"].value = 0.9
    assert p.press_start().accepted


def test_lambda_d_auto_sends_none_and_a_value_when_unticked(dash, link):
    p = dash.panel
    p.select_scenario("exp01-coffee-box")
    assert p.lambda_d_auto.value is True and p.param_inputs["lambda_d"].disabled
    p.lambda_d_auto.value = False
    p.param_inputs["lambda_d"].value = 0.06
    p.press_start()
    assert link.named("start")[-1][2] == {"lambda_d": 0.06}


def test_refused_and_failed_starts_are_shown(dash, link):
    link.accept, link.reason = False, "a run is already going"
    assert not dash.panel.press_start().accepted
    assert "a run is already going" in dash.panel.message_md.content
    link.accept, link.fail_with = True, BusError("no answer on bagit/default/run/control within 5 s")
    assert dash.panel.press_start() is None
    assert "no answer" in dash.panel.message_md.content
    assert dash.history.records() == []


def test_stop_and_reset(dash, link):
    feed_run(dash, "r9", "exp01-coffee-box", "bagging", 0.5)
    assert len(dash.errors) == 10
    assert dash.panel.press_stop().accepted
    assert dash.panel.press_reset().accepted
    assert [c[0] for c in link.calls] == ["stop", "reset"]
    assert len(dash.errors) == 0 and len(dash.commands) == 0  # reset clears the plots


def test_upload_validates_and_selects(dash, link):
    p = dash.panel
    bad = b"name: x\nobject: {vertices: [[0,0,0],[1,0,0]]}\n"
    assert p.upload_scenario("bad.yaml", bad) is None
    assert "object.vertices" in p.message_md.content and "Upload rejected" in p.message_md.content
    assert p.upload_scenario("junk.yaml", b"\xff\xfe\x00") is None
    assert "not UTF-8" in p.message_md.content
    assert p.upload_scenario("notyaml.yaml", b"name: [unclosed") is None
    assert "not valid YAML" in p.message_md.content
    assert p.upload_scenario("big.yaml", b"#" * 2_000_000) is None
    good = find_scenario("exp04").read_bytes().replace(b"name: triangular-prism\n", b"name: my-prism\n", 1)
    s = p.upload_scenario("mine.yaml", good)
    assert s is not None and s.name == "my-prism"
    label = f"{UPLOAD_PREFIX}my-prism"
    assert label in p.picker.options and p.picker.value == label
    dash.flush()
    assert dash.scene.summary["scenario"]["name"] == "my-prism"
    p.press_start()
    sent = link.named("start")[-1][1]
    assert isinstance(sent, dict) and sent["name"] == "my-prism"  # uploads travel as documents


def test_estop_sends_first_and_reports_the_arms(dash, link):
    p = dash.panel
    dash.on_arm_state(arm_state("left", qd=np.full(6, 0.2)))
    dash.on_arm_state(arm_state("right"))
    p.press_estop()
    assert link.named("estop")[0][1] == ESTOP_REASON
    dash.flush()
    assert "E-STOP ENGAGED" in p.status_md.content and "arms still moving" in p.status_md.content
    assert not p.release_button.disabled
    assert p.press_start() is None and link.named("start") == []  # no start while engaged
    dash.on_arm_state(arm_state("left"))
    dash.flush()
    assert "arms stopped" in p.status_md.content and p.arms_stopped() is True
    p.press_release()
    dash.flush()
    assert link.named("release") and "E-STOP" not in p.status_md.content and p.release_button.disabled


def test_estop_from_elsewhere_is_shown_and_its_release_too(dash):
    dash.on_estop(EStop(engage=True, source="arm_driver", reason="watchdog"))
    dash.flush()
    assert "E-STOP ENGAGED** by arm_driver" in dash.panel.status_md.content
    dash.on_estop(EStop(engage=False, source="arm_driver"))  # only the dashboard or the CLI may release it
    dash.flush()
    assert "E-STOP ENGAGED** by arm_driver" in dash.panel.status_md.content
    dash.on_estop(EStop(engage=False, source="cli"))
    dash.flush()
    assert "E-STOP" not in dash.panel.status_md.content


def test_estop_is_not_blocked_by_a_slow_render_or_a_hung_request(dash, link):
    """The E-STOP handler runs on viser's event loop: it goes out while a render pass and a Start
    request are both stuck (until the test lets them go), not after them."""
    slow, release = threading.Event(), threading.Event()
    original = dash.scene.draw_soi

    def stuck(msg):
        slow.set()
        release.wait(HANG_S)
        original(msg)

    def hung_start(scenario, params, controller=None):
        link._record("start", scenario, params, controller)
        release.wait(HANG_S)
        return RunControlReply(accepted=True, run_id="run-hung")

    dash.scene.draw_soi = stuck
    from dashboard_support import planned_exp01

    from bagit.common.messages import SoiState

    dash.config.draw_without_viewers = True  # no browser here: the SOI would wait for one
    dash.on_soi(SoiState(rim=planned_exp01().path[0]))
    dash.start()
    assert slow.wait(HANG_S)
    link.start = hung_start
    starter = threading.Thread(target=dash.panel.press_start, daemon=True)
    starter.start()
    assert wait_until(lambda: link.named("start"))
    fut = asyncio.run_coroutine_threadsafe(dash.panel._estop_clicked(None), dash.server._event_loop)
    fut.result(timeout=HANG_S)
    assert link.named("estop") and starter.is_alive() and not release.is_set()  # out while both are still stuck
    # Stop is not held up by the hung Start either; a second Start is refused, not queued
    assert dash.panel.press_stop().accepted and starter.is_alive()
    assert dash.panel.press_reset() is None and "still waiting" in dash.panel.message_md.content
    release.set()
    starter.join(HANG_S)
    assert not starter.is_alive()


def test_estop_failure_is_reported(dash, link):
    def broken(reason):
        raise BusError("zenoh session closed")

    link.estop = broken
    dash.panel.press_estop()
    assert "E-STOP could NOT be sent: zenoh session closed" in dash.panel.message_md.content


def test_with_no_browser_the_panel_waits_and_the_first_one_gets_it_whole(link):
    """No browser connected: the render passes leave the panel as it was (nobody would see it) and drop the notices
    at its period (they would reach nobody); the first pass a browser sees redraws all of it, tables included."""
    now = [100.0]
    dash = Dashboard(link, DashboardConfig(port=0), start=False, clock=lambda: now[0])
    try:
        p = dash.panel
        dash.render_once()  # the first pass: no browser yet
        before = (p.status_md.content, p.history_md.content, p.progress.value)
        feed_run(dash, "run-008", "exp01-coffee-box", "bagging", 0.4)
        p.note_service_lost("perception")
        for _ in range(3):
            now[0] += 1.0  # past the panel's, the plots' and the tables' periods
            dash.render_once()
        assert (p.status_md.content, p.history_md.content, p.progress.value) == before
        assert not p._notices
        dash.config.draw_without_viewers = True  # as a browser connecting does
        now[0] += 0.01  # at once: not at the panel's next period
        dash.render_once()
        assert "`run-008`" in p.status_md.content and "40 %" in p.status_md.content
        assert p.progress.value == pytest.approx(40.0)
        assert "run-008" in p.history_md.content
    finally:
        dash.close()


def test_run_state_progress_elapsed_and_failure_reason(dash):
    p = dash.panel
    dash.flush()
    assert "idle" in p.status_md.content
    feed_run(dash, "run-007", "exp01-coffee-box", "bagging", 0.4)
    dash.flush()
    assert "`run-007`" in p.status_md.content and "bagging" in p.status_md.content and "40 %" in p.status_md.content
    assert p.progress.value == pytest.approx(40.0)
    dash.on_run_state(RunState(run_id="run-007", scenario="exp01-coffee-box", stage="failed", progress=0.6,
                               elapsed_s=12.0, reason="rim left the workspace"))
    dash.flush()
    assert "**Reason:** rim left the workspace" in p.status_md.content and "12.0 s" in p.status_md.content
    assert p.progress.color == "red"
    assert "failed" in p.history_md.content and "rim left the workspace" in p.history_md.content


def test_live_plots_get_the_errors_commands_and_solve_times(dash):
    feed_run(dash, "run-001", "exp01-coffee-box", "bagging", 0.3, n_status=30)
    dash.on_controller_status(ControllerStatus(stamp=1001.5, run_id="run-001", error_to_subgoal=None, error_to_goal=0.02))
    dash.flush()
    t, sub, goal = dash.panel.plot_errors.data
    assert len(t) == 31 and t[0] == 0.0 and t[-1] == pytest.approx(1.5)
    assert sub[0] == pytest.approx(10.0) and goal[0] == pytest.approx(50.0) and np.isnan(sub[-1])
    t, left, right, la, ra = dash.panel.plot_commands.data
    assert left[0] == pytest.approx(30.0) and right[0] == pytest.approx(30.0)  # 1 mm per 1/30 s
    assert la[0] == pytest.approx(np.degrees(0.06))
    t, solve = dash.panel.plot_solve.data
    assert np.allclose(solve[:30], 2.5)
    # a new run starts the plots afresh
    feed_run(dash, "run-002", "exp01-coffee-box", "pre-bagging", 0.0, n_status=3, t0=2000.0)
    dash.flush()
    assert len(dash.panel.plot_errors.data[0]) == 3


def test_health_shows_services_rates_and_warns_when_one_goes_away(dash):
    dash.on_service("perception", True)
    dash.on_service("controller", True)
    feed_run(dash, "r", "exp01-coffee-box", "bagging", 0.1, n_status=5)
    dash.flush()
    md = dash.panel.health_md.content
    assert "| perception | up |" in md and "controller/status" in md
    dash.on_service("controller", False)
    dash.flush()
    assert "| controller | **DOWN** |" in dash.panel.health_md.content
    assert "controller went away" in dash.panel.warning_md.content
    dash.on_service("controller", True)
    dash.flush()
    assert dash.panel.warning_md.content == ""


def test_an_idle_coordinator_without_a_run_shows_no_run_line(dash):
    p = dash.panel
    p.note_run_state(RunState(stage="idle"))
    text = p.status_markdown()
    assert "Stage:** idle · no run yet" in text and "**Run**" not in text
    p.note_run_state(RunState(run_id="run-9", scenario="exp02-canned-pineapple", stage="perceiving"))
    assert "`run-9`" in p.status_markdown()


def test_the_picker_starts_on_the_rigs_scenario(link):
    """`bagit up exp02` shows exp02's object before any run, not the first bundled scenario's."""
    with Dashboard(link, DashboardConfig(port=0, scenario="exp02"), start=False) as d:
        assert str(d.panel.picker.value).startswith("exp02-")
    with Dashboard(link, DashboardConfig(port=0, scenario="exp"), start=False) as d:  # ambiguous: the first
        assert str(d.panel.picker.value).startswith("exp01-")


def test_no_button_icon_is_read_before_a_browser_connects(dash):
    # each icon is read out of viser's icon zip: a dashboard nobody watches pays none (the browser test sees them come)
    p = dash.panel
    buttons = (p.estop_button, p.release_button, p.upload, p.start_button, p.stop_button, p.reset_button, p.reset_view_button)
    assert [b.icon for b in buttons] == [None] * 7
