"""The closed-loop sweep on Dask's scheduler: a running cluster of two workers on loopback, a run killed at
its time-out, a crashed run, an interrupted sweep resumed, and the records a one-process sweep makes.

The runs are the cheapest real ones: one second of simulated time with floating grippers (`ideal`),
about 1.5 s of wall time each, on three scenarios whose records differ (error, final rim)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import psutil
import pytest
from distributed import Client, LocalCluster

from bagit import cli
from bagit.bench import closed_loop, isolated
from bagit.bench.paper import load_closed_loop
from bagit.common.results import RunResult

KEYS = [(sc, "mpc", "cbirrt", 0, "ideal") for sc in ("exp01-coffee-box", "exp02-canned-pineapple", "exp08-plastic-packing")]
TIME_LIMIT_S = 1.0
# What makes two records the same run (wall times, solve times and provenance are the machine's).
SAME_RUN = ("scenario", "seed", "arms", "success", "stage_reached", "reason", "error_cm", "error_to_goal_m", "duration_s", "ticks",
            "arm_events", "final_rim", "object_vertices")


def same_run(r: dict) -> dict:
    return {k: r.get(k) for k in SAME_RUN}


pytestmark = pytest.mark.processes  # a Dask cluster of worker processes, runs in processes of their own


@pytest.fixture(scope="module")
def reference() -> list[dict]:
    """The one-process sweep: the same runs one after another in this process, no engine."""
    return [isolated.run_one(sc, ctrl, planner, seed, TIME_LIMIT_S, None, arms) for sc, ctrl, planner, seed, arms in KEYS]


@pytest.fixture(scope="module")
def cluster():
    """A running Dask cluster, two one-thread worker processes on loopback, as `dask scheduler` + `dask worker` make."""
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0") as lc, \
            Client(lc) as client:
        yield lc.scheduler_address, client


@pytest.mark.slow
def test_a_sweep_on_a_running_cluster_makes_the_records_of_a_one_process_sweep(cluster, reference, tmp_path):
    address, client = cluster
    out = tmp_path / "closed-loop.jsonl"
    recs = closed_loop.sweep(KEYS, out, timeout_s=120, time_limit_s=TIME_LIMIT_S, cluster=address)
    assert [same_run(r) for r in recs] == [same_run(r) for r in reference]
    assert len({json.dumps(same_run(r)) for r in recs}) == 3  # three different runs, not one repeated
    workers = set(client.nthreads())
    for r in recs:
        prov = RunResult.model_validate(r).provenance
        assert prov.worker in workers and prov.host == socket.gethostname() and prov.commit
    assert sorted(json.loads(line)["scenario"] for line in out.read_text().splitlines()) == [k[0] for k in KEYS]
    runs, _ = load_closed_loop([out])  # bench paper reads the new records
    assert len(runs) == 3


def test_a_run_past_its_time_out_is_killed_and_recorded_failed(cluster, tmp_path):
    address, client = cluster
    (rec,) = closed_loop.sweep(KEYS[:1], tmp_path / "t.jsonl", timeout_s=0.3, time_limit_s=TIME_LIMIT_S, cluster=address)
    assert rec["success"] is False and rec["reason"] == "timed out: no result within 0.3 s of wall time"
    assert RunResult.model_validate(rec).provenance.worker
    # the killed run left nothing behind on the workers, which are still both there
    assert client.run(lambda: [p.pid for p in psutil.Process().children(recursive=True)]) == {w: [] for w in client.nthreads()}


def test_a_run_whose_process_dies_is_a_failed_record_with_the_signal():
    """A crash in native code (SIGSEGV) fails that run only: the task returns its record."""
    got: list[dict] = []
    task = threading.Thread(target=lambda: got.append(isolated.run_isolated(KEYS[0], TIME_LIMIT_S, None, 60.0)))
    task.start()
    deadline = time.monotonic() + 10
    while not (runs := [k for k in psutil.Process().children() if "bagit.bench.isolated" in k.cmdline()]) and time.monotonic() < deadline:
        time.sleep(0.02)
    assert len(runs) == 1
    os.kill(runs[0].pid, signal.SIGSEGV)
    task.join(30)
    assert got and got[0]["success"] is False and got[0]["reason"].startswith("crashed: the run's process died (signal SIGSEGV)")


def _connections(p: psutil.Process) -> list:
    try:  # psutil >= 6 names it net_connections
        return getattr(p, "net_connections", getattr(p, "connections", lambda **_: []))(kind="inet")
    except psutil.NoSuchProcess:
        return []


def _sweep_cmd(out: Path) -> list[str]:
    return [sys.executable, "-m", "bagit.bench.closed_loop", "--only", "exp01,exp02,exp08", "--controllers", "mpc", "--seeds", "1",
            "--arms", "ideal", "--time-limit-s", str(TIME_LIMIT_S), "--workers", "2", "--jsonl", str(out)]


@pytest.mark.slow
def test_an_interrupted_sweep_resumes_where_it_stopped(reference, tmp_path):
    """Ctrl-C after the first record: no process of the sweep outlives it, and the same command runs only the rest."""
    out = tmp_path / "closed-loop.jsonl"
    # A Ctrl-C at a terminal: the sweep runs with SIGINT's default action even when this suite runs as a
    # background job (a shell starts those with SIGINT ignored, and an ignored signal stays so across exec).
    p = subprocess.Popen(_sweep_cmd(out), stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    listening: set[str] = set()  # what the sweep's processes listen on while it runs, sampled beside the wait
    watching = threading.Event()
    watching.set()

    def watch() -> None:
        while watching.is_set():
            try:
                procs = [psutil.Process(p.pid), *psutil.Process(p.pid).children(recursive=True)]
            except psutil.NoSuchProcess:
                return
            listening.update(c.laddr.ip for q in procs for c in _connections(q) if c.status == psutil.CONN_LISTEN)
            time.sleep(0.2)

    watcher = threading.Thread(target=watch, daemon=True)
    watcher.start()
    deadline = time.monotonic() + 90
    while not (out.exists() and out.read_text().count("\n")) and time.monotonic() < deadline and p.poll() is None:
        time.sleep(0.05)
    family = [psutil.Process(p.pid), *psutil.Process(p.pid).children(recursive=True)]
    p.send_signal(signal.SIGINT)  # at once after the first record
    watching.clear()
    watcher.join(10)
    assert listening == {"127.0.0.1"}  # the local cluster's scheduler, workers and HTTP pages: loopback only
    _, err = p.communicate(timeout=60)
    assert p.returncode == 130, err
    _, alive = psutil.wait_procs(family, timeout=10)
    assert not alive, [a.cmdline() for a in alive]
    before = out.read_text()
    n_before = before.count("\n")
    assert 1 <= n_before < 3 and "(sweep stopped); the same command resumes the sweep" in err
    again = subprocess.run(_sweep_cmd(out), check=False, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr
    assert f"{n_before} of 3 runs already in" in again.stderr and f"{3 - n_before} runs on 2 workers" in again.stderr
    after = out.read_text()
    assert after.startswith(before) and after.count("\n") == 3
    recs = {json.loads(line)["scenario"]: json.loads(line) for line in after.splitlines()}
    assert [same_run(recs[k[0]]) for k in KEYS] == [same_run(r) for r in reference]


def test_a_half_written_last_record_is_run_again(tmp_path):
    out = tmp_path / "closed-loop.jsonl"
    whole = json.dumps({"scenario": "exp01-coffee-box", "controller": "mpc", "planner": "cbirrt", "seed": 0, "arms": "ideal", "success": False})
    out.write_text(whole + "\n" + whole[:20])
    closed_loop.drop_torn_tail(out)
    assert out.read_text() == whole + "\n" and len(closed_loop.read_jsonl(out)) == 1


def test_without_the_engine_a_sweep_names_the_extra(monkeypatch, capsys, tmp_path):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed: importing it fails
    code = cli.main(["bench", "sweep", "--only", "exp02", "--controllers", "mpc", "--seeds", "1", "--jsonl", str(tmp_path / "x.jsonl")])
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1 and "pip install 'bagit[cluster]'" in err


def test_records_from_before_the_worker_field_still_read():
    """Every committed closed-loop record reads; one written before the worker field has none."""
    files = sorted(Path(closed_loop.__file__).parent.glob("results/closed-loop*.jsonl"))
    assert files
    for f in files:
        for r in closed_loop.read_jsonl(f):
            worker = RunResult.model_validate(r).provenance.worker
            assert worker == (r.get("provenance") or {}).get("worker")
    before = closed_loop.read_jsonl(files[0])[0]
    before["provenance"].pop("worker", None)
    assert RunResult.model_validate(before).provenance.worker is None
