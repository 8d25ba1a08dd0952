"""`bagit up [SCENARIO]`: the simulator, every service and the dashboard as child processes on loopback.

Prints the dashboard URL, streams the services' output with `[service]` prefixes, waits until
every service is alive, and with a SCENARIO starts a run. `--exit-when-done` waits for the run's
end and exits with its result (0 done, 1 failed or aborted; `--json` prints it). Ctrl-C or
SIGTERM stops every child (see bagit.up).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

NAME = "up"
HELP = "bring the whole simulated rig up: sim, perception, planner, controller, arm driver, dashboard"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="start a run of this scenario once every service is up")
    p.add_argument("--exit-when-done", action="store_true", help="exit when the run ends, with its result")
    p.add_argument("--controller", help="controller of the run (mpc, ibvs, ssvs; default mpc)")
    p.add_argument("--planner", help="planner of the run (default cbirrt)")
    p.add_argument("--seed", type=int, default=0, help="seed of the run and the simulated world")
    p.add_argument("--no-dashboard", action="store_true", help="do not start the dashboard")
    p.add_argument("--record", type=Path, metavar="DIR", help="also run the recorder into DIR")
    p.add_argument("--rig", default="sim", help="rig name (key prefix bagit/<rig>/; default sim)")
    p.add_argument("--fps", type=float, default=10.0, help="simulated camera frames per second (default 10)")
    p.add_argument("--dashboard-port", type=int, default=0, help="dashboard port (default: a free one)")
    p.add_argument("--timeout", type=float, default=600.0, help="with --exit-when-done: give up after S seconds (default 600)")
    p.add_argument("--status-file", type=Path, help="write the rig's status (child PIDs, hub endpoint, URL) here as JSON")
    p.add_argument("--services", metavar="LIST", help="comma-separated subset of the services to start (default: all)")
    p.add_argument("--workdir", type=Path, help="folder for the generated Zenoh config and rig YAML (default: a temporary one)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    import signal
    import threading
    import time

    from bagit.common.errors import BadScenario
    from bagit.up import SERVICES, Up, UpOptions

    if args.exit_when_done and not args.scenario:
        raise BadScenario("--exit-when-done needs a SCENARIO to run")
    if args.scenario:
        from bagit.scenarios import find_scenario

        find_scenario(args.scenario)  # a bad name is a one-line error before anything starts
    if not 0 < args.fps <= 30:
        raise BadScenario(f"--fps must be in (0, 30], got {args.fps}")
    services = tuple(x.strip() for x in args.services.split(",") if x.strip()) if args.services else SERVICES
    services = tuple(s for s in services if not (args.no_dashboard and s == "dashboard"))
    unknown = [s for s in services if s not in SERVICES + ("recorder",)]
    if unknown:
        raise BadScenario(f"--services: unknown service {unknown[0]!r}; choose from {', '.join(SERVICES)}, recorder")
    opts = UpOptions(scenario=args.scenario, controller=args.controller, planner=args.planner, seed=args.seed, rig=args.rig,
                     services=services, record=args.record, fps=args.fps, dashboard_port=args.dashboard_port, workdir=args.workdir,
                     status_file=args.status_file)
    stop = threading.Event()
    main = threading.current_thread() is threading.main_thread()
    previous = {s: signal.signal(s, lambda *_: stop.set()) for s in (signal.SIGINT, signal.SIGTERM)} if main else {}
    t0 = time.monotonic()
    result: dict[str, Any] = {"success": False, "reason": "interrupted"}
    up = Up(opts)
    try:
        up.start()
        if up.dashboard_url:
            up.say(f"dashboard: {up.dashboard_url}")
        missing = up.wait_ready(stop=stop)
        if stop.is_set():
            return result | {"wall_s": time.monotonic() - t0}
        if missing:
            raise BadScenario(f"services not up after {opts.ready_timeout_s:g} s: {', '.join(missing)}")
        up.say(f"all services up in {time.monotonic() - t0:.1f} s: {', '.join(sorted(up.children))}; hub {up.hub}")
        run_id = None
        if args.scenario:
            rep = up.start_run(args.scenario)
            if not rep.accepted:
                raise BadScenario(f"run refused: {rep.reason}")
            run_id = rep.run_id
            up.say(f"run {run_id} started: {args.scenario}")
        if args.exit_when_done:
            state = up.wait_run(run_id, stop, timeout=args.timeout)
            if state is None:
                reason = "interrupted" if stop.is_set() else f"no end of run {run_id} within {args.timeout:g} s"
                return {"success": False, "reason": reason, "run_id": run_id, "wall_s": time.monotonic() - t0}
            truth = _judge_on_truth(up, state, stop)
            ok = state.stage == "done" and (truth is None or truth["success"])
            reason = state.reason if state.stage != "done" else (None if ok else truth["reason"])
            return {
                "success": ok, "run_id": run_id, "scenario": state.scenario, "stage": state.stage,
                "reason": reason, "result": state.result, "truth": truth, "elapsed_s": state.elapsed_s,
                "wall_s": time.monotonic() - t0, "restarts": {n: c.restarts for n, c in up.children.items()},
            }
        up.say("up; Ctrl-C to stop everything")
        stop.wait()
        return {"success": True, "wall_s": time.monotonic() - t0, "run_id": run_id, "restarts": {n: c.restarts for n, c in up.children.items()}}
    finally:
        codes = up.stop()
        up.say("stopped: " + ", ".join(f"{n} {c}" for n, c in codes.items()))
        for s, h in previous.items():
            signal.signal(s, h)


def _judge_on_truth(up: Any, state: Any, stop: Any) -> dict[str, Any] | None:
    """The run judged on the simulator's ground truth, as `bagit run` judges it: the true rim encloses
    the object's outline at least lambda_d/2 above its bottom, the bag never passed through it.
    None without a simulator (a real rig has no ground truth)."""
    import time

    from bagit.common.scenario import Scenario
    from bagit.pipeline import judge
    from bagit.services.planner.goal import bottom_frame

    if up.truth is None or state.scenario_doc is None:
        return None
    deadline = time.monotonic() + 3.0
    while (t := up.truth.get()) is None or t.run_id != state.run_id:
        if time.monotonic() > deadline or stop.wait(0.05):
            return {"success": False, "reason": "no ground truth from the simulator for this run"}
    scenario = Scenario.model_validate(state.scenario_doc)
    V = scenario.object.bottom_vertices()
    ok, err_cm, reason = judge(np.asarray(t.rim), scenario, scenario.lambda_d(), bottom_frame(V)[:3, 2])
    if t.passed_through:
        ok, reason = False, "the bag passed through the object"
    return {"success": ok, "reason": reason, "error_cm": err_cm, "passed_through": t.passed_through,
            "max_penetration_mm": t.max_penetration_m * 1e3, "sim_time_s": t.sim_time, "realtime_factor": t.realtime_factor}


def human(r: dict[str, Any]) -> str:
    if "stage" in r:
        res = r.get("result") or {}
        extra = f", error {res['error_to_goal_m'] * 100:.1f} cm" if res.get("error_to_goal_m") is not None else ""
        return f"run {r['run_id']} ({r.get('scenario')}): {r['stage']}{extra} in {r['elapsed_s']:.1f} s" + (f" ({r['reason']})" if r.get("reason") else "")
    return f"rig stopped after {r['wall_s']:.1f} s"
