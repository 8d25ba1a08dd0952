"""The recorder's file policy: which MCAP file each message goes to, chunking, rotation, disk errors.

- One file per run: a `run/state` with a new run id (and a stage other than idle) closes the
  current file and opens `<rig>_<UTC start>_run-<id>.mcap`. When that run reaches done, failed or
  aborted, the file stays open `linger_s` more (the final states and result) and is then closed;
  a later run/state of the same, finished run does not reopen it.
- Outside runs, messages go to a rolling `<rig>_<UTC start>_idle.mcap`, opened on the first idle
  message; only the newest `keep_idle` idle files of the rig are kept.
- Any file is rotated when it reaches `max_bytes`: the next part is `..._p2.mcap`, `..._p3.mcap`.
- Chunked and compressed MCAP, written with unbuffered writes: a chunk is closed when it reaches
  `chunk_bytes` or `flush_s` after its first message, so a recorder killed with SIGKILL leaves a
  file readable up to its last complete chunk (at most `flush_s` of data lost). A closed file
  ends with the summary, the `bagit.run` metadata (the last run state) and the footer.
- A write error (disk full: ENOSPC, or any OSError) abandons the file, is reported through
  `on_event("error", ...)` once, counts the messages that could not be written, and is retried
  with a new part every `retry_s`; success is reported as `on_event("info", "recording resumed...")`.

No Zenoh here: `node.py` feeds decoded messages in and turns events into stderr lines and run state.
"""

from __future__ import annotations

import errno
import json
import os
import re
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal

from mcap.writer import CompressionType, Writer
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.errors import BadMessage
from bagit.common.messages import SCHEMA_VERSION, Message, RunState
from bagit.common.names import FINAL_STAGES
from bagit.services.recorder.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, json_schema_bytes, schema_name, to_json

TERMINAL_STAGES = FINAL_STAGES
RUN_METADATA = "bagit.run"
MAX_FILE_BYTES = 1 << 40  # rotate at 1 TiB at most: a file must stay small enough to copy, open and recover
RECORDING_METADATA = "bagit.recording"
_UNSAFE = re.compile(r"[^A-Za-z0-9_.-]")


class RecorderConfig(BaseModel):
    """Where and how the recorder writes."""

    model_config = ConfigDict(extra="forbid")

    dir: Path = Field(Path("recordings"), description="folder of the MCAP files")
    max_bytes: int = Field(1 << 30, ge=1 << 16, le=MAX_FILE_BYTES, description="rotate a file when it reaches this size")
    chunk_bytes: int = Field(1 << 20, ge=1 << 10, le=1 << 28, description="close an MCAP chunk at this size (uncompressed)")
    flush_s: float = Field(1.0, gt=0, le=60, description="close a chunk this long after its first message")
    linger_s: float = Field(2.0, ge=0, le=600, description="keep a finished run's file open this long for its last states")
    keep_idle: int = Field(4, ge=1, le=10_000, description="idle files of this rig kept (older ones are deleted)")
    retry_s: float = Field(5.0, gt=0, le=3600, description="after a write error, try a new file this often")
    compression: Literal["zstd", "lz4", "none"] = Field(
        "lz4", description="chunk compression: lz4 keeps up with 30 Hz RGB-D on 2 loaded cores; zstd makes ~40% smaller files"
    )


