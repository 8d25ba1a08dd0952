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

    from bagit.common.errors import BadScenario
    from bagit.common.geometry import closed_polyline_length
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario
    from bagit.services.planner import bagging_soi

    s = Scenario.from_file(find_scenario(args.scenario))
    g0 = s.bag.g0()
    R = s.bag.rim_perimeter or (closed_polyline_length(g0) if g0 is not None else None)
    if R is None:
        raise BadScenario(f"scenario {s.name!r} gives neither bag.rim_perimeter nor bag.initial_rim")
    t0 = time.perf_counter()
    g = bagging_soi(s.object.bottom_vertices(), R, s.bag.n_x, s.params, lambda_d=s.lambda_d(), g0=g0)
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
