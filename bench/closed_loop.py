"""Whole simulated bagging runs over the paper scenarios, seeds and controllers (Tables I and II):
manipulation success, error (cm), time to goal (simulated s) and MPC solve time per tick.

    python -m bagit.bench.closed_loop [--quick] [--seeds N] [--controllers mpc,ibvs,ssvs] [--only exp02,...]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from bagit.common.scenario import Scenario
from bagit.pipeline import run_bagging
from bagit.scenarios import list_scenarios

PAPER = {"mpc_error_cm": "2.10 ± 0.77", "mpc_time_s": "53.09 ± 2.92"}


def run(quick: bool = False, seeds: int | None = None, controllers: list[str] | None = None, only: list[str] | None = None) -> dict:
    n = seeds or (1 if quick else 8)
    ctrls = controllers or (["mpc"] if quick else ["mpc", "ibvs", "ssvs"])
    scen = [p for p in list_scenarios() if not only or any(p.stem.startswith(o) for o in only)]
    if quick and not only:
        scen = scen[:2]
    out: dict = {"seeds": n, "rows": []}
    for path in scen:
        s = Scenario.from_file(path)
        for ctrl in ctrls:
            runs = [run_bagging(s, ctrl, "cbirrt", seed) for seed in range(n)]
            ok = [r for r in runs if r.success]
            solve = np.concatenate([np.asarray(r.history["solve_ms"]) for r in runs])
            solve = solve[solve > 0]
            row = {
                "scenario": path.stem,
                "controller": ctrl,
                "success": len(ok),
                "of": n,
                "error_cm_mean": float(np.mean([r.error_cm for r in ok])) if ok else float("nan"),
                "error_cm_std": float(np.std([r.error_cm for r in ok])) if ok else float("nan"),
                "time_s_mean": float(np.mean([r.duration_s for r in ok])) if ok else float("nan"),
                "solve_ms_median": float(np.median(solve)) if solve.size else 0.0,
                "failures": sorted({f"{r.stage_reached}: {r.reason}" for r in runs if not r.success}),
            }
            out["rows"].append(row)
            print(json.dumps(row), flush=True)
    return out


def table(r: dict) -> str:
    lines = ["| scenario | controller | success | error cm | time s | MPC solve ms |", "|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(
            f"| {x['scenario']} | {x['controller']} | {x['success']}/{x['of']} | {x['error_cm_mean']:.2f} ± {x['error_cm_std']:.2f} | "
            f"{x['time_s_mean']:.1f} | {x['solve_ms_median']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--controllers", default=None)
    ap.add_argument("--only", default=None)
    a = ap.parse_args()
    r = run(a.quick, a.seeds, a.controllers.split(",") if a.controllers else None, a.only.split(",") if a.only else None)
    print(table(r))


if __name__ == "__main__":
    main()
