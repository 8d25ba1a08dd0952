"""Recorder hardening: a hostile message cannot stop the writer, a dead writer is never silent,
a SIGKILLed file opens in the standard mcap reader, a restarted recorder continues its run at
once, and rotation keeps files under --max-mb.

Bus tests use in-process peers on loopback (multicast scouting off); the kill and restart tests
run `bagit recorder` as a subprocess, as `bagit up` does."""

from __future__ import annotations

import io
import json
import logging
import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from bus_support import wait_until
from log_support import LogLines
from mcap.reader import make_reader
from suite_support import HANG_S
from test_recorder_files import T0, Clock, FullDisk

from bagit.bench.probes import hostile_headers, killed_recording, nested_payload, restarted_recorder
from bagit.cli import main
from bagit.common import wire
from bagit.common.bus import BusConfig, Keys, LivelinessWatcher, Publisher, Subscriber, locators, open_session
from bagit.common.errors import BadMessage
from bagit.common.messages import ArmState, CameraInfo, PointCloud, RgbdFrame, RunState, SoiState
from bagit.services.recorder import RecorderConfig, RecordingWriter, read_messages
from bagit.services.recorder.node import RecorderNode, outcome
from bagit.services.recorder.writer import _RawFile

# ---- 1. a hostile message cannot stop the writer; a dead writer is never silent ------------------


def test_deeply_nested_header_is_a_bad_message_not_a_recursion_error():
    """json's C parser raises RecursionError on deep nesting; decode must turn it into BadMessage."""
    with pytest.raises(BadMessage, match="nested too deeply"):
        wire.decode(nested_payload(100_000))
    out: list[BaseException] = []

    def in_thread() -> None:  # the recorder decodes in its writer thread
        try:
            wire.decode(nested_payload(100_000))
        except BaseException as e:  # noqa: BLE001
            out.append(e)

    t = threading.Thread(target=in_thread)
    t.start()
    t.join()
    assert len(out) == 1 and isinstance(out[0], BadMessage)


def test_hostile_headers_are_counted_as_malformed_and_the_recorder_keeps_recording(tmp_path):
    """The user's case through the real command: a ~200 kB nested header on any key (and one that
    decodes but nests too deep for a JSON record) are malformed; everything after is recorded."""
    a = open_session(BusConfig(rig="hostile", adminspace=True))
    try:
        assert len(nested_payload(100_000)) > 200_000
        r = hostile_headers(a, locators(a)[0], "hostile", tmp_path)
    finally:
        a.close()
    res = r["summary"]
    assert r["exit"] == 0, r["stderr"]
    assert res["success"] and res["malformed"] == 3 and res["lost"] == 0 and res["dead"] is None, res
    assert res["messages"] == 52
    assert "malformed message #1" in r["stderr"] and "nested too deeply" in r["stderr"]
    assert r["sois"] == list(range(50))
    assert not r["evil_files"]  # the hostile run state routed nothing, not even held messages


class BrokenFile(_RawFile):
    """A file that takes `room` bytes and then fails with what no retry gets past: an exception
    that is not an OSError (here the ValueError of writing to a closed file)."""

    def __init__(self, path: Path, room: int) -> None:
        super().__init__(path)
        self.room = room

    def _pwrite(self, parts: list[bytes], offset: int) -> None:
        if offset + sum(len(p) for p in parts) > self.room:
            raise ValueError("I/O operation on closed file")
        super()._pwrite(parts, offset)


def test_a_dead_writer_takes_the_token_down_and_reports_the_loss(tmp_path, pair):
    """A writer fault ends recording loudly: liveliness gone, reason on run/state, `stopped` set,
    every message in hand, queued or received afterwards counted lost, the summary a failure."""
    a, b = pair
    rig = "deadwriter"
    keys = Keys(rig)
    watcher = LivelinessWatcher(a, keys)
    states: list[RunState] = []
    Subscriber(a, keys.run_state, RunState, states.append)
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=1024), rig, opener=lambda p: BrokenFile(p, 6000))
    lines = LogLines("bagit.recorder")
    node = RecorderNode(b, keys, w)
    try:
        assert watcher.wait_for("recorder", True, 5.0)
        pub_state = Publisher(a, keys.run_state, RunState)
        pub_soi = Publisher(a, keys.perception_soi, SoiState)
        assert wait_until(lambda: pub_soi.matched and pub_state.matched)
        pub_state.put(RunState(run_id="d1", stage="bagging"))
        for i in range(60):
            pub_soi.put(SoiState(seq=i, rim=np.full((32, 3), float(i))))
            threading.Event().wait(0.002)
        assert node.stopped.wait(5.0), "the writer did not die"
        assert watcher.wait_for("recorder", False, 5.0), "the liveliness token stayed up"
        assert wait_until(lambda: any((s.reason or "").startswith("recorder: writer died: ValueError") for s in states))
        before = node.status()["lost"]
        for i in range(10):  # after the death: received, counted lost, never queued
            pub_soi.put(SoiState(seq=100 + i, rim=np.zeros((32, 3))))
        assert wait_until(lambda: node.status()["lost"] >= before + 10)
    finally:
        status = node.close()
        watcher.close()
        lines.close()
    ok, reason = outcome(status)
    assert not ok and status["lost"] >= 10 and "writer died: ValueError: I/O operation on closed file" in (reason or "")
    assert status["messages"] + status["lost"] == status["received"]  # nothing unaccounted for
    assert any("writer died" in t for t in lines.at(logging.ERROR))


