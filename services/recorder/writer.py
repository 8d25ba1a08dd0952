"""The recorder's file policy: which MCAP file each message goes to, chunking, rotation, disk errors.

- One file per run: a `run/state` with a new run id (and a stage other than idle) closes the
  current file and opens `<rig>_<UTC start>_run-<id>.mcap`. When that run reaches done, failed or
  aborted, the file stays open `linger_s` more (the final states and result) and is then closed;
  a later run/state of the same, finished run does not reopen it.
- Outside runs, messages go to a rolling `<rig>_<UTC start>_idle.mcap`, opened on the first idle
  message; only the newest `keep_idle` idle files of the rig are kept.
- A file is closed before a message would take it over `max_bytes` (summary and footer
  included), and the next part opened: `..._p2.mcap`, `..._p3.mcap`. Only a message larger than
  `max_bytes` by itself makes a larger file (of that message alone). Chunks are at most
  `max_bytes / CHUNKS_PER_FILE`, so the open chunk, counted at its uncompressed bound until
  written, never leaves much of a file unused.
- Chunked and compressed MCAP: a chunk is closed when it reaches `chunk_bytes` (uncompressed)
  or `flush_s` after its first message, and written at once, in one write with a provisional
  trailer (an empty DataEnd, a Footer without summary, the magic) over the previous one. So a
  file is a valid MCAP file after every chunk: one cut by SIGKILL opens in the standard reader
  (`mcap.reader.make_reader`, which streams a file without summary) up to its last complete chunk,
  at most `flush_s` of data lost. A closed file ends with the `bagit.run` metadata (the last run
  state), then the summary and footer as the mcap writer writes them, over the trailer.
- A write error (disk full: ENOSPC, or any OSError) abandons the file (ended again at its last
  complete chunk; removed if none of its messages reached the disk), is reported through `on_event("error", ...)` once, counts the messages that
  did not reach the disk (those of the open chunk too), and is retried with a new part every
  `retry_s`; success is reported as `on_event("info", "recording resumed...")`.

No Zenoh here: `node.py` feeds decoded messages in and turns events into stderr lines and run state.
"""

from __future__ import annotations

import errno
import json
import os
import re
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any, Literal

from mcap.data_stream import RecordBuilder
from mcap.records import Channel, DataEnd, Footer, Metadata, Schema
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer
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
MESSAGE_RECORD_OVERHEAD = 1 + 8 + 2 + 4 + 8 + 8  # opcode, length, channel id, sequence, log and publish time
MESSAGE_INDEX_ENTRY = 8 + 8  # log time and offset of a message in its chunk's MessageIndex
_NEVER = sys.maxsize  # the mcap Writer's chunk size: it never closes a chunk itself
CHUNKS_PER_FILE = 8  # chunks are at most max_bytes / this (and chunk_bytes)
CHUNK_RECORD_OVERHEAD = 1 + 8 + 8 + 8 + 8 + 4 + 4 + 4 + 8  # a Chunk record around its data ("zstd" the longest name)
MESSAGE_INDEX_HEADER = 1 + 8 + 2 + 4  # a MessageIndex record per channel of a chunk, before its entries
STATISTICS_PER_CHANNEL = 2 + 8  # the Statistics record's message count of a channel
# what closing adds besides the open chunk, the schemas, channels, chunk indexes and bagit.run: the
# DataEnd (13), Statistics without channels (55), metadata indexes (2 x ~45), summary offsets (6 x 26),
# Footer (29) and magic (8), rounded up
CLOSE_OVERHEAD = 512
_IOV_MAX = 512  # buffers per pwritev (Linux takes 1024); more are joined first


class RecorderConfig(BaseModel):
    """Where and how the recorder writes."""

    model_config = ConfigDict(extra="forbid")

    dir: Path = Field(Path("recordings"), description="folder of the MCAP files")
    max_bytes: int = Field(1 << 30, ge=1 << 16, le=MAX_FILE_BYTES, description="close a file before a message would take it over this size")
    chunk_bytes: int = Field(1 << 20, ge=1 << 10, le=1 << 28, description="close an MCAP chunk at this size (uncompressed)")
    flush_s: float = Field(1.0, gt=0, le=60, description="close a chunk this long after its first message")
    linger_s: float = Field(2.0, ge=0, le=600, description="keep a finished run's file open this long for its last states")
    keep_idle: int = Field(4, ge=1, le=10_000, description="idle files of this rig kept (older ones are deleted)")
    retry_s: float = Field(5.0, gt=0, le=3600, description="after a write error, try a new file this often")
    compression: Literal["zstd", "lz4", "none"] = Field(
        "lz4", description="chunk compression: lz4 keeps up with 30 Hz RGB-D on 2 loaded cores; zstd makes ~40% smaller files"
    )


