"""`bagit run SCENARIO`: the whole bagging run, closed in simulation, in one process."""

from __future__ import annotations

import argparse
import sys
from typing import Any

NAME = "run"
HELP = "run a whole simulated bagging: camera -> SOI -> goal -> plan -> MPC -> arms"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario")
    p.add_argument("--controller", choices=["mpc", "ibvs", "ssvs"], default="mpc")
    p.add_argument("--planner", choices=["cbirrt", "ffg-rrt", "ts-rrt"], default="cbirrt")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--time-limit", type=float, default=40.0, help="simulated seconds before the run fails")
    p.add_argument("--wall-limit", type=float, default=900.0, help="wall-clock seconds before the run is stopped as too slow")
    p.add_argument("--headless", action="store_true", help="no viewer (the only mode for now: runs are always headless)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.common.scenario import Scenario
    from bagit.pipeline import run_bagging
    from bagit.scenarios import find_scenario

    s = Scenario.from_file(find_scenario(args.scenario))
    say = (lambda m: print(f"[run] {m}", file=sys.stderr, flush=True)) if args.json else (lambda m: print(f"[run] {m}", flush=True))
    r = run_bagging(s, args.controller, args.planner, args.seed, args.time_limit, progress=say, wall_limit_s=args.wall_limit)
    out = r.to_dict()
    out["scenario"] = s.name
    return out


def human(r: dict[str, Any]) -> str:
    verdict = "SUCCESS" if r["success"] else f"FAILED at {r['stage_reached']}: {r['reason']}"
    return (
        f"{r['scenario']} ({r['controller']}, {r['planner']}, seed {r['seed']}): {verdict}\n"
        f"error {r['error_cm']:.2f} cm, {r['duration_s']:.1f} s simulated in {r['wall_s']:.1f} s, "
        f"{r['ticks']} ticks, planning {r['planning_time_s']:.2f} s"
    )
