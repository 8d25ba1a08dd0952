"""One closed-loop run in a child process of its own: the sweep's unit of work on a cluster worker.

Why a child process per run rather than the run in the worker's own thread: a run that crashes in
native code (MuJoCo, OpenGL) kills only its child, and the worker that waits on it stays up and
returns a failed record with the reason; a run that hangs is killed at its time-out, which a thread
cannot be. A dead worker would instead make the scheduler re-run the task on another worker (up
to its `allowed-failures`) and report no reason, and a stuck thread would hold the worker's only slot
for good. A fresh process per run also keeps MuJoCo and OpenGL state from one run out of the next.

The child dies with the worker (Linux's parent-death signal), so a worker that is stopped, or a
local cluster that closes, leaves no run behind. This module does not import the engine: the
worker calls `run_isolated`, and the child is `python -m bagit.bench.isolated`.
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from bagit.common.names import ArmsMode
from bagit.common.results import RunResult, provenance

log = logging.getLogger("bagit.bench.sweep")

Key = tuple[str, str, str, int, str]  # scenario, controller, planner, seed, arms
STDERR_TAIL = 300  # characters of a crashed run's stderr kept in its reason
# A run is one busy core (a worker runs one at a time, one worker per core): numpy's BLAS and OpenMP
# on one thread, as Dask's nanny sets for its workers, whether or not a nanny started this one.
# Two runs on two cores then do not fight over threads, and a run's numbers do not depend on how many cores its machine has.
ONE_THREAD_ENV = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}

# The children of the runs this worker process has going, by sweep, so that a stopped sweep can stop them.
_RUNNING: dict[str, set[subprocess.Popen]] = {}
_RUNNING_LOCK = threading.Lock()


def run_one(
    scenario: str, controller: str, planner: str, seed: int, time_limit_s: float = 40.0, params: dict[str, Any] | None = None,
    arms: ArmsMode = "cr5",
) -> dict[str, Any]:
    """One whole run, `bagit run`'s own, as a JSON-able record (its RunResult) in this process.
    `params`: method parameters overriding the scenario's (an ablation), kept in the record."""
    from bagit.bench.zoo import is_zoo_name, zoo_scenario
    from bagit.common.scenario import Scenario
    from bagit.inprocess import RunOptions, run_inprocess
    from bagit.scenarios import find_scenario

    if is_zoo_name(scenario):  # a bag of the zoo, built again from its name
        sc = zoo_scenario(scenario)[0]
    else:
        sc = Scenario.from_file(find_scenario(scenario))
    r = run_inprocess(RunOptions(scenario=sc, name=scenario, controller=controller, planner=planner, seed=seed, arms=arms,
                                 overrides=dict(params or {}), time_limit_s=time_limit_s))
    return r.model_dump(mode="json")


def failed_record(key: Key, reason: str, wall_s: float, params: dict[str, Any] | None, worker: str | None = None) -> dict[str, Any]:
    """The record of a run that gave no result (crashed, hung, or lost with its worker): the same model, with the reason."""
    sc, ctrl, planner, seed, arms = key
    prov = provenance().model_copy(update={"worker": worker})
    return RunResult(scenario=sc, controller=ctrl, planner=planner, seed=seed, arms=arms, overrides=dict(params or {}), success=False,
                     reason=reason, wall_s=wall_s, provenance=prov).model_dump(mode="json")


class WrongCommit(RuntimeError):
    """This worker's code is at another commit than the sweep's: its record would not be the sweep's code's."""


