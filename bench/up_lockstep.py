"""`bagit up` in lockstep against `bagit run`, side by side: the same run, its wall time and its CPU.

    python -m bagit.bench.up_lockstep [--scenario exp02] [--seed 0] [--no-dashboard] [--no-fork-server] [--hogs N] [--pairs N] [--record] [--json]

Both commands run as child processes of this one, one after the other, on the same machine:

1. `bagit run SCENARIO --json`: the whole rig in one process. Wall time from launch to exit; CPU
   (user + system) from the kernel's accounting of the child.
2. `bagit up SCENARIO --exit-when-done --json` in lockstep (the default), with every service and the
   dashboard: wall time from launch to exit; CPU of the whole process tree (`bagit up` and every
   service it started and reaped), and per service over its life (its `[up] cpu s:` line), per
   simulated second of the run, and `bagit up`'s own and its fork server's (the imports the services
   share; `--no-fork-server`: every service an interpreter of its own, as before). Also the run alone, as a standing rig pays it: from its start to
   its end, wall and CPU of every service and `bagit up` (its `[up] the run:` line); six
   interpreters starting and stopping are the rest. Its wall time is set against `bagit run`'s
   whole process and against `bagit run`'s own run (its `wall_s`: from building the world to the
   end, no interpreter start or imports), run against run.

The record says whether the two runs are bit for bit (ticks, simulated time, error, final rim, arm
events) and that `bagit up`'s is exact, and gives the ratios up / run of wall time and CPU (the
goals: <= 1.1 and <= 1.3). `--hogs N` keeps N busy processes on the cores for the whole measurement
(a loaded machine: the result must not change, only the time). Every record names the commit,
host, CPU, load before and after, and the effective parameters.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import resource
import subprocess
import sys
import time
from typing import Any

from bagit.common.headless import headless_gl
from bagit.common.logs import configure_logging

log = logging.getLogger("bagit.bench.up_lockstep")

GOAL_WALL_RATIO = 1.1
GOAL_CPU_RATIO = 1.3
SAME = ("success", "ticks", "duration_s", "error_cm", "final_rim", "arm_events")  # what "bit for bit" compares


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def _timed(argv: list[str], timeout_s: float) -> tuple[dict[str, Any], str, float, float, int]:
    """Run `argv` to its end: its JSON result (the last line of stdout starting with '{'), its stderr, wall s,
    CPU s of it and every descendant it reaped, and its exit code."""
    env = headless_gl(dict(os.environ))
    cpu0, t0 = _children_cpu_s(), time.perf_counter()
    r = subprocess.run(argv, capture_output=True, text=True, timeout=timeout_s, env=env)
    wall, cpu = time.perf_counter() - t0, _children_cpu_s() - cpu0
    lines = [ln for ln in r.stdout.splitlines() if ln.startswith("{")]
    return (json.loads(lines[-1]) if lines else {}), r.stderr, wall, cpu, r.returncode


def measure(scenario: str = "exp02", seed: int = 0, dashboard: bool = True, hogs: int = 0, timeout_s: float = 900.0,
            fork_server: bool = True) -> dict[str, Any]:
    """`bagit run` then `bagit up` (lockstep) of one scenario and seed, measured (see the module doc)."""
    from bagit.bench.common import compile_bagit, machine
    from bagit.bench.deployed import Hogs, cpu_per_service, run_cost

    compile_bagit()  # both measured with their bytecode, as installed: neither compiles its imports again
    cli = [sys.executable, "-m", "bagit.cli"]
    out: dict[str, Any] = {"machine": machine(), "load_before": [round(x, 2) for x in os.getloadavg()]}
    out["params"] = {"scenario": scenario, "seed": seed, "clock": "lockstep", "dashboard": dashboard, "hogs": hogs,
                     "speed": "as fast as the rig answers (no --speed)", "fork_server": fork_server,
                     "bytecode": "compiled before measuring"}
    with Hogs(hogs):  # their CPU is not counted: they are reaped after the measurement
        run, _, run_wall, run_cpu, run_code = _timed([*cli, "run", scenario, "--seed", str(seed), "--json"], timeout_s)
        up_argv = [*cli, "up", scenario, "--seed", str(seed), "--exit-when-done", "--json", "--timeout", f"{timeout_s:g}"]
        up_argv += ([] if dashboard else ["--no-dashboard"]) + ([] if fork_server else ["--no-fork-server"])
        up, up_err, up_wall, up_cpu, up_code = _timed(up_argv, timeout_s + 60)
    out["load_after"] = [round(x, 2) for x in os.getloadavg()]
    sim_s = float(run.get("duration_s") or 0.0)
    per_service = cpu_per_service(up_err)
    out["run"] = {"exit": run_code, "wall_s": round(run_wall, 2), "cpu_s": round(run_cpu, 2), "result": {k: run.get(k) for k in SAME[:4]},
                  "run_wall_s": run.get("wall_s")}  # its own run: from building the world to the end (no interpreter, no imports)
    out["up"] = {"exit": up_code, "wall_s": round(up_wall, 2), "cpu_s": round(up_cpu, 2), "exact": up.get("exact"),
                 "inexact": up.get("inexact"), "cpu_s_per_service": per_service,
                 "own_cpu_s": cpu_per_service(up_err, "[up] own cpu s: "), "result": {k: up.get(k) for k in SAME[:4]},
                 "realtime_factor": (up.get("truth") or {}).get("realtime_factor")}
    if sim_s > 0:
        out["up"]["cpu_s_per_sim_s"] = {k: round(v / sim_s, 3) for k, v in per_service.items()}
    out["up"]["the_run"] = run_cost(up_err)  # the rig already up: from the run's start to its end
    out["bit_for_bit"] = bool(run) and bool(up) and all(run.get(k) == up.get(k) for k in SAME)
    out["ratio"] = {"wall": round(up_wall / run_wall, 3) if run_wall > 0 else None, "cpu": round(up_cpu / run_cpu, 3) if run_cpu > 0 else None}
    if out["up"]["the_run"] and run_wall > 0 and run_cpu > 0:  # a standing rig's run against a `bagit run` from the shell
        out["ratio_the_run"] = {"wall": round(out["up"]["the_run"]["wall_s"] / run_wall, 3), "cpu": round(out["up"]["the_run"]["cpu_s"] / run_cpu, 3)}
        if run.get("wall_s"):  # run against run: neither pays for starting interpreters
            out["ratio_the_run"]["wall_run_to_run"] = round(out["up"]["the_run"]["wall_s"] / float(run["wall_s"]), 3)
    out["goal"] = goals(out, up.get("exact") is True)
    return out


def measure_pairs(pairs: int, **kw: Any) -> dict[str, Any]:
    """`measure` `pairs` times (each `bagit run`, then `bagit up`, so the two alternate): this machine's run-to-run
    spread (+-10 % in wall and CPU on an idle 2-core VM) is larger than the differences measured. The record is
    the pair whose CPU ratio is the median, with every pair's ratios under `pairs` and their medians, which the
    goals are judged by; bit for bit only if every pair is."""
    import statistics

    rs = [measure(**kw) for _ in range(pairs)]
    if pairs == 1:
        return rs[0]
    med = sorted(rs, key=lambda r: r["ratio"]["cpu"] or 0.0)[pairs // 2]
    out = dict(med)
    out["pairs"] = [{"ratio": r["ratio"], "ratio_the_run": r.get("ratio_the_run"), "run": {k: r["run"][k] for k in ("wall_s", "cpu_s")},
                     "up": {k: r["up"][k] for k in ("wall_s", "cpu_s")}, "bit_for_bit": r["bit_for_bit"]} for r in rs]
    for key in ("ratio", "ratio_the_run"):
        if all(r.get(key) for r in rs):
            out[key] = {k: round(statistics.median(r[key][k] for r in rs), 3) for k in med[key] if all(r[key].get(k) is not None for r in rs)}
    out["bit_for_bit"] = all(r["bit_for_bit"] for r in rs)
    out["load_before"], out["load_after"] = rs[0]["load_before"], rs[-1]["load_after"]
    out["params"] = {**med["params"], "pairs": pairs}
    out["goal"] = goals(out, all(r["up"].get("exact") is True for r in rs))
    return out


def goals(r: dict[str, Any], exact: bool) -> dict[str, bool]:
    """Which goals a record meets: bit for bit and exact; the wall and CPU ratios over the rig's whole life
    (six interpreters started and stopped included) and for the run alone (a standing rig)."""
    def within(ratio: dict[str, Any] | None, key: str, goal: float) -> bool:
        return ratio is not None and ratio.get(key) is not None and ratio[key] <= goal

    whole, alone = r.get("ratio"), r.get("ratio_the_run")
    return {"bit_for_bit": bool(r.get("bit_for_bit")) and exact,
            "wall_ratio": within(whole, "wall", GOAL_WALL_RATIO), "cpu_ratio": within(whole, "cpu", GOAL_CPU_RATIO),
            "wall_ratio_the_run": within(alone, "wall", GOAL_WALL_RATIO), "cpu_ratio_the_run": within(alone, "cpu", GOAL_CPU_RATIO)}


def per_sim_second(fps: float = 10.0, scenario: str = "exp02", seed: int = 0) -> dict[str, Any]:
    """CPU s per simulated s of each service while the arms servo, in lockstep and on the wall clock, both with
    the camera at `fps` (`bench.up_wall.measure`): lockstep's waits must cost no more than the wall clock's pace."""
    from bagit.bench import up_wall

    out: dict[str, Any] = {"fps": fps}
    for clock in ("lockstep", "wall"):
        r = up_wall.measure(scenario, seed, clock=clock, fps=fps)
        out[clock] = {"cpu_s_per_sim_s": r.get("cpu_s_per_sim_s", {}), "servo": r.get("servo", {}), "run": r["run"],
                      "load": [r["load_before"], r["load_after"]]}
    return out


def run(quick: bool = False) -> dict[str, Any]:
    """`bagit bench stages --only up_lockstep`: exp02, seed 0, with the dashboard, against `bagit run`; and
    (unless quick) CPU per simulated second per service in lockstep and on the wall clock at 10 frames/s."""
    r = measure("exp02", 0)
    if not quick:
        r["per_sim_second_at_10fps"] = per_sim_second()
    return r


def markdown(r: dict[str, Any]) -> str:
    """A table from a record of `measure`."""
    from bagit.bench.common import metric_table

    a, b = r["run"], r["up"]
    rows = [
        ("`bagit run`: wall s, CPU s" + (" (the median pair's)" if r.get("pairs") else ""), f"{a['wall_s']}, {a['cpu_s']}"),
        ("`bagit up` (lockstep): wall s, CPU s", f"{b['wall_s']}, {b['cpu_s']}"),
        ("up / run: wall, CPU" + (f" (the median of {len(r['pairs'])} pairs)" if r.get("pairs") else ""),
         f"{r['ratio']['wall']}, {r['ratio']['cpu']} (goals <= {GOAL_WALL_RATIO}, <= {GOAL_CPU_RATIO})"),
        *([("each pair's up / run: wall, CPU", "; ".join(f"{x['ratio']['wall']}, {x['ratio']['cpu']}" for x in r["pairs"]))] if r.get("pairs") else []),
        ("the run alone, the rig already up: wall s, CPU s", "" if not b.get("the_run") else f"{b['the_run']['wall_s']}, {b['the_run']['cpu_s']}"),
        ("the run alone / `bagit run`: wall, CPU", "" if not r.get("ratio_the_run") else f"{r['ratio_the_run']['wall']}, {r['ratio_the_run']['cpu']}"),
        ("`bagit run`'s own run (world built to the end, its `wall_s`) and the run alone / it: wall s, ratio",
         "" if not (r.get("ratio_the_run") or {}).get("wall_run_to_run") else f"{a.get('run_wall_s')}, {r['ratio_the_run']['wall_run_to_run']}"),
        ("bit for bit, exact", f"{r['bit_for_bit']}, {b['exact']}" + (f" ({'; '.join(b['inexact'])})" if b.get("inexact") else "")),
        ("CPU s per service (whole life)", ", ".join(f"{k} {v:.1f}" for k, v in b["cpu_s_per_service"].items())),
        ("CPU s of `bagit up` itself and of its fork server (whole life)", ", ".join(f"{k} {v:.1f}" for k, v in b.get("own_cpu_s", {}).items())),
        ("CPU s per simulated s per service", ", ".join(f"{k} {v:.2f}" for k, v in b.get("cpu_s_per_sim_s", {}).items())),
        ("real-time factor of the up run", b.get("realtime_factor")),
        ("goals met", ", ".join(f"{k} {'yes' if v else 'no'}" for k, v in r["goal"].items())),
    ]
    for clock, x in r.get("per_sim_second_at_10fps", {}).items():
        if isinstance(x, dict):
            cpu = x.get("cpu_s_per_sim_s", {})
            rows.append((f"CPU s per simulated s while servoing, {clock}, 10 frames/s", ", ".join(f"{k} {v:.3f}" for k, v in cpu.items())))
    return metric_table("`bagit up` in lockstep against `bagit run`", r, rows)


def main(argv: list[str] | None = None) -> int:
    from bagit.bench.common import write_results

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenario", default="exp02")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-dashboard", action="store_true")
    ap.add_argument("--no-fork-server", action="store_true", help="`bagit up --no-fork-server`: every service an interpreter of its own")
    ap.add_argument("--hogs", type=int, default=0, help="busy processes on the cores while measuring")
    ap.add_argument("--pairs", type=int, default=1, help="measure this many times, run and up alternating; the ratios are the medians (default 1)")
    ap.add_argument("--json", action="store_true", help="print the record as JSON")
    ap.add_argument("--record", action="store_true", help="write bench/results/up-lockstep-<time>.json and .md")
    ap.add_argument("--per-sim-second", action="store_true", help="also CPU per simulated second per service, lockstep and wall, at 10 frames/s")
    a = ap.parse_args(argv)
    configure_logging()
    if a.pairs < 1:
        ap.error("--pairs must be >= 1")
    r = measure_pairs(a.pairs, scenario=a.scenario, seed=a.seed, dashboard=not a.no_dashboard, hogs=a.hogs, fork_server=not a.no_fork_server)
    if a.per_sim_second:
        r["per_sim_second_at_10fps"] = per_sim_second(scenario=a.scenario, seed=a.seed)
    md = markdown(r)
    if a.record:
        jp, mdp = write_results(f"up-lockstep-{time.strftime('%Y%m%d-%H%M%S')}", r, md)
        log.info("written: %s, %s", jp, mdp)
    print(json.dumps(r, indent=2) if a.json else md)
    return 0 if r["goal"]["bit_for_bit"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