def test_bagit_recorder_with_a_dead_writer_exits_1_with_the_loss_in_its_summary(tmp_path, monkeypatch, capsys):
    """The command, not only the node: a writer fault stops `bagit recorder` at once (not at
    --duration) with exit status 1, and its JSON summary says success false, what was lost and why."""
    rig = "deadcli"
    keys = Keys(rig)
    room = 20_000

    def broken(self: _RawFile, parts: list[bytes], offset: int) -> None:  # the disk fails as BrokenFile's
        if offset + sum(len(p) for p in parts) > room:
            raise ValueError("I/O operation on closed file")
        os.pwritev(self._fd, parts, offset)

    monkeypatch.setattr(_RawFile, "_pwrite", broken)
    a = open_session(BusConfig(rig=rig, adminspace=True))
    stop = threading.Event()

    def traffic() -> None:
        soi = Publisher(a, keys.perception_soi, SoiState)
        rng = np.random.default_rng(5)
        i = 0
        while not stop.is_set():
            soi.put(SoiState(seq=i, rim=rng.normal(size=(32, 3))))
            i += 1
            stop.wait(0.005)

    th = threading.Thread(target=traffic, daemon=True)
    th.start()
    t0 = time.monotonic()
    try:
        code = main(["recorder", "--rig", rig, "-e", locators(a)[0], "--dir", str(tmp_path), "--chunk-kb", "4",
                     "--duration", str(HANG_S), "--json"])
        took = time.monotonic() - t0
    finally:
        stop.set()
        th.join(5)
        a.close()
    res = json.loads(capsys.readouterr().out)
    assert code == 1 and took < HANG_S, (code, took)  # stopped by the death, not by --duration
    assert not res["success"] and res["lost"] > 0 and res["dead"].startswith("writer died: ValueError")
    assert "writer died: ValueError: I/O operation on closed file" in res["reason"]
    assert res["messages"] + res["lost"] + res["malformed"] + res["overflow"] == res["received"]


# ---- 2. a file cut by SIGKILL opens in the standard mcap reader ----------------------------------


def standard_read(data: bytes) -> list[tuple[str, int]]:
    """(topic, log time) of every message `mcap.reader.make_reader(f).iter_messages()` returns."""
    return [(ch.topic, m.log_time) for _, ch, m in make_reader(io.BytesIO(data)).iter_messages()]


def test_the_file_on_disk_is_valid_mcap_after_every_chunk(tmp_path):
    """Snapshot the file after every write: the standard reader always returns exactly the messages
    of the chunks written so far (the open chunk is in memory only)."""
    clock = Clock()
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=4096, flush_s=0.05), "lab", clock=clock)
    t = T0
    sent: list[tuple[str, int]] = []
    chunks_seen = 0
    for i in range(150):
        t += 10_000_000
        clock.t += 0.01
        key = "bagit/lab/run/state" if i % 20 == 0 else "bagit/lab/perception/soi"
        msg = RunState(run_id="s1", stage="bagging", progress=i / 150) if i % 20 == 0 else SoiState(seq=i, rim=np.full((8, 3), float(i)))
        assert w.write(key, msg, t)
        sent.append((key, t))
        if i % 7 == 0:
            w.tick()
        f = w.cur
        assert f is not None
        on_disk = len(sent) - f.chunk_messages
        got = standard_read(f.path.read_bytes())
        assert got == sent[:on_disk]
        chunks_seen += on_disk > 0
    assert chunks_seen > 100
    path = w.cur.path
    w.close()
    assert standard_read(path.read_bytes()) == sent
    _, rec = read_messages(path)
    assert rec.complete


def test_a_file_abandoned_on_a_full_disk_opens_in_the_standard_reader(tmp_path):
    """ENOSPC in the middle of a chunk's write: the file is ended again at its last complete chunk."""
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=2048), "lab", opener=lambda p: FullDisk(p, 9000))
    w.write("bagit/lab/run/state", RunState(run_id="f1", stage="planning"), T0)
    rng = np.random.default_rng(3)  # incompressible rims: lz4 cannot make them fit
    ok = [w.write("bagit/lab/perception/soi", SoiState(seq=i, rim=rng.normal(size=(16, 3))), T0 + i + 1) for i in range(40)]
    assert not all(ok) and w.errors == 1
    first = Path(w.files[0])
    got, rec = read_messages(first)
    assert not rec.complete and len(got) > 0
    assert standard_read(first.read_bytes()) == [(r.topic, r.log_time_ns) for r, _ in got]
    assert w.messages == len(got) and w.messages + w.lost == 41  # the messages of the failed chunk are counted lost


