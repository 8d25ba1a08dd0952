"""The dashboard in a real browser: Debian's headless Chromium driven by Playwright.

Here the dashboard runs in-process, fed with synthetic rig messages built from a real plan of the
paper's Exp. 1, and a recording RunLink stands in for the run coordinator (playing its part: after
Start it publishes the run's states, after E-STOP it stops the arms). The page-level helpers take
only a URL (`BrowserPage`), so the same checks run against `bagit up` once it exists.
Screenshots are saved under artifacts/.
"""

from __future__ import annotations

import os
import threading
import time

import numpy as np
import pytest
from dashboard_support import ARTIFACTS, CLOUD_RGB, FakeRunLink, arm_state, feed_run, feed_scene, wait_until
from suite_support import HANG_S

from bagit.common.messages import RunState
from bagit.dashboard import Dashboard, DashboardConfig, style
from bagit.dashboard.browser import BrowserPage, chromium_available, count_color

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(not chromium_available() and not os.environ.get("CI"), reason="needs playwright and /usr/bin/chromium (apt-get install chromium)"),
]


@pytest.fixture(scope="module")
def link():
    return FakeRunLink()


@pytest.fixture(scope="module")
def dash(link):
    d = Dashboard(link, DashboardConfig(port=0))
    try:
        feed_scene(d)
        yield d
    finally:
        d.close()


@pytest.fixture(scope="module")
def dashboard_url(dash) -> str:
    """The URL the browser checks open; `bagit up`'s dashboard URL in the end-to-end version."""
    return dash.url


@pytest.fixture(scope="module")
def browser(dashboard_url):
    b = BrowserPage(dashboard_url)
    try:
        b.wait_text("Stage:")
        yield b
    finally:
        b.close()


def test_page_loads_and_shows_the_cloud_and_the_soi(browser):
    b = browser
    b.wait_text("E-STOP")
    # the buttons' icons, given once a browser connected (none are read for a dashboard nobody watches)
    b.page.locator("button", has_text="E-STOP").locator("svg").first.wait_for(timeout=10_000)
    assert b.page.locator("button", has_text="Reset camera view").locator("svg").count() == 1
    b.settle(2.5)
    on = b.canvas_pixels()
    green_on = count_color(on, CLOUD_RGB, tol=45)
    soi_on = count_color(on, style.SOI, tol=30)
    assert green_on > 500, f"cloud not visible: {green_on} green pixels"
    assert soi_on > 100, f"SOI not visible: {soi_on} SOI-red pixels"
    b.screenshot(ARTIFACTS / "dashboard_scene.png")
    # the same pixels go when their layer is switched off in the View panel, and come back
    b.toggle_layer("point cloud")
    b.toggle_layer("SOI (live rim)")
    b.settle()
    off = b.canvas_pixels()
    assert count_color(off, CLOUD_RGB, tol=45) < green_on / 10
    assert count_color(off, style.SOI, tol=30) < soi_on / 2
    b.toggle_layer("point cloud")
    b.toggle_layer("SOI (live rim)")
    b.settle()
    assert count_color(b.canvas_pixels(), CLOUD_RGB, tol=45) > green_on / 2
    b.page.get_by_role("button", name="Reset camera view").click()
    assert b.errors == [], b.errors


def _coordinator(dash: Dashboard, link: FakeRunLink, scenario: str, run_id: str, stages: list[tuple[str, float]],
                 moving_until_estop: bool = False) -> threading.Thread:
    """Plays the run coordinator and the arms after the dashboard's Start reaches it."""

    def play() -> None:
        wait_until(lambda: link.runs >= int(run_id[-3:]))  # the dashboard's Start reached the rig
        for stage, progress in stages:
            feed_run(dash, run_id, scenario, stage, progress, n_status=3, t0=time.time())
            time.sleep(0.3)
        if moving_until_estop:
            while not link.named("estop"):
                for arm in ("left", "right"):
                    dash.on_arm_state(arm_state(arm, qd=np.full(6, 0.15)))
                time.sleep(0.05)
            time.sleep(0.3)  # the arms decelerate, then report standstill
            for arm in ("left", "right"):
                dash.on_arm_state(arm_state(arm))
            dash.on_run_state(RunState(run_id=run_id, scenario=scenario, stage="aborted", progress=stages[-1][1],
                                       elapsed_s=5.0, reason="emergency stop"))

    t = threading.Thread(target=play, daemon=True)
    t.start()
    return t


def test_start_runs_a_paper_scenario_to_done(browser, dash, link):
    b = browser
    runs = link.runs
    assert "exp01-coffee-box" in b.options("Scenario")
    b.select("Scenario", "exp01-coffee-box")
    t = _coordinator(dash, link, "exp01-coffee-box", f"run-{runs + 1:03d}",
                     [("perceiving", 0.0), ("planning", 0.0), ("pre-bagging", 0.3), ("bagging", 0.8), ("done", 1.0)])
    b.click_button("Start")
    assert wait_until(lambda: len(link.named("start")) == 1)
    assert link.named("start")[0][1] == "exp01-coffee-box"
    assert b.wait_stage("done", HANG_S) == "done", b.panel_text()
    t.join(5.0)
    b.settle(1.0)
    b.screenshot(ARTIFACTS / "dashboard_done.png")
    b.page.get_by_text("History", exact=True).click()
    b.page.get_by_text(f"run-{runs + 1:03d}").first.wait_for(timeout=1000 * HANG_S)
    assert b.errors == [], b.errors


def test_estop_in_a_second_run_stops_the_arms_and_says_so(browser, dash, link):
    b = browser
    runs = link.runs
    t = _coordinator(dash, link, "exp01-coffee-box", f"run-{runs + 1:03d}", [("pre-bagging", 0.2), ("bagging", 0.6)],
                     moving_until_estop=True)
    b.click_button("Start")
    b.page.get_by_text("Stage: bagging").first.wait_for(timeout=1000 * HANG_S)
    assert wait_until(lambda: dash.panel.arms_stopped() is False)  # the arms move
    clicked = time.monotonic()
    b.click_button("E-STOP")
    assert wait_until(lambda: link.named("estop"))
    assert link.named("estop")[0][-1] >= clicked
    b.page.get_by_text("E-STOP ENGAGED").first.wait_for(timeout=1000 * HANG_S)
    b.page.get_by_text("arms stopped").first.wait_for(timeout=1000 * HANG_S)
    b.page.get_by_text("Stage: aborted").first.wait_for(timeout=1000 * HANG_S)
    t.join(5.0)
    b.screenshot(ARTIFACTS / "dashboard_estop.png")
    # Start is refused while the stop is latched; Release re-arms it
    b.click_button("Start")
    b.page.get_by_text("release it first").first.wait_for(timeout=1000 * HANG_S)
    b.click_button("Release E-stop")
    assert wait_until(lambda: link.named("release"))
    assert b.errors == [], b.errors
