"""Whole simulated bagging runs over the paper scenarios, seeds and controllers (Tables I and II):
manipulation success, error (cm), time to goal (simulated s) and MPC solve time per tick.

Each run is `bagit run`'s own: the in-process rig (bagit.inprocess) with the coordinator, perception,
the controller and, by default, the two CR5s behind the arm driver's rules (`--arms ideal`: the
floating-gripper ablation). Each record is that run's `RunResult` (commit, host, the Dask worker and
effective parameters in its `provenance`).

The runs go to Dask's distributed scheduler: `--cluster tcp://HOST:PORT` hands them to a running one
(workers on other machines, deploy/cluster.md); without it a local cluster of `--workers` processes
on loopback runs them. On a worker each run is a child process of its own (bench/isolated.py), so a
run that crashes (even in native code) or passes `--timeout-s` becomes a failed record with the
reason, and the sweep goes on. With `--jsonl FILE` every run is appended to FILE as it finishes and
runs already there are skipped: a sweep that was stopped resumes where it was. `bagit bench paper`
reads such files (`--closed-loop FILE`). Progress (runs done, failed, time left) goes to stderr.

    python -m bagit.bench.closed_loop [--quick] [--seeds N] [--controllers mpc,ibvs,ssvs] [--planners cbirrt]
                                      [--only exp02,...] [--seed-from S] [--jsonl FILE] [--workers 1] [--timeout-s 900]
                                      [--params JSON] [--time-limit-s 40] [--arms cr5|ideal] [--cluster tcp://HOST:PORT]
    (the same as `bagit bench sweep ...`)
"""

from __future__ import annotations

import argparse
import json
import logging
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bagit.bench.isolated import Key, WrongCommit, failed_record, run_isolated, stop_runs, worker_commit
from bagit.common.errors import BagItError
from bagit.common.logs import configure_logging
from bagit.common.names import CONTROLLER_NAMES, DEFAULT_CONTROLLER
from bagit.common.params import MethodParams, merge_params
from bagit.common.results import provenance
from bagit.scenarios import list_scenarios

if TYPE_CHECKING:
    from distributed import Client, Future

log = logging.getLogger("bagit.bench.sweep")

PAPER = {"mpc_error_cm": "2.10 ± 0.77", "mpc_time_s": "53.09 ± 2.92"}
RUN_TIMEOUT_S = 900.0  # wall time one run may take before its process is killed
CONNECT_TIMEOUT_S = 10.0  # to reach a running scheduler
WORKER_WAIT_S = 120.0  # for a running scheduler's first worker


class EngineMissing(BagItError, RuntimeError):
    """Dask's distributed scheduler is not installed (the `cluster` extra)."""


def record_key(r: dict[str, Any]) -> Key:
    """A record's run: scenario, controller, planner, seed, arms (records before the arms were in every run: ideal)."""
    return (r["scenario"], r["controller"], r["planner"], int(r["seed"]), r.get("arms") or "ideal")


def read_jsonl(path: Path | None) -> list[dict[str, Any]]:
    if path is None or not Path(path).exists():
        return []
    return [json.loads(line) for line in Path(path).read_text().splitlines() if line.strip()]


def drop_torn_tail(path: Path | None) -> None:
    """Cut a last line that a killed sweep left half written (no newline at the end), so that the
    records appended after it stay whole; the run it was is run again."""
    if path is None or not Path(path).exists():
        return
    data = Path(path).read_bytes()
    if data and not data.endswith(b"\n"):
        keep = data.rfind(b"\n") + 1
        log.warning("%s: dropping a half-written last record (%d bytes) left by a stopped sweep", path, len(data) - keep)
        with open(path, "r+b") as f:
            f.truncate(keep)


