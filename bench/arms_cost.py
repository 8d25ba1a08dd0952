"""What the two CR5s cost a run: the same scenario and seed through `bagit run` with the arms (`cr5`)
and with floating grippers (`ideal`), each in a child process, measured in CPU seconds (user + system
of the child, which a loaded machine changes far less than wall time) and wall seconds.

The arms cost CPU twice: their own work per control tick (the driver's Ruckig and reach check, the
simulated controllers' servo loops), and the longer simulated time the arm side's lag makes a run
take. The record keeps both (`cpu_s`, `ticks`), so a report can tell them apart.

    python -m bagit.bench.arms_cost [--only exp01,exp04] [--seed 0] [--jsonl bench/results/arms-cost.jsonl]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bagit.common.headless import headless_gl
from bagit.common.logs import configure_logging
from bagit.common.results import RunResult, provenance

log = logging.getLogger("bagit.bench.arms_cost")

RESULTS = Path(__file__).resolve().parent / "results" / "arms-cost.jsonl"
DEFAULT_SCENARIOS = ("exp01", "exp04", "exp07", "exp11", "obstacles-a")
ARMS = ("cr5", "ideal")


def _children_cpu_s() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def measure(scenario: str, seed: int, arms: str) -> dict[str, Any]:
    """One `bagit run` in a child process: its result, CPU seconds and wall seconds."""
    cmd = [sys.executable, "-m", "bagit.cli", "run", scenario, "--seed", str(seed), "--arms", arms, "--json"]
    cpu0, t0 = _children_cpu_s(), time.perf_counter()
    out = subprocess.run(cmd, capture_output=True, text=True, env=headless_gl(dict(os.environ)))
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    if out.returncode not in (0, 1):
        raise RuntimeError(f"bagit run {scenario} --arms {arms} exited {out.returncode}: {out.stderr.strip()[-300:]}")
    res = RunResult.model_validate_json(out.stdout)
    return {"scenario": scenario, "seed": seed, "arms": arms, "cpu_s": round(cpu, 3), "wall_s": round(wall, 3),
            "duration_s": res.duration_s, "ticks": res.ticks, "success": res.success, "error_cm": res.error_cm,
            "load_1min": round(os.getloadavg()[0], 2),
            "provenance": (res.provenance or provenance()).model_dump(mode="json")}  # the run's own: its effective parameters


def summary(rows: list[dict[str, Any]], source: str = RESULTS.name) -> str:
    """Markdown: per scenario, CPU and ticks with each arm side, and the ratios (from the records)."""
    by = {(r["scenario"], r["seed"], r["arms"]): r for r in rows}
    lines = ["| scenario | seed | cr5 CPU s | ideal CPU s | CPU cr5/ideal | cr5 ticks | ideal ticks | CPU ms per tick cr5/ideal |",
             "|---|---|---|---|---|---|---|---|"]
    tot = {"cr5": 0.0, "ideal": 0.0}
    for (sc, seed, arms), c in sorted(by.items()):
        i = by.get((sc, seed, "ideal"))
        if arms != "cr5" or i is None:
            continue
        tot["cr5"] += c["cpu_s"]
        tot["ideal"] += i["cpu_s"]
        per_tick = (c["cpu_s"] / c["ticks"]) / (i["cpu_s"] / i["ticks"])
        lines.append(f"| {sc} | {seed} | {c['cpu_s']:.1f} | {i['cpu_s']:.1f} | {c['cpu_s'] / i['cpu_s']:.2f} | {c['ticks']} | {i['ticks']} | {per_tick:.2f} |")
    if tot["ideal"]:
        lines.append(f"| all | | {tot['cr5']:.1f} | {tot['ideal']:.1f} | {tot['cr5'] / tot['ideal']:.2f} | | | |")
    commits = sorted({(r.get("provenance") or {}).get("commit", "?")[:10] for r in rows})
    lines.append(f"\nRecords: `{source}`, commit {', '.join(commits)}; CPU is the child's user + system time.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default=",".join(DEFAULT_SCENARIOS), help="scenarios (names or unique prefixes), comma-separated")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jsonl", type=Path, default=RESULTS, help="append each measurement here")
    args = ap.parse_args(argv)
    configure_logging()
    rows = []
    for sc in [s for s in args.only.split(",") if s]:
        for arms in ARMS:
            row = measure(sc, args.seed, arms)
            log.info("%s seed %d %s: %.1f CPU s, %.1f wall s, %d ticks", sc, args.seed, arms, row["cpu_s"], row["wall_s"], row["ticks"])
            with args.jsonl.open("a") as f:
                f.write(json.dumps(row) + "\n")
            rows.append(row)
    print(summary(rows, args.jsonl.name))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
