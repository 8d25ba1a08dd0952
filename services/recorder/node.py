"""The recorder and replay on Zenoh: the only module of the recorder that imports zenoh.

Recording: one subscriber on `bagit/<rig>/**` hands each payload (with its receive time) to a
queue; a writer thread decodes it (`bagit.common.wire`) and gives it to `RecordingWriter`. A
payload that does not decode, or has no MCAP record, whatever it holds (a 200 kB header of nested
brackets included), is counted as malformed and dropped. The Zenoh thread never blocks on the
disk: when the queue holds more than `max_queue_bytes` the sample is dropped and counted. Writer
events go to stderr; a write error (disk full) is also published on `run/state` (the last run
state seen, with the reason), so the dashboard shows it.

At start, messages wait (at most START_HOLD_S) for the first run/state: if it names a run under
way (a recorder restarted mid-run), those received since the run began go to the run's file
at once, not to an idle file until the run's state comes by.

If the writer thread dies all the same (a fault of the writer, not of a message), the recorder
does not linger as a live-looking husk: it counts the message in hand, the queue and everything
received afterwards as lost, undeclares its liveliness token, publishes the reason on run/state
and sets `stopped`, so `bagit recorder` exits with failure (and `bagit up` restarts it).

Replay: messages are published on their recorded keys (or the same keys of another rig) at their
recorded gaps divided by `speed`, restamped to now unless told otherwise. Commands (`controller/cmd`)
and e-stops are left out unless asked for, and even then refused while anything listens to
controller/cmd on the target rig (an arm driver would move the arms).
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from pathlib import Path
from typing import Any

import zenoh

from bagit.common import wire
from bagit.common.bus import DROPS, KEY_TABLE, STATE, BusError, Keys, Publisher, declare_alive
from bagit.common.errors import BadMessage, BadRecording
from bagit.common.messages import Message, RecorderStatus, RunState
from bagit.common.names import FINAL_STAGES
from bagit.services.recorder.reading import Recording
from bagit.services.recorder.writer import RecordingWriter, record_bytes

log = logging.getLogger("bagit.recorder")
LEVELS = {"info": logging.INFO, "warning": logging.WARNING, "error": logging.ERROR}  # the writer's event levels

COMMAND_KEYS = ("controller/cmd", "estop")
# At start, messages wait this long at most for the first run/state (the coordinator republishes
# it at 2 Hz), so a recorder restarted in the middle of a run files them under that run.
START_HOLD_S = 1.0
STATUS_S = 1.0  # the recorder's counters on recorder/status this often (and at each write error)
_STOP = object()


class RecorderNode:
    """Records everything on bagit/<rig>/** through a RecordingWriter (see the module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        writer: RecordingWriter,
        exclude: list[str] | tuple[str, ...] = (),
        max_queue_bytes: int = 256 << 20,
        tick_s: float = 0.05,
        hold_s: float = START_HOLD_S,
    ) -> None:
        self.keys = keys
        self.writer = writer
        self.tick_s = tick_s
        self.max_queue_bytes = max_queue_bytes
        # its own status is about this recorder, not the rig: never in its files
        self.exclude = [zenoh.KeyExpr(f"{keys.prefix}/{e.strip('/')}") for e in exclude] + [zenoh.KeyExpr(keys.recorder_status)]
        self.received = 0
        self.overflow = 0
        self.bad = 0
        self.dropped_dead = 0  # messages in hand, queued or received after the writer died
        self.dead: str | None = None  # why the writer thread died; None while it records
        # set when the writer died: the command stops (and fails) so `bagit up` restarts the recorder
        self.stopped = threading.Event()
        self.stop_ok = False
        self.stop_reason: str | None = None
        self._queued_bytes = 0
        # messages decoded before the first run/state, and until when they may wait for it
        self._held: list[tuple[str, Message, int]] | None = [] if hold_s > 0 else None
        self._hold_until = time.monotonic() + hold_s
        self._lock = threading.Lock()
        self._q: queue.Queue = queue.Queue()
        writer.on_event = self._on_event
        self.started = time.time()
        self._state_pub = Publisher(session, keys.run_state, RunState)
        self._status_pub = Publisher(session, keys.recorder_status, RecorderStatus)
        self._thread = threading.Thread(target=self._run, name="recorder-writer", daemon=True)
        self._thread.start()
        self._sub = session.declare_subscriber(keys.all, self._on_sample)
        self._token: zenoh.LivelinessToken | None = declare_alive(session, keys, "recorder")

    def _on_sample(self, sample: zenoh.Sample) -> None:
        if sample.kind != zenoh.SampleKind.PUT:
            return
        t = time.time_ns()
        key = sample.key_expr
        if any(ex.includes(key) for ex in self.exclude):
            return
        payload = sample.payload.to_bytes()
        with self._lock:
            self.received += 1
            if self.dead is not None:
                self.dropped_dead += 1
                return
            if self._queued_bytes + len(payload) > self.max_queue_bytes:
                self.overflow += 1
                n = self.overflow
                full = True
            else:
                self._queued_bytes += len(payload)
                full = False
        if full:
            if n == 1 or n % 100 == 0:
                self._say("error", f"writer behind: {n} messages dropped (queue over {self.max_queue_bytes >> 20} MiB)")
            return
        self._q.put((str(key), payload, t))

    def _run(self) -> None:
        """The writer thread: nothing may end it unseen; if something does, the recorder dies loudly."""
        try:
            self._loop()
        except BaseException as e:  # noqa: BLE001 - a writer fault: token down, loss counted and reported
            self._die(f"{type(e).__name__}: {_first_line(e)}")

    def _loop(self) -> None:
        next_tick = next_status = time.monotonic()
        while True:
            try:
                item = self._q.get(timeout=self.tick_s)
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is not None:
                key, payload, t = item
                with self._lock:
                    self._queued_bytes -= len(payload)
                self._record(key, payload, t)
            if self._held is not None and time.monotonic() >= self._hold_until:
                self._release(None)  # no run/state in time: what was held goes where it would have
            if time.monotonic() >= next_tick:
                self.writer.tick()
                next_tick = time.monotonic() + self.tick_s
            if time.monotonic() >= next_status:
                self.publish_status()
                next_status = time.monotonic() + STATUS_S
        if self._held is not None:
            self._release(None)

    def _record(self, key: str, payload: bytes, t: int) -> None:
        """Decode and write one payload. Whatever a payload holds, it is recorded or counted as
        malformed; an exception from the writer itself (not the message) propagates: a writer fault."""
        try:
            msg: Message = wire.decode(payload)
        except Exception as e:  # noqa: BLE001 - BadMessage, or anything else a hostile payload provokes
            self._malformed(key, e if isinstance(e, BadMessage) else f"undecodable: {type(e).__name__}: {_first_line(e)}")
            return
        if self._held is not None:
            if not isinstance(msg, RunState):
                self._held.append((key, msg, t))
                return
            try:
                record_bytes(msg)  # a run state that cannot be recorded must not route anything either
            except BadMessage as e:
                self._malformed(key, e)
                return
            self._release(msg)
        self._write(key, msg, t)

    def _write(self, key: str, msg: Message, t: int) -> None:
        try:
            self.writer.write(key, msg, t)
        except BadMessage as e:  # the message has no MCAP record (RecordingWriter.write wrote nothing)
            self._malformed(key, e)

    def _release(self, first: RunState | None) -> None:
        """End the start hold with the first run/state (or None): the held messages received after
        the start of the run it names go to that run's file, those before to where they would have."""
        held, self._held = self._held or [], None
        start = run_start_ns(first) if first is not None else None
        split = len(held) if start is None else next((i for i, (_, _, t) in enumerate(held) if t >= start), len(held))
        for key, msg, t in held[:split]:
            self._write(key, msg, t)
        if split < len(held) and first is not None:
            self.writer.follow(first)
            for key, msg, t in held[split:]:
                self._write(key, msg, t)

    def _malformed(self, key: str, reason: object) -> None:
        self.bad += 1
        DROPS.add(key, str(reason))
        if self.bad <= 5 or self.bad % 100 == 0:
            self._say("error", f"malformed message #{self.bad} on {key} dropped: {reason}")

    def _die(self, reason: str) -> None:
        """The writer thread is ending on a fault: stop recording, count what is lost, take the
        liveliness token down, say why (stderr and run/state), and set `stopped`."""
        with self._lock:
            self.dead = f"writer died: {reason}"  # from now on _on_sample counts, never queues
            while True:
                try:
                    self._q.get_nowait()
                except queue.Empty:
                    break
            self._queued_bytes = 0
        try:
            self.writer.close()  # finish the open file if the writer still can
        except Exception:  # noqa: BLE001 - it may be what failed; the writer then abandoned the file
            self.writer.abandon()
        with self._lock:  # everything received and neither recorded nor counted elsewhere is lost
            self.dropped_dead = self.received - self.writer.messages - self.writer.lost - self.bad - self.overflow
        self._undeclare_token()
        self.stop_reason = f"recorder {self.dead}"
        self._on_event("error", f"{self.dead}; recording stopped ({self.dropped_dead} messages lost so far)")
        self.stopped.set()

    def _undeclare_token(self) -> None:
        token, self._token = self._token, None
        if token is not None:
            try:
                token.undeclare()
            except Exception:  # noqa: BLE001 - the session may be closing
                pass

    def _say(self, level: str, text: str) -> None:
        log.log(LEVELS.get(level, logging.WARNING), "%s", text)

    def publish_status(self) -> None:
        """The counters on recorder/status (`RecorderStatus`), for the run's result."""
        st = self.status()
        error, last = st["dead"] or st["error"], st["last_error"]
        try:
            self._status_pub.put(RecorderStatus(
                started=self.started, messages=st["messages"], lost=st["lost"], overflow=st["overflow"], errors=st["errors"],
                error=str(error)[:1000] if error else None, last_error=str(last)[:1000] if last else None,
                file=str(st["file"])[:1000] if st["file"] else None))
        except Exception as e:  # noqa: BLE001 - reporting must not take the recorder down
            self._say("info", f"could not publish the recorder's status: {e}")

    def _on_event(self, level: str, text: str) -> None:
        self._say(level, text)
        if level == "error":
            self.publish_status()
            base = self.writer.last_run_state or RunState()
            try:
                self._state_pub.put(RunState(
                    run_id=base.run_id, scenario=base.scenario, stage=base.stage, progress=base.progress,
                    elapsed_s=base.elapsed_s, result=base.result, reason=f"recorder: {text}",
                ))
            except Exception as e:  # noqa: BLE001 - reporting must not take the recorder down
                self._say("info", f"could not publish the error on run/state: {e}")

    def status(self) -> dict[str, Any]:
        with self._lock:
            q = {"received": self.received, "overflow": self.overflow, "queued_bytes": self._queued_bytes}
            dropped_dead = self.dropped_dead
        w = self.writer.status()
        return {**w, **q, "lost": w["lost"] + dropped_dead, "malformed": self.bad, "dead": self.dead}

    def close(self) -> dict[str, Any]:
        """Stop listening, write what is queued, finish the open file; the final status."""
        try:
            self._sub.undeclare()
        except zenoh.ZError:
            pass
        self._q.put(_STOP)
        self._thread.join()
        if self.dead is None:
            try:
                self.writer.close()
            except Exception as e:  # noqa: BLE001 - the file could not be finished: the summary says so
                self.dead = f"could not finish the file: {type(e).__name__}: {_first_line(e)}"
                self._say("error", self.dead)
        self.publish_status()
        self._undeclare_token()
        self._state_pub.close()
        self._status_pub.close()
        return self.status()


def outcome(status: dict[str, Any]) -> tuple[bool, str | None]:
    """A recorder's success and its reason from its final status: it failed if its writer died,
    a write failed or the queue overflowed (malformed messages are the sender's fault, counted only)."""
    reasons = []
    if status.get("dead"):
        reasons.append(status["dead"])
    if status.get("errors"):
        reasons.append(f"{status['errors']} write error(s), last: {status.get('last_error')}")
    if status.get("overflow"):
        reasons.append(f"{status['overflow']} messages dropped (writer behind)")
    if status.get("lost") and not reasons:
        reasons.append("messages lost")
    if not reasons:
        return True, None
    return False, "; ".join(reasons) + f" ({status.get('lost', 0)} messages lost)"


def run_start_ns(st: RunState) -> int | None:
    """When the run a run state names began (ns since the epoch, the coordinator's clock: its stamp
    minus the elapsed time), if it is a run under way; None otherwise."""
    if not st.run_id or st.stage == "idle" or st.stage in FINAL_STAGES or not st.elapsed_s > 0 or not 0 < st.stamp < 1e11:
        return None
    return int((st.stamp - st.elapsed_s) * 1e9)


def _first_line(e: BaseException) -> str:
    s = str(e).strip()
    return s.splitlines()[0] if s else ""


# ---------------------------------------------------------------------------------------------
# Replay
# ---------------------------------------------------------------------------------------------


def _rest_of(topic: str) -> tuple[str, str] | None:
    parts = topic.split("/", 2)
    if len(parts) < 3 or parts[0] != "bagit":
        return None
    return parts[1], parts[2]


class Replayer:
    """Publishes a recording's messages at their recorded timing (see the module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        rig: str | None = None,
        speed: float = 1.0,
        with_commands: bool = False,
        restamp: bool = True,
        stop: threading.Event | None = None,
    ) -> None:
        if not (speed > 0 and speed < float("inf")):
            raise BadRecording(f"--speed must be a positive finite number, got {speed}")
        self.session = session
        self.rig = rig
        self.speed = speed
        self.with_commands = with_commands
        self.restamp = restamp
        self.stop = stop or threading.Event()
        self.pubs: dict[str, Publisher] = {}
        self.sent = 0
        self.skipped = 0
        self.bad = 0
        self.lateness: list[float] = []
        self.checked_rigs: set[str] = set()

    def _publisher(self, key: str, cls: type[Message]) -> Publisher:
        pub = self.pubs.get(key)
        if pub is None:
            try:
                pub = Publisher(self.session, key, cls)
            except BusError:
                pub = Publisher(self.session, key, cls, qos=STATE)  # a key outside the table: latest-wins
            self.pubs[key] = pub
        return pub

    def prepare(self, rig: str, wait_s: float) -> bool:
        """Declare the rig's publishers up front and wait (up to wait_s) until a subscriber matches one."""
        for row in KEY_TABLE:
            if row.kind != "pub" or row.message is None or (row.key in COMMAND_KEYS and not self.with_commands):
                continue
            for k in ([row.key.replace("*", "left"), row.key.replace("*", "right")] if "*" in row.key else [row.key]):
                self._publisher(f"bagit/{rig}/{k}", row.message)
        deadline = time.monotonic() + wait_s
        while time.monotonic() < deadline and not self.stop.is_set():
            if any(p.matched for p in self.pubs.values()):
                return True
            time.sleep(0.01)
        return any(p.matched for p in self.pubs.values())

    def _check_commands(self, rig: str) -> None:
        if rig in self.checked_rigs:
            return
        self.checked_rigs.add(rig)
        probe = self._publisher(f"bagit/{rig}/controller/cmd", _command_type())
        deadline = time.monotonic() + 0.3
        while time.monotonic() < deadline and not probe.matched:
            time.sleep(0.01)
        if probe.matched:
            raise BusError(
                f"refusing to replay commands: something subscribes to bagit/{rig}/controller/cmd (an arm driver or a "
                "recorder); replay onto another --rig, or without --with-commands"
            )

    def play(self, path: Path) -> dict[str, Any]:
        """One pass over the file; returns what was sent and whether the file was complete."""
        rec = Recording(path)
        t_start = None
        first_log = first_wall = 0.0
        for r in rec.records():
            if self.stop.is_set():
                break
            if t_start is None:
                t_start, first_log, first_wall = time.monotonic(), r.log_time_ns / 1e9, time.time()
            split = _rest_of(r.topic)
            if split is None:
                self.skipped += 1
                continue
            rig, rest = split[0] if self.rig is None else self.rig, split[1]
            if rest in COMMAND_KEYS:
                if not self.with_commands:
                    self.skipped += 1
                    continue
                self._check_commands(rig)
            try:
                msg = r.message()
            except BadRecording:
                self.bad += 1
                continue
            due = t_start + (r.log_time_ns / 1e9 - first_log) / self.speed
            wait = due - time.monotonic()
            if wait > 0 and self.stop.wait(wait):
                break
            if self.restamp:
                msg = _restamped(msg, first_wall, first_log, self.speed)
            self._publisher(f"bagit/{rig}/{rest}", r.cls).put(msg)
            self.sent += 1
            self.lateness.append(max(0.0, time.monotonic() - due))
        return {"complete": rec.complete, "truncated": rec.truncated, "read": rec.read}

    def close(self) -> None:
        for p in self.pubs.values():
            p.close()


def _command_type() -> type[Message]:
    from bagit.common.messages import Command

    return Command


def _restamped(msg: Message, wall0: float, log0: float, speed: float) -> Message:
    """The message with its stamps moved to replay time (the same offsets from the first record)."""
    upd: dict[str, float] = {"stamp": wall0 + (msg.stamp - log0) / speed}
    src = getattr(msg, "source_stamp", None)
    if isinstance(src, float) and src > 0:
        upd["source_stamp"] = wall0 + (src - log0) / speed
    return msg.model_copy(update=upd)
