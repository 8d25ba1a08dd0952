"""What the sweep's engine (Dask's distributed scheduler) costs on this machine: the wall time of a
closed-loop sweep of cheap runs, beside another harness given as a script (the home-made scheduler
it replaced: `git show aedb961:bench/closed_loop.py > old.py`), and the engine's own overhead per
task (a no-op's round trip; a batch of no-ops' wall time per task). Appends one record to
bench/results/sweep-engine.jsonl with the commit, host and the machine's load.

The runs are the cheapest real ones: 1 s of simulated time with floating grippers (`--arms ideal`),
so the harness's own costs (a process per run, imports, the scheduler) weigh as much as they can.
Sweeps alternate (baseline, engine, baseline, ...) so both see the same load. The engine's runs use one
BLAS/OpenMP thread each (bench/isolated.py); set OMP_NUM_THREADS=MKL_NUM_THREADS=OPENBLAS_NUM_THREADS=1
around this command to give the baseline's runs the same and compare the schedulers alone.

    python -m bagit.bench.sweep_engine [--runs 30] [--workers 2] [--repeats 1] [--baseline old.py] [--no-record]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench.closed_loop import engine
from bagit.bench.common import RESULTS_DIR, machine, stats_ms
from bagit.bench.isolated import ONE_THREAD_ENV
from bagit.common.logs import configure_logging
from bagit.common.results import provenance

log = logging.getLogger("bagit.bench.sweep_engine")

SCENARIOS = "exp01,exp02,exp03"
SWEEP_FLAGS = ["--controllers", "mpc", "--arms", "ideal", "--time-limit-s", "1"]


def noop(_: Any = None) -> None:
    """The task with nothing in it: what is left of its round trip is the engine's."""


def engine_overhead(workers: int = 2, n: int = 200) -> dict[str, Any]:
    """A no-op task's submit-to-result round trip one at a time, and the wall time per task of `n` at once,
    on the sweep's own local cluster (closed_loop.engine), whose start and close are timed too."""
    t0 = time.perf_counter()
    with engine(None, workers) as client:
        start_s = time.perf_counter() - t0
        client.submit(noop, pure=False).result()  # warm: the function reaches the workers
        rtt = []
        for _ in range(n):
            t0 = time.perf_counter()
            client.submit(noop, pure=False).result()
            rtt.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        client.gather(client.map(noop, range(n), pure=False))
        batch_ms = (time.perf_counter() - t0) * 1e3 / n
        t0 = time.perf_counter()
    close_s = time.perf_counter() - t0
    return {"workers": workers, "round_trip": stats_ms(rtt), "batch_ms_per_task": batch_ms, "local_cluster_start_s": start_s,
            "local_cluster_close_s": close_s}


def timed_sweep(cmd: list[str], runs: int, workers: int) -> dict[str, Any]:
    """One sweep of `runs` fresh runs through `cmd` (a harness taking closed_loop's flags), timed from outside."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "sweep.jsonl"
        args = cmd + ["--only", SCENARIOS, "--seeds", str(runs // 3), "--workers", str(workers), "--jsonl", str(out), *SWEEP_FLAGS]
        load0 = os.getloadavg()[0]
        t0 = time.perf_counter()
        subprocess.run(args, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        wall = time.perf_counter() - t0
        recs = [json.loads(line) for line in out.read_text().splitlines()]
    run_wall = [r["wall_s"] for r in recs]
    return {
        "wall_s": wall, "runs": len(recs), "failed_other_than_time_limit": sum("time limit" not in (r.get("reason") or "") for r in recs),
        "run_wall_s_mean": float(np.mean(run_wall)),
        # wall time per run beyond the run itself: the harness (process, imports, scenario, scheduling)
        "overhead_s_per_run": wall * workers / len(recs) - float(np.mean(run_wall)),
        "load_before": load0, "load_after": os.getloadavg()[0],
    }


def run(runs: int = 30, workers: int = 2, repeats: int = 1, baseline: Path | None = None, record: bool = True) -> dict[str, Any]:
    prov, where = provenance().model_dump(mode="json"), machine()  # the code as it was when the sweeps began
    engine_cmd = [sys.executable, "-m", "bagit.bench.closed_loop"]
    sweeps: dict[str, list[dict[str, Any]]] = {"engine": [], "baseline": []}
    for i in range(repeats):
        if baseline is not None:
            sweeps["baseline"].append(timed_sweep([sys.executable, str(baseline)], runs, workers))
            log.info("baseline sweep %d: %.1f s", i + 1, sweeps["baseline"][-1]["wall_s"])
        sweeps["engine"].append(timed_sweep(engine_cmd, runs, workers))
        log.info("engine sweep %d: %.1f s", i + 1, sweeps["engine"][-1]["wall_s"])
    overhead = engine_overhead(workers)
    result = {
        "what": "sweep-engine", "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"), "machine": where, "provenance": prov,
        "threads_env": {k: os.environ.get(k) for k in ONE_THREAD_ENV},  # the baseline's runs inherit it; the engine's set it
        "sweep": {"runs": runs, "workers": workers, "flags": ["--only", SCENARIOS, *SWEEP_FLAGS], "engine": sweeps["engine"],
                  "baseline": sweeps["baseline"], "baseline_script": str(baseline) if baseline else None},
        "engine_overhead": overhead,
    }
    if record:
        with open(RESULTS_DIR / "sweep-engine.jsonl", "a") as f:
            f.write(json.dumps(result) + "\n")
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=30, help="runs per sweep (3 scenarios x runs/3 seeds)")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=1, help="sweeps per harness, alternating")
    ap.add_argument("--baseline", type=Path, default=None, help="another harness script taking closed_loop's flags, timed the same way")
    ap.add_argument("--no-record", action="store_true", help="do not append to bench/results/sweep-engine.jsonl")
    a = ap.parse_args()
    configure_logging(logging.WARNING)
    log.setLevel(logging.INFO)
    import distributed  # noqa: F401 - it sets its loggers' levels when first imported; quieted here

    logging.getLogger("distributed").setLevel(logging.WARNING)
    r = run(a.runs, a.workers, a.repeats, a.baseline, not a.no_record)
    for name in ("baseline", "engine"):
        if ss := r["sweep"][name]:
            print(f"{name}: " + ", ".join(f"{s['wall_s']:.1f} s ({s['overhead_s_per_run']:.2f} s/run beyond the run, load {s['load_before']:.1f})"
                                          for s in ss))
    o = r["engine_overhead"]
    print(f"no-op round trip: median {o['round_trip']['median_ms']:.2f} ms, p95 {o['round_trip']['p95_ms']:.2f} ms; "
          f"{o['batch_ms_per_task']:.2f} ms per task in a batch; local cluster start {o['local_cluster_start_s']:.1f} s, "
          f"close {o['local_cluster_close_s']:.1f} s")


if __name__ == "__main__":
    main()
