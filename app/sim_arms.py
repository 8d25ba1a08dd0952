"""The arm side of `bagit run`: what moves the bag's mounts in the in-process rig.

`Cr5Arms` is the arm driver's one path from a command to a ServoP (`ServoPath`: targets, Ruckig
smoothing, limits, reach, wire) and its watchdog, streaming ServoP, every servo period, to the two
simulated CR5 controllers of the `SimRig`, called in process instead of over TCP; their
feedback records become the `ArmState`s the controller reads, with the driver's fault laid over
them as the `bagit arm-driver` node does. A controller alarm, a refused ServoP or a step that
cannot be held latches a fault: the arms brake and later commands are refused, as on the rig.

`IdealArms` is the ablation: floating grippers that take each increment at once (no arm, no
driver), what the benchmark measured before the CR5s were in every run.

Both count what happened on the arm side (`events()`, the result's `arm_events`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np

from bagit.common.dobot import describe_alarm
from bagit.common.dual_arm import apply_increment
from bagit.common.messages import ArmState, Command
from bagit.common.results import ARM_EVENT_KINDS
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.common.so3 import matrix_to_rpy
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import controller_fault, feedback_state
from bagit.services.arm_driver.servo_path import ServoPath
from bagit.services.sim.cr5_sim import SimulatedCR5
from bagit.services.sim.rig_sim import SimRig

log = logging.getLogger("bagit.run.arms")


class Cr5Arms:
    """Two simulated CR5s behind the arm driver's servo path (see the module docstring)."""

    name = "cr5"

    def __init__(self, rig: RigConfig, robots: dict[ArmName, SimulatedCR5], step: Callable[[float], None], cfg: DriverConfig | None = None):
        """`robots`: the simulated controllers by arm; `step(dt)`: advances them (and the world they move)."""
        self.rig, self.robots, self._step = rig, robots, step
        self.cfg = cfg or DriverConfig()
        self.path = ServoPath(rig, self.cfg, on_event=self._on_event)
        self.period = self.path.period
        self.fault: str | None = None
        self.log: list[tuple[str, str]] = []  # (kind, detail) of each event, for the run's trace

    def _on_event(self, kind: str, detail: str) -> None:
        self.log.append((kind, detail))
        if kind != "hold":
            log.debug("%s: %s", kind, detail)

    @classmethod
    def of(cls, sim: SimRig, cfg: DriverConfig | None = None) -> Cr5Arms:
        """The simulated rig's two CR5s, stepped with its world."""
        return cls(sim.rig, sim.arms, sim.step, cfg)

    def step(self, dt: float) -> None:
        """Advance both controllers (and the world) `dt` simulated seconds."""
        self._step(dt)

    def start(self) -> None:
        """Bring both arms up as the driver does (ClearError, EnableRobot with the payload, SpeedFactor)
        and rest the motion where they are."""
        for a in ARMS:
            robot, conf = self.robots[a], self.rig.arms[a]
            robot.clear_error()
            robot.enable(conf.payload_kg, 1000.0 * np.asarray(conf.mount_offset, dtype=float))
            robot.set_speed_factor(conf.speed_factor)
        found = self.path.restart(self._records())
        if found is None or found:
            self._set_fault("the arms start outside the safety envelope: " + "; ".join(map(str, found or [])))

    def _records(self) -> dict[ArmName, np.ndarray]:
        return {a: self.robots[a].fill_feedback() for a in ARMS}

    def _set_fault(self, why: str) -> None:
        if self.fault is None:
            alarms = [f"{a}: " + ", ".join(f"{i} ({describe_alarm(i)})" for i in self.robots[a].alarms()) for a in ARMS if self.robots[a].alarms()]
            self.fault = why + (f" [alarms: {'; '.join(alarms)}]" if alarms else "")
            self.path.counters["faults"] += 1
            self._on_event("fault", self.fault)
        self.path.stop()

    def submit(self, cmd: Command, now: float) -> None:
        """The controller's command, as the driver takes it: hold brakes to rest; an increment starts a
        stream from where the controllers command the arms if none runs; refused while faulted."""
        if self.fault is not None:
            self.path.counters["rejected"] += 1
            return
        if cmd.mode == "hold":
            self.path.hold(cmd.reason or "controller asked to hold", now)
            return
        if not self.path.moving:
            found = self.path.restart(self._records())
            if found is None or found:
                self._set_fault("cannot restart the stream: " + ("non-finite feedback" if found is None else "; ".join(map(str, found))))
                return
            self.path.counters["reseeds"] += 1
        self.path.submit(np.asarray(cmd.u, dtype=float), float(cmd.dt), now)

    def servo(self, now: float) -> None:
        """One servo period: the controllers' alarms, the watchdog, then ServoP to both arms."""
        for a, rec in self._records().items():
            why = controller_fault(rec)
            if why is not None:
                if self.fault is None:
                    self.path.counters["alarms"] += 1
                self._set_fault(f"{a}: {why}")
        self.path.watchdog(now)
        out = self.path.cycle(now, ARMS)
        if out.fault is not None:
            self._set_fault(out.fault)
        if out.poses is None or self.fault is not None:
            return
        for a, cmd in out.servo.items():
            servo = self.robots[a].servo_j if cmd.name == "ServoJ" else self.robots[a].servo_p
            code = servo(cmd.on_wire(), cmd.t, cmd.aheadtime, cmd.gain)
            if code != 0:
                self._set_fault(f"{a}: {self.cfg.servo_command} refused ({code})")
                return

    def states(self) -> dict[ArmName, ArmState]:
        """Each arm as its controller reports it, the driver's fault laid over (as the arm-driver node does)."""
        out = {}
        for a, rec in self._records().items():
            st = feedback_state(a, rec, self.path.frames[a])
            fault = {"error": True, "error_reason": f"driver fault: {self.fault}"} if self.fault is not None and not st.error_reason else {}
            out[a] = self.path.lay_over(st, **fault)
        return out

    def events(self) -> dict[str, int]:
        c = self.path.counters
        return {k: int(c.get(k, 0)) for k in ARM_EVENT_KINDS}


class IdealArms:
    """Floating grippers: each increment moves the mounts' targets at once (the ablation)."""

    name = "ideal"
    period = None  # no servo cycle

    def __init__(self, sim: SimRig):
        self.sim = sim
        self.poses = {a: np.array(T, dtype=float) for a, T in sim.world.mount_home_poses().items()}
        self.fault: str | None = None  # floating grippers never fault

    def step(self, dt: float) -> None:
        self.sim.world.step(dt)

    def start(self) -> None:
        self.sim.world.set_mount_targets(self.poses)

    def submit(self, cmd: Command, now: float) -> None:
        if cmd.mode == "hold":
            return
        self.poses = apply_increment(self.poses, np.asarray(cmd.u, dtype=float))
        self.sim.world.set_mount_targets(self.poses)

    def servo(self, now: float) -> None:
        return None

    def states(self) -> dict[ArmName, ArmState]:
        return {a: ArmState(arm=a, q=np.zeros(6), qd=np.zeros(6), enabled=True, robot_mode=5,
                            tool_pose=np.concatenate([T[:3, 3], matrix_to_rpy(T[:3, :3])])) for a, T in self.poses.items()}

    def events(self) -> dict[str, int]:
        return dict.fromkeys(ARM_EVENT_KINDS, 0)  # no driver, no arm: nothing to clip, slow or stop
