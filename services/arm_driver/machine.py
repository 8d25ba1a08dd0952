"""The arm driver's supervision as a pure state machine: events in (with `now` where time matters), effects out.

    state, effects = step(state, EstopEngaged("operator"))     # -> [HaltPipe(), Count('estops'), Note('estop', ...)]

What it decides: whether the driver may stream (`blocker`, `mode`), the latches (e-stop, fault),
which links are down and which arms must not be commanded until the stream restarts from the
measured poses, when that restart is due (the arms settled, or SETTLE_TIMEOUT_S after it became
possible), when a run of bad ServoP replies is a fault, and when to ask the controllers for their
alarm ids. What it does not do: sockets, threads, the motion pipeline; `ArmDriver`
(services/arm_driver/driver.py) feeds it what the links and the loop saw and carries out the
effects, in order, under its lock. The state is immutable, so the feedback thread and the node read
it without the lock (a latch is swapped whole).

Why a machine: the same rules were spread over a dozen mutable fields and three threads; here each
transition can be tested alone (tests/arm_driver/test_arm_driver_machine.py), events in -> effects out.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Literal

from bagit.common.rig import ARMS, ArmName

SETTLE_TIMEOUT_S = 1.0  # a restart waits at most this long for the arms to report idle

Mode = Literal["off", "estopped", "fault", "link_down", "restarting", "streaming", "stopping", "holding"]
Blocker = Literal["estopped", "fault", "link_down", "restarting"]


@dataclass(frozen=True)
class DriverState:
    """Everything the driver's rules depend on besides the motion itself."""

    started: bool = False
    closing: bool = False
    estop: bool = False
    estop_reason: str | None = None
    estop_unconfirmed: frozenset[ArmName] = frozenset()  # arms whose controller did not confirm EmergencyStop(1)
    fault: str | None = None
    fault_alarms_asked: bool = False  # GetErrorID asked since the fault latched (once per fault)
    links_down: tuple[tuple[str, str], ...] = ()  # (arm, why), in the order they went down
    needs_reset: bool = False  # the stream restarts from the measured poses before anything moves
    stale: frozenset[ArmName] = frozenset()  # arms not to command until that restart
    reset_asked: float = -math.inf  # when the restart first became possible (it waits for the arms to settle)
    failed_requests: tuple[tuple[str, int], ...] = tuple((a, 0) for a in ARMS)  # motion requests in a row without a good reply

    @property
    def links(self) -> dict[str, str]:
        return dict(self.links_down)

    def failed(self, arm: ArmName) -> int:
        return dict(self.failed_requests)[arm]


# ---- effects ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StopPipe:
    """Brake both arms to rest along the trajectory (the halting profile)."""


@dataclass(frozen=True)
class HaltPipe:
    """Drop the trajectory at once: nothing more is streamed (the e-stop; the controllers stop the arms)."""


@dataclass(frozen=True)
class Restart:
    """Restart the pipeline at rest from the poses the controllers command; report `Restarted`."""


@dataclass(frozen=True)
class ClearInFlight:
    """Forget the ServoP replies still awaited from `arm` (its link is gone)."""

    arm: ArmName


@dataclass(frozen=True)
class ResendEstop:
    """Send EmergencyStop(1) to `arm` again (it reconnected without having confirmed it); report `EstopResent`."""

    arm: ArmName


@dataclass(frozen=True)
class AskAlarms:
    """Ask the controllers for their latched alarm ids (off the servo loop: it blocks); report `AlarmsFound`."""


@dataclass(frozen=True)
class Count:
    """Add one to the driver's counter `name`."""

    name: str


@dataclass(frozen=True)
class Note:
    """An event for the driver's log and its `on_event` subscriber."""

    kind: str
    detail: str


Effect = StopPipe | HaltPipe | Restart | ClearInFlight | ResendEstop | AskAlarms | Count | Note


# ---- events ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Started:
    """Both arms are up and enabled: restart from their poses and run."""


@dataclass(frozen=True)
class Closing:
    """close() began: brake to rest, refuse commands."""


@dataclass(frozen=True)
class Closed:
    """close() is over: the arms are disabled and the links closed."""


@dataclass(frozen=True)
class EstopEngaged:
    reason: str


@dataclass(frozen=True)
class EstopSent:
    """EmergencyStop(1) went out; `unconfirmed`: the arms whose controller did not confirm it."""

    unconfirmed: frozenset[ArmName]


