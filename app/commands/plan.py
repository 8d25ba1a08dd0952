"""`bagit plan SCENARIO`: the SOI path g0 -> g† -> g* with a chosen planner."""

from __future__ import annotations

import argparse
from typing import Any

from bagit.commands import _args
from bagit.common.names import DEFAULT_PLANNER, PLAN_WALL_GUARD_S, PLANNER_NAMES

NAME = "plan"
HELP = "plan the SOI path g0 -> g† -> g* for a scenario"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario")
    p.add_argument("--planner", choices=PLANNER_NAMES, default=DEFAULT_PLANNER)
    p.add_argument("--seed", type=_args.seed, default=0)
    p.add_argument("--time-budget", type=_args.positive_seconds, default=PLAN_WALL_GUARD_S,
                   help=f"seconds of wall time before the search gives up, whatever its iterations (default {PLAN_WALL_GUARD_S:g})")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.planner import plan_scenario

    s = Scenario.from_file(find_scenario(args.scenario))
    r = plan_scenario(s, args.planner, args.seed, time_budget_s=args.time_budget)
    return {
        "scenario": s.name,
        "success": r.success,
        "reason": r.reason,
        "planner": r.planner,
        "path": r.path,
        "dagger_index": r.dagger_index,
        "n_nodes": int(len(r.path)),
        "time_s": r.time_s,
        "iterations": r.iterations,
        "path_length_m": r.path_length(),
    }


def human(r: dict[str, Any]) -> str:
    if not r["success"]:
        return f"{r['scenario']}: {r['planner']} failed after {r['iterations']} iterations ({r['time_s']:.2f} s)"
    return (
        f"{r['scenario']}: {r['planner']} found {r['n_nodes']} nodes (g† at {r['dagger_index']}) in "
        f"{r['time_s']:.3f} s, {r['iterations']} iterations, path length {r['path_length_m']:.3f} m"
    )
