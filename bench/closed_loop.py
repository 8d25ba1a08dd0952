"""Whole simulated bagging runs over the paper scenarios, seeds and controllers (Tables I and II):
manipulation success, error (cm), time to goal (simulated s) and MPC solve time per tick.

Each run is `bagit run`'s own: the in-process rig (bagit.inprocess) with the coordinator, perception,
the controller and, by default, the two CR5s behind the arm driver's rules (`--arms ideal`: the
floating-gripper ablation). Each record is that run's `RunResult` (commit, host and effective
parameters in its `provenance`).

Each run goes in its own worker process, so a run that crashes (even in native code) or hangs
becomes a failed record with the reason, and the sweep goes on. With `--jsonl FILE` every run is
appended to FILE as it finishes and runs already there are skipped: a sweep that was stopped
resumes where it was. `bagit bench paper` reads such files (`--closed-loop FILE`).

    python -m bagit.bench.closed_loop [--quick] [--seeds N] [--controllers mpc,ibvs,ssvs] [--planners cbirrt]
                                      [--only exp02,...] [--seed-from S] [--jsonl FILE] [--workers 1] [--timeout-s 900]
                                      [--params JSON] [--time-limit-s 40] [--arms cr5|ideal]
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.common.names import CONTROLLER_NAMES, DEFAULT_CONTROLLER, ArmsMode
from bagit.common.results import RunResult, provenance
from bagit.scenarios import list_scenarios

PAPER = {"mpc_error_cm": "2.10 ± 0.77", "mpc_time_s": "53.09 ± 2.92"}
RUN_TIMEOUT_S = 900.0  # wall time one run may take before its worker is stopped


Key = tuple[str, str, str, int, str]  # scenario, controller, planner, seed, arms


def run_one(
    scenario: str, controller: str, planner: str, seed: int, time_limit_s: float = 40.0, params: dict[str, Any] | None = None,
    arms: ArmsMode = "cr5",
) -> dict[str, Any]:
    """One whole run, `bagit run`'s own, as a JSON-able record (its RunResult) in this process.
    `params`: method parameters overriding the scenario's (an ablation), kept in the record."""
    from bagit.common.scenario import Scenario
    from bagit.inprocess import RunOptions, run_inprocess
    from bagit.scenarios import find_scenario

    sc = Scenario.from_file(find_scenario(scenario))
    r = run_inprocess(RunOptions(scenario=sc, name=scenario, controller=controller, planner=planner, seed=seed, arms=arms,
                                 overrides=dict(params or {}), time_limit_s=time_limit_s))
    return r.model_dump(mode="json")


def _worker(conn: Any, args: tuple) -> None:
    try:
        conn.send(("ok", run_one(*args)))
    except BaseException as e:  # noqa: BLE001 - every failure goes back as a record
        conn.send(("error", f"{type(e).__name__}: {e}"))
    finally:
        conn.close()


def _failed(key: Key, reason: str, wall_s: float, params: dict[str, Any] | None) -> dict[str, Any]:
    """The record of a run whose worker crashed or hung: the same model, with the reason."""
    sc, ctrl, planner, seed, arms = key
    return RunResult(scenario=sc, controller=ctrl, planner=planner, seed=seed, arms=arms, overrides=dict(params or {}), success=False,
                     reason=reason, wall_s=wall_s, provenance=provenance()).model_dump(mode="json")


def record_key(r: dict[str, Any]) -> Key:
    """A record's run: scenario, controller, planner, seed, arms (records before the arms were in every run: ideal)."""
    return (r["scenario"], r["controller"], r["planner"], int(r["seed"]), r.get("arms") or "ideal")


