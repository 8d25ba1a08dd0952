"""`bagit up [SCENARIO]`: the simulator, every service and the dashboard as child processes on loopback.

Prints the dashboard URL, streams the services' output with `[service]` prefixes, waits until
every service is alive, and with a SCENARIO starts a run. `--exit-when-done` waits for the run's
end and exits with its result (0 done, 1 failed or aborted; `--json` prints it). Ctrl-C or
SIGTERM stops every child (see bagit.up).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bagit.commands import _args
from bagit.common.names import CONTROLLER_NAMES, DEFAULT_CONTROLLER, DEFAULT_PLANNER, PLANNER_NAMES

if TYPE_CHECKING:
    from bagit.up import UpOptions

RECORDER_STATUS_WAIT_S = 3.0  # the recorder's status before a run and after it: at most this long to come
NAME = "up"
HELP = "bring the whole simulated rig up: sim, perception, planner, controller, arm driver, dashboard"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("scenario", nargs="?", help="start a run of this scenario once every service is up")
    p.add_argument("--exit-when-done", action="store_true", help="exit when the run ends, with its result")
    p.add_argument("--controller", choices=CONTROLLER_NAMES, help=f"controller of the run (default {DEFAULT_CONTROLLER})")
    p.add_argument("--planner", choices=PLANNER_NAMES, help=f"planner of the run (default {DEFAULT_PLANNER})")
    p.add_argument("--seed", type=_args.seed, default=0, help="seed of the run and the simulated world")
    p.add_argument("--no-dashboard", action="store_true", help="do not start the dashboard")
    p.add_argument("--record", type=Path, metavar="DIR", help="also run the recorder into DIR")
    p.add_argument("--rig", default="sim", help="rig name (key prefix bagit/<rig>/; default sim)")
    p.add_argument("--clock", choices=["lockstep", "wall"], default="lockstep",
                   help="lockstep (default): every service on the simulator's clock, which waits for them, so a slow machine "
                        "makes a run slower, never different; wall: every service on the wall clock, the simulator paced to it")
    p.add_argument("--speed", type=_args.positive_number, default=None,
                   help="simulated seconds per wall second at most (default: a lockstep run as fast as the rig answers, "
                        "real time between runs and with --clock wall)")
    p.add_argument("--fps", type=_args.positive_number, default=None,
                   help="simulated camera frames per second (default: the control rate in lockstep, as `bagit run`; 10 with --clock wall)")
    p.add_argument("--dashboard-port", type=_args.port, default=0, help="dashboard port (default: a free one)")
    p.add_argument("--timeout", type=_args.positive_seconds, default=600.0, help="with --exit-when-done: give up after S seconds (default 600)")
    p.add_argument("--status-file", type=Path, help="write the rig's status (child PIDs, hub endpoint, URL) here as JSON")
    p.add_argument("--services", metavar="LIST", help="comma-separated subset of the services to start (default: all)")
    p.add_argument("--allow-inexact", action="store_true",
                   help="with --exit-when-done: exit 0 for a successful lockstep run that could not stay exact (a service "
                        "dropped from the wait, an answer made without what it waited for); by default that exits 1")
    p.add_argument("--no-fork-server", action="store_true",
                   help="start every service as an interpreter of its own (default: forks of one that imported what they share)")
    p.add_argument("--shared-cores", action="store_true",
                   help="run every service on every CPU (default: in lockstep, with the simulator and two CPUs or more, the simulator "
                        "keeps the first to itself and the other services run on the rest)")
    p.add_argument("--workdir", type=Path, help="folder for the generated Zenoh config and rig YAML (default: a temporary one)")


def options(args: argparse.Namespace) -> UpOptions:
    """The rig's `UpOptions` from the command line, after every check a child would only fail later."""
    from pydantic import ValidationError

    from bagit.common.errors import BadScenario
    from bagit.common.rig import RigConfig
    from bagit.up import SERVICES, UpOptions

    # Everything a child would only refuse after the rig is up (their logs have the reason; `up` would
    # only see them missing after ready_timeout_s) is refused here, before any child starts.
    if args.exit_when_done and not args.scenario:
        raise BadScenario("--exit-when-done needs a SCENARIO to run")
    if args.scenario:
        from bagit.common.scenario import Scenario
        from bagit.scenarios import find_scenario
        from bagit.services.planner.plan import check_scenario_goal

        check_scenario_goal(Scenario.from_file(find_scenario(args.scenario)))  # a bad file, or a goal out of reach
    try:
        RigConfig(name=args.rig)
    except ValidationError as e:
        raise BadScenario(f"--rig {args.rig!r}: {e.errors()[0]['msg']}") from None
    if args.fps is not None and not 0 < args.fps <= 30:
        raise BadScenario(f"--fps must be in (0, 30], got {args.fps}")
    if args.speed is not None and not 0 < args.speed <= 1000:
        raise BadScenario(f"--speed must be in (0, 1000], got {args.speed}")
    services = tuple(x.strip() for x in args.services.split(",") if x.strip()) if args.services else SERVICES
    services = tuple(s for s in services if not (args.no_dashboard and s == "dashboard"))
    unknown = [s for s in services if s not in SERVICES + ("recorder",)]
    if unknown:
        raise BadScenario(f"--services: unknown service {unknown[0]!r}; choose from {', '.join(SERVICES)}, recorder")
    return UpOptions(scenario=args.scenario, controller=args.controller, planner=args.planner, seed=args.seed, rig=args.rig,
                     services=services, record=args.record, fps=args.fps, dashboard_port=args.dashboard_port, workdir=args.workdir,
                     status_file=args.status_file, clock=args.clock, speed=args.speed,
                     fork_server=not args.no_fork_server, sim_core=not args.shared_cores)


