"""`python -m bagit.bench.rerun FILE... [--where slowed|dirty|harness] [--workers 2]`: re-run, on this commit, the runs of
record files that the arm driver slowed (`arm_events.slowed > 0`; or run from a dirty tree, or that the harness
lost: timed out, crashed), and put each new record in its old one's place.

For a change that can touch only those runs (issue 35's wrist lag engages only where the driver would have
slowed a period, so every run that never slowed is the same bit for bit: checked before such a re-run), this
refreshes a published record without running all of it again: every other line stays as it was, and each
new line names its own commit, host and load in its `provenance`. Each run is the sweep's task
(bench/isolated.py: a child process of its own, with the record's scenario, controller, planner, seed, arms
and `overrides`, the time limit `--time-limit-s`), `--workers` at a time from this process, as `bagit bench
verify` runs them: no Dask scheduler, whose workers a machine paused for minutes (SIGSTOP) would have it
declare dead and run again. Until every file's runs are done they are kept
in FILE.rerun.jsonl beside each (untracked), so a stopped re-run resumes; then each FILE is rewritten at once
and its scratch file removed.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any

from bagit.bench.closed_loop import RUN_TIMEOUT_S, quiet_engine_logs, read_jsonl, record_key
from bagit.bench.isolated import run_isolated
from bagit.bench.zoo import cause

log = logging.getLogger("bagit.bench.rerun")

WHERE: dict[str, Callable[[dict[str, Any]], bool]] = {
    "slowed": lambda r: int((r.get("arm_events") or {}).get("slowed") or 0) > 0,
    "dirty": lambda r: bool((r.get("provenance") or {}).get("dirty")),  # run from a tree with changes: again from a clean one
    # no result of its own (timed out on a loaded machine, crashed): the harness's failure, not the method's
    "harness": lambda r: cause(r) == "harness",
}


def rerun_all(paths: list[Path], where: str = "slowed", workers: int = 1, time_limit_s: float = 40.0,
              timeout_s: float = RUN_TIMEOUT_S) -> dict[Path, list[dict[str, Any]]]:
    """Re-run the records of every file in `paths` that `WHERE[where]` picks, then replace them in place (all
    files at the end: a record file rewritten while runs go on would mark their trees dirty); per file, per
    run, old and new."""
    runs = {p: _runs_of(p, where, workers, time_limit_s, timeout_s) for p in paths}
    out = {}
    for path, (records, new) in runs.items():
        if new:
            tmp = path.with_name(path.name + ".tmp")
            tmp.write_text("".join(json.dumps(new.get(i, r)) + "\n" for i, r in enumerate(records)))
            os.replace(tmp, path)
        _scratch(path).unlink(missing_ok=True)
        out[path] = [{"old": records[i], "new": n} for i, n in sorted(new.items())]
    return out


def _scratch(path: Path) -> Path:
    return path.with_name(path.name + ".rerun.jsonl")


def _runs_of(path: Path, where: str, workers: int, time_limit_s: float, timeout_s: float) -> tuple[list[dict[str, Any]], dict[int, dict[str, Any]]]:
    """`path`'s records and the new record of each one picked, by index (kept in the scratch file as they come)."""
    records = read_jsonl(path)
    picked = [i for i, r in enumerate(records) if WHERE[where](r)]
    have = {record_key(r): r for r in read_jsonl(_scratch(path))}
    todo = [i for i in picked if record_key(records[i]) not in have]
    log.info("%s: %d runs to re-run (%d already done)", path, len(todo), len(picked) - len(todo))
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {pool.submit(run_isolated, record_key(records[i]), time_limit_s, records[i].get("overrides") or None, timeout_s): i
                   for i in todo}
        for fut in as_completed(futures):
            rec = fut.result()
            have[record_key(rec)] = rec
            with open(_scratch(path), "a") as f:
                f.write(json.dumps(rec) + "\n")
            log.info("  %s", row({"old": records[futures[fut]], "new": rec}))
    new = {i: have[record_key(records[i])] for i in picked if record_key(records[i]) in have}
    missing = len(picked) - len(new)
    if missing:
        raise RuntimeError(f"{path}: {missing} runs not recorded; the same command resumes")
    return records, new


def row(pair: dict[str, Any]) -> str:
    """One re-run as a line: the run, then success, error and slowed/lagged periods before -> after."""
    o, n = pair["old"], pair["new"]
    ev = lambda r, k: (r.get("arm_events") or {}).get(k, 0)  # noqa: E731
    return (f"{o['scenario']} {o['controller']} {o['planner']} seed {o['seed']}: success {o['success']} -> {n['success']}, "
            f"error {o.get('error_cm')} -> {n.get('error_cm')} cm, {o.get('duration_s')} -> {n.get('duration_s')} s, "
            f"slowed {ev(o, 'slowed')} -> {ev(n, 'slowed')}, lagged {ev(n, 'lagged')}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", type=Path, nargs="+")
    ap.add_argument("--where", choices=sorted(WHERE), default="slowed")
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--time-limit-s", type=float, default=40.0)
    ap.add_argument("--timeout-s", type=float, default=RUN_TIMEOUT_S)
    a = ap.parse_args()
    quiet_engine_logs()
    log.setLevel(logging.INFO)
    for f, pairs in rerun_all(a.files, a.where, a.workers, a.time_limit_s, a.timeout_s).items():
        log.info("%s: %d runs re-run", f, len(pairs))
        for p in pairs:
            log.info("  %s", row(p))


if __name__ == "__main__":
    main()