@contextmanager
def engine(cluster: str | None, workers: int) -> Iterator[Client]:
    """A client of the scheduler at `cluster`, or of a local cluster of `workers` one-thread processes
    listening on loopback only; closed (and the local cluster with it) on leaving."""
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise EngineMissing("the sweep's cluster engine (Dask) is not installed: pip install 'bagit[cluster]'") from None
    if cluster:
        try:
            client = Client(cluster, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as e:
            raise BagItError(f"cannot reach the Dask scheduler at {cluster}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
        with client:
            try:
                client.wait_for_workers(1, timeout=WORKER_WAIT_S)
            except TimeoutError:
                raise BagItError(f"no Dask worker joined the scheduler at {cluster} within {WORKER_WAIT_S:.0f} s") from None
            check_commits(client)
            yield client
        return
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address="127.0.0.1:0") as lc, \
            Client(lc) as client:
        yield client


def check_commits(client: Client) -> None:
    """Refuse workers whose code is at another commit than this checkout's: their records would mix code."""
    ours = provenance().commit
    theirs = client.run(worker_commit)
    other = {addr: c for addr, c in theirs.items() if c != ours}
    if ours and other:
        listed = ", ".join(f"{addr} at {(c or 'no git checkout')[:10]}" for addr, c in sorted(other.items()))
        raise BagItError(f"Dask workers at another commit than this checkout ({ours[:10]}): {listed}; install the same commit on every worker")


def sweep(
    keys: list[Key],
    jsonl: Path | None = None,
    workers: int = 1,
    timeout_s: float = RUN_TIMEOUT_S,
    time_limit_s: float = 40.0,
    params: dict[str, Any] | None = None,
    cluster: str | None = None,
) -> list[dict[str, Any]]:
    """Run every (scenario, controller, planner, seed, arms) not already in `jsonl` on the Dask scheduler at
    `cluster` (else a local cluster of `workers` processes), each in a process of its own; returns all
    records of these keys (old and new), in the keys' order."""
    if workers < 1 or not timeout_s > 0:
        raise ValueError(f"a sweep needs workers >= 1 and a time-out > 0 s, got {workers} and {timeout_s}")
    drop_torn_tail(jsonl)
    have = {record_key(r): r for r in read_jsonl(jsonl)}
    out = {k: have[k] for k in keys if k in have}
    todo = [k for k in dict.fromkeys(keys) if k not in have]
    if out:
        log.info("%d of %d runs already in %s: skipped", len(out), len(set(keys)), jsonl)
    if todo:
        with engine(cluster, workers) as client:
            _drive(client, todo, out, jsonl, timeout_s, time_limit_s, params)
    return [out[k] for k in keys if k in out]


def _drive(
    client: Client, todo: list[Key], out: dict[Key, dict[str, Any]], jsonl: Path | None, timeout_s: float, time_limit_s: float,
    params: dict[str, Any] | None,
) -> None:
    """Submit every run, record each as it finishes; a stopped sweep (Ctrl-C, an error) cancels what is
    queued and kills its runs on every worker."""
    from distributed import as_completed

    sweep_id = uuid.uuid4().hex[:8]
    futures: dict[Future, Key] = {
        client.submit(run_isolated, k, time_limit_s, params, timeout_s, sweep_id, provenance().commit, key=f"run-{'-'.join(map(str, k))}-{sweep_id}",
                      pure=False): k
        for k in todo
    }
    progress = _Progress(len(todo), len(client.nthreads()))
    stopped = True
    try:
        for fut in as_completed(futures):
            key = futures[fut]
            rec = _record_of(fut, key, params)
            if rec is None:
                continue
            out[key] = rec
            if jsonl is not None:
                with open(jsonl, "a") as f:
                    f.write(json.dumps(rec) + "\n")
            progress.finished(key, rec)
        stopped = False
    finally:
        if stopped:
            _stop(client, list(futures), sweep_id)
        missing = len(todo) - progress.done
        if missing:
            why = "sweep stopped" if stopped else "lost by the engine or refused by a worker, see above"
            log.warning("%d of %d runs not recorded (%s); the same command resumes the sweep", missing, len(todo), why)
        progress.summary()


def _stop(client: Client, futures: list[Future], sweep_id: str) -> None:
    """Kill the sweep's runs on every worker and drop what is queued; best effort (the scheduler may be gone)."""
    try:
        client.run(stop_runs, sweep_id, on_error="ignore")
        client.cancel(futures)
    except Exception as e:  # noqa: BLE001 - stopping must not hide why the sweep stopped
        log.warning("could not stop the sweep's runs on the workers (%s: %s); each ends at its time-out", type(e).__name__, e)


def _record_of(fut: Future, key: Key, params: dict[str, Any] | None) -> dict[str, Any] | None:
    """A finished future's record; a task the engine lost or cancelled gives none (a resume runs it again)."""
    if fut.status == "finished":
        return fut.result()
    if fut.status == "error":
        from distributed import KilledWorker

        e = fut.exception()
        if isinstance(e, WrongCommit):
            log.warning("%s: not run: %s", _label(key), e)
            return None
        if isinstance(e, KilledWorker):
            reason = f"crashed: every worker that ran it died ({e})"
        else:
            reason = f"error: the engine: {type(e).__name__}: {e}"
        return failed_record(key, reason, 0.0, params)
    log.warning("%s: %s by the engine, not recorded", _label(key), fut.status)
    return None


def _label(key: Key) -> str:
    sc, ctrl, planner, seed, arms = key
    return f"{sc} {ctrl} {planner} {arms} seed {seed}"


class _Progress:
    """The sweep's progress on stderr, a line per finished run: done, failed and the estimated time left."""

    def __init__(self, total: int, workers: int) -> None:
        self.total, self.done, self.failed, self.t0 = total, 0, 0, time.monotonic()
        log.info("%d runs on %d workers", total, workers)

    def finished(self, key: Key, rec: dict[str, Any]) -> None:
        self.done += 1
        self.failed += not rec.get("success")
        elapsed = time.monotonic() - self.t0
        left = elapsed / self.done * (self.total - self.done)
        verdict = "success" if rec.get("success") else f"failed at {rec.get('stage_reached')}: {rec.get('reason')}"
        where = (rec.get("provenance") or {}).get("worker") or "?"
        log.info("[%d/%d done, %d failed, ~%s left] %s: %s (%.1f s on %s)", self.done, self.total, self.failed, _duration(left),
                 _label(key), verdict, rec.get("wall_s") or 0.0, where)

    def summary(self) -> None:
        log.info("%d of %d runs recorded (%d failed) in %s", self.done, self.total, self.failed, _duration(time.monotonic() - self.t0))


def _duration(s: float) -> str:
    s = round(s)
    return f"{s // 3600} h {s % 3600 // 60:02d} min" if s >= 3600 else f"{s // 60} min {s % 60:02d} s" if s >= 60 else f"{s} s"


def aggregate(records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per scenario x controller x planner: success / of, error and time over the successes."""
    groups: dict[tuple[str, str, str, str], list[dict[str, Any]]] = {}
    for r in records:
        groups.setdefault(record_key(r)[:3] + record_key(r)[4:], []).append(r)
    rows = []
    for (sc, ctrl, planner, arms), rs in groups.items():
        ok = [r for r in rs if r["success"]]
        solve = [r["solve_ms_median"] for r in rs if r.get("solve_ms_median")]
        rows.append({
            "scenario": sc, "controller": ctrl, "planner": planner, "arms": arms, "success": len(ok), "of": len(rs),
            "error_cm_mean": float(np.mean([r["error_cm"] for r in ok])) if ok else float("nan"),
            "error_cm_std": float(np.std([r["error_cm"] for r in ok])) if ok else float("nan"),
            "time_s_mean": float(np.mean([r["duration_s"] for r in ok])) if ok else float("nan"),
            "solve_ms_median": float(np.median(solve)) if solve else 0.0,
            "failures": sorted({f"{r.get('stage_reached')}: {r.get('reason')}" for r in rs if not r["success"]}),
        })
    return rows


def run(
    quick: bool = False,
    seeds: int | None = None,
    controllers: list[str] | None = None,
    only: list[str] | None = None,
    planners: list[str] | None = None,
    jsonl: Path | None = None,
    workers: int = 1,
    timeout_s: float = RUN_TIMEOUT_S,
    seed_from: int = 0,
    params: dict[str, Any] | None = None,
    time_limit_s: float = 40.0,
    arms: list[str] | None = None,
    cluster: str | None = None,
) -> dict:
    if params:
        merge_params(MethodParams(), params)  # BadScenario naming an unknown or bad key, before any run starts
    n = seeds or (1 if quick else 8)
    ctrls = controllers or ([DEFAULT_CONTROLLER] if quick else list(CONTROLLER_NAMES))
    scen = [p.stem for p in list_scenarios() if not only or any(p.stem.startswith(o) for o in only)]
    if quick and not only:
        scen = scen[:2]
    keys = [(s, c, pl, seed, a) for s in scen for c in ctrls for pl in (planners or ["cbirrt"]) for a in (arms or ["cr5"])
            for seed in range(seed_from, seed_from + n)]
    records = sweep(keys, jsonl, workers, timeout_s, time_limit_s, params, cluster)
    return {"seeds": n, "rows": aggregate(records), "runs": records}


def add_sweep_arguments(p: argparse.ArgumentParser) -> None:
    """The sweep's own flags (`--quick`, `--seeds` and `--only` are `bagit bench`'s shared ones)."""
    from bagit.commands import _args

    p.add_argument("--controllers", default=None, help="for `sweep`: e.g. mpc,ibvs,ssvs (default all; --quick: mpc)")
    p.add_argument("--planners", default=None, help="for `sweep`: e.g. cbirrt,ffg-rrt,ts-rrt (Table II's planner rows)")
    p.add_argument("--arms", default=None, help="for `sweep`: cr5 (default), ideal, or both: cr5,ideal")
    p.add_argument("--seed-from", type=_args.seed, default=0, help="for `sweep`: seeds seed_from .. seed_from + seeds - 1")
    p.add_argument("--jsonl", type=Path, default=None, help="for `sweep`: append each run here; runs already in it are skipped")
    p.add_argument("--time-limit-s", type=_args.positive_seconds, default=40.0, help="for `sweep` and `verify`: simulated seconds a run may take")
    p.add_argument("--timeout-s", type=_args.positive_seconds, default=RUN_TIMEOUT_S,
                   help="for `sweep` and `verify`: wall seconds a run may take before it is killed and recorded failed")
    p.add_argument("--params", type=_args.json_object, default=None,
                   help='for `sweep`: method parameters for every run, JSON, flat names or nested by stage, e.g. \'{"twist_weight": 0}\'')
    p.add_argument("--cluster", default=None, metavar="tcp://HOST:PORT",
                   help="for `sweep`: a running Dask scheduler to run on (deploy/cluster.md); default: a local cluster of --workers")
    p.add_argument("--workers", type=_args.positive_int, default=1, help="for `sweep`: processes of the local cluster (one run each)")


def quiet_engine_logs() -> None:
    """A sweep's logging: the in-process rigs' warnings, the sweep's progress, the engine's troubles only."""
    configure_logging(logging.WARNING)  # a sweep runs many in-process rigs: only their warnings, and its own progress
    log.setLevel(logging.INFO)
    with suppress(ImportError):  # Dask sets its loggers' levels when first imported: import it before quieting them
        import distributed  # noqa: F401
    logging.getLogger("distributed").setLevel(logging.WARNING)  # the local scheduler's chatter: only what goes wrong


def run_from_args(a: argparse.Namespace) -> dict:
    """A sweep from parsed flags (`bagit bench sweep` and this module's own command line); progress on stderr."""
    quiet_engine_logs()
    split = lambda s: s.split(",") if s else None  # noqa: E731
    only = [o for item in a.only for o in item.split(",") if o] if a.only else None
    return run(a.quick, a.seeds, split(a.controllers), only, split(a.planners), a.jsonl, a.workers, a.timeout_s, a.seed_from, a.params,
               a.time_limit_s, split(a.arms), a.cluster)


def table(r: dict) -> str:
    lines = ["| scenario | controller | planner | arms | success | error cm | time s | MPC solve ms |", "|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(
            f"| {x['scenario']} | {x['controller']} | {x['planner']} | {x['arms']} | {x['success']}/{x['of']} | "
            f"{x['error_cm_mean']:.2f} ± {x['error_cm_std']:.2f} | "
            f"{x['time_s_mean']:.1f} | {x['solve_ms_median']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    from bagit.commands import _args

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--seeds", type=_args.positive_int, default=None)
    ap.add_argument("--only", action="append", default=None, help="scenarios whose names start so, e.g. exp01,exp02")
    add_sweep_arguments(ap)
    a = ap.parse_args()
    try:
        r = run_from_args(a)
    except (BagItError, OSError, ValueError) as e:
        ap.exit(2, f"{ap.prog}: error: {str(e).splitlines()[0] if str(e) else type(e).__name__}\n")
    except KeyboardInterrupt:
        ap.exit(130, f"{ap.prog}: interrupted\n")
    print(table(r))


if __name__ == "__main__":
    main()