def run(args: argparse.Namespace) -> dict[str, Any]:
    import threading
    import time

    from bagit.commands._service import stop_on_signals, wait_stop
    from bagit.common.errors import BadScenario
    from bagit.forkserver import ForkServer, child_env
    from bagit.up import WATCHERS, Up

    t0 = time.monotonic()
    # The fork server first, forked from this process while it runs one thread: it shares the imports just
    # made (most of what the services import) instead of making them again in an interpreter of its own.
    forks = None if args.no_fork_server else ForkServer(child_env(), inherit=True)
    try:
        opts = options(args)  # refused here, before any service starts
    except BaseException:
        if forks is not None:
            forks.close()
        raise
    stop = threading.Event()
    restore = stop_on_signals(stop)
    up = Up(opts, forks=forks, t0=t0)
    try:
        up.start()
        if up.dashboard_url:
            up.say(f"dashboard: {up.dashboard_url}")
        # A scenario's run starts once the services it needs are up; the dashboard joins it as it comes up
        waiting = tuple(n for n in WATCHERS if n in up.children) if args.scenario else ()
        missing = up.wait_ready(stop=stop, but=waiting)
        if stop.is_set():
            return {"success": False, "reason": "interrupted", "wall_s": time.monotonic() - t0}
        if missing:
            raise BadScenario(f"services not up after {opts.ready_timeout_s:g} s: {', '.join(missing)}")
        waiting = up.not_up(waiting)
        if waiting:  # (once the last is up, `Up` says "all services up")
            up.say(f"services the run needs up in {time.monotonic() - t0:.1f} s: "
                   f"{', '.join(sorted(set(up.children) - set(waiting)))}; starting with {', '.join(waiting)} still coming up")
        run_id = None
        recorder = None
        if opts.record is not None:  # the recorder's counters, so the run's result says what its recording lost
            from bagit.common.bus import LatestCache
            from bagit.common.messages import RecorderStatus

            recorder = LatestCache(up.session, up.keys.recorder_status, RecorderStatus)
            recorder.wait(RECORDER_STATUS_WAIT_S)
        recording_before = recorder.get() if recorder is not None else None
        run_t0, run_cpu0 = time.monotonic(), up.rig_cpu_s()
        if args.scenario:
            rep = up.start_run(args.scenario)
            if not rep.accepted:
                raise BadScenario(f"run refused: {rep.reason}")
            run_id = rep.run_id
            up.say(f"run {run_id} started: {args.scenario}")
        if args.exit_when_done:
            if run_id is None:  # no SCENARIO is refused with the arguments; an accepted run always has an id
                raise BadScenario("--exit-when-done: no run to follow (the run was started without a run id)")
            state = up.wait_run(run_id, stop, timeout=args.timeout)
            # what the run itself cost a rig already up (the benchmarks compare it with `bagit run`'s)
            up.say(f"the run: {time.monotonic() - run_t0:.2f} s wall, {up.rig_cpu_s() - run_cpu0:.2f} CPU s (every service and bagit up)")
            up.say("restarts: " + (", ".join(f"{n} {c.restarts}" for n, c in up.children.items() if c.restarts) or "none"))
            up.say("cpu s: " + ", ".join(f"{n} {v:.1f}" for n, v in up.cpu_s().items()))  # per service, this run and start-up
            up.say("own cpu s: " + ", ".join(f"{n} {v:.1f}" for n, v in up.own_cpu_s().items()))  # the rest of the rig's
            recording = recording_of_run(recorder, recording_before) if recorder is not None else None
            if recording is not None and not recording.ok:
                up.say(f"the run's recording failed: {recording.lost} messages lost ({recording.error})")
            return run_result(up, run_id, state, stop, args, time.monotonic() - t0, recording).model_dump(mode="json")
        up.say("up; Ctrl-C to stop everything")
        wait_stop(stop)
        return {"success": True, "wall_s": time.monotonic() - t0, "run_id": run_id, "restarts": {n: c.restarts for n, c in up.children.items()}}
    finally:
        codes = up.stop()
        up.say("stopped: " + ", ".join(f"{n} {c}" for n, c in codes.items()))
        restore()


