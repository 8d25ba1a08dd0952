"""Recording and replay over Zenoh on loopback: a recorder process killed with SIGKILL mid-run,
a recording replayed by `bagit replay` with its timing, and disk full reported on run/state.

The run is scripted from a real plan (exp01's CBiRRT path): SOIs along the planned path nodes,
with the goal, path, commands, controller status, arm states, frames, clouds and an e-stop reset,
i.e. a message of every published model, in the order a run produces them."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bus_support import wait_until
from log_support import LogLines
from test_recorder_files import FullDisk

from bagit.cli import main
from bagit.common import wire
from bagit.common.bus import BusConfig, Keys, Publisher, Subscriber, locators, open_session
from bagit.common.errors import BusError
from bagit.common.logs import configure_logging
from bagit.common.messages import (
    ArmState,
    CameraInfo,
    Command,
    ControllerStatus,
    EStop,
    Message,
    PointCloud,
    RgbdFrame,
    RunState,
    SoiState,
)
from bagit.services.recorder import RecorderConfig, RecordingWriter, read_messages
from bagit.services.recorder.node import RecorderNode, Replayer


@pytest.fixture(scope="module")
def plan():
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.planner import plan_scenario

    r = plan_scenario(Scenario.from_file(find_scenario("exp01")), "cbirrt", 0, time_budget_s=10)
    assert r.success and r.goal is not None
    return r


def run_script(plan, run_id: str, steps: int) -> list[tuple[str, Message]]:
    """(key under bagit/<rig>/, message) of a run following the plan: SOIs along its nodes densified to `steps`."""
    nodes = plan.path
    s = np.linspace(0, len(nodes) - 1, steps)
    rims = [nodes[int(np.floor(x))] * (1 - x % 1) + nodes[min(int(np.floor(x)) + 1, len(nodes) - 1)] * (x % 1) for x in s]
    rng = np.random.default_rng(1)
    out: list[tuple[str, Message]] = [
        ("run/state", RunState(run_id=run_id, scenario="coffee-box", stage="perceiving")),
        ("camera/rgbd", RgbdFrame(seq=0, camera=CameraInfo(width=64, height=48),
                                  color=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                                  depth=rng.integers(300, 900, (48, 64), dtype=np.uint16))),
        ("perception/cloud", PointCloud(points=rims[0].astype(np.float32))),
        ("perception/soi", SoiState(seq=0, rim=rims[0], n_points=500)),
        ("run/state", RunState(run_id=run_id, scenario="coffee-box", stage="goal", progress=0.0)),
        ("planner/goal", plan.goal.to_message(run_id=run_id, object_height=0.12)),
        ("run/state", RunState(run_id=run_id, scenario="coffee-box", stage="planning")),
        ("planner/path", plan.to_message(run_id=run_id)),
    ]
    for i, rim in enumerate(rims):
        stage = "pre-bagging" if i < steps // 2 else "bagging"
        out += [
            ("perception/soi", SoiState(seq=i + 1, rim=rim, n_points=500)),
            ("controller/cmd", Command(run_id=run_id, seq=i, u=rng.normal(scale=1e-4, size=12))),
            ("controller/status", ControllerStatus(run_id=run_id, seq=i, stage=stage, progress=i / steps, error_to_goal=0.05 * (1 - i / steps))),
            ("arm/left/state", ArmState(arm="left", q=rng.normal(size=6), qd=np.zeros(6), tool_pose=np.r_[rim[0], 0, 0, 0])),
            ("arm/right/state", ArmState(arm="right", q=rng.normal(size=6), qd=np.zeros(6), tool_pose=np.r_[rim[16], 0, 0, 0])),
            ("run/state", RunState(run_id=run_id, scenario="coffee-box", stage=stage, progress=i / steps, elapsed_s=0.03 * i)),
        ]
    out += [
        ("estop", EStop(engage=False, source="test", reason="reset after the run")),
        ("run/state", RunState(run_id=run_id, scenario="coffee-box", stage="done", progress=1.0,
                               result={"success": True, "error_to_goal": 0.004})),
    ]
    return out


class ScriptPublisher:
    def __init__(self, session, rig: str) -> None:
        self.session, self.prefix, self.pubs = session, f"bagit/{rig}", {}

    def put(self, rest: str, msg: Message) -> str:
        key = f"{self.prefix}/{rest}"
        if key not in self.pubs:
            self.pubs[key] = Publisher(self.session, key, type(msg))
        self.pubs[key].put(msg)
        return key


def _spawn(args: list[str], cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    return subprocess.Popen(["nice", "-n", "10", sys.executable, "-m", "bagit.cli", *args], cwd=cwd, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


@pytest.mark.slow
@pytest.mark.processes
def test_recorder_killed_mid_run_keeps_every_message_up_to_its_last_chunk(tmp_path, plan):
    rig = "reckill"
    a = open_session(BusConfig(rig=rig, adminspace=True))
    proc = None
    try:
        proc = _spawn(["recorder", "--rig", rig, "-e", locators(a)[0], "--dir", str(tmp_path), "--flush-s", "0.2",
                       "--chunk-kb", "16", "--linger-s", "0.2"], tmp_path)
        pub = ScriptPublisher(a, rig)
        probe = Publisher(a, f"bagit/{rig}/perception/soi", SoiState)
        assert wait_until(lambda: probe.matched), "the recorder did not subscribe"
        for i in range(5):  # idle traffic before the run
            probe.put(SoiState(seq=100 + i, rim=plan.path[0]))
            time.sleep(0.02)
        script = run_script(plan, "k1", steps=120)
        kill_at = len(script) * 6 // 10
        sent: list[tuple[str, Message, float]] = []
        killed_t = None
        for j, (rest, msg) in enumerate(script):
            if j == kill_at:
                proc.send_signal(signal.SIGKILL)
                proc.wait(5)
                killed_t = time.monotonic()
            key = pub.put(rest, msg)
            if killed_t is None:
                sent.append((key, msg, time.monotonic()))
            time.sleep(0.004)
        assert proc.returncode == -signal.SIGKILL
    finally:
        if proc is not None and proc.poll() is None:
            proc.kill()
        a.close()
    (run_file,) = tmp_path.glob(f"{rig}_*_run-k1.mcap")
    got, rec = read_messages(run_file)
    assert not rec.complete and rec.truncated  # no footer: killed
    by_key: dict[str, list[Message]] = {}
    for key, msg, _ in sent:
        by_key.setdefault(key, []).append(msg)
    got_by_key: dict[str, list[Message]] = {}
    for r, m in got:
        got_by_key.setdefault(r.topic, []).append(m)
    assert set(got_by_key) <= set(by_key)
    for key, msgs in got_by_key.items():  # every key's recovered messages: exactly what was sent, in order
        assert len(msgs) <= len(by_key[key])
        for m, s in zip(msgs, by_key[key], strict=False):
            assert wire.encode(m) == wire.encode(s), key
    # everything sent well before the kill (flush 0.2 s + margin) is in a complete chunk
    settled = [k for k, _, t in sent if t < killed_t - 1.0]
    assert len(settled) > 100  # enough to mean something, however fast this machine sent them
    assert len(got) >= len(settled), (len(got), len(settled), rec.truncated)
    kinds = {type(m).__name__ for _, m in got}
    assert {"RgbdFrame", "PointCloud", "SoiState", "Goal", "Path", "Command", "ControllerStatus", "ArmState", "RunState"} <= kinds
    (idle,) = tmp_path.glob(f"{rig}_*_idle.mcap")
    idle_msgs, idle_rec = read_messages(idle)
    assert idle_rec.complete and [m.seq for _, m in idle_msgs] == [100, 101, 102, 103, 104]
    runs = json.loads(_cli_json(["runs", str(tmp_path)]))["runs"]
    assert [(r["run_id"], r["stage"], r["complete"]) for r in runs] == [("k1", got_by_key[f"bagit/{rig}/run/state"][-1].stage, False)]


def _cli_json(argv: list[str]) -> str:
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main([*argv, "--json"]) == 0
    return buf.getvalue()


def _record_script(tmp_path: Path, plan, rig: str, gap_s: float) -> tuple[Path, list[tuple[str, Message, int]]]:
    w = RecordingWriter(RecorderConfig(dir=tmp_path, linger_s=0.0), rig)
    t = 1_800_000_000_000_000_000
    rows = []
    for rest, msg in run_script(plan, "rp1", steps=30):
        if rest == "perception/soi":
            t += int(gap_s * 1e9)
        key = f"bagit/{rig}/{rest}"
        msg = msg.model_copy(update={"stamp": t / 1e9})
        w.write(key, msg, t)
        rows.append((key, msg, t))
    w.close()
    (path,) = [Path(f) for f in w.files if "_run-rp1" in f]
    return path, rows


@pytest.mark.processes
def test_replay_publishes_the_same_soi_sequence_with_its_timing(tmp_path, plan):
    path, rows = _record_script(tmp_path, plan, "recorded", gap_s=0.04)
    sois = [m for k, m, _ in rows if k.endswith("/perception/soi")]
    span = (rows[-1][2] - rows[0][2]) / 1e9
    rig = "replayto"
    a = open_session(BusConfig(rig=rig, adminspace=True))
    got: list[tuple[SoiState, float]] = []
    cmds: list = []
    states: list = []
    try:
        keys = Keys(rig)
        Subscriber(a, keys.perception_soi, SoiState, lambda m: got.append((m, time.monotonic())))
        Subscriber(a, keys.controller_cmd, Command, cmds.append)
        Subscriber(a, keys.run_state, RunState, states.append)
        spawned = time.monotonic()
        proc = _spawn(["replay", str(path), "--rig", rig, "-e", locators(a)[0], "--speed", "0.5", "--json"], tmp_path)
        out, err = proc.communicate(timeout=60)
    finally:
        a.close()
    assert proc.returncode == 0, err
    res = json.loads(out)
    assert res["sent"] == len(rows) - sum(1 for k, _, _ in rows if k.endswith(("/controller/cmd", "/estop")))
    assert [m.seq for m, _ in got] == [m.seq for m in sois]
    for (m, _), s in zip(got, sois, strict=False):
        assert np.array_equal(m.rim, s.rim)
    # at the recorded spacing at --speed 0.5, never faster: the last SOI comes no sooner than twice its
    # recorded offset after the replay was started (a busy machine only delays it; a replay that sent all
    # at once would be in within the process's start, about 1 s, well before that)
    last_soi_due = (max(t for k, _, t in rows if k.endswith("/perception/soi")) - rows[0][2]) / 1e9 / 0.5
    assert got[-1][1] - spawned >= last_soi_due, (got[-1][1] - spawned, last_soi_due, span)
    assert cmds == []  # commands are not replayed by default
    assert states[-1].stage == "done" and states[-1].result == {"success": True, "error_to_goal": 0.004}
    assert abs(states[-1].stamp - time.time()) < 3600  # restamped to replay time, not 2027


def test_replay_refuses_commands_while_something_listens_to_them(tmp_path, plan, pair):
    a, b = pair
    path, _ = _record_script(tmp_path, plan, "cmdrig", gap_s=0.001)
    keys = Keys("cmdrig")
    Subscriber(a, keys.controller_cmd, Command, lambda m: None)
    rep = Replayer(b, rig="cmdrig", speed=50.0, with_commands=True)
    with pytest.raises(BusError, match="refusing to replay commands"):
        rep.play(path)
    rep.close()


def test_disk_full_is_reported_on_stderr_and_run_state(tmp_path, pair, capfd):
    a, b = pair
    rig = "diskfull"
    keys = Keys(rig)
    configure_logging()  # as the CLI does: the one format, on stderr
    lines = LogLines("bagit.recorder")
    w = RecordingWriter(RecorderConfig(dir=tmp_path, chunk_bytes=1024), rig, opener=lambda p: FullDisk(p, 5000))
    node = RecorderNode(b, keys, w)
    states: list[RunState] = []
    Subscriber(a, keys.run_state, RunState, states.append)
    pub_state = Publisher(a, keys.run_state, RunState)
    pub_soi = Publisher(a, keys.perception_soi, SoiState)
    assert wait_until(lambda: pub_soi.matched and pub_state.matched)
    pub_state.put(RunState(run_id="df1", stage="bagging", progress=0.3))
    for i in range(60):
        pub_soi.put(SoiState(seq=i, rim=np.full((32, 3), float(i))))
        time.sleep(0.002)
    assert wait_until(lambda: any((s.reason or "").startswith("recorder: recording stopped: disk full") for s in states))
    flagged = next(s for s in states if s.reason and s.reason.startswith("recorder:"))
    assert flagged.run_id == "df1" and flagged.stage == "bagging"
    status = node.close()
    assert status["errors"] >= 1 and status["lost"] > 0 and "ENOSPC" in status["error"]
    lines.close()
    assert any("disk full" in t for t in lines.at(logging.ERROR))
    assert "ERROR bagit.recorder: recording stopped: disk full (ENOSPC)" in capfd.readouterr().err


@pytest.mark.processes
def test_recorder_stopped_by_sigterm_closes_its_files_with_the_result(tmp_path, plan):
    rig = "recterm"
    a = open_session(BusConfig(rig=rig, adminspace=True))
    try:
        proc = _spawn(["recorder", "--rig", rig, "-e", locators(a)[0], "--dir", str(tmp_path), "--linger-s", "30", "--json"],
                      tmp_path)
        pub = ScriptPublisher(a, rig)
        probe = Publisher(a, f"bagit/{rig}/run/state", RunState)
        assert wait_until(lambda: probe.matched), "the recorder did not subscribe"
        script = run_script(plan, "t1", steps=10)
        for rest, msg in script:
            pub.put(rest, msg)
            time.sleep(0.003)
        time.sleep(0.3)
        proc.send_signal(signal.SIGTERM)  # within the linger: the run file is closed by the shutdown
        out, err = proc.communicate(timeout=20)
    finally:
        a.close()
    assert proc.returncode == 0, err
    res = json.loads(out)
    assert res["messages"] == len(script) and res["lost"] == 0 and res["malformed"] == 0
    (run_file,) = tmp_path.glob(f"{rig}_*_run-t1.mcap")
    got, rec = read_messages(run_file)
    assert rec.complete and len(got) == len(script)
    runs = json.loads(_cli_json(["runs", str(tmp_path)]))["runs"]
    assert runs[0]["run_id"] == "t1" and runs[0]["complete"] and runs[0]["result"] == {"success": True, "error_to_goal": 0.004}
