"""Recorder files without Zenoh: MCAP JSON records and schemas, per-run/idle files, rotation,
recovery of truncated files, disk-full reporting, run listing and replay timing."""

from __future__ import annotations

import base64
import errno
import json
from pathlib import Path

import numpy as np
import pytest
from bus_support import assert_same_message, example_message
from mcap.reader import make_reader

from bagit.cli import main
from bagit.common import wire
from bagit.common.errors import BadRecording
from bagit.common.messages import MESSAGE_TYPES, PointCloud, RunState, SoiState
from bagit.services.recorder import RecorderConfig, RecordingWriter, list_runs, read_messages, replay_offsets
from bagit.services.recorder.reading import Recording
from bagit.services.recorder.schema import array_fields, from_json, json_schema_bytes, schema_name, to_json
from bagit.services.recorder.writer import _RawFile


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def _writer(tmp_path: Path, events: list | None = None, clock: Clock | None = None, **cfg) -> RecordingWriter:
    cfg.setdefault("linger_s", 1.0)
    return RecordingWriter(RecorderConfig(dir=tmp_path, **cfg), "lab",
                           on_event=(lambda lvl, txt: events.append((lvl, txt))) if events is not None else None,
                           clock=clock or Clock())


T0 = 1_800_000_000_000_000_000


@pytest.mark.parametrize("kind", sorted(MESSAGE_TYPES))
def test_json_record_round_trip_keeps_the_wire_bytes(kind):
    msg = example_message(kind)
    rec = json.loads(to_json(msg))
    schema = json.loads(json_schema_bytes(type(msg)))
    assert schema["type"] == "object" and set(rec) <= set(schema["properties"])
    for name in array_fields(type(msg)):
        a = getattr(msg, name)
        if a is not None:  # the array travels as its raw little-endian bytes, base64-wrapped
            assert base64.b64decode(rec[name]["data"]) == np.ascontiguousarray(a).astype(a.dtype.newbyteorder("<")).tobytes()
            prop = schema["properties"][name]
            nd = next(x for x in prop.get("anyOf", [prop]) if x.get("title") == "NdArray")
            assert nd["properties"]["data"]["contentEncoding"] == "base64"
    back = from_json(type(msg), to_json(msg))
    assert_same_message(msg, back)
    assert wire.encode(back) == wire.encode(msg)


def test_hostile_records_raise_bad_recording():
    good = json.loads(to_json(example_message("soi")))
    cases = [
        b"not json",
        b"[1, 2]",
        json.dumps({**good, "rim": {"dtype": "object", "shape": [32, 3], "data": good["rim"]["data"]}}).encode(),
        json.dumps({**good, "rim": {"dtype": "<f8", "shape": [10**6, 3], "data": good["rim"]["data"]}}).encode(),
        json.dumps({**good, "rim": {"dtype": "<f8", "shape": [32, 3], "data": "!!!"}}).encode(),
        json.dumps({**good, "rim": {"dtype": "<f8", "shape": [1, 3], "data": good["rim"]["data"]}}).encode(),
        json.dumps({**good, "rim": [[0, 0, 0]] * 4, "extra": 1}).encode(),
    ]
    for c in cases:
        with pytest.raises(BadRecording):
            from_json(SoiState, c)


def _run(w: RecordingWriter, run_id: str, n: int, t: int, clock: Clock | None = None, result: dict | None = None) -> int:
    w.write("bagit/lab/run/state", RunState(run_id=run_id, stage="perceiving"), t)
    for i in range(n):
        t += 1_000_000
        w.write("bagit/lab/perception/soi", SoiState(seq=i, rim=np.full((8, 3), float(i))), t)
    t += 1_000_000
    w.write("bagit/lab/run/state", RunState(run_id=run_id, stage="done", progress=1.0, result=result), t)
    return t


