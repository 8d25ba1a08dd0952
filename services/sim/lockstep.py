"""Lockstep: the simulator steps on only when the rig has answered the last frame and servo tick.

Two pure parts, with no bus and no clock of their own:

- `Schedule`: when the next camera frame and the next servo tick fall, on the simulated clock.
  `bagit run` and `bagit sim` both step by it, so the two hosts see the same events at the same
  simulated times (a servo tick first when both fall at once, then the frame).
- `Lockstep`: what the simulator still waits for. The simulator says what it just did
  (`servo_tick`, `frame`); the services' `StepAck`s (sim/ack), the simulated controllers' count
  of servo commands received and liveliness changes come in; `pending(now)` says who it still
  waits for. The chain of one frame, as `bagit run` runs it in one process:
    perception (the SOI, or none) -> the coordinator (its stage after the SOI; planning included)
    -> in a servo stage, the controller's command and status for it -> the arm driver's receipt
    of the command, and the coordinator's stage once it handled the status (the run may end there);
  and of one servo tick: the arm driver's cycle, then its ServoPs landed in the controllers.
  Perception's answer goes to the coordinator only (`ANSWERS_FOLLOWED`): the coordinator answers a
  frame once perception has, so its answer stands for both (a silence there is booked to perception
  first, as the chain's first link, then to the coordinator). So does the controller's, when its tick
  sent a status (the status is its answer): the coordinator's answer to that status names the tick's
  command; a tick with no status the controller answers itself.
  A service that is gone, or silent for `timeout_s` of wall time, is dropped from the wait for
  the rest of the run and said so: the simulated clock then goes on, and the coordinator's own
  limits (on that clock) fail the run with its reason. Between runs nothing is waited for.
  Such a drop, and an answer that says it went without something (`StepAck.late`), make the run
  not exact (`inexact`): the simulator's final truth says so, and so does `bagit up`'s result.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from bagit.common.lockstep import LOCKSTEP_TIMEOUT_S
from bagit.common.messages import StepAck
from bagit.common.names import FINAL_STAGES, LOCKSTEP_SERVICES, SERVO_STAGES

EPS_S = 1e-9
STAMP_TOL_S = 1e-6  # a frame's stamp matched in an answer
EARLY_KEPT = 16  # answers kept for steps not announced yet (a few per step)
# The services whose answers (sim/ack/<service>, and the coordinator's to statuses) the simulator follows.
ANSWERS_FOLLOWED: tuple[str, ...] = ("planner", "controller", "arm-driver")


@dataclass
class Schedule:
    """The simulated times of the next frame, the next servo tick (period None: no arms to tick) and,
    with frames further apart than the controller's keep-alive pace `keep_s`, its keep-alive ticks
    between them (`keep_due`): at a frame's time plus k * keep_s, k = 1, 2, ... before the next frame."""

    frame_dt: float
    period: float | None
    next_frame: float
    next_servo: float
    ticks: int = 0  # servo ticks so far
    keep_s: float | None = None  # None: frames come at least that often, no keep-alive ticks
    next_keep: float = float("inf")

    @classmethod
    def starting(cls, now: float, frame_dt: float, period: float | None, ticks: int = 0, keep_s: float | None = None) -> Schedule:
        """Both events due at `now`; servo ticks numbered on from `ticks` (their numbers never repeat);
        keep-alive ticks every `keep_s` between frames further apart than that."""
        return cls(frame_dt, period, now, now, ticks, keep_s if keep_s is not None and frame_dt > keep_s + EPS_S else None)

    def servo_due(self, now: float) -> int | None:
        """The number of the servo tick due at `now` (and the schedule moves past it), else None."""
        if self.period is None or now < self.next_servo - EPS_S:
            return None
        self.next_servo += self.period
        self.ticks += 1
        return self.ticks - 1

    def frame_pending(self, now: float) -> bool:
        """Whether a frame is due at `now` (the schedule does not move)."""
        return now >= self.next_frame - EPS_S

    def frame_due(self, now: float) -> bool:
        """Whether a frame is due at `now` (and the schedule moves past it)."""
        if now < self.next_frame - EPS_S:
            return False
        frame = self.next_frame
        self.next_frame += self.frame_dt
        if self.keep_s is not None:
            self.next_keep = self._before_frame(frame + self.keep_s)
        return True

    def keep_due(self, now: float) -> bool:
        """Whether a keep-alive tick is due at `now` (and the schedule moves past it); never at a frame's time."""
        if self.keep_s is None or now < self.next_keep - EPS_S:
            return False
        self.next_keep = self._before_frame(self.next_keep + self.keep_s)
        return True

    def _before_frame(self, t: float) -> float:
        """`t` if it falls before the next frame, else never (the frame's own tick comes first)."""
        return t if t < self.next_frame - EPS_S else float("inf")

    def until_next(self, now: float) -> float:
        """Simulated seconds to step before the next event (> 0)."""
        due = min(self.next_frame, self.next_servo) if self.period is not None else self.next_frame
        return max(min(due, self.next_keep) - now, EPS_S)


