"""Reading recordings back: messages (recovering truncated files), run summaries, replay timing.

A file the recorder closed ends with a summary and a footer. A file whose recorder was killed (or
whose disk filled) ends at its last complete chunk with a provisional footer that has no summary
(the writer keeps one there), or, if the kill cut a write, with a partial record. Either way it
is read sequentially with mcap's StreamReader, chunk CRCs checked, and reading stops at the
first record that is incomplete or corrupt, so every message of every complete chunk comes back
and nothing after. `Recording.truncated` says why it is not complete.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mcap.exceptions import McapError
from mcap.reader import SeekingReader
from mcap.records import Channel, Footer, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from bagit.common.errors import BadRecording
from bagit.common.messages import Message, RunState
from bagit.services.recorder.schema import MESSAGE_ENCODING, class_for_schema, from_json
from bagit.services.recorder.writer import RECORDING_METADATA, RUN_METADATA

MAX_RECORD_BYTES = 1 << 30
_MAGIC = b"\x89MCAP0\r\n"


@dataclass(frozen=True)
class Record:
    """One recorded message: its Zenoh key, model, receive and publish times (ns), JSON record."""

    topic: str
    cls: type[Message]
    log_time_ns: int
    publish_time_ns: int
    data: bytes

    def message(self) -> Message:
        """The message itself (BadRecording if the record is malformed)."""
        return from_json(self.cls, self.data)


@dataclass
class Recording:
    """A sequential read of one MCAP file. Iterate `records()` once; afterwards `complete` (the
    footer was reached), `truncated` (why reading stopped early), `metadata` and `skipped`
    (channels that are not BagIt JSON) are filled in."""

    path: Path
    complete: bool = False
    truncated: str | None = None
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    skipped: int = 0
    read: int = 0

    def records(self) -> Iterator[Record]:
        if not self.path.is_file():
            raise BadRecording(f"{self.path}: no such recording")
        with open(self.path, "rb") as fh:
            if fh.read(len(_MAGIC)) != _MAGIC:
                raise BadRecording(f"{self.path}: not an MCAP file (bad magic)")
            fh.seek(0)
            reader = StreamReader(fh, validate_crcs=True, record_size_limit=MAX_RECORD_BYTES)
            schemas: dict[int, Schema] = {}
            channels: dict[int, tuple[str, type[Message]] | None] = {}
            it = reader.records
            footer: Footer | None = None
            while True:
                try:
                    rec = next(it)
                except StopIteration:
                    break
                except (McapError, EOFError, struct.error, zlib.error, ValueError, MemoryError, UnicodeDecodeError) as e:
                    self.truncated = f"stopped after {self.read} messages: {type(e).__name__}: {str(e) or 'incomplete record'}"
                    break
                except Exception as e:  # noqa: BLE001 - zstd/lz4 raise their own types on a cut chunk
                    self.truncated = f"stopped after {self.read} messages: {type(e).__name__}: {e}"
                    break
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = _channel(rec, schemas)
                elif isinstance(rec, McapMessage):
                    ch = channels.get(rec.channel_id)
                    if ch is None:
                        self.skipped += 1
                        continue
                    self.read += 1
                    yield Record(ch[0], ch[1], rec.log_time, rec.publish_time, bytes(rec.data))
                elif isinstance(rec, Metadata):
                    self.metadata[rec.name] = dict(rec.metadata)
                elif isinstance(rec, Footer):
                    footer = rec
            # a footer followed by a cut closing magic is still a cut file: complete needs both
            self.complete = footer is not None and self.truncated is None
            if footer is None and self.truncated is None:
                self.truncated = f"stopped after {self.read} messages: no footer (the recorder did not close the file)"
            elif self.complete and footer is not None and footer.summary_start == 0 and RECORDING_METADATA in self.metadata:
                # the recorder closes every file with a summary: this is the provisional trailer of a file being written
                self.complete = False
                self.truncated = f"stopped after {self.read} messages: the recorder did not close the file (no summary)"


def _channel(ch: Channel, schemas: dict[int, Schema]) -> tuple[str, type[Message]] | None:
    schema = schemas.get(ch.schema_id)
    if ch.message_encoding != MESSAGE_ENCODING or schema is None:
        return None
    try:
        return ch.topic, class_for_schema(schema.name)
    except BadRecording:
        return None


def read_messages(path: str | Path) -> tuple[list[tuple[Record, Message]], Recording]:
    """Every message of a file (as far as it is readable), decoded, with the read's outcome."""
    rec = Recording(Path(path))
    out = [(r, r.message()) for r in rec.records()]
    return out, rec


# ---------------------------------------------------------------------------------------------
# Run summaries (`bagit runs`)
# ---------------------------------------------------------------------------------------------


