"""The rig's clock as a service on the bus reads it: this host's, or the simulator's sim/clock."""

from __future__ import annotations

import zenoh

from bagit.common.bus.keys import Keys
from bagit.common.bus.pubsub import Subscriber
from bagit.common.clock import ClockKind, SimClock, WallClock, make_clock
from bagit.common.messages import ClockTick


def rig_clock(session: zenoh.Session, keys: Keys, kind: ClockKind) -> tuple[WallClock | SimClock, Subscriber | None]:
    """The clock a service on this bus reads: the wall clock, or a SimClock following sim/clock
    (close the returned subscriber with the service)."""
    clock = make_clock(kind)
    if not isinstance(clock, SimClock):
        return clock, None
    sim = clock
    return clock, Subscriber(session, keys.sim_clock, ClockTick, lambda m: sim.advance(m.t, m.servo_tick, m.control_step))

