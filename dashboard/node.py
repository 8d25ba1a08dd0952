"""The dashboard on Zenoh: subscribe to the rig's keys, drive run/control and estop.

The subscriber callbacks go straight to the Dashboard's `on_*` methods, which only leave the
message for the render thread, so the Zenoh threads are never held up by drawing. The e-stop
publisher is declared up front: pressing E-STOP is one `put` on a reliable, express, real-time key.
The streams only a browser looks at (the display cloud, the SOI, the arms' states: "watched") are
subscribed to only while one is connected: perception makes the cloud only for a subscriber, and the
SOI and the arms' states come at every step of a run (about a thousand deliveries in a run of exp02),
so a dashboard nobody looks at costs the rig neither. The plots' series (commands, errors) and the
run's history are followed all the time: a browser that connects mid-run sees the run from its start.
The commands and statuses (one each a step) are `Polled`: Zenoh keeps them until the render thread
takes them (`Dashboard.feed`), so no thread here wakes for each.
"""

from __future__ import annotations

import logging
import threading
from typing import Any

from bagit.common.bus import (
    BusConfig,
    Keys,
    LivelinessWatcher,
    Polled,
    Publisher,
    Subscriber,
    declare_alive,
    open_session,
    request_run_control,
)
from bagit.common.errors import BusError
from bagit.common.messages import (
    ArmState,
    Command,
    ControllerStatus,
    EStop,
    Goal,
    Path,
    PointCloud,
    RunControl,
    RunControlReply,
    RunState,
    SoiState,
)
from bagit.common.names import ESTOP_SOURCE_DASHBOARD
from bagit.common.rig import RigConfig
from bagit.dashboard.server import Dashboard, DashboardConfig

log = logging.getLogger("bagit.dashboard")

SERVICE_NAME = "dashboard"
FEED_CAPACITY = 512  # messages a polled stream keeps for the render thread (a step's each; 17 s of a 30 Hz run)


class ZenohRunLink:
    """RunLink over the bus: run/control queries and puts on estop. Its e-stops carry `source`, by default
    the dashboard's name in ESTOP_RELEASE_SOURCES: the arm driver takes a release from those only."""

    def __init__(self, session: Any, keys: Keys, timeout_s: float = 5.0, source: str = ESTOP_SOURCE_DASHBOARD) -> None:
        self.session = session
        self.keys = keys
        self.timeout_s = timeout_s
        self.source = source
        self._estop = Publisher(session, keys.estop, EStop)

    def start(self, scenario: str | dict[str, Any], params: dict[str, Any], controller: str | None = None) -> RunControlReply:
        if isinstance(scenario, dict):
            req = RunControl(action="start", scenario_doc=scenario, params=params, controller=controller)
        else:
            req = RunControl(action="start", scenario=scenario, params=params, controller=controller)
        return request_run_control(self.session, self.keys, req, timeout=self.timeout_s)

    def stop(self) -> RunControlReply:
        return request_run_control(self.session, self.keys, RunControl(action="stop"), timeout=self.timeout_s)

    def reset(self) -> RunControlReply:
        return request_run_control(self.session, self.keys, RunControl(action="reset"), timeout=self.timeout_s)

    def estop(self, reason: str) -> None:
        self._estop.put(EStop(engage=True, source=self.source, reason=reason))

    def release_estop(self, reason: str) -> None:
        self._estop.put(EStop(engage=False, source=self.source, reason=reason))

    def close(self) -> None:
        self._estop.close()


class DashboardNode:
    """A Zenoh session, the subscriptions, the liveliness token and the Dashboard they feed."""

    def __init__(self, bus: BusConfig, config: DashboardConfig | None = None, rig: RigConfig | None = None,
                 query_timeout_s: float = 5.0) -> None:
        self.bus = bus
        self.keys = Keys(bus.rig)
        self.session = open_session(bus)
        self._closers: list[Any] = []
        self._watched_subs: list[Subscriber[Any]] = []  # the watched streams (module doc), while a browser is connected
        self._watch_lock = threading.Lock()
        try:
            self.link = ZenohRunLink(self.session, self.keys, query_timeout_s)
            self._closers.append(self.link)
            self.dashboard = Dashboard(self.link, config, rig)
            k = self.keys
            d = self.dashboard
            for key, msg_type, cb in (
                (k.planner_goal, Goal, d.on_goal),
                (k.planner_path, Path, d.on_path),
                (k.run_state, RunState, d.on_run_state),
                (k.estop, EStop, d.on_estop),
            ):
                self._closers.append(Subscriber(self.session, key, msg_type, cb))
            cmds = Polled(self.session, k.controller_cmd, Command, FEED_CAPACITY)
            statuses = Polled(self.session, k.controller_status, ControllerStatus, FEED_CAPACITY)
            self._closers += [cmds, statuses]
            d.feed(cmds.take, d.on_command)
            d.feed(statuses.take, d.on_controller_status)
            d.server.on_client_connect(lambda _client: self._follow_viewers())
            d.server.on_client_disconnect(lambda _client: self._follow_viewers())
            self._follow_viewers()
            self._closers.append(LivelinessWatcher(self.session, k, d.on_service))
            self._token = declare_alive(self.session, k, SERVICE_NAME)
        except BaseException:
            self.close()
            raise

    @property
    def url(self) -> str:
        return self.dashboard.url

    def _follow_viewers(self) -> None:
        """Subscribe to the watched streams while a browser is connected (or `draw_without_viewers`), not otherwise."""
        d = self.dashboard
        with self._watch_lock:
            if getattr(self, "_closed", False):
                return
            watched = d.config.draw_without_viewers or bool(d.server.get_clients())
            if watched and not self._watched_subs:
                k = self.keys
                self._watched_subs = [Subscriber(self.session, k.perception_cloud, PointCloud, d.on_cloud),
                                      Subscriber(self.session, k.perception_soi, SoiState, d.on_soi),
                                      Subscriber(self.session, k.arm_state_any, ArmState, d.on_arm_state)]
            elif not watched and self._watched_subs:
                subs, self._watched_subs = self._watched_subs, []
                for s in subs:
                    s.close()

    def close(self) -> None:
        with self._watch_lock:
            if getattr(self, "_closed", False):
                return
            self._closed = True
            watched, self._watched_subs = self._watched_subs, []
        for c in [*reversed(self._closers), *watched]:
            try:
                c.close()
            except Exception:  # noqa: BLE001 - closing what is left
                log.exception("closing %s failed", type(c).__name__)
        self._closers = []
        token = getattr(self, "_token", None)
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # noqa: BLE001
                pass
        d = getattr(self, "dashboard", None)
        if d is not None:
            d.close()
        try:
            self.session.close()
        except Exception as e:  # noqa: BLE001
            raise BusError(f"closing the zenoh session failed: {e}") from None

    def __enter__(self) -> DashboardNode:
        return self

    def __exit__(self, *_: Any) -> None:
        self.close()