@dataclass(frozen=True)
class EstopReleased:
    """Both controllers released, cleared and re-enabled (reset_estop)."""


@dataclass(frozen=True)
class EstopResent:
    arm: ArmName
    error: str | None = None  # None: sent


@dataclass(frozen=True)
class FaultRaised:
    why: str


@dataclass(frozen=True)
class ArmAlarm:
    """An arm's feedback reports its controller in error (counted once per latched fault)."""

    arm: ArmName
    why: str


@dataclass(frozen=True)
class FaultCleared:
    """The arms were cleared and re-enabled (clear_fault)."""


@dataclass(frozen=True)
class LinkLost:
    arm: ArmName
    why: str


@dataclass(frozen=True)
class LinkBack:
    """`arm`'s controller reconnected and its first feedback packet arrived."""

    arm: ArmName


@dataclass(frozen=True)
class Restarted:
    """What a `Restart` found: 'no_feedback' (an arm has not reported: nothing changes), 'non_finite'
    (its pose cannot be restarted from), or 'ok' with the envelope's `violations` (a fault if any)."""

    outcome: Literal["ok", "no_feedback", "non_finite"]
    violations: tuple[str, ...] = ()


@dataclass(frozen=True)
class Cycle:
    """A servo cycle at `now` (the motion's clock); `moving`: the pipeline streams or brakes;
    `settled`: both arms report idle and still."""

    now: float
    moving: bool
    settled: bool


@dataclass(frozen=True)
class ReplyOk:
    arm: ArmName


@dataclass(frozen=True)
class ReplyRejected:
    """A ServoP refused by the controller."""

    why: str


@dataclass(frozen=True)
class ReplyFailed:
    """A ServoP answered with garbage or not at all."""

    arm: ArmName
    why: str
    max_failed: int


@dataclass(frozen=True)
class AlarmsDue:
    """The supervisor's turn: ask for the alarm ids of a fault not yet asked about."""


@dataclass(frozen=True)
class AlarmsFound:
    text: str  # '' : none found


Event = (
    Started | Closing | Closed | EstopEngaged | EstopSent | EstopReleased | EstopResent | FaultRaised | ArmAlarm | FaultCleared
    | LinkLost | LinkBack | Restarted | Cycle | ReplyOk | ReplyRejected | ReplyFailed | AlarmsDue | AlarmsFound
)


# ---- queries ---------------------------------------------------------------------------------------


def blocker(s: DriverState) -> Blocker | None:
    """Why streaming is blocked while running (the latched states first), or None."""
    if s.estop:
        return "estopped"
    if s.fault is not None:
        return "fault"
    if s.links_down:
        return "link_down"
    if s.needs_reset:
        return "restarting"
    return None


def refusal(s: DriverState) -> str | None:
    """Why a command is refused now ('not_running' or a blocker), or None."""
    if not s.started or s.closing:
        return "not_running"
    return blocker(s)


def mode(s: DriverState, pipe_mode: str) -> Mode:
    """off | estopped | fault | link_down | restarting | streaming | stopping | holding (`pipe_mode`: the pipeline's)."""
    if not s.started:
        return "off"
    b = blocker(s)
    if b is not None:
        return b
    return "streaming" if pipe_mode == "position" else "stopping" if pipe_mode == "stopping" else "holding"


def commandable(s: DriverState, arm: ArmName) -> bool:
    """May `arm` be sent motion (its link is up and it is not waiting for the restart)?"""
    return arm not in s.links and arm not in s.stale


# ---- transitions -----------------------------------------------------------------------------------


def _fault(s: DriverState, why: str) -> tuple[DriverState, list[Effect]]:
    """Latch the first fault (a later one does not replace it); brake either way."""
    if s.fault is None:
        return replace(s, fault=why, fault_alarms_asked=False), [Count("faults"), Note("fault", why), StopPipe()]
    return s, [StopPipe()]


def _with_failed(s: DriverState, arm: ArmName, n: int) -> DriverState:
    return replace(s, failed_requests=tuple((a, n if a == arm else k) for a, k in s.failed_requests))


