"""The arm driver on Zenoh: the only module of the arm driver that imports zenoh.

    node = ArmDriverNode(session, keys, ArmDriver(rig, DriverConfig()), state_rate_hz=None)
    ...                                   # controller/cmd -> submit, estop -> latch / reset
    node.close()                          # smooth stop, hold, DisableRobot, disconnect

In: `controller/cmd` (each Command to `ArmDriver.submit`: servo increments, or hold), `estop`
(engage, from anyone, latches EmergencyStop on both controllers; engage=False resets it, from the
dashboard or the CLI only: `ESTOP_RELEASE_SOURCES`) and `run/state` (a new run clears a fault
latched in the last one: starting a run is the operator's reset; the e-stop latch is never cleared
this way, and a fault whose cause persists latches again).

The run gate (`gate.command_refusal`): a servo command moves the arms only if its `run_id` is the
run run/state shows in a servo stage (pre-bagging, bagging); anything else is refused, counted in
the driver's `rejections` (`no_active_run`, `wrong_run`) and shown as the event `refused: ...`.
Holds always pass. When the run the arms streamed for leaves the servo stages, or another run
replaces it, the node holds the arms. Out: `arm/<side>/state`
from each feedback packet (or at most `state_rate_hz`), with the driver's own condition laid over
the controller's: `estopped` while the latch holds, `error` and `error_reason` while a driver
fault (or a lost link) stops the arms, and for `notice_s` after a watchdog stop, a clipped
target or a refused command, that event as `error_reason` (with `error` False). Every driver
event is also written to stderr (repeats of the same event at most every 5 s).

With `clock="sim"` (a lockstep simulator) the driver cycles on sim/clock's servo ticks and the node
answers the simulator on sim/ack: each tick once cycled (with the ServoPs it sent), and each
command once taken or refused, so the world never steps past a command the arms have not seen.
The bring-up happens before anything is subscribed: commands that arrive before the arms are
enabled are never queued. When commands stop arriving the driver's watchdog holds the arms.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any

import zenoh  # noqa: F401 - the node is where the service meets the bus

from bagit.common.bus import Keys, Publisher, Subscriber, rig_clock
from bagit.common.clock import ClockKind
from bagit.common.errors import BagItError
from bagit.common.lockstep import LOCKSTEP_TIMEOUT_S
from bagit.common.messages import ArmState, Command, EStop, RunState, StepAck
from bagit.common.names import ACTIVE_STAGES, FINAL_STAGES
from bagit.common.results import ARM_EVENT_KINDS
from bagit.common.rig import ARMS
from bagit.services.arm_driver.driver import ArmDriver
from bagit.services.arm_driver.gate import NO_ACTIVE_RUN, Refusal, command_refusal, stream_end

log = logging.getLogger("bagit.arm_driver")

SERVICE_NAME = "arm-driver"
REPEAT_S = 5.0  # the same event is printed again at most this often
# Events that are the driver going about its work: logged at INFO and not shown on ArmState.
ROUTINE_EVENTS = frozenset({"started", "closed", "estop_reset", "fault_cleared", "reconnected"})


class ArmDriverNode:
    """Wires an ArmDriver to the rig's bus (see the module doc). Starts the driver (bring-up)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        driver: ArmDriver,
        state_rate_hz: float | None = None,
        notice_s: float = 1.0,
        clock: ClockKind = "wall",
    ) -> None:
        self.keys = keys
        self.driver = driver
        self.notice_s = notice_s
        self.min_interval = 0.0 if not state_rate_hz else 1.0 / state_rate_hz
        self._last_pub = {a: -1e9 for a in ARMS}
        self._lock = threading.Lock()
        self._notice: tuple[float, str] | None = None
        self._printed: dict[str, tuple[float, str]] = {}
        self._clipped_seen = 0
        self._events_base: dict[str, int] = {}
        self.published = {a: 0 for a in ARMS}
        self.commands = 0
        self.refused = 0
        self.estops = 0
        self._pubs = {a: Publisher(session, keys.arm_state(a), ArmState, lockstep=clock == "sim") for a in ARMS}
        # the run gate: run/state as last heard, and the run the arms last streamed for; `_gate` makes
        # a command's check and its submit one step against a run/state that ends the run
        self._gate = threading.Lock()
        self._run_state: RunState | None = None
        self._streaming_run: str | None = None
        self._parked: tuple[Command, threading.Timer] | None = None  # lockstep: a command waiting for its run/state
        self._run_id: str | None = None  # the last run started (run/state)
        self._park_lock = threading.Lock()
        driver.on_state = self._on_state
        driver.on_event = self._on_event
        self._clock, self._clock_sub = rig_clock(session, keys, clock)
        self._ack = Publisher(session, keys.step_ack(SERVICE_NAME), StepAck) if self._clock.simulated else None
        if self._clock.simulated:
            driver.set_clock(self._clock, on_tick=self._on_tick)
        driver.start()  # ProtocolError: a controller is unreachable or refuses; nothing declared yet
        self._estop_sub = Subscriber(session, keys.estop, EStop, self._on_estop)
        self._cmd_sub = Subscriber(session, keys.controller_cmd, Command, self._on_command)
        self._run_sub = Subscriber(session, keys.run_state, RunState, self._on_run_state)

    @property
    def run_state(self) -> RunState | None:
        """The last run/state heard (None: none yet): the run gate's view of which run servoes."""
        with self._gate:
            return self._run_state

    # -- in ----------------------------------------------------------------------------------------

    def _on_command(self, cmd: Command) -> None:
        with self._gate:
            refusal = command_refusal(cmd, self._run_state)
            if refusal is not None and self._may_park(cmd, refusal):
                return
            expired = self._parked is not None and self._parked[0] is cmd
            self._parked = None
            if refusal is None:
                ok = self.driver.submit(cmd)
                refusal = None if ok else self.driver.last_refusal
            else:
                ok = False
                self.driver.refuse(refusal)
            if ok and cmd.mode == "servo":
                self._streaming_run = cmd.run_id
        if self._ack is not None:
            late = "the run/state that lets its command through" if expired and not ok else None
            self._answer(StepAck(service=SERVICE_NAME, run_id=cmd.run_id, cmd_seq=cmd.seq, late=late))
        with self._lock:
            self.commands += 1
            if not ok:
                self.refused += 1
        if not ok:
            so_far = ", ".join(f"{k} {v}" for k, v in self.driver.rejections.items())
            self._on_event("refused", f"{refusal or f'command {cmd.seq}'} (so far: {so_far})",
                           repeat_key=f"refused {refusal.reason if refusal else ''}")
        clipped = self.driver.counters.get("clipped", 0)
        if clipped != self._clipped_seen:
            self._clipped_seen = clipped
            self._on_event("clipped", "; ".join(self.driver.path.last_violations) or "target clipped")

    def _may_park(self, cmd: Command, refusal: Refusal) -> bool:
        """Lockstep: the first command of a run that run/state still shows planning waits (unanswered, so
        the simulator waits too) for the run/state that lets it through: the two come on their own keys
        and either may arrive first. Judged again on that run/state, or refused after the lockstep
        time-out (its answer then says so: the run is not exact)."""
        st = self._run_state
        if self._ack is None or refusal.reason != NO_ACTIVE_RUN or st is None or st.run_id != cmd.run_id or st.stage not in ACTIVE_STAGES:
            return False
        if self._parked is not None and self._parked[0] is cmd:
            return False  # its time is up: it stays refused
        timer = threading.Timer(LOCKSTEP_TIMEOUT_S, self._unpark, kwargs={"expired": True})
        timer.daemon = True
        self._parked = (cmd, timer)
        timer.start()
        return True

    def _unpark(self, expired: bool = False) -> None:
        """Judge the parked command again: on a new run/state (parked again if still refused), or
        refused for good when its time is up."""
        with self._park_lock:
            parked = self._parked
            if parked is None or (expired and threading.current_thread() is not parked[1]):
                return  # judged already, or a timer of an earlier wait
            parked[1].cancel()
            if not expired:
                self._parked = None
        self._on_command(parked[0])

    def _on_tick(self, tick: int, sent: dict[str, int], late: str | None = None) -> None:
        self._answer(StepAck(service=SERVICE_NAME, run_id=self._run_id, tick=tick, servo_sent=sent, late=late))

    def _answer(self, ack: StepAck) -> None:
        try:
            assert self._ack is not None
            self._ack.put(ack.model_copy(update={"stamp": self._clock.now()}))
        except Exception as e:  # noqa: BLE001 - a closing session; the simulator's wait says who is missing
            self._on_event("publish", f"sim/ack: {type(e).__name__}: {e}")

    def _on_estop(self, msg: EStop) -> None:
        with self._lock:
            self.estops += 1
        try:
            self.driver.handle_estop(msg)
        except BagItError as e:
            latched = ", the e-stop stays latched" if self.driver.mode == "estopped" else ""
            self._on_event("estop", f"reset refused{latched}: {e}")
        except Exception as e:  # noqa: BLE001 - a reset that fails must not take the node down
            self._on_event("estop", f"reset failed, the e-stop stays latched: {type(e).__name__}: {e}")

    def _on_run_state(self, msg: RunState) -> None:
        with self._gate:
            self._run_state = msg
            why = stream_end(self._streaming_run, msg)
            if why is not None:
                self._streaming_run = None
                self.driver.hold(why)
        if self._parked is not None:
            self._unpark()
        if msg.run_id is None or msg.run_id == self._run_id or msg.stage in FINAL_STAGES + ("idle",):
            return
        self._run_id = msg.run_id
        self._events_base = self._event_counts(base={})  # the arm states count this run's events from here
        if self.driver.mode != "fault":  # an e-stop latch reads 'estopped' and stays
            return
        # ClearError and EnableRobot wait for the controllers' replies: not on the bus's thread
        threading.Thread(target=self._clear_fault, args=(msg.run_id,), name="arm-clear-fault", daemon=True).start()

    def _clear_fault(self, run_id: str) -> None:
        try:
            self.driver.clear_fault()
            self._on_event("fault_cleared", f"run {run_id} started")
        except Exception as e:  # noqa: BLE001 - the fault stays latched and the arms hold; say why
            self._on_event("fault", f"run {run_id} started but the fault could not be cleared: {type(e).__name__}: {e}")

    # -- out ---------------------------------------------------------------------------------------

    def _on_event(self, kind: str, detail: str, repeat_key: str | None = None) -> None:
        """Show an event on ArmState for `notice_s` and print it; the same text (or the same
        `repeat_key`: a flood of refusals for one reason) is printed again at most every REPEAT_S."""
        now = time.monotonic()
        text = f"{kind}: {detail}"
        key = repeat_key or text
        with self._lock:
            if kind not in ROUTINE_EVENTS:
                self._notice = (now, text)
            last = self._printed.get(kind)
            due = last is None or last[1] != key or now - last[0] >= REPEAT_S
            if due:
                self._printed[kind] = (now, key)
        if due:
            log.log(logging.INFO if kind in ROUTINE_EVENTS else logging.WARNING, "%s", text)

    def _on_state(self, state: ArmState) -> None:
        now = time.monotonic()
        if now - self._last_pub[state.arm] < self.min_interval:
            return
        self._last_pub[state.arm] = now
        overlay = self._overlay(now)
        overlay["events"] = self._event_counts()
        if overlay:
            if state.error_reason:
                overlay.pop("error_reason", None)  # the controller's own error comes first
            state = state.model_copy(update=overlay)
        try:
            self._pubs[state.arm].put(state)
            self.published[state.arm] += 1
        except Exception as e:  # noqa: BLE001 - the feedback thread must survive a closed session
            self._on_event("publish", f"arm/{state.arm}/state: {type(e).__name__}: {e}")

    def _event_counts(self, base: dict[str, int] | None = None) -> dict[str, int]:
        """The driver's clips, slow-downs, watchdog stops, refusals, alarms and faults since this run began."""
        c, base = self.driver.counters, self._events_base if base is None else base
        return {k: int(c.get(k, 0)) - base.get(k, 0) for k in ARM_EVENT_KINDS}

    def _overlay(self, now: float) -> dict[str, Any]:
        """What the driver adds to the controller's report: fault, lost link, recent event."""
        d = self.driver
        fault = d.fault  # read without the lock: the driver's state is swapped whole
        links = d.state.links
        if fault is not None:
            return {"error": True, "error_reason": f"driver fault: {fault}"}
        if links:
            return {"error": True, "error_reason": "link lost: " + "; ".join(f"{a}: {w}" for a, w in links.items())}
        with self._lock:
            notice = self._notice
        if notice is not None and now - notice[0] <= self.notice_s:
            return {"error_reason": notice[1]}
        return {}

    def status(self) -> dict[str, Any]:
        st = self.driver.status()
        with self._lock:
            return {
                "mode": st["mode"],
                "estop": st["estop"],
                "fault": st["fault"],
                "commands": self.commands,
                "refused": self.refused,
                "rejections": st["rejections"],
                "estops_received": self.estops,
                "states_published": dict(self.published),
                "driver_counters": st["counters"],
                "violations": st["violations"],
            }

    def close(self) -> dict[str, Any]:
        """Stop listening, bring the arms to rest, disable them, disconnect; the final status."""
        for s in (self._cmd_sub, self._estop_sub, self._run_sub):
            s.close()
        try:
            self.driver.close()
        except Exception as e:  # noqa: BLE001 - report, and still close the publishers
            log.error(f"shutdown: {type(e).__name__}: {e}")
        out = self.status()
        self.driver.on_state = None
        self.driver.on_tick = None
        for p in (*self._pubs.values(), self._ack, self._clock_sub):
            if p is not None:
                p.close()
        return out
