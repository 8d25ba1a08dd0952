"""The deployed stack against the one-process run: each scenario and seed through `bagit up` (every
service its own process, on Zenoh, lockstep on the simulator's clock) and through `bagit run` (the
same parts in one process), and how their results compare.

Lockstep makes the deployed run the same computation as `bagit run`'s: the records say whether the two
agree bit for bit (ticks, simulated time, error, final rim), else by how much; the issue's bar is the
same success and an error within 0.2 cm. Each record is one (scenario, seed) pair with both
RunResults, appended to a JSONL as it finishes (a stopped sweep resumes); `bagit bench paper` puts
the summary in its table as the column "deployed stack", and `markdown` makes the full table.

    python -m bagit.bench.deployed [--only exp02,...] [--seeds 2] [--jsonl bench/results/deployed-vs-run.jsonl]
                                   [--speed 1000] [--controller mpc]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from bagit.common.headless import headless_gl
from bagit.common.logs import configure_logging
from bagit.common.names import CONTROLLER_NAMES, DEFAULT_CONTROLLER
from bagit.common.results import RunResult, provenance
from bagit.scenarios import list_scenarios

log = logging.getLogger("bagit.bench.deployed")

RESULTS = Path(__file__).resolve().parent / "results" / "deployed-vs-run.jsonl"
ERROR_TOLERANCE_CM = 0.2  # the issue's bar: the same success and an error within this of `bagit run`'s
UP_TIMEOUT_S = 900.0  # wall time one `bagit up` run may take (a loaded machine slows lockstep, never changes it)


def _last_json(text: str) -> dict[str, Any]:
    lines = [ln for ln in text.strip().splitlines() if ln.startswith("{")]
    if not lines:
        raise ValueError("no JSON result on stdout")
    return json.loads(lines[-1])


def cpu_per_service(stderr: str, prefix: str = "[up] cpu s: ") -> dict[str, float]:
    """The CPU seconds `bagit up` said each service used ('[up] cpu s: sim 12.3, perception 4.5, ...'); with
    prefix '[up] own cpu s: ', its own and its fork server's ('bagit up 1.2, fork server 0.6')."""
    line = next((ln for ln in reversed(stderr.splitlines()) if ln.startswith(prefix)), "")
    out = {}
    for item in line.removeprefix(prefix).split(", "):
        name, _, v = item.rpartition(" ")
        if name:
            out[name] = float(v)
    return out


def run_cost(stderr: str) -> dict[str, float] | None:
    """What `bagit up` said the run itself cost, the rig already up ('[up] the run: 12.34 s wall, 15.67 CPU s ...')."""
    m = re.search(r"^\[up\] the run: ([0-9.]+) s wall, ([0-9.]+) CPU s", stderr, re.MULTILINE)
    return {"wall_s": float(m.group(1)), "cpu_s": float(m.group(2))} if m else None


def deployed(scenario: str, seed: int, controller: str, speed: float | None) -> tuple[RunResult, float, dict[str, float]]:
    """`bagit up SCENARIO --exit-when-done --json` (lockstep, no dashboard), its wall time and CPU per service."""
    t0 = time.perf_counter()
    argv = [sys.executable, "-m", "bagit.cli", "up", scenario, "--exit-when-done", "--json", "--no-dashboard",
            "--seed", str(seed), "--controller", controller, "--timeout", f"{UP_TIMEOUT_S:g}"]
    argv += ["--speed", f"{speed:g}"] if speed else []
    r = subprocess.run(argv, capture_output=True, text=True, timeout=UP_TIMEOUT_S + 120,
                       env=headless_gl(dict(os.environ)))
    try:
        res = RunResult.model_validate(_last_json(r.stdout))
    except ValueError as e:
        res = RunResult(scenario=scenario, controller=controller, seed=seed, reason=f"bagit up gave no result ({e}): {r.stderr[-300:]}")
    return res, time.perf_counter() - t0, cpu_per_service(r.stderr)


def alone(scenario: str, seed: int, controller: str) -> tuple[RunResult, float]:
    """`bagit run`'s run of the same scenario and seed, in this process, and its wall time."""
    from bagit.common.scenario import Scenario
    from bagit.inprocess import RunOptions, run_inprocess
    from bagit.scenarios import find_scenario

    t0 = time.perf_counter()
    res = run_inprocess(RunOptions(scenario=Scenario.from_file(find_scenario(scenario)), name=scenario, controller=controller, seed=seed))
    return res, time.perf_counter() - t0


def compare(run: RunResult, up: RunResult) -> dict[str, Any]:
    """How the deployed run compares with the one-process run."""
    d_err = None if run.error_cm is None or up.error_cm is None else round(abs(run.error_cm - up.error_cm), 4)
    identical = (run.ticks, run.duration_s, run.error_cm, run.final_rim, run.arm_events) == (up.ticks, up.duration_s, up.error_cm, up.final_rim,
                                                                                          up.arm_events)
    return {"same_success": run.success == up.success, "d_error_cm": d_err, "identical": identical,
            "within": run.success == up.success and (d_err is not None and d_err <= ERROR_TOLERANCE_CM or not run.success)}


