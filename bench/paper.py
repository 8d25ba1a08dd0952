"""`bagit bench paper`: the paper's Tables I and II and its bagging-SOI statistics, measured here.

Planning (Table II): every experiment's scenario x planner x seed, planned from the scenario's g0
(the paper's planning columns do not involve the arms). Bagging SOI (section VII-A): random, tilted
placements of twelve bottom shapes. Manipulation (Tables I and II) comes from closed-loop runs
(`bagit run`, `bench/closed_loop.py`) read from JSON/JSONL files; experiments or controllers with
no runs are reported as "not run", never filled in.

    python -m bagit.bench.paper [--quick] [--seeds N] [--reuse paper.json] [--closed-loop F] [--out DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bagit.bench import paper_data as P
from bagit.bench.common import RESULTS_DIR, machine, write_results
from bagit.bench.deployed import load as load_deployed
from bagit.bench.deployed import summary as deployed_summary
from bagit.common.errors import BagItError
from bagit.common.geometry import rpy_to_matrix
from bagit.common.scenario import Scenario
from bagit.scenarios import list_scenarios

QUICK_SCENARIOS = ["exp01", "exp06", "exp11"]  # a box, a tilted object, a bound one
FIGURE_DIR = "paper"


def scenarios(quick: bool) -> list[Path]:
    """The experiments' scenarios (exp01..exp12) and the obstacle layouts of Fig. 7(c)."""
    allp = list_scenarios()
    if quick:
        return [p for p in allp if p.stem[:5] in QUICK_SCENARIOS]
    return allp


# ---------------------------------------------------------------- planning (Table II)


