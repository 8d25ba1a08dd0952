"""`bagit demo`: the main job of `make demo`.

Until the simulated bagging run lands, it extracts the SOI from the bundled sample rim cloud.
"""

from __future__ import annotations

import argparse
from importlib import resources
from typing import Any

NAME = "demo"
HELP = "run the demo: extract the SOI from the bundled sample rim cloud"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--n-x", type=int, default=32, help="number of SOI points (default 32)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.commands import extract

    sample = resources.files("bagit.common") / "data" / "sample_rim.ply"
    with resources.as_file(sample) as path:
        args.cloud = str(path)
        result = extract.run(args)
    result["cloud"] = "bundled sample_rim.ply"
    return result


def human(result: dict[str, Any]) -> str:
    from bagit.commands import extract

    return "BagIt demo: SOI of the bundled sample rim cloud\n" + extract.human(result)