def _record_bytes(*records: Any) -> bytes:
    """MCAP records serialised as the mcap writer serialises them."""
    b = RecordBuilder()
    for r in records:
        r.write(b)
    return b.end()


# What a file being written ends with between chunks: an empty DataEnd, a Footer without a
# summary, the closing magic. The standard reader (mcap.reader.make_reader) finds the footer, sees
# no summary and streams the file from its start, so a file cut by SIGKILL opens anywhere.
OPEN_TRAILER = _record_bytes(
    DataEnd(data_section_crc=0), Footer(summary_start=0, summary_offset_start=0, summary_crc=0)
) + MCAP0_MAGIC


class _RawFile:
    """The file the MCAP writer writes through. Its writes are collected and put on disk by
    `commit()` in one positioned write: the new records over the previous trailer, followed by a
    fresh OPEN_TRAILER (none when `final`, after the writer's own summary and footer). So at any
    time the file on disk is a valid MCAP file ending at its last complete chunk. RecordingWriter
    commits right after every write of the MCAP writer (start, a chunk, the end), so nothing waits
    here for a SIGKILL to lose; short writes are completed, ENOSPC raises."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
        self._done = 0  # bytes of records on disk; the trailer follows them
        self._parts: list[bytes] = []  # what the MCAP writer wrote since the last commit (not copied)
        self._pending = 0

    def write(self, data: bytes | bytearray | memoryview) -> int:
        self._parts.append(data if isinstance(data, bytes) else bytes(data))
        self._pending += len(data)
        return len(data)

    def tell(self) -> int:
        return self._done + self._pending

    def flush(self) -> None:
        pass

    def commit(self, final: bool = False) -> None:
        """Put what was written since the last commit on disk, with the trailer (module doc)."""
        self._pwrite(self._parts if final else [*self._parts, OPEN_TRAILER], self._done)
        self._done += self._pending
        self._parts, self._pending = [], 0
        if final:
            os.ftruncate(self._fd, self._done)

    def _pwrite(self, parts: list[bytes], offset: int) -> None:
        """Write `parts` at `offset` in one pwritev (the rest after a short write)."""
        total = sum(len(p) for p in parts)
        n = os.pwritev(self._fd, parts, offset) if 0 < len(parts) <= _IOV_MAX else 0
        if n < total:
            rest = memoryview(b"".join(parts))[n:]
            while rest:
                k = os.pwrite(self._fd, rest, offset + total - len(rest))
                if k <= 0:
                    raise OSError(errno.ENOSPC, "no progress writing", str(self.path))
                rest = rest[k:]

    def abandon(self) -> None:
        """After a failed commit: drop what was not written and end the file at its last complete
        chunk again (the old trailer's place is already allocated), then close it. Never raises."""
        self._parts, self._pending = [], 0
        try:
            if self._fd >= 0:
                self._pwrite([OPEN_TRAILER], self._done)
                os.ftruncate(self._fd, self._done + len(OPEN_TRAILER))
        except OSError:
            pass
        _quiet_close(self)

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)


