"""Shared benchmark plumbing: timing statistics, machine description, result files."""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

RESULTS_DIR = Path(__file__).resolve().parent / "results"


def compile_bagit() -> int:
    """Compile every BagIt module's bytecode now (`make setup` does too); the number of package folders.
    Why: a benchmark that starts processes times their imports, and without bytecode (an editable checkout
    where Python may not write it, PYTHONDONTWRITEBYTECODE) each process compiles its imports again, more
    for one process that imports every service (`bagit run`) than for each service of `bagit up`."""
    import compileall
    import importlib

    roots = {Path(p) for name in ("bagit", "bagit.common", "bagit.services", "bagit.dashboard", "bagit.scenarios", "bagit.bench",
                                 "bagit.deploy")
             for p in importlib.import_module(name).__path__}
    roots = {r for r in roots if not any(o != r and o in r.parents for o in roots)}  # bagit.services may sit inside bagit's
    for r in roots:
        compileall.compile_dir(r, quiet=1, workers=0)
    return len(roots)


def timeit(fn: Callable[[], Any], repeat: int, warmup: int = 1) -> dict[str, float]:
    """Wall time of `fn` over `repeat` calls, as min / median / p95 / mean in milliseconds."""
    for _ in range(warmup):
        fn()
    t = np.empty(repeat)
    for i in range(repeat):
        t0 = time.perf_counter()
        fn()
        t[i] = time.perf_counter() - t0
    return stats_ms(t * 1e3)


def stats_ms(samples_ms: np.ndarray | list[float]) -> dict[str, float]:
    """min / median / p95 / mean of samples already in milliseconds."""
    a = np.asarray(samples_ms, dtype=float)
    if a.size == 0:
        return {"n": 0}
    return {
        "n": int(a.size),
        "min_ms": float(a.min()),
        "median_ms": float(np.median(a)),
        "p95_ms": float(np.percentile(a, 95)),
        "mean_ms": float(a.mean()),
    }


def machine() -> dict[str, Any]:
    """What the numbers were measured on, with the libraries, BLAS and CPU flags (`numerics`, see bagit.common.machine)."""
    import numpy

    from bagit.common.machine import cpu_model, numerics
    from bagit.common.results import provenance

    return {
        "cpu": cpu_model(),
        "commit": provenance().commit,
        "host": provenance().host,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": numpy.__version__,
        "platform": platform.platform(),
        "when": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        "numerics": numerics().model_dump(mode="json"),
    }


def metric_table(title: str, r: dict[str, Any], rows: list[tuple[str, Any]]) -> str:
    """A one-run record as a markdown table: its provenance (commit, host, CPU, when, load before and after,
    parameters: `r["machine"]`, `r["load_before"]`, `r["load_after"]`, `r["params"]`), then `rows`."""
    m = r["machine"]
    head = [("commit", m.get("commit")), ("host", m.get("host")), ("cpu", f"{m.get('cpu')}, {m.get('cores')} cores"),
            ("when", m.get("when")), ("load average before / after", f"{r['load_before']} / {r['load_after']}"),
            ("parameters", ", ".join(f"{k} {v}" for k, v in r["params"].items()))]
    lines = [f"# {title}", "", "| metric | value |", "| --- | --- |"] + [f"| {k} | {v} |" for k, v in head + rows]
    return "\n".join(lines) + "\n"


def write_results(name: str, data: dict[str, Any], markdown: str, out_dir: Path | None = None) -> tuple[Path, Path]:
    """Write `<name>.json` and `<name>.md` under bench/results (or `out_dir`)."""
    d = Path(out_dir) if out_dir else RESULTS_DIR
    d.mkdir(parents=True, exist_ok=True)
    jp, mp = d / f"{name}.json", d / f"{name}.md"
    jp.write_text(json.dumps(data, indent=2, default=_jsonable))
    mp.write_text(markdown)
    return jp, mp


def _jsonable(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    return str(o)


def flatten(d: dict[str, Any], prefix: str = "") -> dict[str, float]:
    """Numeric leaves of a nested result, keyed by dotted path (for `bench compare`)."""
    out: dict[str, float] = {}
    for k, v in d.items():
        key = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(flatten(v, key))
        elif isinstance(v, (int, float)) and not isinstance(v, bool):
            out[key] = float(v)
    return out