def step(s: DriverState, ev: Event) -> tuple[DriverState, list[Effect]]:
    """The next state and the effects, in the order they are to be carried out."""
    eff: list[Effect]
    if isinstance(ev, Started):  # `closing` stays as it was: a driver once closed is not reopened
        return replace(s, started=True), [Restart(), Note("started", "both arms enabled")]
    if isinstance(ev, Closing):
        return replace(s, closing=True), [StopPipe()]
    if isinstance(ev, Closed):
        return replace(s, started=False), [Note("closed", "both arms disabled" if not s.estop else "closed with the e-stop latched")]
    if isinstance(ev, EstopEngaged):
        return replace(s, estop=True, estop_reason=ev.reason), [HaltPipe(), Count("estops"), Note("estop", ev.reason)]
    if isinstance(ev, EstopSent):
        return replace(s, estop_unconfirmed=frozenset(ev.unconfirmed)), []
    if isinstance(ev, EstopReleased):
        if not s.estop:
            return s, []
        return (replace(s, estop=False, estop_reason=None, estop_unconfirmed=frozenset(), fault=None, needs_reset=True),
                [Note("estop_reset", "controllers released and enabled")])
    if isinstance(ev, EstopResent):
        if ev.error is not None:
            return s, [Note("estop", f"{ev.arm}: still not sent: {ev.error}")]
        return replace(s, estop_unconfirmed=s.estop_unconfirmed - {ev.arm}), [Note("estop", f"{ev.arm}: re-sent after reconnecting")]
    if isinstance(ev, FaultRaised):
        return _fault(s, ev.why)
    if isinstance(ev, ArmAlarm):
        counted: list[Effect] = [Count("alarms")] if s.fault is None else []
        s2, eff = _fault(s, f"{ev.arm}: {ev.why}")
        return s2, counted + eff
    if isinstance(ev, FaultCleared):
        if s.fault is None:
            return s, []
        return (replace(s, fault=None, needs_reset=True, failed_requests=tuple((a, 0) for a in ARMS)),
                [Note("fault_cleared", "arms enabled")])
    if isinstance(ev, LinkLost):
        s2 = replace(s, stale=s.stale | {ev.arm}, needs_reset=True)
        eff = []
        if ev.arm not in s.links:
            s2 = replace(s2, links_down=s.links_down + ((ev.arm, ev.why),))
            eff = [Count("links_lost"), Note("link_lost", f"{ev.arm}: {ev.why}"), ClearInFlight(ev.arm)]
        return s2, eff + [StopPipe()]
    if isinstance(ev, LinkBack):
        s2 = replace(s, links_down=tuple((a, w) for a, w in s.links_down if a != ev.arm))
        eff = [Count("reconnects"), Note("reconnected", ev.arm)]
        if s.estop and ev.arm in s.estop_unconfirmed:
            eff.append(ResendEstop(ev.arm))
        return s2, eff
    if isinstance(ev, Restarted):
        if ev.outcome == "no_feedback":
            return s, []
        if ev.outcome == "non_finite":
            return _fault(s, "the feedback reports a non-finite pose; cannot restart from it")
        s2 = replace(s, needs_reset=False, reset_asked=-math.inf, stale=frozenset())
        if ev.violations:
            return _fault(s2, "the arms are outside the safety envelope: " + "; ".join(ev.violations))
        return s2, []
    if isinstance(ev, Cycle):
        if s.estop or not (s.needs_reset and not s.links_down and s.fault is None and not ev.moving):
            return s, []
        asked = ev.now if s.reset_asked == -math.inf else s.reset_asked
        s2 = replace(s, reset_asked=asked)
        return s2, [Restart()] if ev.settled or ev.now - asked > SETTLE_TIMEOUT_S else []
    if isinstance(ev, ReplyOk):
        return _with_failed(s, ev.arm, 0), []
    if isinstance(ev, ReplyRejected):
        return (s, []) if s.estop else _fault(s, ev.why)  # a ServoP that crossed the e-stop on the wire is refused: expected
    if isinstance(ev, ReplyFailed):
        n = s.failed(ev.arm) + 1
        s2 = _with_failed(s, ev.arm, n)
        eff = [Count("servo_failed"), Note("servo", ev.why)]
        if n >= ev.max_failed:
            s3, more = _fault(s2, f"{ev.arm}: {n} motion requests in a row without a good reply ({ev.why})")
            return s3, eff + more
        return s2, eff
    if isinstance(ev, AlarmsDue):
        if s.fault is not None and not s.fault_alarms_asked:
            return replace(s, fault_alarms_asked=True), [AskAlarms()]
        return s, []
    if isinstance(ev, AlarmsFound):
        if not ev.text:
            return s, []
        s2 = replace(s, fault=f"{s.fault} [alarms: {ev.text}]") if s.fault is not None else s
        return s2, [Note("alarms", ev.text)]
    raise TypeError(f"not a driver event: {ev!r}")