Opener = Callable[[Path], _RawFile]


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
    chunk_started: float | None = None  # clock time of the open chunk's first message
    chunk_messages: int = 0  # messages in the open chunk (not on disk yet)
    chunk_bytes: int = 0  # the open chunk's records and message index, uncompressed
    summary_bytes: int = 0  # what the summary will hold: schemas, channels, chunk indexes, counts
    run_meta_bytes: int = 0  # the bagit.run metadata record closing will add
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
        # a file holds at least CHUNKS_PER_FILE chunks, so chunks stay small next to a small --max-mb
        self.chunk_limit = min(cfg.chunk_bytes, cfg.max_bytes // CHUNKS_PER_FILE)
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
            f = self._current(log_time_ns, key, msg, data)
        except OSError as e:
            self._fail(e, now)
            self.lost += 1
            return False
        self._add(f, key, msg, data, log_time_ns, now)
        self.messages += 1
        if f.chunk_bytes >= self.chunk_limit and not self._close_chunk(f, now):
            return False  # the chunk did not reach the disk: its messages, this one included, are lost
        if self.error is not None:
            self.on_event("info", f"recording resumed in {f.path} after {self.lost} lost messages")
            self.error = None
        return True

    def follow(self, st: RunState) -> None:
        """Take a run state into account without recording it (the node's start hold)."""
        self._follow_run(st, self.clock())

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
            self._close_chunk(f, now)

    def _close_chunk(self, f: _Open, now: float) -> bool:
        """Write the open chunk (and a fresh trailer); False after a write error (reported, counted)."""
        try:
            self._write_chunk(f)
        except OSError as e:
            self._fail(e, now, f)
            return False
        return True

    def _write_chunk(self, f: _Open) -> None:
        """Write the open chunk now (OSError on a write error, the chunk then still open)."""
        f.writer.flush()
        f.fh.commit()
        f.summary_bytes += chunk_index_bytes(len(f.channels))
        f.chunk_started, f.chunk_messages, f.chunk_bytes = None, 0, 0

    # ---- files ---------------------------------------------------------------------------------

    def _wanted(self) -> tuple[str, str | None]:
        return ("run", self.run_id) if self.run_id is not None else ("idle", None)

    def _current(self, log_time_ns: int, key: str, msg: Message, data: bytes) -> _Open:
        """The file this message goes to. A file it would take over max_bytes is closed first (the
        open chunk is written first, so its compressed size counts, not a bound), unless the file
        holds nothing yet: a message larger than max_bytes gets a file of its own."""
        kind, rid = self._wanted()
        f = self.cur
        if f is not None and (f.kind != kind or f.run_id != rid):
            self._close()
            f = None
        part = 1
        if f is not None and f.messages > 0 and self._size_bound(f, key, msg, data) > self.cfg.max_bytes:
            if f.chunk_messages:
                self._write_chunk(f)
            if self._size_bound(f, key, msg, data) > self.cfg.max_bytes:
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
            # chunks are closed here, not by mcap. mcap's Writer declares IO[Any] but only writes, tells and flushes: _RawFile does those
            w = Writer(fh, chunk_size=_NEVER, compression=compression)  # type: ignore[arg-type]
            w.start(profile="", library=f"bagit {self.version}".strip())
            w.add_metadata(RECORDING_METADATA, {
                "rig": self.rig, "kind": kind, "run_id": rid or "", "part": str(part),
                "started_ns": str(log_time_ns), "schema_version": str(SCHEMA_VERSION),
                "encoding": "json records: arrays as {dtype, shape, data: base64 of the wire bytes}",
            })
            fh.commit()
        except BaseException as e:
            fh.abandon()
            _unlink(path)  # a file without its header records nothing: none is left behind
            if isinstance(e, OSError) and not e.filename:
                raise OSError(e.errno, e.strerror, str(path)) from None  # the report names the file
            raise
        self.cur = _Open(path=path, kind=kind, run_id=rid, part=part, fh=fh, writer=w, started_ns=log_time_ns)
        self.files.append(str(path))
        self.on_event("info", f"recording {kind}{' ' + rid if rid else ''} to {path}")
        if kind == "idle":
            self._prune_idle()
        return self.cur

    def _new_records(self, f: _Open, key: str, cls: type[Message]) -> int:
        """Bytes of the schema and channel records a message on `key` adds to `f` (0 if it has them);
        each goes in the chunk and again in the summary."""
        if key in f.channels:
            return 0
        return (0 if cls in f.schemas else schema_record_bytes(cls)) + channel_record_bytes(key, cls)

    def _size_bound(self, f: _Open, key: str, msg: Message, data: bytes) -> int:
        """At most how large `f` is once closed if this message goes in now: what is on disk, the open
        chunk at its compression bound (lz4 and zstd never grow data by more), its message index and
        chunk index, and the summary, run metadata and footer that closing adds."""
        new = self._new_records(f, key, type(msg))
        channels = len(f.channels) + (key not in f.channels)
        meta = metadata_record_bytes(RUN_METADATA, run_metadata(msg)) if isinstance(msg, RunState) else f.run_meta_bytes
        chunk = f.chunk_bytes + new + message_bytes(data)
        return (f.fh.tell() + CHUNK_RECORD_OVERHEAD + compressed_bound(chunk) + MESSAGE_INDEX_HEADER * channels
                + chunk_index_bytes(channels) + f.summary_bytes + new + STATISTICS_PER_CHANNEL * (key not in f.channels)
                + meta + CLOSE_OVERHEAD)

    def _add(self, f: _Open, key: str, msg: Message, data: bytes, log_time_ns: int, now: float) -> None:
        cls = type(msg)
        ch = f.channels.get(key)
        if ch is None:
            new = self._new_records(f, key, cls)
            sid = f.schemas.get(cls)
            if sid is None:
                sid = f.schemas[cls] = f.writer.register_schema(schema_name(cls), SCHEMA_ENCODING, json_schema_bytes(cls))
            ch = f.channels[key] = f.writer.register_channel(key, MESSAGE_ENCODING, sid, channel_metadata(cls))
            f.chunk_bytes += new
            f.summary_bytes += new + STATISTICS_PER_CHANNEL
        publish_ns = int(msg.stamp * 1e9) if 0 < msg.stamp < 1e11 else log_time_ns
        f.writer.add_message(ch, log_time=log_time_ns, data=data, publish_time=publish_ns, sequence=f.messages)
        f.messages += 1
        f.chunk_messages += 1
        f.chunk_bytes += message_bytes(data)
        if isinstance(msg, RunState):
            f.last_run_state = msg
            f.run_meta_bytes = metadata_record_bytes(RUN_METADATA, run_metadata(msg))
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
            f.fh.commit(final=True)
        except OSError as e:
            self._fail(e, self.clock(), f)
            return
        except BaseException:
            self._drop(f)
            raise
        _quiet_close(f.fh)
        self.on_event("info", f"closed {f.path} ({f.messages} messages)")

    def _drop(self, f: _Open) -> None:
        """Give up a file: the open chunk's messages are lost, the file ends at its last complete chunk."""
        self.messages -= f.chunk_messages
        self.lost += f.chunk_messages
        f.chunk_messages = 0
        f.fh.abandon()

    def _fail(self, e: OSError, now: float, f: _Open | None = None) -> None:
        f = f or self.cur
        if f is self.cur:
            self.cur = None
        if f is not None:
            on_disk = f.messages - f.chunk_messages
            self._drop(f)
            self.failed = (f.kind, f.run_id, f.part)
            if on_disk == 0:  # nothing of it reached the disk: no empty file piles up at each retry
                _unlink(f.path)
                if str(f.path) in self.files:
                    self.files.remove(str(f.path))
        self.errors += 1
        self.retry_at = now + self.cfg.retry_s
        where = f.path if f is not None else Path(e.filename) if e.filename else self.cfg.dir
        self.last_error = describe_os_error(e, where)
        if self.error is None:
            self.error = self.last_error
            self.reported_at = now
            self.on_event("error", f"recording stopped: {self.error}; retrying every {self.cfg.retry_s:g} s")
        elif now - self.reported_at >= 60.0:
            self.reported_at = now
            self.on_event("error", f"recording still failing: {self.last_error}; {self.lost} messages lost")

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

    def abandon(self) -> None:
        """Give up the open file without finishing it (after a writer fault): its open chunk is lost."""
        f, self.cur = self.cur, None
        if f is not None:
            self._drop(f)

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


def message_bytes(data: bytes) -> int:
    """What a message with this record adds to its chunk: its Message record and message index entry."""
    return MESSAGE_RECORD_OVERHEAD + len(data) + MESSAGE_INDEX_ENTRY


def compressed_bound(n: int) -> int:
    """The most n bytes become under lz4 or zstd (both bound their output by n + n/255 + a frame's
    headers; n/64 + 64 covers that with room to spare); none leaves them as they are."""
    return n + n // 64 + 64


def chunk_index_bytes(channels: int) -> int:
    """A ChunkIndex record: times, offsets, lengths, sizes, compression name, one entry per channel."""
    return 1 + 8 + 8 * 4 + 4 + 10 * channels + 8 + 4 + 4 + 8 + 8


def channel_metadata(cls: type[Message]) -> dict[str, str]:
    return {"kind": cls.KIND, "schema_version": str(SCHEMA_VERSION)}


@cache
def schema_record_bytes(cls: type[Message]) -> int:
    return len(_record_bytes(Schema(id=0, name=schema_name(cls), encoding=SCHEMA_ENCODING, data=json_schema_bytes(cls))))


def channel_record_bytes(key: str, cls: type[Message]) -> int:
    return len(_record_bytes(Channel(id=0, topic=key, message_encoding=MESSAGE_ENCODING, schema_id=0,
                                     metadata=channel_metadata(cls))))


def metadata_record_bytes(name: str, data: dict[str, str]) -> int:
    return len(_record_bytes(Metadata(name=name, metadata=data)))


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


def _unlink(path: Path) -> None:
    try:
        path.unlink()
    except OSError:
        pass


def _quiet_close(fh: Any) -> None:
    try:
        fh.close()
    except OSError:
        pass