def file_summary(path: str | Path) -> dict[str, Any]:
    """What a file holds: kind (run/idle), run id, its last run state, times, counts, complete or not.

    A closed file answers from its summary section and metadata (no message is read); a truncated
    one is scanned with recovery for its last run state."""
    p = Path(path)
    out: dict[str, Any] = {"file": str(p), "bytes": p.stat().st_size}
    meta: dict[str, dict[str, str]] = {}
    quick = _summary_of_closed(p)
    if quick is not None:
        stats, meta = quick
        out.update(complete=True, truncated=None, messages=stats[0], start_ns=stats[1], end_ns=stats[2])
        last = _state_from_metadata(meta.get(RUN_METADATA))
    else:
        rec = Recording(p)
        last = None
        start = end = None
        for r in rec.records():
            start = r.log_time_ns if start is None else min(start, r.log_time_ns)
            end = r.log_time_ns if end is None else max(end, r.log_time_ns)
            if r.cls is RunState:
                try:
                    last = r.message()  # type: ignore[assignment]
                except BadRecording:
                    pass
        meta = rec.metadata
        out.update(complete=rec.complete, truncated=rec.truncated, messages=rec.read, start_ns=start, end_ns=end)
    info = meta.get(RECORDING_METADATA, {})
    out["kind"] = info.get("kind") or ("run" if "_run-" in p.name else "idle")
    out["rig"] = info.get("rig")
    out["part"] = int(info.get("part") or 1)
    out["run_id"] = info.get("run_id") or (last.run_id if last else None) or None
    out["last_state"] = None if last is None else {
        "run_id": last.run_id, "scenario": last.scenario, "stage": last.stage, "progress": last.progress,
        "elapsed_s": last.elapsed_s, "reason": last.reason, "result": last.result,
    }
    return out


def _summary_of_closed(p: Path) -> tuple[tuple[int, int, int], dict[str, dict[str, str]]] | None:
    """(messages, start, end) and metadata from a closed file's summary; None if it has none."""
    try:
        with open(p, "rb") as fh:
            reader = SeekingReader(fh, record_size_limit=MAX_RECORD_BYTES)
            summary = reader.get_summary()
            if summary is None or summary.statistics is None:
                return None
            meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
            s = summary.statistics
            return (s.message_count, s.message_start_time, s.message_end_time), meta
    except Exception:  # noqa: BLE001 - a truncated file has no footer; mcap raises assorted errors
        return None


def _state_from_metadata(m: dict[str, str] | None) -> RunState | None:
    if not m:
        return None
    try:
        return RunState(
            run_id=m.get("run_id") or None,
            scenario=m.get("scenario") or None,
            stage=m.get("stage") or "idle",
            progress=float(m.get("progress") or 0.0),
            elapsed_s=float(m.get("elapsed_s") or 0.0),
            reason=m.get("reason") or None,
            result=json.loads(m["result"]) if m.get("result") else None,
            stamp=float(m.get("stamp") or 0.0),
        )
    except (ValueError, TypeError):
        return None


def list_runs(folder: str | Path) -> dict[str, Any]:
    """The runs recorded in a folder (their parts merged), newest last, and the idle files."""
    d = Path(folder)
    if not d.is_dir():
        raise BadRecording(f"{d}: no such folder of recordings")
    runs: dict[str, dict[str, Any]] = {}
    idle: list[dict[str, Any]] = []
    unreadable: list[dict[str, str]] = []
    for p in sorted(d.glob("*.mcap")):
        try:
            s = file_summary(p)
        except (BadRecording, OSError) as e:
            unreadable.append({"file": str(p), "reason": str(e)})
            continue
        if s["kind"] != "run" or not s["run_id"]:
            idle.append(s)
            continue
        r = runs.setdefault(s["run_id"], {"run_id": s["run_id"], "files": [], "messages": 0, "bytes": 0,
                                          "start_ns": None, "end_ns": None, "complete": True, "last_state": None})
        r["files"].append(s["file"])
        r["messages"] += s["messages"]
        r["bytes"] += s["bytes"]
        r["complete"] = r["complete"] and bool(s["complete"])
        if s["start_ns"] is not None:
            r["start_ns"] = s["start_ns"] if r["start_ns"] is None else min(r["start_ns"], s["start_ns"])
            r["end_ns"] = s["end_ns"] if r["end_ns"] is None else max(r["end_ns"], s["end_ns"])
        if s["last_state"] is not None:
            r["last_state"] = s["last_state"]  # files sorted by start time: the last part's wins
    rows = []
    for r in sorted(runs.values(), key=lambda r: r["start_ns"] or 0):
        st = r.pop("last_state") or {}
        rows.append({
            **r,
            "duration_s": (r["end_ns"] - r["start_ns"]) / 1e9 if r["start_ns"] is not None else 0.0,
            "scenario": st.get("scenario"),
            "stage": st.get("stage"),
            "progress": st.get("progress"),
            "reason": st.get("reason"),
            "result": st.get("result"),
        })
    return {"dir": str(d), "runs": rows, "idle_files": len(idle), "idle_bytes": sum(s["bytes"] for s in idle), "unreadable": unreadable}


# ---------------------------------------------------------------------------------------------
# Replay timing
# ---------------------------------------------------------------------------------------------


def replay_offsets(log_times_ns: list[int], speed: float) -> list[float]:
    """Seconds after the replay's start at which each message is due: the recorded gaps / speed."""
    if not speed > 0 or speed != speed or speed == float("inf"):
        raise BadRecording(f"replay speed must be a positive finite number, got {speed}")
    if not log_times_ns:
        return []
    t0 = log_times_ns[0]
    return [max(0.0, (t - t0) / 1e9 / speed) for t in log_times_ns]
