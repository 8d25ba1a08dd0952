"""`bagit goal SCENARIO`: the bagging SOI g† and goal SOI g* of a scenario."""

from __future__ import annotations

import argparse
from typing import Any

NAME = "goal"
HELP = "compute the bagging ellipse, g† and g* for a scenario"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario")


def run(args: argparse.Namespace) -> dict[str, Any]:
    import time

    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.planner.plan import bagging_goal

    s = Scenario.from_file(find_scenario(args.scenario))
    t0 = time.perf_counter()
    g, R = bagging_goal(s, s.bag.g0())  # the coordinator's goal rule, reach included
    return {
        "scenario": s.name,
        "rim_perimeter": R,
        "ellipse": g.ellipse.model_dump(),
        "perimeter": g.perimeter,
        "c1": g.c1,
        "c2": g.c2,
        "c3": g.c3,
        "c3_applied": g.c3_applied,
        "oriented_by": g.oriented_by,
        "lambda_d": g.lambda_d,
        "frame": g.frame,
        "g_dagger": g.g_dagger,
        "g_star": g.g_star,
        "time_ms": (time.perf_counter() - t0) * 1e3,
    }


# why c3 is or is not held to lambda_3, by what set the ellipse's orientation
C3_NOTE = {
    "axis": "",
    "bag": " (C3 not applied: oriented like the bag's opening, dagger_shape: bag)",
    "none": " (C3 dropped: no principal axis)",
}


def human(r: dict[str, Any]) -> str:
    e = r["ellipse"]
    return (
        f"{r['scenario']}: bagging ellipse a={e['a']:.4f} m b={e['b']:.4f} m, perimeter {r['perimeter']:.4f} m "
        f"(R = {r['rim_perimeter']:.4f} m)\n"
        f"c1 = {r['c1']:.3f}  c2 = {r['c2']:.4f} m  c3 = {r['c3']:.4f}{C3_NOTE[r['oriented_by']]}\n"
        f"g* = g† + {r['lambda_d']:.3f} m along the object; {len(r['g_dagger'])} points; {r['time_ms']:.1f} ms"
    )
