"""Whole simulated bagging runs over the paper scenarios, seeds and controllers (Tables I and II):
manipulation success, error (cm), time to goal (simulated s) and MPC solve time per tick.

Each run goes in its own worker process, so a run that crashes (even in native code) or hangs
becomes a failed record with the reason, and the sweep goes on. With `--jsonl FILE` every run is
appended to FILE as it finishes and runs already there are skipped: a sweep that was stopped
resumes where it was. `bagit bench paper` reads such files (`--closed-loop FILE`).

    python -m bagit.bench.closed_loop [--quick] [--seeds N] [--controllers mpc,ibvs,ssvs] [--planners cbirrt]
                                      [--only exp02,...] [--seed-from S] [--jsonl FILE] [--workers 1] [--timeout-s 900]
                                      [--params JSON] [--time-limit-s 40]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.scenarios import list_scenarios

PAPER = {"mpc_error_cm": "2.10 ± 0.77", "mpc_time_s": "53.09 ± 2.92"}
RUN_TIMEOUT_S = 900.0  # wall time one run may take before its worker is stopped


def run_one(
    scenario: str, controller: str, planner: str, seed: int, time_limit_s: float = 40.0, params: dict[str, Any] | None = None
) -> dict[str, Any]:
    """One whole run as a JSON-able record (no arrays but the final rim), in this process.
    `params`: method parameters overriding the scenario's (an ablation), kept in the record."""
    from bagit.common.params import MethodParams
    from bagit.common.scenario import Scenario
    from bagit.pipeline import run_bagging
    from bagit.scenarios import find_scenario

    sc = Scenario.from_file(find_scenario(scenario))
    if params:
        sc = sc.model_copy(update={"params": MethodParams.model_validate({**sc.params.model_dump(exclude_unset=True), **params})})
    r = run_bagging(sc, controller, planner, seed, time_limit_s)
    solve = np.asarray(r.history.get("solve_ms", []), dtype=float)
    solve = solve[solve > 0]
    d = r.to_dict()
    d.pop("object_vertices", None)
    d["final_rim"] = np.round(np.asarray(d["final_rim"], dtype=float), 5).tolist()
    d.update(scenario=scenario, solve_ms_median=float(np.median(solve)) if solve.size else None)
    if params:
        d["params"] = dict(params)
    return {k: (v.item() if isinstance(v, np.generic) else (None if isinstance(v, float) and not np.isfinite(v) else v)) for k, v in d.items()}


def _worker(conn: Any, args: tuple) -> None:
    try:
        conn.send(("ok", run_one(*args)))
    except BaseException as e:  # noqa: BLE001 - every failure goes back as a record
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _failed(key: tuple[str, str, str, int], stage: str, reason: str, wall_s: float) -> dict[str, Any]:
    sc, ctrl, planner, seed = key
    return {"scenario": sc, "controller": ctrl, "planner": planner, "seed": seed, "success": False, "stage_reached": stage,
            "reason": reason, "error_cm": None, "duration_s": None, "wall_s": wall_s}


