"""Planning success and time over the paper scenarios for the three planners (like the paper's Table II).

    python -m bagit.bench.planner [--quick] [--seeds N]
"""

from __future__ import annotations

import argparse

import numpy as np

from bagit.common.scenario import Scenario
from bagit.scenarios import list_scenarios
from bagit.services.planner import PLANNERS, plan_scenario


def run(quick: bool = False, seeds: int | None = None) -> dict:
    n = seeds or (3 if quick else 100)
    scen = list_scenarios()
    if quick:
        scen = scen[:4]
    out: dict = {"seeds": n, "scenarios": {}}
    for path in scen:
        s = Scenario.from_file(path)
        row = {}
        for planner in sorted(PLANNERS):
            times, lengths, ok = [], [], 0
            for seed in range(n):
                r = plan_scenario(s, planner, seed)
                if r.success:
                    ok += 1
                    times.append(r.time_s)
                    lengths.append(r.path_length())
            row[planner] = {
                "success": ok,
                "success_rate": ok / n,
                "median_s": float(np.median(times)) if times else float("nan"),
                "p95_s": float(np.percentile(times, 95)) if times else float("nan"),
                "mean_s": float(np.mean(times)) if times else float("nan"),
                "std_s": float(np.std(times)) if times else float("nan"),
                "path_length_m": float(np.median(lengths)) if lengths else float("nan"),
            }
        out["scenarios"][path.stem] = row
    return out


def table(r: dict) -> str:
    lines = [f"| scenario | planner | success /{r['seeds']} | median s | p95 s | mean ± std s | path m |", "|---|---|---|---|---|---|---|"]
    for name, row in r["scenarios"].items():
        for planner, m in row.items():
            lines.append(
                f"| {name} | {planner} | {m['success']} | {m['median_s']:.3f} | {m['p95_s']:.3f} | "
                f"{m['mean_s']:.3f} ± {m['std_s']:.3f} | {m['path_length_m']:.3f} |"
            )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None)
    a = ap.parse_args()
    print(table(run(a.quick, a.seeds)))


if __name__ == "__main__":
    main()