def measure_planning(paths: list[Path], seeds: int, planners: list[str] = P.PLANNERS) -> list[dict[str, Any]]:
    """One record per scenario x planner x seed: success, time, iterations, path length, reason."""
    from bagit.services.planner import plan_scenario

    records = []
    for path in paths:
        s = Scenario.from_file(path)
        for planner in planners:
            t0 = time.perf_counter()
            for seed in range(seeds):
                try:
                    r = plan_scenario(s, planner, seed)
                    rec = {"success": r.success, "time_s": r.time_s, "iterations": r.iterations, "reason": r.reason,
                           "path_length_m": r.path_length() if r.success else None, "nodes": len(r.path)}
                except BagItError as e:  # a scenario the planner refuses is a failure with its reason
                    rec = {"success": False, "time_s": 0.0, "iterations": 0, "reason": str(e), "path_length_m": None, "nodes": 0}
                records.append({"scenario": path.stem, "planner": planner, "seed": seed, **rec})
            print(f"[paper] planning {path.stem} {planner}: {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    return records


def planning_summary(records: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """scenario -> planner -> success / of / time mean, std, median (over the successful plans)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for rec in records:
        out.setdefault(rec["scenario"], {}).setdefault(rec["planner"], {"runs": []})["runs"].append(rec)
    for row in out.values():
        for cell in row.values():
            runs = cell.pop("runs")
            t = np.array([r["time_s"] for r in runs if r["success"]])
            cell.update(
                success=int(sum(r["success"] for r in runs)),
                of=len(runs),
                time_mean_s=float(t.mean()) if t.size else None,
                time_std_s=float(t.std()) if t.size else None,
                time_median_s=float(np.median(t)) if t.size else None,
                time_max_s=float(t.max()) if t.size else None,
                failures=sorted({r["reason"] for r in runs if not r["success"] and r["reason"]}),
            )
    return out


# ---------------------------------------------------------------- bagging SOI (section VII-A)


SCALE_RANGE = (0.75, 1.6)  # each placement's size against bench.goal's outline (the largest do not fit the bag)


def measure_placements(n: int, seed: int = 0, scale_range: tuple[float, float] = SCALE_RANGE) -> list[dict[str, Any]]:
    """n random placements cycling over the twelve shapes of `bench.goal`, tilted up to 20 degrees, turned
    and moved at random, and scaled by a random factor in `scale_range`: the goal is computed in the
    bottom frame, so pose alone would give each shape the same c1 every time."""
    from bagit.bench.goal import R, shapes
    from bagit.services.planner import bagging_soi

    rng = np.random.default_rng(seed)
    outlines = shapes()
    names = list(outlines)
    records = []
    for k in range(n):
        name = names[k % len(names)]
        scale = float(rng.uniform(*scale_range))
        xy = outlines[name] * scale
        rpy = [rng.uniform(-0.35, 0.35), rng.uniform(-0.35, 0.35), rng.uniform(-np.pi, np.pi)]
        Rm = rpy_to_matrix(rpy)
        v = np.column_stack([xy, np.zeros(len(xy))]) @ Rm.T + rng.uniform([-0.1, -0.1, 0.4], [0.1, 0.1, 0.6])
        tilt = float(np.degrees(np.arccos(np.clip(Rm[2, 2], -1, 1))))
        rec: dict[str, Any] = {"shape": name, "tilt_deg": round(tilt, 2), "scale": round(scale, 4)}
        t0 = time.perf_counter()
        try:
            g = bagging_soi(v, R, 32)
        except BagItError as e:
            records.append({**rec, "valid": False, "reason": str(e)})
            continue
        rec.update(valid=True, time_ms=(time.perf_counter() - t0) * 1e3, c1=g.c1, c2=g.c2, c3=g.c3, c3_applied=g.c3_applied,
                   a=g.ellipse.a, b=g.ellipse.b)
        records.append(rec)
    return records


def placement_summary(records: list[dict[str, Any]]) -> dict[str, Any]:
    """Mean c1, c2, c3 overall (c3 over the shapes that have a principal axis), per shape, tilted or not."""
    ok = [r for r in records if r["valid"]]

    def stats(rs: list[dict[str, Any]]) -> dict[str, Any]:
        c3 = [r["c3"] for r in rs if r["c3_applied"]]
        return {
            "n": len(rs),
            "c1_mean": float(np.mean([r["c1"] for r in rs])) if rs else None,
            "c1_max": float(np.max([r["c1"] for r in rs])) if rs else None,
            "c2_mean": float(np.mean([r["c2"] for r in rs])) if rs else None,
            "c3_mean": float(np.mean(c3)) if c3 else None,
            "c3_n": len(c3),
        }

    per_shape = {name: stats([r for r in ok if r["shape"] == name]) for name in dict.fromkeys(r["shape"] for r in records)}
    t = [r["time_ms"] for r in ok]
    return {
        "placements": len(records),
        "shapes": len(per_shape),
        "valid": len(ok),
        "infeasible": sorted({r["reason"].split(";")[0] for r in records if not r["valid"]})[:3],
        "all": stats(ok),
        "tilted_over_10deg": stats([r for r in ok if r["tilt_deg"] > 10]),
        "per_shape": per_shape,
        "time_ms_median": float(np.median(t)) if t else None,
    }


# ---------------------------------------------------------------- manipulation (closed-loop files)


def _run_key(r: dict[str, Any]) -> tuple[str, str, str, int, str]:
    """scenario, controller, planner, seed, arms (a record of before the arms were in every run: ideal)."""
    return (str(r["scenario"]), str(r.get("controller", "mpc")), str(r.get("planner", "cbirrt")), int(r.get("seed", 0)),
            str(r.get("arms") or "ideal"))


def load_closed_loop(files: list[Path]) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(per-run records, already aggregated rows) from JSONL (one run per line) or JSON files
    (`{"runs": [...]}` or `bench.closed_loop`'s `{"rows": [...]}`). A later run of the same
    scenario/controller/planner/seed replaces an earlier one."""
    runs: dict[tuple[str, str, str, int, str], dict[str, Any]] = {}
    rows: list[dict[str, Any]] = []
    for f in files:
        try:
            text = Path(f).read_text()
        except OSError as e:
            raise ValueError(f"cannot read closed-loop results {f}: {e}") from None
        try:
            if str(f).endswith(".jsonl"):
                items = [json.loads(line) for line in text.splitlines() if line.strip()]
            else:
                doc = json.loads(text)
                items = doc.get("runs", []) if isinstance(doc, dict) else doc
                rows += [dict(r, source=str(f)) for r in (doc.get("rows", []) if isinstance(doc, dict) else [])]
        except json.JSONDecodeError as e:
            raise ValueError(f"closed-loop results {f} are not valid JSON: {e}") from None
        for r in items:
            if not isinstance(r, dict) or "scenario" not in r or "success" not in r:
                raise ValueError(f"closed-loop results {f}: a record without scenario/success: {str(r)[:80]}")
            runs[_run_key(r)] = dict(r, source=Path(f).name)
    return list(runs.values()), rows


IDEAL = "/ideal"  # the method's label suffix for runs with floating grippers (the ablation)


def method_of(controller: str, planner: str, arms: str = "cr5") -> str:
    """The Table II row a run belongs to: the controller's name, or mpc+<planner> for the planner baselines;
    with `/ideal` for runs without the arms."""
    return (controller if planner == "cbirrt" else f"{controller}+{planner}") + ("" if arms == "cr5" else IDEAL)


def manipulation_summary(runs: list[dict[str, Any]], rows: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, Any]]]:
    """scenario -> method -> success / of / error and time (mean, std over successful runs)."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in runs:
        sc, ctrl, planner, _, arms = _run_key(r)
        groups.setdefault((sc, method_of(ctrl, planner, arms)), []).append(r)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for (sc, method), rs in sorted(groups.items()):
        ok = [r for r in rs if r["success"]]
        err = [r["error_cm"] for r in ok if r.get("error_cm") is not None]
        dur = [r["duration_s"] for r in ok if r.get("duration_s") is not None]
        wall = [r["wall_s"] for r in rs if r.get("wall_s")]
        events: dict[str, int] = {}
        for r in rs:
            for k, v in (r.get("arm_events") or {}).items():
                events[k] = events.get(k, 0) + int(v)
        out.setdefault(sc, {})[method] = {
            "success": len(ok),
            "of": len(rs),
            "seeds": sorted(int(r.get("seed", 0)) for r in rs),
            "error_cm_mean": float(np.mean(err)) if err else None,
            "error_cm_std": float(np.std(err)) if err else None,
            "time_s_mean": float(np.mean(dur)) if dur else None,
            "time_s_std": float(np.std(dur)) if dur else None,
            "wall_s_mean": float(np.mean(wall)) if wall else None,
            "arm_events": events,
            "commits": sorted({(r.get("provenance") or {}).get("commit") or "?" for r in rs}),
            "failures": sorted({(f"{r['stage_reached']}: " if r.get("stage_reached") else "") + str(r.get("reason")) for r in rs if not r["success"]}),
            "sources": sorted({r["source"] for r in rs}),
        }
    for row in rows:  # aggregated rows only where no per-run records exist
        method = method_of(row.get("controller", "mpc"), row.get("planner", "cbirrt"))
        if method in out.get(row["scenario"], {}):
            continue

        def num(k: str, row: dict = row) -> float | None:
            v = row.get(k)
            return None if v is None or not np.isfinite(v) else float(v)

        out.setdefault(row["scenario"], {})[method] = {
            "success": int(row["success"]), "of": int(row["of"]), "seeds": None,
            "error_cm_mean": num("error_cm_mean"), "error_cm_std": num("error_cm_std"),
            "time_s_mean": num("time_s_mean"), "time_s_std": None, "wall_s_mean": None, "arm_events": {}, "commits": ["?"],
            "failures": row.get("failures", []), "sources": [Path(row["source"]).name],
        }
    return out


def same_runs_as_mpc(runs: list[dict[str, Any]]) -> dict[str, list[int]]:
    """method -> [runs identical to mpc's (same scenario and seed: same ticks and error), runs compared].

    Why: where every planner's trimmed, smoothed path is the same (no obstacle between g0 and g†),
    MPC along it is the same run, so those rows add no evidence about the planners; the report says so."""
    keyed = [(_run_key(r), r) for r in runs]
    mpc = {(sc, seed, arms): r for (sc, ctrl, planner, seed, arms), r in keyed if method_of(ctrl, planner) == "mpc"}
    out: dict[str, list[int]] = {}
    for (sc, ctrl, planner, seed, arms), r in keyed:
        method = method_of(ctrl, planner, arms)
        ref = mpc.get((sc, seed, arms))
        if not method.startswith("mpc+") or ref is None:
            continue
        same = r.get("ticks") == ref.get("ticks") and r.get("error_cm") == ref.get("error_cm") and r["success"] == ref["success"]
        k = out.setdefault(method, [0, 0])
        k[0] += int(same)
        k[1] += 1
    return out


def find_closed_loop(out_dir: Path) -> list[Path]:
    """Closed-loop result files kept next to the report: closed-loop*.jsonl / closed-loop*.json."""
    return sorted(p for p in out_dir.glob("closed-loop*.json*") if p.suffix in (".json", ".jsonl"))


# ---------------------------------------------------------------- the whole benchmark


DEPLOYED_FILE = "deployed-vs-run.jsonl"  # bagit.bench.deployed's records


def run(
    quick: bool = False,
    seeds: int | None = None,
    reuse: Path | None = None,
    closed_loop: list[Path] | None = None,
    out_dir: Path | None = None,
    placements: int | None = None,
    figures: bool = True,
) -> dict[str, Any]:
    """Measure (or reuse, from an earlier paper.json) the planning runs, measure the placements, read the
    closed-loop runs, and write paper.md/json and the figures. A quick or partial run (`quick`, fewer seeds or
    placements) writes beside the published report, in `quick/` under the results folder, never over it."""
    from bagit.bench.paper_report import markdown

    partial = quick or (seeds is not None and seeds < 10) or (placements is not None and placements < 1000)
    out = Path(out_dir) if out_dir else (RESULTS_DIR / "quick" if partial else RESULTS_DIR)
    n_seeds = seeds or (3 if quick else 10)
    if n_seeds < 1:
        raise ValueError(f"--seeds must be at least 1, got {n_seeds}")
    n_place = placements or (100 if quick else 1000)
    old: dict[str, Any] = {}
    if reuse is not None:
        try:
            old = json.loads(Path(reuse).read_text())
        except (OSError, json.JSONDecodeError) as e:
            raise ValueError(f"cannot reuse {reuse}: {e}") from None
        if not old.get("planning_runs"):
            raise ValueError(f"{reuse} is not a `bagit bench paper` result (no planning_runs)")
    load_start = os.getloadavg()
    t0 = time.perf_counter()
    paths = scenarios(quick)
    plan_runs = old.get("planning_runs") or measure_planning(paths, n_seeds)
    t_plan = time.perf_counter() - t0
    place_runs = measure_placements(n_place)  # cheap and seeded: always measured afresh
    cl_files = list(closed_loop) if closed_loop is not None else find_closed_loop(Path(out_dir) if out_dir else RESULTS_DIR)
    cl_runs, cl_rows = load_closed_loop(cl_files)
    result: dict[str, Any] = {
        "machine": machine(),
        "quick": quick,
        "seeds": max((r["seed"] for r in plan_runs), default=-1) + 1,
        "reused": str(reuse) if reuse else None,
        "planning_wall_s": old.get("planning_wall_s", t_plan),
        # planning times are wall-clock: the machine's load while they were taken (1, 5, 15 min averages)
        "planning_measured": old.get("planning_measured") or (old["machine"]["when"] if old else None),
        "planning_commit": old.get("planning_commit") if old else machine().get("commit"),  # the code that planned
        "planning_load_avg": old.get("planning_load_avg") if old else [round(v, 2) for v in (*load_start, *os.getloadavg())],
        "planning": planning_summary(plan_runs),
        "placements": placement_summary(place_runs),
        "manipulation": manipulation_summary(cl_runs, cl_rows),
        "manipulation_same_as_mpc": same_runs_as_mpc(cl_runs),
        "deployed": deployed_summary(load_deployed(out / DEPLOYED_FILE)),  # `bagit up` against `bagit run`, per scenario
        "closed_loop_files": [str(f) for f in cl_files],
        "paper": {"planning": P.PLANNING, "manipulation": P.MANIPULATION, "table1": P.TABLE1, "soi": P.SOI_STATS},
        "planning_runs": plan_runs,
        "placement_runs": place_runs,
    }
    figs: list[str] = []
    if figures:
        from bagit.bench.paper_figures import draw_all

        figs = [str(p.relative_to(out)) for p in draw_all(result, out / FIGURE_DIR)]
    result["figures"] = figs
    jp, mp = write_results("paper", result, markdown(result), out)
    result["files"] = {"json": str(jp), "markdown": str(mp)}
    return result


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=int, default=None)
    ap.add_argument("--reuse", type=Path, default=None)
    ap.add_argument("--closed-loop", type=Path, action="append", default=None)
    ap.add_argument("--out", type=Path, default=None)
    a = ap.parse_args()
    r = run(a.quick, a.seeds, a.reuse, a.closed_loop, a.out)
    print(Path(r["files"]["markdown"]).read_text())


if __name__ == "__main__":
    main()