class Hogs:
    """`n` busy processes, one core's worth of work each, for as long as the `with` lasts: a loaded machine."""

    def __init__(self, n: int) -> None:
        self.n = n
        self.procs: list[subprocess.Popen[bytes]] = []

    def __enter__(self) -> Hogs:
        self.procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(self.n)]
        return self

    def __exit__(self, *exc: object) -> None:
        for p in self.procs:
            p.kill()
            p.wait()


def pair(scenario: str, seed: int, controller: str, speed: float | None, hogs: int = 0) -> dict[str, Any]:
    with Hogs(hogs):
        up, up_wall, cpu = deployed(scenario, seed, controller, speed)
    run, run_wall = alone(scenario, seed, controller)
    return {"scenario": scenario, "seed": seed, "controller": controller, **compare(run, up), "exact": up.exact,
            "run": run.model_dump(mode="json"), "up": up.model_dump(mode="json"),
            "wall_s": {"run": round(run_wall, 2), "up": round(up_wall, 2)}, "cpu_s_per_service": cpu, "load_avg": [round(v, 2) for v in os.getloadavg()],
            "effective": {"speed": speed, "clock": "lockstep", "hogs": hogs},
            "provenance": provenance(up.provenance.params if up.provenance else {}).model_dump(mode="json")}


def load(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    out = []
    for ln in path.read_text().splitlines():
        if ln.strip():
            out.append(json.loads(ln))
    return out


def summary(records: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per scenario: pairs, how many agree bit for bit, how many within the bar, the largest error difference."""
    out: dict[str, dict[str, Any]] = {}
    for r in records:
        s = out.setdefault(r["scenario"], {"pairs": 0, "identical": 0, "within": 0, "max_d_error_cm": 0.0})
        s["pairs"] += 1
        s["identical"] += bool(r["identical"])
        s["within"] += bool(r["within"])
        s["max_d_error_cm"] = max(s["max_d_error_cm"], r["d_error_cm"] or 0.0)
    return out


def markdown(records: list[dict[str, Any]]) -> str:
    """The full table: per scenario and seed, both runs side by side."""
    if not records:
        return "No deployed-stack records.\n"
    commits = sorted({(r["provenance"] or {}).get("commit", "?")[:10] for r in records})
    lines = ["# The deployed stack (`bagit up`, lockstep) against `bagit run`\n",
             f"{len(records)} pairs; commit(s) {', '.join(commits)}; host {records[0]['provenance'].get('host')} "
             f"({records[0]['provenance'].get('cpu')}, {records[0]['provenance'].get('cores')} cores).\n",
             "| scenario | seed | run: success | run: error cm | run: ticks | up: success | up: error cm | up: ticks | "
             "bit for bit | exact | within 0.2 cm | wall s run / up |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(records, key=lambda r: (r["scenario"], r["seed"])):
        a, b = r["run"], r["up"]
        lines.append(f"| {r['scenario']} | {r['seed']} | {a['success']} | {a['error_cm']} | {a['ticks']} | {b['success']} | "
                     f"{b['error_cm']} | {b['ticks']} | {'yes' if r['identical'] else 'no'} | {r.get('exact', '-')} | {'yes' if r['within'] else 'NO'} | "
                     f"{r['wall_s']['run']:.0f} / {r['wall_s']['up']:.0f} |")
    n, same, within = len(records), sum(r["identical"] for r in records), sum(r["within"] for r in records)
    wall = sum(r["wall_s"]["up"] for r in records) / max(sum(r["wall_s"]["run"] for r in records), 1e-9)
    lines += ["", f"Bit for bit: {same}/{n}; same success and error within {ERROR_TOLERANCE_CM} cm: {within}/{n}; "
              f"wall time of `bagit up` (process start-up included) / `bagit run`: {wall:.2f}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--only", default=None, help="comma-separated scenarios (default: all bundled)")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--controller", choices=CONTROLLER_NAMES, default=DEFAULT_CONTROLLER)
    p.add_argument("--speed", type=float, default=None, help="bagit up --speed (default none: lockstep as fast as the rig answers)")
    p.add_argument("--jsonl", type=Path, default=RESULTS)
    p.add_argument("--hogs", type=int, default=0, help="busy processes hogging the cores while `bagit up` runs (a loaded machine)")
    p.add_argument("--markdown", type=Path, default=None, help="write the table here (default: beside the JSONL, .md)")
    a = p.parse_args(argv)
    configure_logging()
    names = a.only.split(",") if a.only else [Path(s).stem for s in list_scenarios()]
    done = {(r["scenario"], r["seed"], r["controller"]) for r in load(a.jsonl)}
    a.jsonl.parent.mkdir(parents=True, exist_ok=True)
    for name in names:
        for seed in range(a.seeds):
            if (name, seed, a.controller) in done:
                continue
            rec = pair(name, seed, a.controller, a.speed, a.hogs)
            with a.jsonl.open("a") as f:
                f.write(json.dumps(rec) + "\n")
            log.info("%s s%d: run %s %.2f cm / up %s %.2f cm: %s", name, seed, rec["run"]["success"], rec["run"]["error_cm"] or -1,
                     rec["up"]["success"], rec["up"]["error_cm"] or -1, "bit for bit" if rec["identical"] else f"d {rec['d_error_cm']} cm")
    md = a.markdown or a.jsonl.with_suffix(".md")
    md.write_text(markdown(load(a.jsonl)))
    log.info("wrote %s", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