def recording_of_run(recorder: Any, before: Any, timeout_s: float = RECORDER_STATUS_WAIT_S) -> Any:
    """The recorder's part in a run (`RecordingReport`) from its status cache (`LatestCache` of
    recorder/status) and its status when the run began: the first status received from now on (the
    run has ended), at most `timeout_s` away, else the newest; None without a recorder."""
    import time

    from bagit.common.results import recording_report

    recorder.wait(timeout_s, newer_than=time.monotonic())
    return recording_report(before, recorder.get())


def run_result(up: Any, run_id: str | None, state: Any, stop: Any, args: argparse.Namespace, wall_s: float, recording: Any = None) -> Any:
    """The run's RunResult, as `bagit run --json` gives it: the coordinator's result, with the simulator's
    ground truth (the true rim judged as `bagit run` judges it), the arm side's event counts and, with a
    recorder, what became of the run's recording (`recording`, a RecordingReport)."""
    from bagit.common.results import ARM_EVENT_KINDS, RunResult, points_list, provenance

    if state is None:
        reason: str | None = "interrupted" if stop.is_set() else f"no end of run {run_id} within {args.timeout:g} s"
        return RunResult(run_id=run_id, scenario=args.scenario, controller=args.controller, planner=args.planner, seed=args.seed,
                         arms="cr5", reason=reason, wall_s=round(wall_s, 3), recording=recording, provenance=provenance())
    res = RunResult.model_validate(state.result) if state.result else RunResult(
        run_id=run_id, scenario=state.scenario, seed=args.seed, stage_reached=state.stage, reason=state.reason)
    truth, final_rim, sim_truth = _truth(up, state, stop)
    arm = up.arm_states.latest() if up.arm_states is not None else None
    events = {k: int((arm.events if arm is not None else {}).get(k, 0)) for k in ARM_EVENT_KINDS}
    ok = res.success and (truth is None or truth.success)
    reason = res.reason if not res.success else (None if truth is None else truth.reason)
    params = {}
    if state.scenario_doc is not None:
        from bagit.common.params import merge_params
        from bagit.common.scenario import Scenario

        sc = Scenario.model_validate(state.scenario_doc)
        params = merge_params(sc.params, state.params).flat()
    return res.model_copy(update=dict(
        arms="cr5", success=ok, reason=reason, truth=truth, error_cm=truth.error_cm if truth is not None else res.error_cm,
        final_rim=points_list(final_rim) if final_rim is not None else res.final_rim, wall_s=round(wall_s, 3), arm_events=events,
        exact=_exact(sim_truth, args), inexact=list(sim_truth.inexact) if sim_truth is not None else [], recording=recording,
        provenance=provenance(params)))


def _exact(sim_truth: Any, args: argparse.Namespace) -> bool | None:
    """Lockstep: whether the simulator answered every step of the run in full (False without its final truth);
    None on the wall clock (a run there is never `bagit run`'s, bit for bit)."""
    if getattr(args, "clock", "lockstep") != "lockstep":
        return None
    return bool(sim_truth is not None and sim_truth.final and sim_truth.exact)


def _truth(up: Any, state: Any, stop: Any) -> tuple[Any, np.ndarray | None, Any]:
    """The run judged on the simulator's ground truth (`services.sim.judge`), the true rim at `n_x` points
    and the SimTruth it came from; (None, None, None) without a simulator (a real rig has no ground truth)."""
    import time

    from bagit.common.geometry import resample_closed
    from bagit.common.results import RunTruth
    from bagit.common.scenario import Scenario
    from bagit.services.planner.goal import bottom_frame
    from bagit.services.sim.judge import truth_of

    if up.truth is None or state.scenario_doc is None:
        return None, None, None
    deadline = time.monotonic() + 3.0
    # the world as the run ended (the simulator's final truth); a periodic sample of the run only if none comes
    while (t := up.final_truths.get(state.run_id)) is None:
        if time.monotonic() > deadline or stop.wait(0.05):
            t = up.truth.get()
            if t is not None and t.run_id == state.run_id:
                break
            return RunTruth(success=False, reason="no ground truth from the simulator for this run"), None, None
    scenario = Scenario.model_validate(state.scenario_doc)
    V = scenario.object.bottom_vertices()
    truth = truth_of(np.asarray(t.rim), t.passed_through, t.max_penetration_m, scenario, bottom_frame(V)[:3, 2],
                     realtime_factor=t.realtime_factor)
    return truth, resample_closed(np.asarray(t.rim), scenario.bag.n_x), t


def human(r: dict[str, Any]) -> str:
    if "stage_reached" in r:
        from bagit.common.results import RunResult

        return RunResult.model_validate(r).headline()
    return f"rig stopped after {r['wall_s']:.1f} s"