def run_isolated(
    key: Key, time_limit_s: float, params: dict[str, Any] | None, timeout_s: float, sweep_id: str = "", commit: str | None = None,
) -> dict[str, Any]:
    """The sweep's task: run `key` in a child process, kill it after `timeout_s` of wall time; always a record,
    whose provenance names the worker that ran it (`worker`: its address; `host`: its machine). A worker at
    another commit than `commit` (one that joined after the sweep checked them) runs nothing: WrongCommit."""
    worker = _worker_address()
    if commit and worker_commit() != commit:
        raise WrongCommit(f"worker {worker} is at commit {(worker_commit() or 'none')[:10]}, the sweep at {commit[:10]}")
    sc, ctrl, planner, seed, arms = key
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="bagit-run-") as tmp:
        out, err_path = Path(tmp) / "result.json", Path(tmp) / "stderr.txt"
        args = json.dumps([sc, ctrl, planner, seed, time_limit_s, params, arms])
        with open(err_path, "wb") as err:
            proc = subprocess.Popen([sys.executable, "-m", "bagit.bench.isolated", args, str(out), str(os.getpid())],
                                    stdin=subprocess.DEVNULL, stdout=err, stderr=err, start_new_session=True,
                                    env={**os.environ, **ONE_THREAD_ENV})
        _track(sweep_id, proc, add=True)
        try:
            try:
                proc.wait(timeout=timeout_s)
            except subprocess.TimeoutExpired:
                _kill(proc)
                return failed_record(key, f"timed out: no result within {timeout_s:g} s of wall time", time.monotonic() - t0, params, worker)
        finally:
            _kill(proc)  # its process group too: nothing the run started outlives it
            _track(sweep_id, proc, add=False)
        wall = time.monotonic() - t0
        got = _read_result(out)
        if got is not None:
            if "error" in got:
                return failed_record(key, f"error: {got['error']}", wall, params, worker)
            rec = got["record"]
            rec["provenance"] = dict(rec.get("provenance") or provenance().model_dump(mode="json"), worker=worker)
            return rec
        tail = err_path.read_text(errors="replace").strip()[-STDERR_TAIL:].splitlines()
        return failed_record(key, f"crashed: the run's process died ({_exit_status(proc.returncode)})" + (f": {tail[-1]}" if tail else ""),
                             wall, params, worker)


def stop_runs(sweep_id: str) -> int:
    """Kill this worker's runs of sweep `sweep_id` (the sweep was stopped); how many there were."""
    with _RUNNING_LOCK:
        procs = list(_RUNNING.get(sweep_id, ()))
    for p in procs:
        _kill(p)
    return len(procs)


def worker_commit() -> str | None:
    """The commit of the code this worker runs (the sweep checks it against its own)."""
    return provenance().commit


def _read_result(path: Path) -> dict[str, Any] | None:
    """The child's answer, or None when it died before writing one."""
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError):
        return None


def _exit_status(code: int) -> str:
    if code >= 0:
        return f"exit code {code}"
    try:
        return f"signal {signal.Signals(-code).name}"
    except ValueError:
        return f"signal {-code}"


def _track(sweep_id: str, proc: subprocess.Popen, add: bool) -> None:
    with _RUNNING_LOCK:
        if add:
            _RUNNING.setdefault(sweep_id, set()).add(proc)
        elif sweep_id in _RUNNING:
            _RUNNING[sweep_id].discard(proc)
            if not _RUNNING[sweep_id]:
                del _RUNNING[sweep_id]


def _kill(proc: subprocess.Popen) -> None:
    """SIGKILL the run's process group (it leads one: start_new_session) and reap it."""
    if proc.poll() is None:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    proc.wait()


def _worker_address() -> str | None:
    """The address of the Dask worker running this task (None outside one)."""
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return None


def _die_with_parent(parent_pid: int) -> None:
    """Be killed when the worker that started this run dies (Linux; elsewhere the run's time-out is the bound)."""
    if sys.platform.startswith("linux"):
        pr_set_pdeathsig = 1
        ctypes.CDLL(None, use_errno=True).prctl(pr_set_pdeathsig, signal.SIGKILL)
    if os.getppid() != parent_pid:  # the worker died before the signal was armed
        os._exit(1)


def main(argv: list[str] | None = None) -> None:
    """The child: `python -m bagit.bench.isolated ARGS_JSON RESULT_PATH PARENT_PID` writes {"record": ...} or {"error": ...}."""
    args_json, result_path, parent_pid = argv or sys.argv[1:]
    _die_with_parent(int(parent_pid))
    try:
        got: dict[str, Any] = {"record": run_one(*json.loads(args_json))}
    except BaseException as e:  # noqa: BLE001 - every failure of the run goes back as its record's reason
        got = {"error": f"{type(e).__name__}: {e}"}
    tmp = Path(result_path + ".part")  # whole or absent: a child killed while writing leaves no half answer
    tmp.write_text(json.dumps(got))
    os.replace(tmp, result_path)


if __name__ == "__main__":
    main()
