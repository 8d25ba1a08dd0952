"""Lockstep's limits and its one way of waiting, shared by the simulator and every service.

In lockstep (`clock: sim`) the simulator steps the world on only when the rig has answered the
last frame or servo tick, so a run through `bagit up` is `bagit run`'s whatever the machine's load.
For that every wait on the way must end on what it waits for, never on a short wall-clock bound:
a service the scheduler keeps off the CPU, or one stopped (SIGSTOP) for seconds, only makes the
run slower. `StepWait` is that wait: woken by `notify()` when a message it may be waiting for
arrives (no polling), it gives up only after `LOCKSTEP_TIMEOUT_S` of wall time, which is the
simulator's own limit for a silent service; an answer made after such a give-up says so
(`StepAck.late`) and the run's result is then marked not exact.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

# A service silent this long (wall) is no longer waited for in that run (the simulator), and a
# service waiting this long for a message of the step answers without it (`StepAck.late`).
LOCKSTEP_TIMEOUT_S = 30.0
# The Zenoh link lease in lockstep: longer than any pause a run should survive exactly, so a stopped
# process keeps its links (and its liveliness token) and nothing sent meanwhile is lost. A process
# that dies closes its sockets, which every peer sees at once, whatever the lease.
LOCKSTEP_LEASE_MS = 60_000
_STOP_CHECK_S = 1.0  # a wait looks at its stop event at least this often (close() also notifies)


class StepWait:
    """A condition that the messages of a step notify (see the module docstring)."""

    def __init__(self) -> None:
        self._cond = threading.Condition()

    def notify(self, *_: object) -> None:
        """Something arrived: the waiter looks again (usable directly as a subscriber callback)."""
        with self._cond:
            self._cond.notify_all()

    def wait(self, ready: Callable[[], bool], stop: threading.Event, timeout_s: float = LOCKSTEP_TIMEOUT_S) -> bool:
        """Until `ready()` (True), `stop` is set or `timeout_s` of wall time has passed (False)."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not ready():
                left = deadline - time.monotonic()
                if stop.is_set() or left <= 0:
                    return False
                self._cond.wait(min(left, _STOP_CHECK_S))
        return True
