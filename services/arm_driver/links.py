"""Both CR5 controllers over TCP/IP V4: the requests the driver makes of them, and what their replies mean.

`Cr5Links` holds a `DobotClient` per arm and does the blocking parts of the driver's work: bring-up
(ClearError, EnableRobot with the payload, SpeedFactor, then waiting for the arm to report enabled),
shutdown, EmergencyStop to both arms back to back, the ServoPs of a period with their replies
checked a period later (so a slow controller never stalls the other arm), and the alarm ids of a
fault. It decides nothing: what a reply or a record means for the driver comes back as a machine
event (`machine.py`) for the driver to step.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable, Sequence

import numpy as np

from bagit.common.dobot import RobotMode, describe_alarm
from bagit.common.errors import ProtocolError
from bagit.common.rig import ARMS, ArmName, RigConfig
from bagit.services.arm_driver import machine as m
from bagit.services.arm_driver.client import CommandRejected, ConnectionLost, DobotClient, PendingReply
from bagit.services.arm_driver.config import DriverConfig
from bagit.services.arm_driver.frames import controller_fault
from bagit.services.arm_driver.wire import ServoCommand

RUNNING_MODES = (int(RobotMode.ENABLE), int(RobotMode.RUNNING))
SETTLED_MM_S = 1.0  # an arm this slow (and idle) is where it will stay


class Cr5Links:
    """The two controllers' clients (see the module docstring); `on_feedback(arm)` makes each packet's callback."""

    def __init__(self, rig: RigConfig, cfg: DriverConfig, on_feedback: Callable[[ArmName], Callable[[np.ndarray, float], None]]):
        self.rig, self.cfg = rig, cfg
        self.clients = {
            a: DobotClient(
                a, rig.arms[a].host, rig.arms[a].dashboard_port, rig.arms[a].feedback_port,
                reply_timeout_s=cfg.reply_timeout_s, connect_timeout_s=cfg.connect_timeout_s,
                reconnect_initial_s=cfg.reconnect_initial_s, reconnect_max_s=cfg.reconnect_max_s,
                on_feedback=on_feedback(a),
            )
            for a in ARMS
        }
        self.seen_epoch = {a: 0 for a in ARMS}
        self.in_flight: dict[ArmName, deque[PendingReply]] = {a: deque() for a in ARMS}

    def record(self, arm: ArmName) -> np.ndarray | None:
        """The arm's newest feedback record (None before its first packet since connecting)."""
        return self.clients[arm].latest()[0]

    # -- bring-up and shutdown -------------------------------------------------------------------

    def open(self) -> None:
        """Connect to both controllers and bring them up as on the real rig. Raises ProtocolError
        (unreachable, a refused command, an arm that never reports enabled, a tool or user frame other
        than 0); both arms are disabled and disconnected again then."""
        try:
            for c in self.clients.values():
                c.connect()
            for a, c in self.clients.items():
                self.seen_epoch[a] = c.epoch
                if not c.wait_feedback(max(self.cfg.feedback_timeout_s * 5, 1.0)):
                    raise ProtocolError(f"{a}: no feedback packet on port {c.feedback_port}")
            self.bring_up()
            for a in ARMS:
                rec = self.record(a)
                assert rec is not None
                if int(rec["Tool"]) != 0 or int(rec["User"]) != 0:
                    raise ProtocolError(
                        f"{a}: tool frame {int(rec['Tool'])} / user frame {int(rec['User'])} selected; "
                        "the driver commands the flange in the base frame (tool 0, user 0)"
                    )
        except BaseException:
            for c in self.clients.values():
                if c.connected:
                    try:
                        c.disable()
                    except ProtocolError:
                        pass
                c.close()
            raise

    def enable(self, arm: ArmName) -> None:
        """ClearError, EnableRobot (the payload and its centre), SpeedFactor."""
        c, conf = self.clients[arm], self.rig.arms[arm]
        c.clear_error()
        x, y, z = conf.mount_offset
        c.enable(conf.payload_kg, (1000.0 * x, 1000.0 * y, 1000.0 * z))
        c.speed_factor(conf.speed_factor)

    def bring_up(self, arms: Sequence[ArmName] = ARMS) -> None:
        """`enable` each of `arms`, then wait until both arms report enabled."""
        for a in arms:
            self.enable(a)
        deadline = time.monotonic() + self.cfg.enable_timeout_s
        while True:
            waiting = [a for a in ARMS if not self._enabled(self.record(a))]
            if not waiting:
                return
            if time.monotonic() > deadline:
                rec = self.record(waiting[0])
                mode = int(rec["RobotMode"]) if rec is not None else "unknown"
                raise ProtocolError(f"{waiting[0]}: not enabled {self.cfg.enable_timeout_s:.1f} s after EnableRobot (robot mode {mode})")
            time.sleep(0.01)

    @staticmethod
    def _enabled(rec: np.ndarray | None) -> bool:
        return rec is not None and bool(int(rec["EnableStatus"])) and int(rec["RobotMode"]) in RUNNING_MODES

    def close(self, disable: bool, on_error: Callable[[str, str], None]) -> None:
        """DisableRobot (if `disable`) and disconnect both."""
        for a, c in self.clients.items():
            if c.connected and disable:
                try:
                    c.disable()
                except ProtocolError as e:
                    on_error("shutdown", f"{a}: DisableRobot failed: {e}")
            c.close()

    def clear_faults(self) -> None:
        """Bring up again the arms in error, disabled or not in a running mode (ProtocolError: no feedback)."""
        for a in ARMS:
            rec = self.record(a)
            if rec is None:
                raise ProtocolError(f"{a}: no feedback; cannot clear the fault")
            if int(rec["ErrorStatus"]) or not self._enabled(rec):
                self.enable(a)
        self.bring_up(())

    # -- e-stop ----------------------------------------------------------------------------------

    def emergency_stop(self, on_error: Callable[[str, str], None]) -> dict[ArmName, bool]:
        """EmergencyStop(1) to both, then wait for both replies: neither waits for the other's. Per arm: confirmed."""
        text = self.clients[ARMS[0]].emergency_stop_text(True)
        pending: dict[ArmName, PendingReply] = {}
        for a, c in self.clients.items():
            try:
                pending[a] = c.send(text)
            except ProtocolError as e:
                on_error("estop", f"{a}: not sent: {e}")
        reached = {a: False for a in ARMS}
        for a, p in pending.items():
            try:
                self.clients[a].check(self.clients[a].wait(p))
                reached[a] = True
            except ProtocolError as e:
                on_error("estop", f"{a}: not confirmed: {e}")
        return reached

    def resend_emergency_stop(self, arm: ArmName) -> str | None:
        """EmergencyStop(1) to a controller back on line, not waiting for its reply; why it failed, or None."""
        c = self.clients[arm]
        try:
            c.send(c.emergency_stop_text(True))
            return None
        except ProtocolError as e:
            return str(e)

    def release_emergency_stop(self) -> None:
        """EmergencyStop(0) to both, then the bring-up (ProtocolError: refused or not connected)."""
        for a, c in self.clients.items():
            if not c.connected:
                raise ProtocolError(f"{a}: cannot reset the e-stop: not connected ({c.last_error})")
            c.check(c.request(c.emergency_stop_text(False)))
        self.bring_up()

    def alarms(self) -> str:
        """The controllers' latched alarm ids, described: which limit tripped, not just that one did."""
        found: list[str] = []
        for a, c in self.clients.items():
            if not c.connected:
                continue
            try:
                ids = sorted({i for group in c.error_ids() for i in group})
            except ProtocolError as e:
                found.append(f"{a}: GetErrorID failed ({e})")
                continue
            if ids:
                found.append(f"{a}: " + ", ".join(f"{i} ({describe_alarm(i)})" for i in ids))
        return "; ".join(found)

    # -- the servo period ------------------------------------------------------------------------

    def send(self, commands: dict[ArmName, ServoCommand], step: Callable[[m.Event], object], halted: Callable[[], bool]) -> list[ArmName]:
        """Each arm's ServoP (its reply is checked a period later), unless `halted()` (the e-stop latched) when
        its turn on the wire comes; the arms it went to. A link lost sending one is stepped (`step`) at once."""
        sent = []
        for a, cmd in commands.items():
            text = DobotClient.servo_text(cmd.name, cmd.values, cmd.t, cmd.aheadtime, cmd.gain)
            try:
                pending = self.clients[a].send_unless(text, halted)
            except ProtocolError as e:
                step(m.LinkLost(a, str(e)))
                continue
            if pending is not None:
                self.in_flight[a].append(pending)
                sent.append(a)
        return sent

    def check_replies(self, now: float, lockstep: bool, failed: Callable[[ArmName], int], step: Callable[[m.Event], object]) -> None:
        """Earlier periods' ServoP replies, each stepped (`step`) as an event as it is read: a refusal, a
        lost link, a failed request; a good one only where `failed(arm)` has a tally to reset. Lockstep:
        the simulated controller has taken every ServoP of the last tick (the world waited for it), so
        its reply is on the way: waited for from now, never judged by a wall-clock age a pause of this
        process (or of the simulator) would inflate."""
        for a, queue in self.in_flight.items():
            while queue and (lockstep or queue[0].done or now - queue[0].sent_at >= self.cfg.reply_timeout_s):
                p, c = queue.popleft(), self.clients[a]
                try:
                    c.check(c.wait(p, timeout=self.cfg.reply_timeout_s if lockstep and not p.done else 0.0))
                    if not failed(a):
                        continue  # a good reply with no tally to reset: no need to step the machine
                    event: m.Event = m.ReplyOk(a)
                except CommandRejected as e:
                    event = m.ReplyRejected(str(e))  # refused across the e-stop on the wire: expected, no fault
                except ConnectionLost as e:
                    event = m.LinkLost(a, str(e))
                except ProtocolError as e:
                    event = m.ReplyFailed(a, str(e), self.cfg.max_failed_requests)
                step(event)

    def watch(self, rig_now: float | None, supervising: Callable[[], bool], step: Callable[[m.Event], object]) -> None:
        """Each link's condition, stepped (`step`) as events: down, silent longer than `feedback_timeout_s`
        (dropped), back (after its first packet), a controller in error, an arm disabled behind the
        driver's back (the last two only while `supervising()`: not latched or closing). `rig_now`: the
        simulated rig's time (None on the wall clock): a link is silent when the rig's clock has gone
        past its newest packet's stamp, since a simulator the machine starves sends nothing because
        nothing happens, which is no lost link."""
        for a, c in self.clients.items():
            if not c.connected:
                step(m.LinkLost(a, c.last_error or "disconnected"))
                continue
            rec = self.record(a)
            silent = c.silent_for() if rig_now is None or rec is None else max(0.0, rig_now - float(rec["TimeStamp"]) / 1000.0)
            if silent > self.cfg.feedback_timeout_s:
                c.drop(f"no feedback for {silent * 1000:.0f} ms")
                step(m.LinkLost(a, "feedback lost"))
                continue
            if c.epoch != self.seen_epoch[a]:
                if self.record(a) is None:
                    continue  # reconnected; wait for its first packet
                self.seen_epoch[a] = c.epoch
                step(m.LinkBack(a))  # the machine re-asserts a latched e-stop, or restarts from the measured pose
            rec = self.record(a)
            if rec is None or not supervising():
                continue
            if (why := controller_fault(rec)) is not None:
                step(m.ArmAlarm(a, why))
            elif not int(rec["EnableStatus"]):
                step(m.FaultRaised(f"{a}: disabled (robot mode {int(rec['RobotMode'])})"))

    def settled(self) -> bool:
        """Both controllers report the arm idle and still, so the measured pose is where it will stay."""
        for a in ARMS:
            rec = self.record(a)
            if rec is None or int(rec["RobotMode"]) != int(RobotMode.ENABLE):
                return False
            if np.linalg.norm(rec["TCPSpeedActual"][:3]) > SETTLED_MM_S:
                return False
        return True

    def in_error(self, arm: ArmName) -> bool:
        rec = self.record(arm)
        return rec is None or controller_fault(rec) is not None
