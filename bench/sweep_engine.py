"""What the sweep's engine (Dask's distributed scheduler) costs on this machine: the wall time of a
closed-loop sweep of cheap runs, beside another harness given as a script (the home-made scheduler
it replaced: `git show aedb961:bench/closed_loop.py > old.py`), and the engine's own overhead per
task (a no-op's round trip; a batch of no-ops' wall time per task). Appends one record to
bench/results/sweep-engine.jsonl with the commit, host and the machine's load.

The runs are the cheapest real ones: 1 s of simulated time with floating grippers (`--arms ideal`),
so the harness's own costs (a process per run, imports, the scheduler) weigh as much as they can.
Sweeps alternate (baseline, engine, baseline, ...) so both see the same load.

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

from bagit.bench.common import RESULTS_DIR, machine, stats_ms
from bagit.common.results import provenance

log = logging.getLogger("bagit.bench.sweep_engine")

SCENARIOS = "exp01,exp02,exp03"
SWEEP_FLAGS = ["--controllers", "mpc", "--arms", "ideal", "--time-limit-s", "1"]


def noop(_: Any = None) -> None:
    """The task with nothing in it: what is left of its round trip is the engine's."""


def engine_overhead(workers: int = 2, n: int = 200) -> dict[str, Any]:
    """A no-op task's submit-to-result round trip one at a time, and the wall time per task of `n` at once,
    on a local cluster like the sweep's (processes on loopback, one thread each)."""
    from distributed import Client, LocalCluster

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0") as lc, \
            Client(lc) as client:
        client.submit(noop, pure=False).result()  # warm: the function reaches the workers
        rtt = []
        for _ in range(n):
            t0 = time.perf_counter()
            client.submit(noop, pure=False).result()
            rtt.append((time.perf_counter() - t0) * 1e3)
        t0 = time.perf_counter()
        client.gather(client.map(noop, range(n), pure=False))
        batch_ms = (time.perf_counter() - t0) * 1e3 / n
    return {"workers": workers, "round_trip": stats_ms(rtt), "batch_ms_per_task": batch_ms}


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
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(message)s", stream=sys.stderr)
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
          f"{o['batch_ms_per_task']:.2f} ms per task in a batch")


if __name__ == "__main__":
    main()
