"""Which commands may move the arms, and who may release the e-stop: the arm driver's gate, pure.

The arms move only for the run the coordinator announced on run/state as servoing (its stage in
`SERVO_STAGES`), and only on commands that are still fresh when they are applied:

    why = command_refusal(cmd, run)            # the node, for each command: None, or a Refusal
    why = stale_refusal(cmd.stamp, now, limits.watchdog_s)   # the driver, as it applies one: None, or a Refusal
    why = stream_end(streaming_run, run)       # the node, on run/state: the run it streamed for is over
    why = estop_refusal(msg)                   # a release from anyone but the operator's tools

A hold is always taken (holding is always safe), and an e-stop engage from anyone. Each refusal has
a short `reason`, counted in the driver's `rejections`, and a sentence for the event. No bus, no
clock: the node and the driver pass in what they know.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from bagit.common.messages import Command, EStop, RunState
from bagit.common.names import ESTOP_RELEASE_SOURCES, SERVO_STAGES

NO_ACTIVE_RUN = "no_active_run"  # no run/state yet, no run id, or the run is not in a servo stage
WRONG_RUN = "wrong_run"  # a command for another run (or for none) than the servoing one
STALE = "stale"  # made longer ago than the watchdog: queued while the driver was stopped, or late
CLOCK_SKEW = "clock_skew"  # stamped further ahead of this host's clock than the watchdog
ESTOP_RELEASE_SOURCE = "estop_release_source"  # a release from a source not in ESTOP_RELEASE_SOURCES


@dataclass(frozen=True)
class Refusal:
    """Why a command (or an e-stop release) was not taken: `reason` is counted, `detail` is said."""

    reason: str
    detail: str

    def __str__(self) -> str:
        return f"{self.reason}: {self.detail}"


def servoing(run: RunState | None) -> bool:
    """True if `run` (the last run/state) names a run whose arms the controller moves now."""
    return run is not None and run.run_id is not None and run.stage in SERVO_STAGES


def command_refusal(cmd: Command, run: RunState | None) -> Refusal | None:
    """None if `cmd` may go to the driver under the last run/state `run`; else why not.

    Hold commands always pass. A servo command must carry the run id of a run that run/state shows in
    a servo stage: a sender that is not the run's controller, or a command from a run that is over,
    never moves the arms."""
    if cmd.mode == "hold":
        return None
    if not servoing(run):
        where = "no run/state yet" if run is None else f"run/state: run {run.run_id} {run.stage}"
        return Refusal(NO_ACTIVE_RUN, f"command {cmd.seq} for run {cmd.run_id}: no run is servoing ({where})")
    assert run is not None
    if cmd.run_id != run.run_id:
        return Refusal(WRONG_RUN, f"command {cmd.seq} is for run {cmd.run_id}, the servoing run is {run.run_id}")
    return None


def stale_refusal(stamp: float, now: float, max_age_s: float) -> Refusal | None:
    """None if a command made at `stamp` (its sender's wall clock) is fresh at `now` (ours); else why not.

    Older than `max_age_s` (the watchdog's time): it waited in a queue while the driver was stopped or
    starved, and the watchdog would already have stopped the arms it meant to move. Further ahead than
    that, or not a number: the hosts' clocks disagree, and no age can be trusted."""
    age = now - stamp
    if not math.isfinite(age):
        return Refusal(CLOCK_SKEW, f"its stamp {stamp!r} is no time")
    if age < -max_age_s:
        return Refusal(CLOCK_SKEW, f"stamped {-age:.2f} s ahead of this host's clock (limit {max_age_s:g} s): are the clocks synchronised?")
    if age > max_age_s:
        return Refusal(STALE, f"made {age:.2f} s ago, longer than the watchdog's {max_age_s:g} s")
    return None


def stream_end(streaming_run: str | None, run: RunState) -> str | None:
    """Why the arms must hold now that run/state says `run`, if they were streaming for `streaming_run`."""
    if streaming_run is None:
        return None
    if run.run_id != streaming_run:
        return f"run {streaming_run} is over (run/state: run {run.run_id} {run.stage})"
    if run.stage not in SERVO_STAGES:
        return f"run {streaming_run} {run.stage}" + (f": {run.reason}" if run.reason else "")
    return None


def estop_refusal(msg: EStop) -> Refusal | None:
    """None if `msg` may act: any engage, or a release from one of ESTOP_RELEASE_SOURCES."""
    if msg.may_act():
        return None
    return Refusal(ESTOP_RELEASE_SOURCE,
                   f"a release from {msg.source!r}: only {' and '.join(ESTOP_RELEASE_SOURCES)} may release the e-stop")