@dataclass
class _Frame:
    stamp: float
    stage: str | None = None  # the coordinator answered (after perception): its stage after the frame
    cmd_seq: int | None = None
    status_seq: int | None = None  # the controller's status for the frame
    controller: bool = False  # the controller answered
    after: str | None = None  # the coordinator's stage once it handled that status


@dataclass
class Lockstep:
    """What the simulator still waits for (see the module docstring)."""

    timeout_s: float = LOCKSTEP_TIMEOUT_S
    services: tuple[str, ...] = LOCKSTEP_SERVICES
    run_id: str | None = None
    dropped: dict[str, str] = field(default_factory=dict)  # service -> why it is no longer waited for
    frame: _Frame | None = None
    tick: tuple[int, float] | None = None  # (n, wall time asked)
    tick_sent: dict[str, int] | None = None  # the driver's ServoPs of the tick, per arm
    tick_base: dict[str, int] = field(default_factory=dict)  # the controllers' counts when the tick began
    received: dict[str, int] = field(default_factory=dict)  # the controllers' counts now
    commands: deque[int] = field(default_factory=lambda: deque(maxlen=64))  # seqs of the commands the driver has received
    since: float = 0.0  # wall time the current wait began
    notes: list[str] = field(default_factory=list)  # what the host should say (drops)
    stage: str | None = None  # the coordinator's stage after the last frame (or keep-alive tick) answered
    inexact: list[str] = field(default_factory=list)  # why the last run started is not exact (kept past its end)
    # Answers for a step not announced yet (as far as this side knows): an answer can overtake the
    # simulator's own bookkeeping of what it published. Taken up when that step is announced.
    early: deque[StepAck] = field(default_factory=lambda: deque(maxlen=EARLY_KEPT))

    # -- what the simulator does ------------------------------------------------------------------

    def start_run(self, run_id: str | None) -> None:
        """A new run (None: no run, nothing waited for; what made the last one inexact is kept)."""
        self.run_id, self.dropped, self.frame, self.tick, self.tick_sent = run_id, {}, None, None, None
        self.stage = None
        self.commands.clear()
        self.early.clear()
        if run_id is not None:
            self.inexact = []

    @property
    def active(self) -> bool:
        return self.run_id is not None

    def servo_tick(self, n: int, counts: dict[str, int], wall: float) -> None:
        """Servo tick n was published; `counts`: each simulated controller's servo commands so far."""
        self.tick, self.tick_sent, self.tick_base, self.received, self.since = (n, wall), None, dict(counts), dict(counts), wall

    def frame_published(self, stamp: float, wall: float) -> None:
        self.frame, self.since = _Frame(stamp), wall
        self._take_early(wall)

    def keepalive_published(self, stamp: float, wall: float) -> None:
        """A keep-alive tick at `stamp` (frames sparser than the controller's keep-alive pace): in a
        servo stage (as the last frame left it) the controller's answer, its command's receipt and
        the coordinator's answer to its status (a hold's) are waited for, as for a frame's."""
        self.frame, self.since = _Frame(stamp, stage=self.stage or "idle"), wall
        self._take_early(wall)

    def _take_early(self, wall: float) -> None:
        """The answers that came before the step now announced: its own are taken, older ones dropped."""
        f, held = self.frame, list(self.early)
        self.early.clear()
        for ack in held:
            if f is not None and ack.frame is not None and ack.frame > f.stamp + STAMP_TOL_S:
                self.early.append(ack)  # later still
            else:
                self.on_ack(ack, wall, held=True)

    def controllers(self, counts: dict[str, int]) -> None:
        """The simulated controllers' servo command counts now."""
        self.received = dict(counts)

    # -- what comes in ----------------------------------------------------------------------------

    def on_ack(self, ack: StepAck, wall: float, held: bool = False) -> None:
        """An answer (`held`: one kept in `early`, now taken up)."""
        if ack.late and not held and self.active and ack.run_id == self.run_id and len(self.inexact) < 100:
            self.inexact.append(f"{ack.service} answered without {ack.late}")
        f = self.frame
        if ack.service != "arm-driver" and ack.frame is not None and (f is None or ack.frame > f.stamp + STAMP_TOL_S):
            self.early.append(ack)  # for a step whose announcement this side has not booked yet
            return
        if ack.service == "arm-driver" and ack.tick is not None and self.tick is not None and ack.tick == self.tick[0]:
            self.tick_sent = dict(ack.servo_sent or {})
        elif ack.service == "arm-driver" and ack.cmd_seq is not None:
            self.commands.append(ack.cmd_seq)  # the receipt may overtake the controller's own answer
        elif f is None or (ack.frame is not None and abs(ack.frame - f.stamp) > STAMP_TOL_S):
            return
        elif ack.service == "planner" and ack.status_seq is not None:  # it stands for the controller's answer too
            f.after = ack.stage or "idle"
            f.controller, f.cmd_seq, f.status_seq = True, ack.cmd_seq, ack.status_seq
        elif ack.service == "planner":
            f.stage = ack.stage or "idle"
        elif ack.service == "controller":
            f.controller, f.cmd_seq, f.status_seq = True, ack.cmd_seq, ack.status_seq
        else:
            return
        self.since = wall  # progress: the silence clock starts again

    def on_alive(self, service: str, alive: bool) -> None:
        if not alive and self.active and service in self.services and service not in self.dropped:
            self._drop(service, "its liveliness token is gone")

    def _drop(self, service: str, why: str) -> None:
        self.dropped[service] = why
        self.inexact.append(f"{service} no longer waited for: {why}")
        self.notes.append(f"lockstep: no longer waiting for {service} in run {self.run_id}: {why}")

    # -- the verdict ------------------------------------------------------------------------------

    def _waits_for(self, service: str) -> bool:
        return self.active and service in self.services and service not in self.dropped

    def tick_pending(self) -> list[str]:
        """What the servo tick still waits for (the arm driver's cycle, its ServoPs landed); [] = the
        world may step on, as far as the tick goes."""
        if self.tick is None or not self._waits_for("arm-driver"):
            return []
        n = self.tick[0]
        if self.tick_sent is None:
            return [f"arm-driver: servo tick {n}"]
        late = [a for a, k in self.tick_sent.items() if self.received.get(a, 0) - self.tick_base.get(a, 0) < k]
        return [f"{a} CR5: the servo command of tick {n}" for a in late]

    def pending(self) -> list[str]:
        """Who the simulator still waits for, as short texts; [] = step on."""
        out = self.tick_pending()
        f = self.frame
        if f is None:
            return out
        if f.stage is None and self._waits_for("planner"):
            first = "perception" if self._waits_for("perception") else "planner"  # the chain's first link still waited on
            return out + [f"{first}: frame {f.stamp:.3f}"]
        if f.stage not in SERVO_STAGES:
            return out
        if not f.controller and self._waits_for("controller"):
            return out + [f"controller: frame {f.stamp:.3f}"]
        if f.cmd_seq is not None and f.cmd_seq not in self.commands and self._waits_for("arm-driver"):
            out.append(f"arm-driver: command {f.cmd_seq}")
        if f.controller and f.status_seq is not None and f.after is None and self._waits_for("planner"):
            out.append(f"planner: controller status {f.status_seq}")
        return out

    def ended(self) -> bool:
        """Whether the frame just answered ended the run (the coordinator's stage after it is final)."""
        f = self.frame
        return f is not None and (f.after in FINAL_STAGES or f.stage in FINAL_STAGES)

    def expire(self, wall: float) -> list[str]:
        """Drop the services the wait has been on for `timeout_s`; returns who is still pending."""
        waiting = self.pending()
        if waiting and wall - self.since > self.timeout_s:
            for w in waiting:
                service = w.split(":")[0]
                service = "arm-driver" if service.endswith("CR5") else service
                if service not in self.dropped:
                    self._drop(service, f"no answer for {self.timeout_s:g} s ({w})")
            self.since = wall
            waiting = self.pending()
        return waiting

    def done_with_step(self) -> None:
        """The simulator steps on: the tick and frame answered are forgotten (the stage they left kept)."""
        f = self.frame
        if f is not None:
            self.stage = f.after or f.stage or self.stage
        self.tick, self.tick_sent, self.frame = None, None, None
