"""`bagit run SCENARIO`: one whole simulated bagging in one process, the deployed stack's own logic
(coordinator, perception, controller, the arm driver's motion rules, two simulated CR5s) on the
simulator's clock. See bagit.inprocess."""

from __future__ import annotations

import argparse
import logging
from typing import Any

from bagit.commands import _args
from bagit.common.names import ARMS_MODES, CONTROLLER_NAMES, DEFAULT_CONTROLLER, DEFAULT_PLANNER, PLANNER_NAMES

log = logging.getLogger("bagit.run")

NAME = "run"
HELP = "run a whole simulated bagging in one process: camera -> SOI -> goal -> plan -> MPC -> arm driver -> CR5s"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", help="scenario file, or the name of a bundled scenario")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, default=DEFAULT_CONTROLLER)
    p.add_argument("--planner", choices=PLANNER_NAMES, default=DEFAULT_PLANNER)
    p.add_argument("--seed", type=_args.seed, default=0)
    p.add_argument("--arms", choices=ARMS_MODES, default="cr5",
                   help="cr5: the two CR5s through the arm driver's rules (default); ideal: floating grippers (an ablation)")
    p.add_argument("--params", type=_args.json_object, default=None, help='method parameters over the scenario\'s, JSON, e.g. \'{"twist_weight": 0}\'')
    p.add_argument("--fps", type=_args.positive_number, default=None, help="camera frames per simulated second (default: the control rate)")
    p.add_argument("--time-limit", type=_args.positive_seconds, default=40.0, help="simulated seconds of servoing before the run fails")
    p.add_argument("--wall-limit", type=_args.positive_seconds, default=900.0, help="wall-clock seconds before the run is stopped as too slow")
    p.add_argument("--headless", action="store_true", help="no viewer (the only mode: runs are always headless)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.common.params import merge_params
    from bagit.common.scenario import Scenario
    from bagit.inprocess import RunOptions, run_inprocess
    from bagit.scenarios import find_scenario
    from bagit.services.planner.plan import check_scenario_goal

    path = find_scenario(args.scenario)
    s = Scenario.from_file(path)
    # bad parameters, a goal too large for the bag or out of the arms' reach: one line, before the world is built
    check_scenario_goal(s.model_copy(update={"params": merge_params(s.params, args.params)}))
    opts = RunOptions(scenario=s, name=path.stem, controller=args.controller, planner=args.planner, seed=args.seed, arms=args.arms,
                      overrides=args.params or {}, time_limit_s=args.time_limit, wall_limit_s=args.wall_limit, fps=args.fps)
    return run_inprocess(opts, progress=log.info).model_dump(mode="json")


def human(r: dict[str, Any]) -> str:
    from bagit.common.results import RunResult

    res = RunResult.model_validate(r)
    ev = ", ".join(f"{k} {v}" for k, v in res.arm_events.items() if v)
    return res.headline() + (f"\narm events: {ev}" if ev else "")
