"""Test helpers for the arm driver: two simulated CR5 controllers on loopback, recorders, a TCP proxy
(`bagit.services.sim.harness`, shared with the benchmarks and the probes), a controller stand-in and
the arm-driver node on an in-process bus."""

from __future__ import annotations

import contextlib
import threading
import time

import numpy as np

from bagit.common.messages import Command
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.sim.harness import (  # noqa: F401 - re-exported for the arm driver tests
    HOME_CENTRE,
    HOME_HALF_SEPARATION,
    FeedbackRecorder,
    RecordingServer,
    SimPair,
    TcpProxy,
    home_poses,
    servo_parameter,
    servo_positions,
    start_sims,
)
from bagit.up import SIM_DRIVER_TIMEOUTS

# The link time-outs `bagit up` gives a driver whose simulated controllers share the machine with it
# (a busy machine stalls the simulated feedback a while); tests of a lost link set their own.
SIM_CFG = DriverConfig(**SIM_DRIVER_TIMEOUTS)


def stream_at_rest(server: RecordingServer, t0: float) -> bool:
    """The ServoP targets `server` accepted since `t0` end at rest: the last two are the same point."""
    ts, xyz = servo_positions(server, t0=t0)
    return len(ts) >= 2 and float(np.linalg.norm(xyz[-1] - xyz[-2])) < 1e-4


class Streamer:
    """A controller stand-in: submits the increment u (12,) to a driver at `rate_hz` from a thread
    until stopped (or, with until_refused, until the driver refuses one)."""

    def __init__(self, drv, u: np.ndarray, rate_hz: float = 30.0, until_refused: bool = False) -> None:
        self.drv, self.u, self.dt, self.until_refused = drv, u, 1.0 / rate_hz, until_refused
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        k = 0
        while not self._stop.is_set():
            if not self.drv.submit(Command(u=self.u, dt=self.dt, seq=k)) and self.until_refused:
                return
            k += 1
            time.sleep(self.dt)

    def start(self) -> Streamer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()


@contextlib.contextmanager
def node_on_bus(rig: str, cfg: DriverConfig):
    """(sims, node, peer session, keys): an ArmDriverNode for two simulated CR5s on one in-process Zenoh
    peer, the test's publishers on the other; the node's log lines kept in `node.events`."""
    from bus_support import session_pair
    from log_support import LogLines

    from bagit.common.bus import Keys
    from bagit.services.arm_driver.driver import ArmDriver
    from bagit.services.arm_driver.node import ArmDriverNode

    sims = start_sims()
    gen = session_pair(rig)
    a, b = next(gen)
    lines = LogLines("bagit.arm_driver")
    node = ArmDriverNode(a, Keys(rig), ArmDriver(sims.rig, cfg))
    node.events = lines.messages
    try:
        yield sims, node, b, Keys(rig)
    finally:
        node.close()
        lines.close()
        gen.close()
        sims.close()