def test_one_file_per_run_idle_between_and_the_result_in_its_metadata(tmp_path):
    clock = Clock()
    w = _writer(tmp_path, clock=clock)
    w.write("bagit/lab/perception/soi", example_message("soi"), T0)  # idle: before any run
    t = _run(w, "r1", 5, T0 + 10**9, result={"success": True, "error_to_goal": 0.004})
    clock.t += 0.5
    w.write("bagit/lab/controller/status", example_message("controller_status"), t + 1)  # still within the linger
    clock.t += 1.0
    w.tick()  # linger over: the run file is closed
    w.write("bagit/lab/run/state", RunState(run_id="r1", stage="done"), t + 2)  # republished final state: idle
    t = _run(w, "r/../2", 3, t + 10**9)
    w.close()
    names = [Path(f).name for f in w.files]
    assert len(names) == 4
    assert "_idle" in names[0] and "_run-r1" in names[1] and "_idle" in names[2] and "_run-r_.._2" in names[3]
    assert all(Path(f).parent == tmp_path for f in w.files)  # a hostile run id cannot leave the folder
    msgs, rec = read_messages(w.files[1])
    assert rec.complete and rec.truncated is None
    assert [type(m).__name__ for _, m in msgs] == ["RunState"] + ["SoiState"] * 5 + ["RunState", "ControllerStatus"]
    with open(w.files[1], "rb") as fh:  # the standard reader sees JSON channels with jsonschema schemas
        r = make_reader(fh)
        s = r.get_summary()
        assert {c.message_encoding for c in s.channels.values()} == {"json"}
        assert {x.encoding for x in s.schemas.values()} == {"jsonschema"}
        assert {x.name for x in s.schemas.values()} == {schema_name(RunState), schema_name(SoiState), "bagit.ControllerStatus"}
        meta = {m.name: m.metadata for m in r.iter_metadata()}
    assert meta["bagit.run"]["stage"] == "done" and json.loads(meta["bagit.run"]["result"])["error_to_goal"] == 0.004
    runs = list_runs(tmp_path)["runs"]
    assert [r["run_id"] for r in runs] == ["r1", "r/../2"]
    assert runs[0]["stage"] == "done" and runs[0]["result"] == {"success": True, "error_to_goal": 0.004}
    assert runs[0]["messages"] == 8 and runs[0]["complete"]


def test_rotation_by_size_and_idle_files_pruned(tmp_path):
    w = _writer(tmp_path, max_bytes=1 << 16, chunk_bytes=4096, compression="none", keep_idle=2)
    rng = np.random.default_rng(0)
    t = T0
    for _i in range(30):  # ~20 kB each: ~600 kB of idle data -> >= 5 files of 64 kB
        t += 1_000_000
        cloud = PointCloud(points=rng.normal(size=(1000, 3)), colors=rng.integers(0, 255, (1000, 3)))
        w.write("bagit/lab/perception/cloud", cloud, t)
    w.close()
    assert len(w.files) >= 5
    left = sorted(tmp_path.glob("*.mcap"))
    assert len(left) == 2 and {str(p) for p in left} == set(w.files[-2:])
    assert Path(w.files[1]).name.endswith("_p2.mcap")
    total = sum(read_messages(p)[1].read for p in left)
    assert 0 < total < 30


def _chunked_file(tmp_path: Path) -> tuple[Path, list]:
    w = _writer(tmp_path, chunk_bytes=2048, compression="zstd")
    t = _run(w, "cut", 120, T0)
    w.close()
    assert t > T0
    path = Path(w.files[0])
    msgs, rec = read_messages(path)
    assert rec.complete and len(msgs) == 122
    return path, msgs


def test_truncated_file_reads_back_every_message_of_its_complete_chunks(tmp_path):
    path, full = _chunked_file(tmp_path / "src")
    data = path.read_bytes()
    with open(path, "rb") as fh:
        chunks = sorted(make_reader(fh).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) >= 5
    times = [r.log_time_ns for r, _ in full]
    cut_dir = tmp_path / "cut"
    cut_dir.mkdir()
    # every 173rd byte from the first chunk, and each cut inside the footer and closing magic
    for cut in [*range(chunks[0].chunk_start_offset, len(data) - 1, 173), *range(len(data) - 40, len(data))]:
        p = cut_dir / f"c{cut}.mcap"
        p.write_bytes(data[:cut])
        expected = sum(1 for c in chunks if c.chunk_start_offset + c.chunk_length <= cut
                       for tt in times if c.message_start_time <= tt <= c.message_end_time)
        got, rec = read_messages(p)
        assert not rec.complete and rec.truncated
        assert len(got) == expected, (cut, rec.truncated)
        for (ra, ma), (rb, mb) in zip(got, full, strict=False):
            assert ra.topic == rb.topic and ra.log_time_ns == rb.log_time_ns
            assert_same_message(ma, mb)
    (cut_dir / "c0.mcap").write_bytes(data[:3])
    with pytest.raises(BadRecording, match="not an MCAP file"):
        list(Recording(cut_dir / "c0.mcap").records())


