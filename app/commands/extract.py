"""`bagit extract CLOUD --n-x N`: the SOI of a rim cloud file (.ply, .pcd, .npy) and the time it took.

The SOI runs counter-clockwise seen from above, starting at the smallest angle from +x (see
`bagit.services.perception.extract_soi`). Result: soi (n_x x 3 list, metres), n_x, n_points, time_ms.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np

from bagit.commands import _args

NAME = "extract"
HELP = "extract the bag rim (SOI) from a point-cloud file"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("cloud", help="rim cloud: .ply, .pcd or .npy, world frame, metres")
    p.add_argument("--n-x", type=_args.soi_points, default=32, help="number of SOI points (default 32)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.services.perception import extract_soi, load_cloud

    points = load_cloud(args.cloud)
    t0 = time.perf_counter()
    soi = extract_soi(points, args.n_x)
    ms = (time.perf_counter() - t0) * 1e3
    return {"soi": soi.tolist(), "n_x": args.n_x, "n_points": int(len(points)), "time_ms": ms}


def human(result: dict[str, Any]) -> str:
    soi = np.asarray(result["soi"])
    rows = [f"{i:3d}  {p[0]: .4f} {p[1]: .4f} {p[2]: .4f}" for i, p in enumerate(soi)]
    head = f"SOI: {result['n_x']} points from {result['n_points']} in {result['time_ms']:.1f} ms (x y z, metres)"
    return "\n".join([head, *rows])
