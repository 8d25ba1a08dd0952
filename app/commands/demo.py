"""`bagit demo`: the main job of `make demo`: a whole simulated bagging run of a paper scenario.

`--sample` instead extracts the SOI from the bundled sample rim cloud (no simulator needed).
"""

from __future__ import annotations

import argparse
from importlib import resources
from typing import Any

from bagit.commands import _args

NAME = "demo"
HELP = "run the demo: a simulated bagging run (or, with --sample, SOI extraction from a bundled cloud)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scenario", default="exp02-canned-pineapple", help="bundled scenario to bag")
    p.add_argument("--sample", action="store_true", help="only extract the SOI from the bundled sample rim cloud")
    p.add_argument("--n-x", type=_args.soi_points, default=32, help="number of SOI points for --sample (default 32)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    if args.sample:
        from bagit.commands import extract

        sample = resources.files("bagit.common") / "data" / "sample_rim.ply"
        with resources.as_file(sample) as path:
            args.cloud = str(path)
            result = extract.run(args)
        result["cloud"] = "bundled sample_rim.ply"
        return result
    from bagit.commands import run as run_cmd

    parser = argparse.ArgumentParser()
    run_cmd.add_arguments(parser)
    run_args = parser.parse_args([args.scenario])  # `bagit run SCENARIO` with its defaults (mpc, cbirrt, seed 0, the CR5s)
    run_args.json = args.json
    return run_cmd.run(run_args)


def human(result: dict[str, Any]) -> str:
    from bagit.commands import extract
    from bagit.commands import run as run_cmd

    if "soi" in result:
        return "BagIt demo: SOI of the bundled sample rim cloud\n" + extract.human(result)
    return "BagIt demo: a simulated bagging run\n" + run_cmd.human(result)