def test_runs_lists_a_truncated_run_from_its_last_recovered_state(tmp_path, capsys):
    path, _ = _chunked_file(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) * 2 // 3])
    assert main(["runs", str(tmp_path), "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    (run,) = out["runs"]
    assert run["run_id"] == "cut" and run["stage"] == "perceiving" and not run["complete"]
    assert 0 < run["messages"] < 122
    assert main(["runs", str(tmp_path)]) == 0
    assert "truncated" in capsys.readouterr().out
    assert main(["runs", str(tmp_path / "nope")]) == 2


class FullDisk(_RawFile):
    """A file that takes `room` bytes, then fails like a full disk: what fits is written, then ENOSPC."""

    def __init__(self, path: Path, room: int) -> None:
        super().__init__(path)
        self.room = room

    def _pwrite(self, parts: list[bytes], offset: int) -> None:
        data = b"".join(parts)
        fits = max(0, min(len(data), self.room - offset))
        if fits:
            super()._pwrite([data[:fits]], offset)
        if fits < len(data):
            raise OSError(errno.ENOSPC, "No space left on device")


def test_disk_full_is_reported_counted_and_retried(tmp_path):
    events: list = []
    clock = Clock()
    room = {"n": 6000}
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=1024, retry_s=5.0), "lab",
                        opener=lambda p: FullDisk(p, room["n"]), on_event=lambda lvl, txt: events.append((lvl, txt)), clock=clock)
    w.write("bagit/lab/run/state", RunState(run_id="r9", stage="planning"), T0)
    ok = [w.write("bagit/lab/perception/soi", SoiState(seq=i, rim=np.full((32, 3), float(i))), T0 + i + 1) for i in range(40)]
    assert not all(ok)
    errors = [t for lvl, t in events if lvl == "error"]
    assert len(errors) == 1 and "disk full (ENOSPC)" in errors[0] and "_run-r9" in errors[0]
    assert w.status()["error"] and w.status()["lost"] == ok.count(False) and w.lost > 0
    clock.t += 1.0
    assert not w.write("bagit/lab/perception/soi", example_message("soi"), T0 + 100)  # before the retry time
    room["n"] = 1 << 30  # space freed
    clock.t += 5.0
    assert w.write("bagit/lab/perception/soi", example_message("soi"), T0 + 101)
    assert any("recording resumed" in t for lvl, t in events if lvl == "info")
    assert w.status()["error"] is None and Path(w.files[-1]).name.endswith("_run-r9_p2.mcap")
    w.close()
    got, rec = read_messages(w.files[0])  # the abandoned part keeps what reached the disk
    assert not rec.complete and all(isinstance(m, (RunState, SoiState)) for _, m in got)


def test_a_disk_full_from_the_start_leaves_no_file_at_any_retry_and_resumes(tmp_path):
    """Issue 36: a 3 MB tmpfs full before the run began got a header-only file at every 5 s retry. A file
    none of whose messages reached the disk is removed; when space returns, recording resumes."""
    events: list = []
    clock = Clock()
    room = {"n": 700}  # a header fits, no chunk does
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=1024, retry_s=5.0), "lab",
                        opener=lambda p: FullDisk(p, room["n"]), on_event=lambda lvl, txt: events.append((lvl, txt)), clock=clock)
    w.write("bagit/lab/run/state", RunState(run_id="r1", stage="planning"), T0)
    for retry in range(20):
        for i in range(30):
            w.write("bagit/lab/perception/soi", SoiState(seq=i, rim=np.full((32, 3), float(i))), T0 + retry * 100 + i)
        clock.t += 5.0
    assert w.errors >= 20 and w.lost > 0 and w.status()["error"]
    assert list(tmp_path.glob("*.mcap")) == [] and w.files == []
    assert sum(lvl == "error" for lvl, _ in events) <= 2  # reported once (and again after a minute), not at every retry
    room["n"] = 1 << 30
    clock.t += 5.0
    assert w.write("bagit/lab/perception/soi", example_message("soi"), T0 + 10_000)
    w.close()
    assert [Path(f).exists() for f in w.files] == [True] and w.status()["error"] is None


def test_replay_offsets_follow_the_recorded_gaps():
    assert replay_offsets([5_000_000_000, 5_100_000_000, 5_400_000_000], 2.0) == pytest.approx([0.0, 0.05, 0.2])
    assert replay_offsets([], 1.0) == []
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(BadRecording):
            replay_offsets([1], bad)
