"""The control panel: E-STOP, run control, run state, live plots, health, parameters, history, view.

Buttons act through a RunLink. The E-STOP handler is an async callback, so it runs on viser's
event loop as soon as the click arrives, never queued behind the thread pool, and the first thing
it does is send the stop. Everything shown is re-rendered by `refresh()` on the dashboard's render
thread from state the receive threads left (`note_*`, O(1)); a widget is only sent to the browsers
when its content changed.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path as FilePath
from typing import Any, Literal, TypeVar

import numpy as np
import viser
import viser.uplot

from bagit.common.errors import BadScenario, BagItError
from bagit.common.messages import ArmState, ControllerStatus, EStop, RunControlReply, RunState
from bagit.common.names import CONTROLLER_NAMES, ESTOP_SOURCE_DASHBOARD, FAILED_STAGES, SERVO_STAGES
from bagit.common.params import MethodParams
from bagit.common.scenario import Scenario
from bagit.dashboard.health import HealthBoard, health_markdown
from bagit.dashboard.history import FINAL_STAGES, RunHistory, history_markdown
from bagit.dashboard.params import FIELDS, LAMBDA_D_AUTO_VALUE, overrides
from bagit.dashboard.runlink import RunLink
from bagit.dashboard.scene import LAYER_LABELS, LAYERS, SceneView
from bagit.dashboard.series import Series

log = logging.getLogger("bagit.dashboard")

B = TypeVar("B", viser.GuiButtonHandle, viser.GuiUploadButtonHandle)

ARM_STOPPED_RAD_S = 1e-3  # every joint slower than this: the arm has stopped
MAX_UPLOAD_BYTES = 1_000_000
UPLOAD_PREFIX = "upload: "
ESTOP_REASON = "E-STOP pressed on the dashboard"
RIG_DEFAULT = "rig default"  # the Controller picker's choice that leaves the controller to the coordinator
# the colours viser's notifications take
NotificationColor = Literal["dark", "gray", "red", "pink", "grape", "violet", "indigo", "blue", "cyan", "green", "lime", "yellow", "orange",
                            "teal"]


def _one_line(e: BaseException) -> str:
    s = str(e).strip()
    return s.splitlines()[0] if s else type(e).__name__


def _plot_arrays(arrays: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """uPlot needs at least one x value; an empty series is shown as one point at t = 0."""
    if len(arrays[0]) == 0:
        return tuple(np.zeros(1) for _ in arrays)
    return arrays


class Panel:
    """The GUI of one ViserServer. `scenarios` are the bundled scenario files the picker offers."""

    def __init__(
        self,
        server: viser.ViserServer,
        link: RunLink,
        scene: SceneView,
        *,
        history: RunHistory,
        health: HealthBoard,
        errors: Series,
        commands: Series,
        solve: Series,
        scenarios: list[FilePath],
        show_scenario: Callable[[Scenario], None],
        clock: Callable[[], float] = time.monotonic,
        initial: str | None = None,
    ) -> None:
        self.server = server
        self.link = link
        self.scene = scene
        self.history = history
        self.health = health
        self.errors, self.commands, self.solve = errors, commands, solve
        self._show_scenario = show_scenario
        self._clock = clock
        self._lock = threading.Lock()
        self._busy = threading.Lock()  # one start/stop/reset request at a time
        self._run: tuple[RunState, float] | None = None
        self._status: ControllerStatus | None = None
        self._arms: dict[str, ArmState] = {}
        self._estop: dict[str, Any] = {"engaged": False}
        self._message = ("Pick a scenario and press Start.", "info")
        self._notices: deque[tuple[str, str, NotificationColor]] = deque(maxlen=20)
        self._bundled = {p.stem: p for p in scenarios}
        self._uploads: dict[str, Scenario] = {}
        self._scenario: Scenario | None = None
        self._base = MethodParams()
        self._filling = False
        self._plot_versions: dict[str, int] = {}
        self._shown: dict[str, Any] = {}
        self.estop_calls: list[float] = []  # monotonic times the E-STOP handler sent the stop
        self._icons: list[tuple[viser.GuiButtonHandle | viser.GuiUploadButtonHandle, viser.IconName]] = []  # not shown yet
        self.server.on_client_connect(lambda _client: self._show_icons())
        self._build()
        # The picker starts on the rig's scenario (an exact name or a unique prefix, e.g. `exp02`), else the first.
        match = [k for k in self._bundled if initial is not None and (k == initial or k.startswith(initial))]
        first = match[0] if len(match) == 1 else next(iter(self._bundled), None)
        if first is not None:
            self.select_scenario(first)

    # --- layout --------------------------------------------------------------------------------

    def _iconned(self, button: B, icon: viser.IconName) -> B:
        """`button`, its icon given when the first browser connects (`_show_icons`): viser reads each icon
        out of a 5,000-entry zip (~20 ms here), a cost a rig nobody watches need not pay at its start."""
        self._icons.append((button, icon))
        return button

    def _show_icons(self) -> None:
        icons, self._icons = self._icons, []
        for button, icon in icons:
            button.icon = icon

    def _build(self) -> None:
        gui = self.server.gui
        gui.configure_theme(control_layout="fixed", control_width="large", show_share_button=False, dark_mode=False)
        self.estop_button = self._iconned(gui.add_button("E-STOP", color="red", hint="stop both arms now (latching)"), viser.Icon.ALERT_OCTAGON)
        self.estop_button.on_click(self._estop_clicked)
        uid = getattr(getattr(self.estop_button, "_impl", None), "uuid", None)
        if uid:  # make it large: style the button by its element id
            gui.add_html(
                f"<style>[id='{uid}'] {{ height: 4.2rem !important; --button-height: 4.2rem; font-size: 1.6rem !important;"
                f" --button-fz: 1.6rem; letter-spacing: 0.12em; }}</style>"
            )
        self.release_button = self._iconned(gui.add_button("Release E-stop", color="gray", disabled=True), viser.Icon.LOCK_OPEN)
        self.release_button.on_click(lambda _e: self.press_release())
        self.status_md = gui.add_markdown("**Stage:** idle")
        self.progress = gui.add_progress_bar(0.0, color="blue")
        self.message_md = gui.add_markdown("")

        with gui.add_folder("Run"):
            self.picker = gui.add_dropdown("Scenario", tuple(self._bundled) or ("(none)",))
            self.picker.on_update(self._on_pick)
            self.controller_pick = gui.add_dropdown("Controller", (RIG_DEFAULT, *CONTROLLER_NAMES), initial_value=RIG_DEFAULT,
                                                    hint="the run's controller; rig default: the one `bagit up --controller` named (mpc)")
            self.upload = self._iconned(gui.add_upload_button("Upload scenario", mime_type=".yaml,.yml,.json,text/yaml,application/json"), viser.Icon.UPLOAD)
            self.upload.on_upload(self._on_upload)
            self.start_button = self._iconned(gui.add_button("Start", color="green"), viser.Icon.PLAYER_PLAY)
            self.start_button.on_click(self._on_start)
            self.stop_button = self._iconned(gui.add_button("Stop", color="orange"), viser.Icon.PLAYER_STOP)
            self.stop_button.on_click(self._on_stop)
            self.reset_button = self._iconned(gui.add_button("Reset"), viser.Icon.REFRESH)
            self.reset_button.on_click(self._on_reset)

        with gui.add_folder("Live plots"):
            axes = (viser.uplot.Axis(label="time since the run started (s)"), viser.uplot.Axis())
            scales = {"x": viser.uplot.Scale(time=False)}
            self.plot_errors = gui.add_uplot(
                _plot_arrays(self.errors.arrays()),
                (viser.uplot.Series(label="t (s)"), viser.uplot.Series(label="to subgoal (mm)", stroke="#ff00c8", width=2),
                 viser.uplot.Series(label="to g* (mm)", stroke="#d71923", width=2)),
                title="SOI error", axes=axes, scales=scales, aspect=2.0,
            )
            self.plot_commands = gui.add_uplot(
                _plot_arrays(self.commands.arrays()),
                (viser.uplot.Series(label="t (s)"), viser.uplot.Series(label="left (mm/s)", stroke="#2b6fd6", width=2),
                 viser.uplot.Series(label="right (mm/s)", stroke="#e08a1e", width=2),
                 viser.uplot.Series(label="left (deg/s)", stroke="#2b6fd6", dash=(4, 4), width=1),
                 viser.uplot.Series(label="right (deg/s)", stroke="#e08a1e", dash=(4, 4), width=1)),
                title="Command norms", axes=axes, scales=scales, aspect=2.0,
            )
            self.plot_solve = gui.add_uplot(
                _plot_arrays(self.solve.arrays()),
                (viser.uplot.Series(label="t (s)"), viser.uplot.Series(label="MPC solve (ms)", stroke="#1e9e4a", width=2)),
                title="MPC solve time", axes=axes, scales=scales, aspect=2.0,
            )

        with gui.add_folder("Service health"):
            self.warning_md = gui.add_markdown("")
            self.health_md = gui.add_markdown(health_markdown(self.health))

        with gui.add_folder("Parameters", expand_by_default=False):
            gui.add_markdown("Applied to the **next** run, over the scenario's own values.")
            self.param_inputs: dict[str, Any] = {}
            for f in FIELDS:
                if f.name == "lambda_d":
                    self.lambda_d_auto = gui.add_checkbox("λd auto", True, hint="half the object height")
                    self.lambda_d_auto.on_update(lambda _e: self._params_changed())
                value = self._base.get(f.name)
                h = gui.add_number(f.label, LAMBDA_D_AUTO_VALUE if value is None else value, step=f.step, hint=f.hint)
                h.on_update(lambda _e: self._params_changed())
                self.param_inputs[f.name] = h
            self.params_md = gui.add_markdown("")
            self.params_reset = gui.add_button("Use the scenario's values")
            self.params_reset.on_click(lambda _e: self._fill_params(self._base))

        with gui.add_folder("History", expand_by_default=False):
            self.history_md = gui.add_markdown(history_markdown(self.history))

        with gui.add_folder("View", expand_by_default=False):
            self.layer_boxes = {}
            for layer in LAYERS:
                cb = gui.add_checkbox(LAYER_LABELS[layer], True)
                cb.on_update(self._layer_toggle(layer))
                self.layer_boxes[layer] = cb
            self.reset_view_button = self._iconned(gui.add_button("Reset camera view"), viser.Icon.CAMERA)
            self.reset_view_button.on_click(lambda _e: self.scene.reset_view())

    # --- the E-STOP ----------------------------------------------------------------------------

    async def _estop_clicked(self, _event: Any) -> None:
        self.press_estop()

    def press_estop(self) -> None:
        """Send the e-stop first; only then record and show it."""
        error = None
        try:
            self.link.estop(ESTOP_REASON)
        except Exception as e:  # noqa: BLE001 - the operator must see why the stop did not go out
            error = _one_line(e)
        now = self._clock()
        self.estop_calls.append(now)
        if error is not None:
            log.error("E-STOP could not be sent: %s", error)
            self._say(f"E-STOP could NOT be sent: {error}", "error")
            return
        with self._lock:
            self._estop = {"engaged": True, "source": ESTOP_SOURCE_DASHBOARD, "reason": ESTOP_REASON, "wall": time.time(), "at": now}
        self._set(self.release_button, "disabled", False)
        self._say("sent; the arms are told to stop.", "estop")

    def press_release(self) -> None:
        try:
            self.link.release_estop("released on the dashboard")
        except BagItError as e:
            self._say(f"release failed: {_one_line(e)}", "error")
            return
        with self._lock:
            self._estop = {"engaged": False}
        self._set(self.release_button, "disabled", True)
        self._say("E-stop released.", "info")

    # --- run control ---------------------------------------------------------------------------

    # viser's callbacks return None (or a coroutine): the handlers' results are not theirs to see

    def _on_pick(self, _e: object) -> None:
        if not self._filling:
            self.select_scenario(str(self.picker.value))

    def _on_upload(self, _e: object) -> None:
        self.upload_scenario(self.upload.value.name, self.upload.value.content)

    def _on_start(self, _e: object) -> None:
        self.press_start()

    def _on_stop(self, _e: object) -> None:
        self.press_stop()

    def _on_reset(self, _e: object) -> None:
        self.press_reset()

    def _layer_toggle(self, layer: str) -> Callable[[viser.GuiEvent[viser.GuiCheckboxHandle]], None]:
        def toggle(e: viser.GuiEvent[viser.GuiCheckboxHandle]) -> None:
            self.scene.set_layer_visible(layer, bool(e.target.value))

        return toggle

    def _say(self, text: str, level: str = "info") -> None:
        with self._lock:
            self._message = (text, level)
        self._render_message()

    def _render_message(self) -> None:
        text, level = self._message
        icon = {"error": "**Error:** ", "warn": "**Warning:** ", "estop": "**E-STOP:** "}.get(level, "")
        self._set(self.message_md, "content", f"{icon}{text}" if text else "")

    def _request(self, what: str, call: Callable[[], RunControlReply]) -> RunControlReply | None:
        if not self._busy.acquire(blocking=False):
            self._say(f"{what}: another request is still waiting for the rig", "warn")
            return None
        try:
            return call()
        except BagItError as e:
            self._say(f"{what} failed: {_one_line(e)}", "error")
            return None
        finally:
            self._busy.release()

    def current_overrides(self) -> dict[str, Any]:
        """The parameter overrides the form holds (BadScenario when a value is invalid)."""
        return overrides(self._base, self._form_values())

    def press_start(self) -> RunControlReply | None:
        with self._lock:
            engaged = self._estop.get("engaged", False)
        if engaged:
            self._say("Start refused: the E-stop is engaged; release it first.", "error")
            return None
        choice = str(self.picker.value)
        try:
            params = self.current_overrides()
        except BadScenario as e:
            self._say(f"Start refused: {_one_line(e)}", "error")
            return None
        if choice in self._uploads:
            target: str | dict[str, Any] = self._uploads[choice].model_dump(mode="json", exclude_none=True)
        elif choice in self._bundled:
            target = choice
        else:
            self._say("Start refused: no scenario selected.", "error")
            return None
        controller = None if self.controller_pick.value == RIG_DEFAULT else str(self.controller_pick.value)
        self.start_button.disabled = True
        try:
            reply = self._request("Start", lambda: self.link.start(target, params, controller))
        finally:
            self.start_button.disabled = False
        if reply is None:
            return None
        if reply.accepted:
            run_id = reply.run_id or f"run-{int(time.time())}"
            self.history.started(run_id, choice, params)
            self._say(f"Started {choice} as run {run_id}" + (f" with {controller}" if controller else "") + (f" with {params}" if params else ""), "ok")
        else:
            self._say(f"Start refused by the rig: {reply.reason or 'no reason given'}", "error")
        return reply

    def press_stop(self) -> RunControlReply | None:
        """Stop goes out at once, even while a Start or Reset is still waiting for the rig."""
        try:
            reply = self.link.stop()
        except BagItError as e:
            self._say(f"Stop failed: {_one_line(e)}", "error")
            return None
        if reply is not None:
            self._say("Stop accepted." if reply.accepted else f"Stop refused: {reply.reason}", "info" if reply.accepted else "error")
        return reply

    def press_reset(self) -> RunControlReply | None:
        reply = self._request("Reset", self.link.reset)
        if reply is not None:
            if reply.accepted:
                for s in (self.errors, self.commands, self.solve):
                    s.clear()
                self._say("Reset accepted.", "info")
            else:
                self._say(f"Reset refused: {reply.reason}", "error")
        return reply

    # --- scenarios and parameters ----------------------------------------------------------------

    def select_scenario(self, choice: str) -> Scenario | None:
        """Load the picked scenario, show it in the scene and its parameters in the form."""
        try:
            if choice in self._uploads:
                s = self._uploads[choice]
            elif choice in self._bundled:
                s = Scenario.from_file(self._bundled[choice])
            else:
                return None
        except BadScenario as e:
            self._say(_one_line(e), "error")
            return None
        self._scenario = s
        self._base = s.params
        if str(self.picker.value) != choice:
            self._filling = True
            try:
                self.picker.value = choice  # type: ignore[misc]  # viser declares value's setter apart from its getter: mypy sees no setter
            finally:
                self._filling = False
        self._fill_params(s.params)
        self._show_scenario(s)
        return s

    def upload_scenario(self, filename: str, content: bytes) -> Scenario | None:
        """Validate an uploaded scenario; on success add it to the picker and select it."""
        try:
            if len(content) > MAX_UPLOAD_BYTES:
                raise BadScenario(f"{filename}: {len(content)} bytes is more than a scenario file needs ({MAX_UPLOAD_BYTES})")
            try:
                text = content.decode("utf-8")
            except UnicodeDecodeError:
                raise BadScenario(f"{filename}: not UTF-8 text") from None
            s = Scenario.from_text(text, filename or "upload")
        except BadScenario as e:
            self._say(f"Upload rejected: {_one_line(e)}", "error")
            self._notify("Scenario rejected", _one_line(e), "red")
            return None
        label = f"{UPLOAD_PREFIX}{s.name}"
        self._uploads[label] = s
        self._filling = True
        try:
            self.picker.options = tuple(self._bundled) + tuple(self._uploads)
        finally:
            self._filling = False
        self.select_scenario(label)
        self._say(f"Uploaded scenario {s.name!r} is valid and selected.", "ok")
        return s

    def _form_values(self) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for f in FIELDS:
            v = self.param_inputs[f.name].value
            if f.name == "lambda_d" and self.lambda_d_auto.value:
                v = None
            out[f.name] = v
        return out

    def _fill_params(self, p: MethodParams) -> None:
        self._filling = True
        try:
            for f in FIELDS:
                v = p.get(f.name)
                if f.name == "lambda_d":
                    self.lambda_d_auto.value = v is None  # type: ignore[misc]  # (viser's value setter, as above)
                    v = LAMBDA_D_AUTO_VALUE if v is None else v
                self.param_inputs[f.name].value = v
        finally:
            self._filling = False
        self._params_changed()

    def _params_changed(self) -> None:
        if self._filling:
            return
        self.param_inputs["lambda_d"].disabled = bool(self.lambda_d_auto.value)
        try:
            ov = self.current_overrides()
        except BadScenario as e:
            self._set(self.params_md, "content", f"**Invalid:** {_one_line(e)}")
            return
        text = ", ".join(f"{k} = {v:g}" if isinstance(v, float) else f"{k} = {v}" for k, v in ov.items())
        self._set(self.params_md, "content", f"Next run: {text}" if ov else "Next run: the scenario's values")

    # --- what the receive threads leave ------------------------------------------------------------

    def note_run_state(self, msg: RunState) -> None:
        with self._lock:
            self._run = (msg, self._clock())

    def note_status(self, msg: ControllerStatus) -> None:
        with self._lock:
            self._status = msg

    def note_arm(self, msg: ArmState) -> None:
        with self._lock:
            self._arms[msg.arm] = msg

    def note_estop(self, msg: EStop) -> None:
        with self._lock:
            if msg.engage:
                if not self._estop.get("engaged"):
                    self._estop = {"engaged": True, "source": msg.source, "reason": msg.reason, "wall": msg.stamp, "at": self._clock()}
            else:
                self._estop = {"engaged": False}

    def note_service_lost(self, service: str) -> None:
        self._notices.append(("Service lost", f"{service} went away (its liveliness token is gone)", "red"))

    # --- rendering (render thread) -----------------------------------------------------------------

    def _set(self, handle: Any, attr: str, value: Any) -> None:
        key = f"{id(handle)}.{attr}"
        if self._shown.get(key) != value:
            self._shown[key] = value
            setattr(handle, attr, value)

    def arms_stopped(self) -> bool | None:
        """True when every arm reporting has all joints still; None before any arm reported."""
        with self._lock:
            arms = list(self._arms.values())
        if not arms:
            return None
        return all(np.all(np.isfinite(a.qd)) and float(np.max(np.abs(a.qd))) < ARM_STOPPED_RAD_S for a in arms)

    def status_markdown(self) -> str:
        with self._lock:
            run = self._run
            status = self._status
            estop = dict(self._estop)
            arms = dict(self._arms)
        lines = []
        if run is None or (run[0].run_id is None and run[0].stage == "idle"):  # the coordinator idle, no run (yet, or after Reset)
            lines.append("**Stage:** idle · no run yet")
        else:
            msg, received = run
            elapsed = msg.elapsed_s
            if msg.stage not in FINAL_STAGES and msg.stage != "idle":
                elapsed += self._clock() - received
            lines.append(f"**Run** `{msg.run_id or '-'}` · {msg.scenario or '-'}")
            sub = ""
            if status is not None and (status.run_id in (None, msg.run_id)) and msg.stage in SERVO_STAGES:
                sub = f" · subgoal {status.subgoal_index}"
            lines.append(f"**Stage:** {msg.stage} · {100 * msg.progress:.0f} % · {elapsed:.1f} s{sub}")
            if msg.stage in FAILED_STAGES or msg.reason:
                lines.append(f"**Reason:** {msg.reason or 'none given'}")
        if estop.get("engaged"):
            stopped = self.arms_stopped()
            speeds = ", ".join(f"{a} {float(np.max(np.abs(s.qd))):.3f} rad/s" for a, s in sorted(arms.items()))
            arm_text = (
                "no arm state received" if stopped is None
                else f"arms stopped ({speeds})" if stopped else f"arms still moving ({speeds})"
            )
            when = time.strftime("%H:%M:%S", time.localtime(estop.get("wall", time.time())))
            lines.append(f"**E-STOP ENGAGED** by {estop.get('source')} at {when} · {arm_text}")
        elif any(a.error for a in arms.values()):
            bad = [f"{a.arm}: {a.error_reason or 'error'}" for a in arms.values() if a.error]
            lines.append("**Arm error:** " + "; ".join(bad))
        return "  \n".join(lines)

    def refresh(self, plots: bool = True, slow: bool = True) -> None:
        """Re-render the panel from the latest state (render thread)."""
        self._set(self.status_md, "content", self.status_markdown())
        with self._lock:
            run = self._run
            estop = self._estop.get("engaged", False)
        progress = 0.0 if run is None else 100.0 * run[0].progress
        self._set(self.progress, "value", round(progress, 1))
        self._set(self.progress, "color", "red" if estop or (run and run[0].stage in FAILED_STAGES) else
                  "green" if run and run[0].stage == "done" else "blue")
        self._set(self.release_button, "disabled", not estop)
        self._render_message()
        while self._notices:
            title, body, color = self._notices.popleft()
            self._notify(title, body, color)
        if plots:
            for name, series, handle in (("errors", self.errors, self.plot_errors), ("commands", self.commands, self.plot_commands),
                                         ("solve", self.solve, self.plot_solve)):
                if self._plot_versions.get(name) != series.version:
                    self._plot_versions[name] = series.version
                    handle.data = _plot_arrays(series.arrays())
        if slow:
            self._set(self.health_md, "content", health_markdown(self.health))
            warnings = self.health.warnings()
            self._set(self.warning_md, "content", "  \n".join(f"**Warning: {w}**" for w in warnings))
            self._set(self.history_md, "content", history_markdown(self.history))

    def forget_notices(self) -> None:
        """Drop the pending notices: with no browser connected they reach nobody (as `_notify` would send them)."""
        self._notices.clear()

    def _notify(self, title: str, body: str, color: NotificationColor) -> None:
        for client in self.server.get_clients().values():
            try:
                client.add_notification(title, body, color=color, auto_close_seconds=15.0)
            except Exception:  # noqa: BLE001 - a client that just left
                pass
