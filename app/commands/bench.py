"""`bagit bench`: measure every stage (`stages`), reproduce the paper's tables (`paper`), run closed-loop sweeps
(`sweep`, locally or on a Dask cluster), compare the deployed stack with `bagit run` (`deployed`), re-run issue 25's findings
(`probes`), re-run a sample of a record file and test it against the record (`verify`), compare runs (`compare`), run
bags of other fabrics, sizes, colours and light (`zoo`), split the rig over network namespaces as over lab machines (`multihost`),
train the BimaManip baseline's SOI dynamics or measure its held-out error (`bimamanip`)."""

from __future__ import annotations

import argparse
import importlib
import json
import logging
import time
from pathlib import Path
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.bench")

NAME = "bench"
HELP = ("run the benchmarks: `stages`, `paper`, `sweep` (closed-loop runs), `deployed` (bagit up against bagit run), "
        "`probes` (issue 25's findings re-run), `verify RECORDS` (re-run a sample of a record file: bit for bit? the same distribution?), "
        "`zoo` (bags of other fabrics, sizes, colours, light), `multihost` (the rig split over network namespaces, as root), "
        "`bimamanip` (the BimaManip baseline's learned SOI dynamics: its held-out error, or --train), or `compare OLD NEW`")

# The stage benchmarks, each a module under bagit.bench with `run(quick: bool) -> dict`.
STAGES = ["perception", "goal", "planner", "controller", "arm_driver", "stop_time", "cr5", "sim", "zenoh", "recorder", "latency", "up_wall", "up_lockstep",
          "camera_modes"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.bench.closed_loop import add_sweep_arguments
    from bagit.bench.verify import add_verify_arguments

    p.add_argument("what", choices=["stages", "paper", "sweep", "deployed", "probes", "verify", "compare", "zoo", "multihost", "bimamanip"],
                   help="which benchmark")
    p.add_argument("files", nargs="*", help="for `compare`: OLD.json NEW.json; for `verify`: the record files (.jsonl)")
    p.add_argument("--quick", action="store_true", help="a small subset (minutes), for CI smoke tests")
    p.add_argument("--only", action="append", default=None,
                   help="stage(s) to run, e.g. --only planner; for `sweep`: scenarios whose names start so, e.g. exp01,exp02; "
                   "for `probes`: group(s), v4 cli recorder arm; for `multihost`: the scenario (default exp02)")
    p.add_argument("--no-doc", action="store_true", help="for `probes`: leave the probe section of docs/testing.md as it is")
    p.add_argument("--out", type=Path, default=None, help="results folder (default bench/results)")
    p.add_argument("--seeds", type=_args.positive_int, default=None, help="for `paper`: seeds per experiment and planner (default 10; --quick 3); "
                   "for `sweep`: seeds per scenario, controller, planner and arms (default 8; --quick 1)")
    p.add_argument("--reuse", type=Path, default=None, help="for `paper`: take planning and placements from this paper.json")
    p.add_argument(
        "--closed-loop", type=Path, action="append", default=None,
        help="for `paper`: closed-loop results (.jsonl runs or .json); default: closed-loop*.json[l] in the results folder",
    )
    p.add_argument("--bags", type=_args.positive_int, default=None, help="for `zoo`: bags to draw (default 100; --quick 4)")
    p.add_argument("--zoo-seed", type=_args.seed, default=0, help="for `zoo`: bag i is drawn from (zoo seed, i)")
    p.add_argument("--record", action="store_true", help="for `zoo`: write the runs and the report under bench/results (or --out)")
    p.add_argument("--zoo-set", choices=["core", "envelope"], default="core",
                   help="for `zoo`: the core ranges (a lab's ordinary bags) or the envelope (to find where BagIt stops)")
    p.add_argument("--perception", action="store_true",
                   help="for `zoo`: measure perception's SOI against the true rim on each bag's first frames (no run)")
    p.add_argument("--write-bag", default=None, metavar="NAME",
                   help="for `zoo`: write the zoo bag NAME (zoo-<set>-<seed>-<i>) as a scenario file NAME.yaml in --out (default .), run nothing")
    p.add_argument("--train", action="store_true",
                   help="for `bimamanip`: simulate the data and train the model, writing its weights and record (services/controller/data/)")
    add_sweep_arguments(p)
    add_verify_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.bench.common import machine, write_results

    if args.what == "compare":
        if len(args.files) != 2:
            raise ValueError("bench compare needs two result files: OLD.json NEW.json")
        return compare(Path(args.files[0]), Path(args.files[1]))
    if args.what == "deployed":
        from bagit.bench import deployed

        argv = ["--only", ",".join(args.only)] if args.only else []
        argv += ["--seeds", str(args.seeds or (1 if args.quick else 2))]
        if args.out is not None:
            argv += ["--jsonl", str(Path(args.out) / "deployed-vs-run.jsonl")]
        code = deployed.main(argv)
        return {"success": code == 0}
    if args.what == "probes":
        from bagit.bench import probes

        unknown = sorted(set(args.only or []) - set(probes.RUNNERS))
        if unknown:
            raise ValueError(f"unknown probe group(s) {unknown}; choose from {list(probes.RUNNERS)}")
        return probes.run(args.only, doc=not args.no_doc)
    if args.what == "paper":
        from bagit.bench import paper

        return paper.run(quick=args.quick, seeds=args.seeds, reuse=args.reuse, closed_loop=args.closed_loop, out_dir=args.out)
    if args.what == "sweep":
        from bagit.bench import closed_loop

        return closed_loop.run_from_args(args)
    if args.what == "zoo":
        from bagit.bench import zoo

        return zoo.run_from_args(args)
    if args.what == "multihost":
        from bagit.bench import multihost

        return multihost.run_from_args(args)
    if args.what == "verify":
        from bagit.bench import verify

        return verify.run_from_args(args)
    if args.what == "bimamanip":
        from bagit.bench import bimamanip

        return bimamanip.run(train=args.train, quick=args.quick, out_dir=args.out)
    stages = args.only or STAGES
    unknown = sorted(set(stages) - set(STAGES))
    if unknown:
        raise ValueError(f"unknown stage(s) {unknown}; choose from {STAGES}")
    results: dict[str, Any] = {"machine": machine(), "quick": args.quick, "stages": {}}
    for name in stages:
        log.info("%s ...", name)
        t0 = time.perf_counter()
        mod = importlib.import_module(f"bagit.bench.{name}")
        results["stages"][name] = mod.run(quick=args.quick)
        log.info("%s done in %.1f s", name, time.perf_counter() - t0)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    jp, mp = write_results(f"stages-{stamp}", results, stages_markdown(results), args.out)
    results["files"] = {"json": str(jp), "markdown": str(mp)}
    return results


def stages_markdown(results: dict[str, Any]) -> str:
    """A readable summary: one table per stage of every numeric result."""
    from bagit.bench.common import flatten

    m = results["machine"]
    lines = [
        "# Stage benchmarks",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, numpy {m['numpy']}; {m['when']}"
        + ("; quick subset" if results.get("quick") else ""),
        "",
    ]
    if m.get("numerics"):
        from bagit.common.machine import Numerics

        lines += [f"Numerics: {Numerics.model_validate(m['numerics']).summary()}", ""]
    for name, res in results["stages"].items():
        table = getattr(importlib.import_module(f"bagit.bench.{name}"), "markdown", None)  # a stage's own table from its record
        if table is not None:
            lines += [f"## {name}", "", table(res).split("\n", 2)[-1].strip(), ""]
            continue
        lines += [f"## {name}", "", "| metric | value |", "| --- | --- |"]
        for k, v in flatten(res).items():
            lines.append(f"| {k} | {v:.4g} |")
        lines.append("")
    return "\n".join(lines)


def compare(old: Path, new: Path) -> dict[str, Any]:
    """Every numeric metric present in both files, with its change."""
    from bagit.bench.common import flatten

    try:
        a, b = (flatten(json.loads(p.read_text())) for p in (old, new))
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"cannot read benchmark results: {e}") from None
    rows = []
    for k in sorted(set(a) & set(b)):
        ratio = b[k] / a[k] if a[k] else float("inf") if b[k] else 1.0
        rows.append({"metric": k, "old": a[k], "new": b[k], "ratio": ratio})
    return {"old": str(old), "new": str(new), "rows": rows, "only_old": sorted(set(a) - set(b)), "only_new": sorted(set(b) - set(a))}