class _RawFile:
    """An unbuffered file the MCAP writer writes through: every write reaches the OS at once (no
    Python buffer to lose on SIGKILL) and short writes are completed, so ENOSPC raises."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._pos = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        view = memoryview(data).cast("B")
        done = 0
        while done < len(view):
            n = os.write(self._fd, view[done:])
            if n <= 0:
                raise OSError(errno.ENOSPC, "no progress writing", str(self.path))
            done += n
        self._pos += done
        return done

    def tell(self) -> int:
        return self._pos

    def flush(self) -> None:
        pass

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)


Opener = Callable[[Path], Any]


def default_opener(path: Path) -> _RawFile:
    return _RawFile(path)


def safe_chunk(text: str, limit: int = 64) -> str:
    """A run id or rig name made safe as part of a file name (it comes from the network)."""
    s = _UNSAFE.sub("_", text)[:limit].strip(".")
    return s or "_"


def describe_os_error(e: OSError, path: Path | None) -> str:
    what = "disk full (ENOSPC)" if e.errno == errno.ENOSPC else f"write error ({errno.errorcode.get(e.errno or 0, e.errno)})"
    return f"{what} on {path}: {e.strerror or e}"


@dataclass
class _Open:
    """One MCAP file being written."""

    path: Path
    kind: str  # "run" or "idle"
    run_id: str | None
    part: int
    fh: Any
    writer: Writer
    started_ns: int
    schemas: dict[type, int] = field(default_factory=dict)
    channels: dict[str, int] = field(default_factory=dict)
    messages: int = 0
    chunk_started: float | None = None
    last_run_state: RunState | None = None


class RecordingWriter:
    """Routes messages to MCAP files: per run, rolling while idle, rotated by size (module doc)."""

    def __init__(
        self,
        cfg: RecorderConfig,
        rig: str,
        opener: Opener = default_opener,
        on_event: Callable[[str, str], None] | None = None,
        clock: Callable[[], float] = time.monotonic,
        version: str = "",
    ) -> None:
        self.cfg = cfg
        self.rig = safe_chunk(rig)
        self.opener = opener
        self.on_event = on_event or (lambda level, text: None)
        self.clock = clock
        self.version = version
        self.cur: _Open | None = None
        self.run_id: str | None = None
        self.finish_at: float | None = None
        self.finished_runs: set[str] = set()
        self.files: list[str] = []
        self.messages = 0
        self.lost = 0
        self.errors = 0
        self.error: str | None = None  # the write error in progress (None once recording resumed)
        self.last_error: str | None = None  # the latest write error, kept after recovery for the summary
        self.retry_at = 0.0
        self.reported_at = 0.0
        self.failed: tuple[str, str | None, int] | None = None
        self.last_run_state: RunState | None = None
        cfg.dir.mkdir(parents=True, exist_ok=True)

    # ---- routing -------------------------------------------------------------------------------

    def write(self, key: str, msg: Message, log_time_ns: int) -> bool:
        """Record one message received on `key` at `log_time_ns` (ns since the epoch). False if lost.

        BadMessage if the message cannot be made a record (e.g. fields nested deeper than the JSON
        encoder goes): nothing is written and the message has no effect, not even on the run."""
        data = record_bytes(msg)
        now = self.clock()
        if isinstance(msg, RunState):
            self._follow_run(msg, now)
        if self.error is not None and now < self.retry_at:
            self.lost += 1
            return False
        try:
            f = self._current(log_time_ns)
            self._add(f, key, msg, data, log_time_ns, now)
        except OSError as e:
            self._fail(e, now)
            self.lost += 1
            return False
        if self.error is not None:
            self.on_event("info", f"recording resumed in {f.path} after {self.lost} lost messages")
            self.error = None
        self.messages += 1
        return True

    def _follow_run(self, st: RunState, now: float) -> None:
        self.last_run_state = st
        rid = st.run_id
        if rid and st.stage != "idle" and rid != self.run_id and rid not in self.finished_runs:
            self._end_run()
            self.run_id, self.finish_at = rid, None
            return
        if self.run_id is None:
            return
        if rid != self.run_id or st.stage == "idle":
            self._end_run()
        elif st.stage in TERMINAL_STAGES and self.finish_at is None:
            self.finish_at = now + self.cfg.linger_s

    def _end_run(self) -> None:
        if self.run_id is not None:
            self.finished_runs.add(self.run_id)
        self.run_id, self.finish_at = None, None
        self._close()

    def tick(self) -> None:
        """Periodic upkeep: close a chunk older than flush_s, end a run after its linger."""
        now = self.clock()
        if self.finish_at is not None and now >= self.finish_at:
            self._end_run()
        f = self.cur
        if f is not None and f.chunk_started is not None and now - f.chunk_started >= self.cfg.flush_s:
            try:
                f.writer.flush()
                f.chunk_started = None
            except OSError as e:
                self._fail(e, now)

    # ---- files ---------------------------------------------------------------------------------

    def _wanted(self) -> tuple[str, str | None]:
        return ("run", self.run_id) if self.run_id is not None else ("idle", None)

    def _current(self, log_time_ns: int) -> _Open:
        kind, rid = self._wanted()
        f = self.cur
        if f is not None and (f.kind != kind or f.run_id != rid):
            self._close()
            f = None
        part = 1
        if f is not None and f.fh.tell() >= self.cfg.max_bytes:
            part = f.part + 1
            self._close()
            f = None
        elif f is None and self.error is not None and self.failed is not None and self.failed[:2] == (kind, rid):
            part = self.failed[2] + 1  # a retry after a write error continues the same run or idle period
        if f is None:
            f = self._open(kind, rid, part, log_time_ns)
        return f

    def _open(self, kind: str, rid: str | None, part: int, log_time_ns: int) -> _Open:
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(log_time_ns / 1e9))
        base = f"{self.rig}_{stamp}_" + (f"run-{safe_chunk(rid or '')}" if kind == "run" else "idle")
        if part > 1:
            base += f"_p{part}"
        path = self.cfg.dir / f"{base}.mcap"
        n = 1
        while path.exists():
            n += 1
            path = self.cfg.dir / f"{base}-{n}.mcap"
        fh = self.opener(path)
        try:
            compression = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}[self.cfg.compression]
            w = Writer(fh, chunk_size=self.cfg.chunk_bytes, compression=compression)
            w.start(profile="", library=f"bagit {self.version}".strip())
            w.add_metadata(RECORDING_METADATA, {
                "rig": self.rig, "kind": kind, "run_id": rid or "", "part": str(part),
                "started_ns": str(log_time_ns), "schema_version": str(SCHEMA_VERSION),
                "encoding": "json records: arrays as {dtype, shape, data: base64 of the wire bytes}",
            })
        except BaseException:
            _quiet_close(fh)
            raise
        self.cur = _Open(path=path, kind=kind, run_id=rid, part=part, fh=fh, writer=w, started_ns=log_time_ns)
        self.files.append(str(path))
        self.on_event("info", f"recording {kind}{' ' + rid if rid else ''} to {path}")
        if kind == "idle":
            self._prune_idle()
        return self.cur

    def _add(self, f: _Open, key: str, msg: Message, data: bytes, log_time_ns: int, now: float) -> None:
        cls = type(msg)
        ch = f.channels.get(key)
        if ch is None:
            sid = f.schemas.get(cls)
            if sid is None:
                sid = f.schemas[cls] = f.writer.register_schema(schema_name(cls), SCHEMA_ENCODING, json_schema_bytes(cls))
            ch = f.channels[key] = f.writer.register_channel(
                key, MESSAGE_ENCODING, sid, {"kind": cls.KIND, "schema_version": str(SCHEMA_VERSION)}
            )
        publish_ns = int(msg.stamp * 1e9) if 0 < msg.stamp < 1e11 else log_time_ns
        f.writer.add_message(ch, log_time=log_time_ns, data=data, publish_time=publish_ns, sequence=f.messages)
        f.messages += 1
        if isinstance(msg, RunState):
            f.last_run_state = msg
        if f.chunk_started is None:
            f.chunk_started = now

    def _close(self) -> None:
        """Finish the current file (summary, run metadata, footer). A failure is reported, not raised."""
        f, self.cur = self.cur, None
        if f is None:
            return
        try:
            st = f.last_run_state
            if st is not None:
                f.writer.add_metadata(RUN_METADATA, run_metadata(st))
            f.writer.finish()
        except OSError as e:
            self._fail(e, self.clock(), f)
        finally:
            _quiet_close(f.fh)
        self.on_event("info", f"closed {f.path} ({f.messages} messages)")

    def _fail(self, e: OSError, now: float, f: _Open | None = None) -> None:
        f = f or self.cur
        if f is self.cur:
            self.cur = None
        if f is not None:
            _quiet_close(f.fh)
            self.failed = (f.kind, f.run_id, f.part)
        self.errors += 1
        self.retry_at = now + self.cfg.retry_s
        self.last_error = describe_os_error(e, f.path if f is not None else None)
        if self.error is None:
            self.error = self.last_error
            self.reported_at = now
            self.on_event("error", f"recording stopped: {self.error}; retrying every {self.cfg.retry_s:g} s")
        elif now - self.reported_at >= 60.0:
            self.reported_at = now
            self.on_event("error", f"recording still failing: {describe_os_error(e, f.path if f else None)}; {self.lost} messages lost")

    def _prune_idle(self) -> None:
        idle = sorted(self.cfg.dir.glob(f"{self.rig}_*_idle*.mcap"), key=_mtime)
        current = self.cur.path if self.cur is not None else None
        for p in idle[: max(0, len(idle) - self.cfg.keep_idle)]:
            if p != current:
                try:
                    p.unlink()
                except OSError:
                    pass

    def close(self) -> None:
        """Finish the open file, if any."""
        self._close()

    def status(self) -> dict[str, Any]:
        return {
            "file": str(self.cur.path) if self.cur is not None else None,
            "run_id": self.run_id,
            "files": list(self.files),
            "messages": self.messages,
            "lost": self.lost,
            "errors": self.errors,
            "error": self.error,
            "last_error": self.last_error,
        }


def record_bytes(msg: Message) -> bytes:
    """The MCAP record of a message; BadMessage if it has none (a hostile message must not stop the writer)."""
    try:
        return to_json(msg)
    except Exception as e:  # noqa: BLE001 - pydantic/json raise ValueError, RecursionError, TypeError...
        raise BadMessage(f"{msg.KIND}: cannot be recorded: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}") from None


def run_metadata(st: RunState) -> dict[str, str]:
    """The `bagit.run` metadata record of a file: its last run state, every value a string (MCAP)."""
    return {
        "run_id": st.run_id or "",
        "scenario": st.scenario or "",
        "stage": st.stage,
        "progress": repr(float(st.progress)),
        "elapsed_s": repr(float(st.elapsed_s)),
        "reason": st.reason or "",
        "result": json.dumps(st.result) if st.result is not None else "",
        "stamp": repr(float(st.stamp)),
    }


def _mtime(p: Path) -> float:
    try:
        return p.stat().st_mtime
    except OSError:
        return 0.0


def _quiet_close(fh: Any) -> None:
    try:
        fh.close()
    except OSError:
        pass