@pytest.mark.slow
@pytest.mark.processes
def test_recorder_killed_with_sigkill_leaves_a_file_the_standard_reader_opens(tmp_path):
    """The user's case: `make_reader(f).iter_messages()` on a SIGKILLed recorder's file returns every
    message up to the last complete chunk (it returned none: RecordLengthLimitExceeded)."""
    a = open_session(BusConfig(rig="sigkill", adminspace=True))
    try:
        r = killed_recording(a, locators(a)[0], "sigkill", tmp_path)
    finally:
        a.close()
    assert r["returncode"] == -signal.SIGKILL
    assert not r["complete"] and r["truncated"]
    assert r["same"] and r["standard"] > 0  # the standard reader reads what bagit's reads
    assert r["settled_in_order"], (r["settled"], r["seqs"][:5], len(r["seqs"]))  # every SOI older than --flush-s, in order


# ---- 4. rotation keeps files under --max-mb -----------------------------------------------------


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_rotation_keeps_every_file_under_max_bytes_with_a_small_limit(tmp_path, compression):
    """--max-mb 0.1 with the default 1 MB chunks made ~13x larger files (a file was only checked
    once a whole chunk was on disk). Now: every file at most max_bytes, nearly full, complete, and
    together every message in order; a message larger than the limit gets a file of its own."""
    max_bytes = 100_000
    w = RecordingWriter(RecorderConfig(dir=tmp_path, max_bytes=max_bytes, compression=compression, keep_idle=10_000), "lab",
                        clock=Clock())
    rng = np.random.default_rng(4)
    t = T0
    sent: list[tuple[str, int]] = []
    huge_at = 700

    def put(key: str, msg: Any) -> None:
        nonlocal t
        t += 1_000_000
        assert w.write(f"bagit/lab/{key}", msg, t)
        sent.append((f"bagit/lab/{key}", t))

    put("run/state", RunState(run_id="m1", stage="bagging"))
    for i in range(1400):
        put("perception/soi", SoiState(seq=i, rim=rng.normal(size=(32, 3))))
        put("arm/left/state", ArmState(arm="left", q=rng.normal(size=6), qd=np.zeros(6), tool_pose=rng.normal(size=6)))
        if i % 15 == 0:
            put("run/state", RunState(run_id="m1", stage="bagging", progress=i / 1400, result={"note": "x" * (i % 300)}))
        if i % 100 == 50:
            put("perception/cloud", PointCloud(points=rng.normal(size=(2000, 3)).astype(np.float32)))
        if i == huge_at:  # ~130 kB of JSON: larger than the limit by itself
            put("camera/rgbd", RgbdFrame(seq=i, camera=CameraInfo(width=160, height=120),
                                         color=rng.integers(0, 255, (120, 160, 3), dtype=np.uint8),
                                         depth=rng.integers(0, 4000, (120, 160), dtype=np.uint16)))
    w.close()
    files = [Path(f) for f in w.files]
    assert len(files) > 10 and all(f.name.endswith(f"_p{i + 1}.mcap") for i, f in enumerate(files) if i)
    got: list[tuple[str, int]] = []
    first_record: list[int] = []
    alone = []
    for i, f in enumerate(files):
        msgs, rec = read_messages(f)
        assert rec.complete, f
        got += [(r.topic, r.log_time_ns) for r, _ in msgs]
        first_record.append(len(msgs[0][0].data))
        size = f.stat().st_size
        if size > max_bytes:
            alone.append(i)
            assert [type(m).__name__ for _, m in msgs] == ["RgbdFrame"], (f.name, size)
    assert got == sent
    assert len(alone) == 1
    sizes = [f.stat().st_size for f in files]
    # closed when the next message would not fit, not long before: a file and the next file's first
    # record come near the limit (most files are over 95 % full; those before a 33 kB cloud less)
    fill = [(sizes[i] + first_record[i + 1]) / max_bytes for i in range(len(files) - 1) if i != alone[0]]
    assert min(fill) > 0.9, sorted(fill)[:3]


# ---- 3. a restarted recorder continues the run in the run's file -------------------------------------


@pytest.mark.slow
@pytest.mark.processes
def test_a_restarted_recorder_continues_the_run_in_a_run_file(tmp_path, capsys):
    """`bagit up` restarts a dead recorder; the new one began 4.4 s late (a scipy import in the CLI
    and messages filed as idle until a run/state came by). Now the current run's messages go to the run's
    file, nothing of the run to an idle file; the time from its start to the first of them is printed here
    and held to 1 s by the probe rec-restart (`bagit bench probes`)."""
    a = open_session(BusConfig(rig="restart", adminspace=True))
    try:
        r = restarted_recorder(a, locators(a)[0], "restart", tmp_path)
    finally:
        a.close()
    res = r["summary"]
    assert res["success"] and [Path(f).name for f in res["files"]] == [Path(res["files"][0]).name]
    assert "_run-r1" in res["files"][0] and r["file_complete"]
    with capsys.disabled():
        print(f"\nrestarted recorder: first message of the run recorded {r['delay_s']:.3f} s after its start")
    assert r["delay_s"] > 0, r["delay_s"]  # how soon after its start: the probe rec-restart (`bagit bench probes`)
    assert not r["idle_files"]
    assert r["runs"] == [("r1", 2, False)]  # the killed part is truncated
