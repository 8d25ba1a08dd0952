"""The Dashboard: a viser server, its scene and panel, fed with the rig's messages.

    dash = Dashboard(link)              # link: a RunLink (Zenoh: bagit.dashboard.node.ZenohRunLink)
    dash.on_soi(soi)                    # from any thread, returns at once
    print(dash.url)                     # http://127.0.0.1:8080
    dash.close()

The `on_*` methods only leave the message in a latest-wins slot (and append plot samples); a
render thread draws what is due, each layer at most at its rate (clouds 10 Hz, SOI and arms
30 Hz, the panel 5 Hz), so a burst of messages never queues up behind the browser. It binds
127.0.0.1 unless `host` says otherwise.
"""

from __future__ import annotations

import contextlib
import logging
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path as FilePath
from typing import Any

import numpy as np
import viser
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.errors import BadScenario, BagItError
from bagit.common.messages import ArmState, CameraInfo, Command, ControllerStatus, EStop, Goal, Path, PointCloud, RunState, SoiState
from bagit.common.rig import RigConfig
from bagit.common.scenario import Scenario
from bagit.dashboard.arms import command_speeds
from bagit.dashboard.health import HealthBoard
from bagit.dashboard.history import RunHistory
from bagit.dashboard.intake import LatestSlots
from bagit.dashboard.panel import Panel
from bagit.dashboard.runlink import RunLink
from bagit.dashboard.scene import SceneView
from bagit.dashboard.series import Series

log = logging.getLogger("bagit.dashboard")

LATENCY_SAMPLES = 4096
LIVE_LAYERS = ("cloud", "soi", "arm", "cmd")  # redrawn many times a second: only worth it for a browser watching


class DashboardConfig(BaseModel):
    """Where the dashboard listens and how fast each layer may be redrawn."""

    model_config = ConfigDict(extra="forbid")

    host: str = Field("127.0.0.1", min_length=1, description="bind address; loopback unless widened explicitly")
    port: int = Field(8080, ge=0, le=65535, description="0 = any free port (tests)")
    max_cloud_points: int = Field(20000, ge=100, le=1_000_000, description="points of a cloud drawn at most")
    scenario: str | None = Field(None, description="bundled scenario the picker starts on (the world the rig shows); default the first")
    cloud_hz: float = Field(10.0, gt=0, le=120)
    soi_hz: float = Field(30.0, gt=0, le=120)
    arm_hz: float = Field(30.0, gt=0, le=120)
    command_hz: float = Field(15.0, gt=0, le=120)
    panel_hz: float = Field(5.0, gt=0, le=60)
    plot_hz: float = Field(4.0, gt=0, le=60)
    slow_hz: float = Field(1.0, gt=0, le=10, description="health and history tables")
    plot_capacity: int = Field(1800, ge=10, le=100_000, description="samples kept per live plot")
    draw_without_viewers: bool = Field(
        False, description="draw the live layers (cloud, SOI, arms, command) and the panel with no browser connected; False: the "
        "layers wait in their latest-wins slots, and the first browser to connect gets the newest and the panel redrawn at once "
        "(a rig nobody watches spends no CPU on them)")


def _percentiles(x: list[float]) -> dict[str, float]:
    if not x:
        return {"n": 0}
    a = np.asarray(x) * 1000.0
    return {"n": len(a), "min_ms": float(a.min()), "median_ms": float(np.median(a)), "p95_ms": float(np.percentile(a, 95)),
            "max_ms": float(a.max())}


