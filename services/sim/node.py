"""The simulator on Zenoh: the services' camera, and the world reset between runs.

`SimNode.run()` paces the simulated rig (bagit.services.sim.rig_sim.SimRig, its CR5s on TCP) to
the wall clock and publishes an RgbdFrame on camera/rgbd `fps` times per simulated second (by
default WALL_FPS; in lockstep the run's control rate, a frame per control tick as in `bagit run`),
stamped with the wall-clock time the image was taken (so perception and control can judge its
age). If the machine cannot keep up, simulated time runs slower than the wall clock: frames then
come less often per wall second, and the node says its real-time factor on stderr and in
sim/truth.

Between runs the world follows run/state: a new run id in `perceiving` with a scenario_doc
rebuilds the world for that scenario and seed, re-places the simulated CR5s at its start (their
TCP servers and clients stay), lets the bag settle, and only then publishes frames again, so no
frame of the old world is stamped after the reset. In lockstep the world the node starts with settles
at once, while the services start: a run of that scenario and seed (`bagit up SCENARIO`'s) then takes
it as it is (`SimRig.resettle`, the same world bit for bit), so its reset costs next to nothing.

Ground truth goes on sim/truth (tests and benchmarks only; no service subscribes to it).

With `clock="sim"` (the bus config's `clock: sim`, `bagit up`'s default) the node runs lockstep
instead (`run` -> `_run_lockstep`): the rig's clock is the simulated controllers' time, published
on sim/clock at every event of the `Schedule` (a servo tick, then a frame, stamped with that time;
with frames sparser than the run's controller keep-alive pace, keep-alive ticks between them),
and while a run is active the world steps on only when the rig has answered (`Lockstep`, from the
services' sim/ack and the controllers' servo counts). A loaded machine then makes a run slower,
never different. A lockstep run goes as fast as the rig answers (no faster than `speed` if set);
between runs it is paced to the wall clock (`speed`, default real time) and the world rests while no
arm moves (`SimRig.idle`). While the rig works on
a frame the world already steps on to the next event (`_step_ahead`: provably the same world), so
the simulator's physics overlaps the services' work on the machine's other core; and a servo tick
that falls with a frame is answered while that frame renders (the render reads the world at the
tick, which the tick's ServoPs move only after it; the world steps on once they have landed).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.bus import Keys, LivelinessWatcher, Publisher, Subscriber, declare_alive
from bagit.common.clock import ClockKind
from bagit.common.dobot import describe_alarm
from bagit.common.errors import BagItError
from bagit.common.lockstep import LOCKSTEP_TIMEOUT_S
from bagit.common.messages import ClockTick, RgbdFrame, RunState, SimTruth, StepAck
from bagit.common.names import FINAL_STAGES
from bagit.common.params import MethodParams, merge_params
from bagit.common.scenario import Scenario
from bagit.services.controller.session import tick_period
from bagit.services.sim.lockstep import ANSWERS_FOLLOWED, Lockstep, Schedule
from bagit.services.sim.rig_sim import SETTLE_S, SimRig, camera_fps
from bagit.services.sim.truth import GroundTruth

EXPIRE_CHECK_S = 1.0  # lockstep: while waiting, how often (wall) a silent service's time-out is looked at
IDLE_FPS = 2.0  # lockstep between runs: camera frames per simulated second (the scene stays live; nothing is servoed)

SERVICE_NAME = "sim"


class SimNodeConfig(BaseModel):
    """Rates of the simulator node."""

    model_config = ConfigDict(extra="forbid")

    speed: float | None = Field(None, gt=0, le=1000, description="simulated seconds per wall second at most; None: a lockstep run as "
                                "fast as the rig answers, real time otherwise (between runs, on the wall clock)")
    fps: float | None = Field(None, gt=0, le=120, description="camera frames per simulated second (at most the camera's rate); "
                              "None: `camera_fps`'s default, the run's control rate in lockstep, WALL_FPS on the wall clock")
    camera: bool = True
    chunk_s: float = Field(0.02, gt=0, le=0.2, description="simulated seconds stepped between checks")
    settle_s: float = Field(SETTLE_S, ge=0, le=10, description="simulated seconds the bag hangs still after a reset, no frames")
    truth_hz: float = Field(2.0, gt=0, le=50)
    report_every_s: float = Field(5.0, gt=0, description="how often the real-time factor is printed (wall seconds)")
    lockstep_timeout_s: float = Field(LOCKSTEP_TIMEOUT_S, gt=0, le=3600,
                                      description="lockstep: a service silent this long (wall s) is no longer waited for")


@dataclass
class SimStats:
    sim_s: float = 0.0
    wall_s: float = 0.0
    realtime_factor: float = 0.0
    frames: int = 0
    resets: int = 0


class SimNode:
    """A SimRig on the bus (see the module docstring). `run()` blocks until `stop` is set."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        rig: SimRig,
        config: SimNodeConfig | None = None,
        scenario_name: str | None = None,
        say: Callable[[str], None] = print,
        clock: ClockKind = "wall",
    ) -> None:
        self.cfg = config or SimNodeConfig()
        self.clock = clock
        self.rig = rig
        self.keys = keys
        self.say = say
        self.scenario_name = scenario_name
        self.run_id: str | None = None
        self.stats = SimStats()
        self._rtf_window = 1.0  # simulated over wall seconds over the last report window (periodic truth)
        self._run_t0 = (0.0, time.monotonic())  # the current run's start: rig clock, wall (monotonic)
        self._step_truth: GroundTruth | None = None  # lockstep: the truth of the step the world stepped ahead of
        # lockstep: the world time of the last frame (between runs, IDLE_FPS of them). The first comes an idle
        # period after the start: a run asked at once (`bagit up SCENARIO`) then renders first in its own world,
        # and the start-up world never pays a renderer (~0.1 CPU s of GL context and noise, beside services starting)
        self._idle_frame = self.rig.time
        self._lock = threading.Lock()
        self._pending: tuple[str, dict[str, Any], int, str | None, dict[str, Any]] | None = None
        self._keep_s: float | None = None  # lockstep: the run's controller keep-alive pace (`tick_period`)
        self._fps = camera_fps(self.cfg.fps, clock == "sim", MethodParams().controller.control_rate_hz)  # the run's, from its reset
        self._seen_runs: set[str] = set()
        self._world_frames = 0  # frames of the current world (lockstep numbers frames per world)
        self._ended: str | None = None  # the last run whose final truth went out (or is due)
        self._truth_due = False
        self._camera_paused: str | None = None
        self._frame_pub = Publisher(session, keys.camera_rgbd, RgbdFrame, lockstep=clock == "sim")
        self._truth_pub = Publisher(session, keys.sim_truth, SimTruth)
        self._state_sub = Subscriber(session, keys.run_state, RunState, self._on_state)
        self._cond = threading.Condition(self._lock)
        self._waiting_tick_only = False  # what the lockstep wait is waiting for (`_wake_if_answered`)
        self.lockstep = Lockstep(timeout_s=self.cfg.lockstep_timeout_s)
        self._lockstep_parts: list[Any] = []
        if clock == "sim":
            rig.stamp_feedback(on_servo=self._on_servo)  # the controllers' feedback stamped on the rig's clock
            self._clock_pub = Publisher(session, keys.sim_clock, ClockTick)
            self._keepalive_pub = Publisher(session, keys.sim_keepalive, ClockTick)
            answers = [keys.step_ack(s) for s in ANSWERS_FOLLOWED] + [keys.status_ack("planner")]
            self._lockstep_parts = [self._clock_pub, self._keepalive_pub, *(Subscriber(session, k, StepAck, self._on_ack) for k in answers),
                                    LivelinessWatcher(session, keys, self._on_alive)]
        self._session = session
        # lockstep: alive once its clock has ticked (`_run_lockstep`): a run started on a clock never heard would
        # take 0 for its start, and its first tick (2**30 s on) for a time-out long past
        self._token: zenoh.LivelinessToken | None = None if clock == "sim" else declare_alive(session, keys, SERVICE_NAME)

    def _on_ack(self, ack: StepAck) -> None:
        with self._cond:
            self.lockstep.on_ack(ack, time.monotonic())
            self._wake_if_answered()

    def _on_servo(self) -> None:
        """A servo command reached a simulated controller: the lockstep wait may be over."""
        with self._cond:
            self._wake_if_answered()

    def _wake_if_answered(self) -> None:
        """(With _cond held.) Wake the loop's wait once what it waits for is in (`_waiting_tick_only`: the servo
        tick's answers; else the whole step's), not at every answer: one that leaves another missing changes
        nothing the wait acts on (each used to wake it: ~2,700 wake-ups a run of exp02). What else ends a
        wait (a new run, a liveliness change, `stop`) wakes it directly, and a silent service's time-out is
        looked at on the wait's own timed wake-up."""
        self.lockstep.controllers(self.rig.servo_counts())
        if not (self.lockstep.tick_pending() if self._waiting_tick_only else self.lockstep.pending()):
            self._cond.notify_all()

    def _on_alive(self, service: str, alive: bool) -> None:
        with self._cond:
            self.lockstep.on_alive(service, alive)
            self._cond.notify_all()

    def _on_state(self, s: RunState) -> None:
        if s.run_id is not None and s.run_id == self.run_id and s.stage in FINAL_STAGES:
            with self._cond:
                if self.lockstep.run_id == s.run_id:
                    self.lockstep.start_run(None)  # the run is over: nothing more to wait for
                if self._ended != s.run_id:
                    self._ended, self._truth_due = s.run_id, True  # the loop publishes it next
                self._cond.notify_all()
            return
        if s.stage != "perceiving" or not s.run_id or s.scenario_doc is None:
            return
        with self._cond:
            self._cond.notify_all()
            if s.run_id in self._seen_runs:
                return
            self._seen_runs.add(s.run_id)
            self._pending = (s.run_id, s.scenario_doc, int(s.seed or 0), s.scenario, dict(s.params or {}))

    def _reset(self, run_id: str, doc: dict[str, Any], seed: int, name: str | None, params: dict[str, Any] | None = None) -> None:
        t0 = time.monotonic()
        try:
            scenario = Scenario.from_dict(doc, "run/state scenario_doc")
            rate = self._control_rate(scenario, params)
            settled = self.cfg.settle_s > 0 and self.rig.resettle(scenario, seed, self.cfg.settle_s)  # the start-up world, settled
            if not settled:
                self.rig.reset(scenario, seed)
        except (BagItError, ValueError) as e:
            # frames of the old world would be taken for this run's: publish none until a good reset
            self._camera_paused = f"run {run_id}: cannot build its world: {e}"
            self.say(f"ERROR: {self._camera_paused}; camera paused")
            return
        self._run_t0 = (self.rig.epoch, t0)  # the run's real-time factor counts from its reset (the world's time 0)
        if self.cfg.settle_s > 0 and not settled:
            self.rig.settle(self.cfg.settle_s)
        self._camera_paused = None
        self._world_frames = 0
        self._keep_s = tick_period(rate, self.rig.rig.safety.watchdog_s)
        self._fps = camera_fps(self.cfg.fps, self.clock == "sim", rate)
        self.run_id = run_id
        self.scenario_name = name or scenario.name
        self.stats.resets += 1
        how = "the world it started with, settled then" if settled else "built and settled now"
        self.say(f"run {run_id}: world reset to {self.scenario_name} (seed {seed}) in {time.monotonic() - t0:.2f} s: {how}")

    @staticmethod
    def _control_rate(scenario: Scenario, params: dict[str, Any] | None) -> float:
        """The run's control rate as the controller takes it: the scenario's parameters with the run's on top
        (parameters the coordinator let through; should they not merge, the scenario's rate)."""
        try:
            return merge_params(scenario.params, params or {}).controller.control_rate_hz
        except BagItError:
            return scenario.params.controller.control_rate_hz

    def _publish_truth(self, final: bool = False) -> None:
        """Ground truth now; `final`: the world as the run ended, with the run's own real-time factor (from
        its reset) and, in lockstep, whether every step of it was answered in full."""
        gt = (self._step_truth if final else None) or self.rig.ground_truth()  # a step the world has already left: its truth
        exact: dict[str, Any] = {}
        if final and self.clock == "sim":  # (called with and without _cond held: the list is copied whole, not locked)
            inexact = list(self.lockstep.inexact[:100])
            exact = {"exact": not inexact, "inexact": inexact}
        rtf = self._rtf_window
        if final:
            rtf = (self.rig.clock_s - self._run_t0[0]) / max(time.monotonic() - self._run_t0[1], 1e-9)
        self._truth_pub.put(SimTruth(
            run_id=self.run_id, scenario=self.scenario_name, sim_time=gt.time, realtime_factor=rtf,
            frames=self.stats.frames, rim=gt.rim, passed_through=bool(gt.passed_through),
            max_penetration_m=float(gt.max_penetration_m), clearance_m=float(min(gt.clearance_m, 1e3)), final=final, **exact,
        ))

    def _truths(self, wall: float, next_truth: float) -> float:
        """The final truth of a run that just ended, and the periodic one when due; the next one's time."""
        with self._cond:
            due, self._truth_due = self._truth_due, False
        if due:
            self._final_truth()
        if wall < next_truth:
            return next_truth
        try:
            self._publish_truth()
        except Exception as e:  # noqa: BLE001 - truth is for tests; never stop the rig for it
            self.say(f"ground truth not published: {type(e).__name__}: {e}")
        return wall + 1.0 / self.cfg.truth_hz

    def _final_truth(self) -> None:
        """The world as the run ended, once: what the run is judged on."""
        try:
            self._publish_truth(final=True)
        except Exception as e:  # noqa: BLE001 - truth is for tests; never stop the rig for it
            self.say(f"final ground truth not published: {type(e).__name__}: {e}")

    def run(self, stop: threading.Event, duration: float | None = None) -> SimStats:
        """Step, render, publish and follow resets until `stop` (or `duration` simulated seconds)."""
        if self.clock == "sim":
            return self._run_lockstep(stop, duration)
        cfg = self.cfg
        speed = cfg.speed or 1.0
        t_sim0, t_wall0 = self.rig.time, time.monotonic()  # pacing origin, moved at each reset
        sim_total, wall_start = 0.0, time.monotonic()
        next_frame = self.rig.time
        next_truth = next_report = time.monotonic()
        win_sim, win_wall = self.rig.time, time.monotonic()
        while not stop.is_set() and (duration is None or sim_total < duration - 1e-9):
            with self._lock:
                pending, self._pending = self._pending, None
            if pending is not None:
                self._reset(*pending)
                t_sim0, t_wall0 = self.rig.time, time.monotonic()
                next_frame = self.rig.time
                win_sim, win_wall = self.rig.time, time.monotonic()
                continue
            before = self.rig.time
            self.rig.step(cfg.chunk_s)
            self._say_alarms()
            sim_total += self.rig.time - before
            if cfg.camera and self._camera_paused is None and self.rig.time >= next_frame - 1e-9:
                taken = time.time()
                frame = self.rig.render_rgbd(self.stats.frames)
                frame.stamp = taken  # wall clock of the image, not simulated time
                self._frame_pub.put(frame)
                self.stats.frames += 1
                next_frame += 1.0 / self._fps
                if next_frame < self.rig.time:  # behind: skip frames rather than bunch them up
                    next_frame = self.rig.time + 1.0 / self._fps
            now = time.monotonic()
            next_truth = self._truths(now, next_truth)
            if now >= next_report:
                if now - win_wall > 0.5:
                    self._rtf_window = (self.rig.time - win_sim) / (now - win_wall)
                    win_sim, win_wall = self.rig.time, now
                if self._rtf_window < 0.95 * speed:
                    self.say(f"behind real time: x{self._rtf_window:.2f} (asked x{speed:g}); {self.stats.frames} frames so far")
                next_report = now + cfg.report_every_s
            ahead = (self.rig.time - t_sim0) / speed - (time.monotonic() - t_wall0)
            if ahead > 0:
                stop.wait(ahead)
            elif ahead < -1.0:
                t_sim0, t_wall0 = self.rig.time, time.monotonic()  # never race to catch up a backlog
        wall = time.monotonic() - wall_start
        self.stats.sim_s, self.stats.wall_s = sim_total, wall
        self.stats.realtime_factor = sim_total / wall if wall > 0 else 0.0
        return self.stats

    # -- lockstep -----------------------------------------------------------------------------------

    def _run_lockstep(self, stop: threading.Event, duration: float | None) -> SimStats:
        """The lockstep loop (see the module docstring): events by `Schedule`, waits by `Lockstep`."""
        cfg, rig = self.cfg, self.rig
        period = float(rig.rig.safety.servo_period_s)
        # The events fall on the world's time (as `bagit run` steps by it, so both round the steps
        # alike); what goes out is stamped on the rig's clock, which never goes back.
        self._publish_clock(rig.clock_s, None)
        self._token = declare_alive(self._session, self.keys, SERVICE_NAME)
        if cfg.settle_s > 0:  # the world it starts with settles now, as a run's reset would: a run of it need not (`_reset`)
            rig.settle(cfg.settle_s, between=self._settling)
        sched = Schedule.starting(rig.time, 1.0 / self._fps, period)
        t_sim0, t_wall0 = rig.clock_s, time.monotonic()
        start, wall_start = rig.clock_s, time.monotonic()
        next_truth = next_report = time.monotonic()
        self._publish_clock(rig.clock_s, None)
        while not stop.is_set() and (duration is None or rig.clock_s - start < duration - 1e-9):
            with self._lock:
                pending, self._pending = self._pending, None
            if pending is not None:
                with self._cond:
                    self.lockstep.start_run(None)
                self._reset(*pending)
                if self.run_id == pending[0]:
                    with self._cond:
                        self.lockstep.start_run(self.run_id)
                rig.push_feedback()
                sched = Schedule.starting(rig.time, 1.0 / self._fps, period, sched.ticks, keep_s=self._keep_s)
                t_sim0, t_wall0 = rig.clock_s, time.monotonic()
                continue
            now, world_t = rig.clock_s, rig.time
            framing = sched.frame_pending(world_t)
            idle = not self.lockstep.active and world_t - self._idle_frame < 1.0 / IDLE_FPS - 1e-9  # between runs: fewer frames
            render = framing and cfg.camera and self._camera_paused is None and not idle
            n = sched.servo_due(world_t)
            if n is not None:
                with self._cond:
                    self.lockstep.servo_tick(n, rig.servo_counts(), time.monotonic())
                self._publish_clock(now, n, frame=framing)
                if not render:  # else answered while the frame renders (below)
                    self._wait(stop)
            stepped = False  # the world already stepped to the next event while the rig worked on this one
            if sched.frame_due(world_t):
                if n is None:
                    self._publish_clock(now, None, frame=True)
                if render:
                    self._idle_frame = world_t
                    frame = rig.render_rgbd(self._world_frames)  # numbered (and its noise seeded) per world, as in `bagit run`
                    self._world_frames += 1
                    frame.stamp = now  # the rig's clock
                    frame.run_id = self.run_id  # the run whose world this is: perception judges it in that run's terms
                    with self._cond:
                        self.lockstep.frame_published(now, time.monotonic())
                    self._frame_pub.put(frame)
                    self.stats.frames += 1
                    if n is not None:
                        self._wait(stop, tick_only=True)
                    stepped = self._step_ahead(sched.until_next(world_t))
                    self._wait(stop)
            elif sched.keep_due(world_t):  # frames sparser than the controller's keep-alive pace
                with self._cond:  # waited for before it goes out: an answer may come back before the next line
                    self.lockstep.keepalive_published(now, time.monotonic())
                self._publish_clock(now, None, keepalive=True)
                stepped = self._step_ahead(sched.until_next(world_t))
                self._wait(stop)
            wall = time.monotonic()
            next_truth = self._truths(wall, next_truth)
            self._step_truth = None
            if wall >= next_report:
                next_report = wall + cfg.report_every_s
                self._rtf_window = (rig.clock_s - start) / max(wall - wall_start, 1e-9)
            if not stepped:
                advance = rig.step if self.lockstep.active else rig.idle  # between runs a world at rest is not simulated again
                advance(sched.until_next(world_t))
            rig.push_feedback()
            self._say_alarms()
            if cfg.speed is None and self.lockstep.active:  # a lockstep run: as fast as the rig answers
                t_sim0, t_wall0 = rig.clock_s, time.monotonic()
                continue
            ahead = (rig.clock_s - t_sim0) / (cfg.speed or 1.0) - (time.monotonic() - t_wall0)
            if ahead > 0:
                stop.wait(ahead)
            elif ahead < -1.0:
                t_sim0, t_wall0 = rig.clock_s, time.monotonic()  # never race to catch up a backlog
        wall = time.monotonic() - wall_start
        self.stats.sim_s, self.stats.wall_s = rig.clock_s - start, wall
        self.stats.realtime_factor = self.stats.sim_s / wall if wall > 0 else 0.0
        return self.stats

    def _settling(self) -> None:
        """Between the start-up settle's steps: the controllers' feedback (an arm driver coming up waits for its
        arms') and the clock (a run is started on it: its first tick may have gone out before anyone's
        subscription reached this session)."""
        self.rig.push_feedback()
        self._publish_clock(self.rig.clock_s, None)

    def _step_ahead(self, dt: float) -> bool:
        """Lockstep, after a frame (or keep-alive tick) went out: step the world on to the next event while
        the rig works on this one, on the other core. The same world as stepping after the answers: until
        the next servo tick nothing the rig sends reaches it (its ServoPs go out on servo ticks, and the
        feedback of the new step is pushed only after the wait). The truth of this step is kept first:
        should the run end on it, its final truth is the world as it ended, as `bagit run` judges it.
        Only while a run is waited for (between runs nothing waits)."""
        if not self.lockstep.active:
            return False
        self._step_truth = self.rig.ground_truth()
        self.rig.step(dt)
        return True

    def _publish_clock(self, t: float, servo_tick: int | None, keepalive: bool = False, frame: bool = False) -> None:
        """A step on sim/clock; a keep-alive one on sim/clock/keepalive too, the controller's only ticks (it need not
        wake for the two or so servo and frame ticks of every frame)."""
        tick = ClockTick(t=t, servo_tick=servo_tick, run_id=self.lockstep.run_id, stamp=t, keepalive=keepalive, frame=frame)
        self._clock_pub.put(tick)
        if keepalive:
            self._keepalive_pub.put(tick)

    def _wait(self, stop: threading.Event, tick_only: bool = False) -> None:
        """Until the rig has answered this step (or a new run, or `stop`). The last of its answers wakes it (an
        ack, a servo command reaching a simulated controller: `_wake_if_answered`), as do a liveliness change
        and a new run: nothing polls;
        the timed wake-up only lets `expire` drop a service silent for the lockstep time-out.
        `tick_only`: until the servo tick is answered, its ServoPs landed (the world may then step on),
        the frame's answers still awaited: the step is not done."""
        with self._cond:
            self._waiting_tick_only = tick_only
            while not stop.is_set() and self._pending is None:
                self.lockstep.controllers(self.rig.servo_counts())
                waiting = self.lockstep.expire(time.monotonic())
                for note in self.lockstep.notes:
                    self.say(note)
                self.lockstep.notes.clear()
                if tick_only:
                    if not self.lockstep.tick_pending():
                        return
                elif not waiting:
                    if self.lockstep.ended() and self._ended != self.run_id:
                        self._ended = self.run_id
                        self._final_truth()  # at the very step the run ended, before the world moves on
                        self.lockstep.start_run(None)
                    break
                self._cond.wait(EXPIRE_CHECK_S)
            if not tick_only:  # (a tick-only wait ended by `stop` or a new run: the step's full wait says so)
                self.lockstep.done_with_step()

    def _say_alarms(self) -> None:
        """Print why a simulated controller alarmed (its GetErrorID gives the id only)."""
        for name, arm in self.rig.arms.items():
            while arm.alarm_log:
                t, alarm, detail = arm.alarm_log.popleft()
                self.say(f"{name} CR5 alarm {alarm} ({describe_alarm(alarm)}) at t = {t:.2f} s" + (f": {detail}" if detail else ""))

    def close(self) -> None:
        for x in (self._state_sub, self._frame_pub, self._truth_pub, *self._lockstep_parts):
            x.close()
        try:
            if self._token is not None:
                self._token.undeclare()
        except zenoh.ZError:
            pass