def read_jsonl(path: Path | None) -> list[dict[str, Any]]:
    if path is None or not Path(path).exists():
        return []
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def sweep(
    keys: list[Key],
    jsonl: Path | None = None,
    workers: int = 1,
    timeout_s: float = RUN_TIMEOUT_S,
    time_limit_s: float = 40.0,
    params: dict[str, Any] | None = None,
) -> list[dict[str, Any]]:
    """Run every (scenario, controller, planner, seed, arms) not already in `jsonl`, `workers` at a time, each
    in a fresh process; returns all records of these keys (old and new)."""
    have = {record_key(r): r for r in read_jsonl(jsonl)}
    todo = [k for k in keys if k not in have]
    ctx = mp.get_context("spawn")  # no forked MuJoCo / OpenGL state
    running: list[tuple[tuple, Any, Any, float]] = []
    out = {k: have[k] for k in keys if k in have}

    def record(key: tuple, rec: dict[str, Any]) -> None:
        out[key] = rec
        if jsonl is not None:
            with open(jsonl, "a") as f:
                f.write(json.dumps(rec) + "\n")
        print(json.dumps({k: rec.get(k) for k in ("scenario", "controller", "planner", "seed", "arms", "success", "stage_reached", "reason",
                                                  "error_cm", "duration_s", "wall_s")}), flush=True)

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
            sc, ctrl, planner, seed, arms = key
            p = ctx.Process(target=_worker, args=(send, (sc, ctrl, planner, seed, time_limit_s, params, arms)), daemon=True)
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
                record(key, payload if status == "ok" else _failed(key, f"error: {payload}", wall, params))
            elif not p.is_alive():
                record(key, _failed(key, f"crashed: the worker process died (exit code {p.exitcode})", wall, params))
            elif wall > timeout_s:
                p.kill()
                record(key, _failed(key, f"timed out: no result within {timeout_s:.0f} s of wall time", wall, params))
            else:
                continue
            p.join(5)
            recv.close()
            running.remove(item)
        time.sleep(0.2)


def aggregate(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per scenario x controller x planner: success / of, error and time over the successes."""
    groups: dict[tuple[str, str, str, str], list[dict[str, Any]]] = {}
    for r in records:
        groups.setdefault(record_key(r)[:3] + record_key(r)[4:], []).append(r)
    rows = []
    for (sc, ctrl, planner, arms), rs in groups.items():
        ok = [r for r in rs if r["success"]]
        solve = [r["solve_ms_median"] for r in rs if r.get("solve_ms_median")]
        rows.append({
            "scenario": sc, "controller": ctrl, "planner": planner, "arms": arms, "success": len(ok), "of": len(rs),
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
    arms: list[str] | None = None,
) -> dict:
    n = seeds or (1 if quick else 8)
    ctrls = controllers or ([DEFAULT_CONTROLLER] if quick else list(CONTROLLER_NAMES))
    scen = [p.stem for p in list_scenarios() if not only or any(p.stem.startswith(o) for o in only)]
    if quick and not only:
        scen = scen[:2]
    keys = [(s, c, pl, seed, a) for s in scen for c in ctrls for pl in (planners or ["cbirrt"]) for a in (arms or ["cr5"])
            for seed in range(seed_from, seed_from + n)]
    records = sweep(keys, jsonl, workers, timeout_s, time_limit_s, params)
    return {"seeds": n, "rows": aggregate(records), "runs": records}


def table(r: dict) -> str:
    lines = ["| scenario | controller | planner | arms | success | error cm | time s | MPC solve ms |", "|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(
            f"| {x['scenario']} | {x['controller']} | {x['planner']} | {x['arms']} | {x['success']}/{x['of']} | {x['error_cm_mean']:.2f} ± {x['error_cm_std']:.2f} | "
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
    ap.add_argument("--arms", default=None, help="cr5 (default), ideal, or both: cr5,ideal")
    a = ap.parse_args()
    split = lambda s: s.split(",") if s else None  # noqa: E731
    r = run(a.quick, a.seeds, split(a.controllers), split(a.only), split(a.planners), a.jsonl, a.workers, a.timeout_s, a.seed_from, a.params, a.time_limit_s, split(a.arms))
    print(table(r))


if __name__ == "__main__":
    main()