def human(result: dict[str, Any]) -> str:
    if result.get("kind") == "zoo-bag":
        return f"written: {result['scenario']} (run it with: bagit run {result['scenario']} --seed {result['seed']})"
    if result.get("kind") == "zoo-perception":
        from bagit.bench.zoo_perception import markdown as perception_markdown

        return perception_markdown(result) + (f"\nwritten: {result['files']['markdown']}" if "files" in result else "")
    if result.get("kind") == "zoo":
        from bagit.bench.zoo import markdown as zoo_markdown

        return zoo_markdown(result) + (f"\nwritten: {result['files']['markdown']}" if "files" in result else "")
    if result.get("kind") == "verify":
        from bagit.bench.verify import markdown

        return markdown(result) + f"\nwritten: {result['written']['markdown']}"
    if result.get("kind") == "probes":
        from bagit.bench.probes import summary

        return summary(result)
    if "runs" in result and "rows" in result:
        from bagit.bench.closed_loop import table

        return table(result)
    if "rows" in result:
        out = [f"{'metric':60s} {'old':>12s} {'new':>12s} {'new/old':>8s}"]
        for r in result["rows"]:
            out.append(f"{r['metric']:60s} {r['old']:12.4g} {r['new']:12.4g} {r['ratio']:8.2f}")
        return "\n".join(out)
    if "planning_runs" in result:
        return paper_summary(result)
    if "stages" in result:
        return stages_markdown(result) + f"\nwritten: {result['files']['markdown']}"
    return json.dumps(result, indent=2, default=str)


def paper_summary(r: dict[str, Any]) -> str:
    """A few lines for the terminal; the tables are in the Markdown report."""
    lines = [f"planning ({r['seeds']} seeds):"]
    for stem, row in r["planning"].items():
        cells = [f"{p} {c['success']}/{c['of']} {c['time_mean_s'] or float('nan'):.3f} s" for p, c in row.items()]
        lines.append(f"  {stem:32s} " + "  ".join(cells))
    a = r["placements"]["all"]
    lines.append(f"bagging SOI over {r['placements']['valid']} placements: mean c1 {a['c1_mean']:.3f}, c2 {a['c2_mean']:.4f} m, c3 {a['c3_mean']:.4f}")
    n = sum(c["of"] for row in r["manipulation"].values() for c in row.values())
    lines.append(f"closed-loop runs read: {n}" + ("" if n else " (manipulation: not run)"))
    lines.append(f"written: {r['files']['markdown']}, {r['files']['json']}, {len(r['figures'])} figures")
    return "\n".join(lines)