class Dashboard:
    """The web dashboard. `start=False` leaves the render thread off (tests call `flush()`)."""

    def __init__(
        self,
        link: RunLink,
        config: DashboardConfig | None = None,
        rig: RigConfig | None = None,
        *,
        scenarios: list[FilePath] | None = None,
        start: bool = True,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.config = config or DashboardConfig()
        c = self.config
        self._clock = clock
        with contextlib.redirect_stdout(sys.stderr):  # viser prints its banner on stdout, which is for --json
            self.server = viser.ViserServer(host=c.host, port=c.port, label="BagIt dashboard", verbose=False)
        try:
            self.server.scene.configure_default_lights(True, cast_shadow=False)
            self.scene = SceneView(self.server, rig, c.max_cloud_points)
            self.scene.reset_view()
            self.history = RunHistory()
            self.health = HealthBoard(clock=clock)
            self.errors = Series(("to_subgoal_mm", "to_goal_mm"), c.plot_capacity)
            self.commands = Series(("left_mm_s", "right_mm_s", "left_deg_s", "right_deg_s"), c.plot_capacity)
            self.solve = Series(("solve_ms",), c.plot_capacity)
            self._slots = LatestSlots(
                {"cloud": 1 / c.cloud_hz, "soi": 1 / c.soi_hz, "arm": 1 / c.arm_hz, "cmd": 1 / c.command_hz, "subgoal": 1 / c.soi_hz},
                default_period_s=0.0,
                clock=clock,
            )
            if scenarios is None:
                from bagit.scenarios import list_scenarios

                scenarios = list_scenarios()
            self._run_scenario: str | None = None
            self.panel = Panel(
                self.server, link, self.scene, history=self.history, health=self.health, errors=self.errors,
                commands=self.commands, solve=self.solve, scenarios=scenarios, show_scenario=self.show_scenario, clock=clock,
                initial=c.scenario,
            )
        except BaseException:
            with contextlib.redirect_stdout(sys.stderr):
                self.server.stop()
            raise
        self._latency: dict[str, deque[float]] = {}
        self._render_errors: dict[str, int] = {}
        self._last_error: dict[str, str] = {}
        self._next = {"panel": 0.0, "plots": 0.0, "slow": 0.0}
        self._panel_behind = False  # the panel was skipped while no browser watched (`_held`): redrawn whole for the next
        self._feeds: list[tuple[Callable[[], list[Any]], Callable[[Any], None]]] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if start:
            self.start()

    # --- lifecycle -----------------------------------------------------------------------------

    @property
    def url(self) -> str:
        host = self.server.get_host()
        shown = "127.0.0.1" if host in ("0.0.0.0", "") else host
        if ":" in shown and not shown.startswith("["):
            shown = f"[{shown}]"
        return f"http://{shown}:{self.server.get_port()}/"

    def start(self) -> None:
        if self._thread is None:
            self._thread = threading.Thread(target=self._loop, name="dashboard-render", daemon=True)
            self._thread.start()

    def close(self) -> None:
        self._stop.set()
        self._slots.wake.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
            self._thread = None
        with contextlib.redirect_stdout(sys.stderr):
            self.server.stop()

    def __enter__(self) -> Dashboard:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()

    # --- intake (any thread; O(1)) -------------------------------------------------------------

    def on_cloud(self, msg: PointCloud) -> None:
        self.health.note("perception/cloud")
        self._slots.put("cloud", msg)

    def on_soi(self, msg: SoiState) -> None:
        self.health.note("perception/soi")
        self._slots.put("soi", msg)

    def on_goal(self, msg: Goal) -> None:
        self.health.note("planner/goal")
        self._slots.put("goal", msg)

    def on_path(self, msg: Path) -> None:
        self.health.note("planner/path")
        self._slots.put("path", msg)

    def on_command(self, msg: Command) -> None:
        self.health.note("controller/cmd")
        ll, rl, la, ra = command_speeds(msg.u, msg.dt)
        self.commands.add(msg.stamp, (ll * 1000, rl * 1000, np.degrees(la), np.degrees(ra)), msg.run_id)
        self._slots.put("cmd", msg)

    def on_controller_status(self, msg: ControllerStatus) -> None:
        self.health.note("controller/status")
        mm = lambda v: None if v is None else 1000.0 * v  # noqa: E731
        self.errors.add(msg.stamp, (mm(msg.error_to_subgoal), mm(msg.error_to_goal)), msg.run_id)
        self.solve.add(msg.stamp, (msg.solve_ms,), msg.run_id)
        self.panel.note_status(msg)
        self._slots.put("subgoal", msg.subgoal_index)

    def on_arm_state(self, msg: ArmState) -> None:
        self.health.note(f"arm/{msg.arm}/state")
        self.panel.note_arm(msg)
        self._slots.put(f"arm:{msg.arm}", msg)

    def on_run_state(self, msg: RunState) -> None:
        self.health.note("run/state")
        self.history.update(msg)
        self.panel.note_run_state(msg)
        if msg.scenario and msg.scenario != self._run_scenario:
            # a run of another scenario: show its object (a picker preview stays until then)
            self._run_scenario = msg.scenario
            self._slots.put("scenario_name", msg.scenario)

    def on_estop(self, msg: EStop) -> None:
        self.health.note("estop")
        if msg.may_act():  # a release from anyone but the dashboard or the CLI leaves the latch shown
            self.panel.note_estop(msg)

    def feed(self, take: Callable[[], list[Any]], on: Callable[[Any], None]) -> None:
        """A stream the render thread takes at its own pace (at least `command_hz` while a browser watches,
        the panel's rate otherwise), each message given to `on`: for streams that come at every step and
        need no Zenoh thread woken for each message (the plots' commands and statuses: `bagit.common.bus.Polled`)."""
        self._feeds.append((take, on))

    def _take_feeds(self) -> None:
        for take, on in self._feeds:
            for msg in take():
                on(msg)

    def on_camera_info(self, info: CameraInfo) -> None:
        self._slots.put("camera", info)

    def on_service(self, service: str, alive: bool) -> None:
        """A liveliness change (bagit.common.bus.LivelinessWatcher's on_change)."""
        if self.health.service_changed(service, alive):
            self.panel.note_service_lost(service)

    def show_scenario(self, scenario: Scenario) -> None:
        """Draw a scenario's object and obstacles (the picker's choice, or the running one)."""
        self._slots.put("scenario", scenario)

    # --- rendering (the render thread, or flush()) ----------------------------------------------

    def _find_scenario(self, name: str) -> Scenario | None:
        for label, s in self.panel._uploads.items():
            if s.name == name or label == name:
                return s
        from bagit.scenarios import find_scenario, list_scenarios

        try:
            return Scenario.from_file(find_scenario(name))
        except BadScenario:
            pass
        for p in list_scenarios():  # a RunState may carry the scenario's `name:` rather than its file name
            try:
                s = Scenario.from_file(p)
            except BadScenario:
                continue
            if s.name == name:
                return s
        return None

    def _draw(self, key: str, value: Any) -> None:
        sc = self.scene
        if key == "cloud":
            sc.draw_cloud(value)
        elif key == "soi":
            sc.draw_soi(value)
        elif key == "goal":
            sc.draw_goal(value)
        elif key == "path":
            sc.draw_path(value)
        elif key == "subgoal":
            sc.set_subgoal(value)
        elif key.startswith("arm:"):
            sc.draw_arm(value)
        elif key == "cmd":
            sc.draw_command(value)
        elif key == "camera":
            sc.draw_camera(value)
        elif key == "scenario":
            sc.draw_scenario(value)
        elif key == "scenario_name":
            s = self._find_scenario(value)
            if s is not None:
                sc.draw_scenario(s)

    def render_once(self, force: bool = False) -> int:
        """Take what the feeds hold, draw every due layer and, when due, refresh the panel. Returns the number
        of layers drawn."""
        self._take_feeds()
        held = self._held()
        items = self._slots.take_due(force=force, hold=held)
        for key, item in items.items():
            try:
                self._draw(key, item.value)
            except (BagItError, ValueError) as e:
                n = self._render_errors[key] = self._render_errors.get(key, 0) + 1
                self._last_error[key] = str(e).splitlines()[0] if str(e) else type(e).__name__
                if n <= 3 or n % 100 == 0:
                    log.warning("could not draw %s (#%d): %s", key, n, self._last_error[key])
                continue
            q = self._latency.get(key.split(":", 1)[0])
            if q is None:
                q = self._latency[key.split(":", 1)[0]] = deque(maxlen=LATENCY_SAMPLES)
            q.append(self._clock() - item.received)
        now = self._clock()
        c = self.config
        if force or now >= self._next["panel"] or (self._panel_behind and not held):
            self._next["panel"] = now + 1 / c.panel_hz
            if held and not force:  # nobody to show it to: redrawn whole on the first pass a browser sees
                self._panel_behind = True
                self.panel.forget_notices()
                return len(items)
            whole, self._panel_behind = force or self._panel_behind, False
            plots = whole or now >= self._next["plots"]
            slow = whole or now >= self._next["slow"]
            self.panel.refresh(plots=plots, slow=slow)
            if plots:
                self._next["plots"] = now + 1 / c.plot_hz
            if slow:
                self._next["slow"] = now + 1 / c.slow_hz
        return len(items)

    def _held(self) -> tuple[str, ...]:
        """The live layers while no browser is connected (unless `draw_without_viewers`)."""
        if self.config.draw_without_viewers or self.server.get_clients():
            return ()
        return LIVE_LAYERS

    def flush(self) -> None:
        """Draw everything pending now, ignoring the rate limits (tests, shutdown)."""
        self.render_once(force=True)

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.render_once()
            except Exception:  # noqa: BLE001 - the renderer must outlive one bad frame
                log.exception("dashboard render pass failed")
            held = self._held()
            due = self._slots.next_due_in(hold=held)
            panel_in = max(0.0, self._next["panel"] - self._clock())
            if self._feeds and not held:  # the feeds' live layer (the command) at its rate
                panel_in = min(panel_in, 1 / self.config.command_hz)
            if due is None and held:
                self._stop.wait(min(panel_in, 0.1) if panel_in > 0 else 0.005)  # a browser may connect: look again soon
            elif due is None:
                self._slots.wake.wait(timeout=panel_in if panel_in > 0 else 0.005)
            else:
                self._stop.wait(max(0.002, min(due, panel_in)))

    # --- introspection -------------------------------------------------------------------------

    def stats(self) -> dict[str, Any]:
        """Intake counts, render errors and draw latency (receive -> sent to the browsers) per layer."""
        return {
            "slots": self._slots.stats(),
            "render_errors": dict(self._render_errors),
            "last_error": dict(self._last_error),
            "latency": {k: _percentiles(list(v)) for k, v in self._latency.items()},
            "clients": len(self.server.get_clients()),
        }