def read_jsonl(path: Path | None) -> list[dict[str, Any]]:
    if path is None or not Path(path).exists():
        return []
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def sweep(
    keys: list[tuple[str, str, str, int]],
    jsonl: Path | None = None,
    workers: int = 1,
    timeout_s: float = RUN_TIMEOUT_S,
    time_limit_s: float = 40.0,
    params: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """Run every (scenario, controller, planner, seed) not already in `jsonl`, `workers` at a time, each in
    a fresh process; returns all records of these keys (old and new)."""
    have = {(r["scenario"], r["controller"], r["planner"], int(r["seed"])): r for r in read_jsonl(jsonl)}
    todo = [k for k in keys if k not in have]
    ctx = mp.get_context("spawn")  # no forked MuJoCo / OpenGL state
    running: list[tuple[tuple, Any, Any, float]] = []
    out = {k: have[k] for k in keys if k in have}

    def record(key: tuple, rec: dict[str, Any]) -> None:
        out[key] = rec
        if jsonl is not None:
            with open(jsonl, "a") as f:
                f.write(json.dumps(rec) + "\n")
        print(json.dumps({k: rec.get(k) for k in ("scenario", "controller", "planner", "seed", "success", "stage_reached", "reason", "error_cm")}), flush=True)

    try:
        _drive(todo, running, ctx, record, workers, timeout_s, time_limit_s, params)
    finally:  # stopped (Ctrl-C, an error): no worker outlives the sweep
        for _, p, _, _ in running:
            if p.is_alive():
                p.kill()
    return [out[k] for k in keys if k in out]


def _drive(
    todo: list, running: list, ctx: Any, record: Any, workers: int, timeout_s: float, time_limit_s: float, params: dict[str, Any] | None
) -> None:
    """Start workers while there is work and room, collect results, kill runs over `timeout_s`."""
    while todo or running:
        while todo and len(running) < max(1, workers):
            key = todo.pop(0)
            recv, send = ctx.Pipe(duplex=False)
            p = ctx.Process(target=_worker, args=(send, (*key, time_limit_s, params)), daemon=True)
            p.start()
            send.close()
            running.append((key, p, recv, time.monotonic()))
        for item in list(running):
            key, p, recv, t0 = item
            wall = time.monotonic() - t0
            if recv.poll():
                try:
                    status, payload = recv.recv()
                except EOFError:
                    status, payload = "error", "the worker closed its pipe without a result"
                record(key, payload if status == "ok" else _failed(key, "error", payload, wall))
            elif not p.is_alive():
                record(key, _failed(key, "crashed", f"the worker process died (exit code {p.exitcode})", wall))
            elif wall > timeout_s:
                p.kill()
                record(key, _failed(key, "timed out", f"no result within {timeout_s:.0f} s of wall time", wall))
            else:
                continue
            p.join(5)
            recv.close()
            running.remove(item)
        time.sleep(0.2)


def aggregate(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per scenario x controller x planner: success / of, error and time over the successes."""
    groups: dict[tuple[str, str, str], list[dict[str, Any]]] = {}
    for r in records:
        groups.setdefault((r["scenario"], r["controller"], r["planner"]), []).append(r)
    rows = []
    for (sc, ctrl, planner), rs in groups.items():
        ok = [r for r in rs if r["success"]]
        solve = [r["solve_ms_median"] for r in rs if r.get("solve_ms_median")]
        rows.append({
            "scenario": sc, "controller": ctrl, "planner": planner, "success": len(ok), "of": len(rs),
            "error_cm_mean": float(np.mean([r["error_cm"] for r in ok])) if ok else float("nan"),
            "error_cm_std": float(np.std([r["error_cm"] for r in ok])) if ok else float("nan"),
            "time_s_mean": float(np.mean([r["duration_s"] for r in ok])) if ok else float("nan"),
            "solve_ms_median": float(np.median(solve)) if solve else 0.0,
            "failures": sorted({f"{r.get('stage_reached')}: {r.get('reason')}" for r in rs if not r["success"]}),
        })
    return rows


def run(
    quick: bool = False,
    seeds: int | None = None,
    controllers: list[str] | None = None,
    only: list[str] | None = None,
    planners: list[str] | None = None,
    jsonl: Path | None = None,
    workers: int = 1,
    timeout_s: float = RUN_TIMEOUT_S,
    seed_from: int = 0,
    params: dict[str, Any] | None = None,
    time_limit_s: float = 40.0,
) -> dict:
    n = seeds or (1 if quick else 8)
    ctrls = controllers or (["mpc"] if quick else ["mpc", "ibvs", "ssvs"])
    scen = [p.stem for p in list_scenarios() if not only or any(p.stem.startswith(o) for o in only)]
    if quick and not only:
        scen = scen[:2]
    keys = [(s, c, pl, seed) for s in scen for c in ctrls for pl in (planners or ["cbirrt"]) for seed in range(seed_from, seed_from + n)]
    records = sweep(keys, jsonl, workers, timeout_s, time_limit_s, params)
    return {"seeds": n, "rows": aggregate(records), "runs": records}


def table(r: dict) -> str:
    lines = ["| scenario | controller | planner | success | error cm | time s | MPC solve ms |", "|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(
            f"| {x['scenario']} | {x['controller']} | {x['planner']} | {x['success']}/{x['of']} | {x['error_cm_mean']:.2f} ± {x['error_cm_std']:.2f} | "
            f"{x['time_s_mean']:.1f} | {x['solve_ms_median']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--controllers", default=None)
    ap.add_argument("--planners", default=None, help="e.g. cbirrt,ffg-rrt,ts-rrt (Table II's planner rows)")
    ap.add_argument("--only", default=None)
    ap.add_argument("--jsonl", type=Path, default=None, help="append each run here; runs already in it are skipped")
    ap.add_argument("--seed-from", type=int, default=0, help="seeds seed_from .. seed_from + seeds - 1")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--timeout-s", type=float, default=RUN_TIMEOUT_S)
    ap.add_argument("--time-limit-s", type=float, default=40.0, help="simulated seconds a run may take")
    ap.add_argument("--params", type=json.loads, default=None, help='method parameters for every run, JSON, e.g. \'{"du_weight": 100}\'')
    a = ap.parse_args()
    split = lambda s: s.split(",") if s else None  # noqa: E731
    r = run(a.quick, a.seeds, split(a.controllers), split(a.only), split(a.planners), a.jsonl, a.workers, a.timeout_s, a.seed_from, a.params, a.time_limit_s)
    print(table(r))


if __name__ == "__main__":
    main()
