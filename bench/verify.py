"""`bagit bench verify RECORDS [--sample N] [--seed K]`: re-run a sample of a record file's runs on this
machine and say how many are bit for bit, and whether the distribution agrees.

Each sampled run goes through the path that made the sweep's records (bench/isolated.py: `bagit run`'s
in-process rig in a child process, one BLAS thread) with the record's scenario, controller, planner,
seed, arms and `--params` overrides. A run is bit for bit when its success, ticks, error, simulated time
and final true rim are the record's exactly. On another machine or install they need not be (the closed
loop grows a last-bit difference: docs/experiments.md, "Bit for bit"), and what should hold is the
distribution: success (Fisher's exact test on the two samples; McNemar's exact test on the pairs), error
and time over the runs that succeeded both times (Wilcoxon's signed-rank test on the pairs, which the same
scenario and seed make; Mann-Whitney's U on the two samples). The sample is the same for the same seed.

Its record (the rows, the tests, every re-run's RunResult and this machine's provenance) goes to
bench/results/verify/ under a new name: a published record is never overwritten.
"""

from __future__ import annotations

import argparse
import hashlib
import logging
import math
import random
import statistics
import time
from pathlib import Path
from typing import Any

from bagit.bench.closed_loop import RUN_TIMEOUT_S, read_jsonl
from bagit.bench.isolated import run_isolated
from bagit.common.results import provenance

log = logging.getLogger("bagit.bench.verify")

VERIFY_DIR = Path(__file__).resolve().parent / "results" / "verify"
ALPHA = 0.05  # the family's level: each of the three questions (success, error, time) is tested at ALPHA / 3 (Bonferroni)
QUESTIONS = ("success", "error_cm", "duration_s")
# What must be equal for a re-run to be its record bit for bit.
SAME_FIELDS = ("success", "ticks", "error_cm", "duration_s", "final_rim")


def sample_indices(n_records: int, sample: int | None, seed: int) -> list[int]:
    """`sample` distinct indices of `n_records` records drawn with `seed` (all when `sample` is None or larger), ascending."""
    if sample is None or sample >= n_records:
        return list(range(n_records))
    if sample < 1:
        raise ValueError(f"a sample needs at least one run, got {sample}")
    return sorted(random.Random(seed).sample(range(n_records), sample))


def bit_for_bit(old: dict[str, Any], new: dict[str, Any]) -> bool:
    """Whether `new` is `old`'s run exactly: SAME_FIELDS all equal (a float compared as it was written)."""
    return all(old.get(f) == new.get(f) for f in SAME_FIELDS)


def compare_distributions(old: list[dict[str, Any]], new: list[dict[str, Any]]) -> dict[str, Any]:
    """The tests of the module docstring on records paired by position (old[i] is new[i]'s run): each with its p-value."""
    from scipy import stats

    if len(old) != len(new) or not old:
        raise ValueError(f"the tests need the same number of old and new runs, at least one: got {len(old)} and {len(new)}")
    so, sn = [bool(r.get("success")) for r in old], [bool(r.get("success")) for r in new]
    table = [[sum(so), len(so) - sum(so)], [sum(sn), len(sn) - sum(sn)]]
    only_old = sum(a and not b for a, b in zip(so, sn, strict=True))
    only_new = sum(b and not a for a, b in zip(so, sn, strict=True))
    success = {
        "old": sum(so), "new": sum(sn), "of": len(so), "only_old": only_old, "only_new": only_new,
        "fisher_p": float(stats.fisher_exact(table)[1]),
        "mcnemar_p": float(stats.binomtest(only_old, only_old + only_new, 0.5).pvalue) if only_old + only_new else 1.0,
    }
    out: dict[str, Any] = {"success": success}
    both = [(o, n) for o, n, a, b in zip(old, new, so, sn, strict=True) if a and b]
    for field in QUESTIONS[1:]:
        pairs = [(float(o[field]), float(n[field])) for o, n in both if o.get(field) is not None and n.get(field) is not None]
        out[field] = paired_tests(pairs)
    p_values = [success["fisher_p"], success["mcnemar_p"]] + [p for f in QUESTIONS[1:] for p in (out[f]["wilcoxon_p"], out[f]["mannwhitney_p"])
                                                             if p is not None]
    out["alpha_per_question"] = ALPHA / len(QUESTIONS)
    out["agrees"] = all(p >= ALPHA / len(QUESTIONS) for p in p_values)
    return out


def paired_tests(pairs: list[tuple[float, float]]) -> dict[str, Any]:
    """Means, the median paired difference (new - old), Wilcoxon's signed-rank p on the pairs (Pratt's handling of zero
    differences, which bit-for-bit pairs are; 1.0 when every pair is equal) and Mann-Whitney's U p on the two samples."""
    from scipy import stats

    out: dict[str, Any] = {"n": len(pairs), "old_mean": None, "new_mean": None, "median_diff": None, "wilcoxon_p": None, "mannwhitney_p": None}
    if not pairs:
        return out
    a, b = [p[0] for p in pairs], [p[1] for p in pairs]
    diffs = [y - x for x, y in pairs]
    out.update(old_mean=statistics.fmean(a), new_mean=statistics.fmean(b), median_diff=statistics.median(diffs))
    if all(d == 0 for d in diffs):
        out.update(wilcoxon_p=1.0, mannwhitney_p=1.0)
        return out
    out["wilcoxon_p"] = float(stats.wilcoxon(a, b, zero_method="pratt").pvalue)
    out["mannwhitney_p"] = float(stats.mannwhitneyu(a, b, alternative="two-sided").pvalue)
    return out


def verify(
    files: list[Path], sample: int | None = None, seed: int = 0, time_limit_s: float = 40.0, timeout_s: float = RUN_TIMEOUT_S,
    out_dir: Path | None = None,
) -> dict[str, Any]:
    """Re-run the sample of `files`' records (read in order, concatenated), compare, write the record; its dict."""
    from bagit.bench.common import write_results

    records = [r for f in files for r in _read(f)]
    if not records:
        raise ValueError(f"no run records in {', '.join(map(str, files))}")
    picked = sample_indices(len(records), sample, seed)
    ours = provenance()
    rows, new_runs = [], []
    t0 = time.monotonic()
    for i, idx in enumerate(picked, 1):
        old = records[idx]
        key = (old["scenario"], old["controller"], old["planner"], int(old["seed"]), old.get("arms") or "ideal")
        new = run_isolated(key, time_limit_s, old.get("overrides") or None, timeout_s)
        new_runs.append(new)
        rows.append(_row(idx, old, new))
        log.info("[%d/%d] %s %s seed %d: %s (%d -> %d ticks, %s -> %s cm)", i, len(picked), key[0], key[4], key[3],
                 "bit for bit" if rows[-1]["bit_for_bit"] else "differs", old.get("ticks") or 0, new.get("ticks") or 0,
                 old.get("error_cm"), new.get("error_cm"))
    olds = [records[i] for i in picked]
    commits = sorted({(r.get("provenance") or {}).get("commit") or "?" for r in olds})
    result: dict[str, Any] = {
        "kind": "verify",
        "files": [{"path": str(f), "sha256": hashlib.sha256(Path(f).read_bytes()).hexdigest(), "records": len(_read(f))} for f in files],
        "sample": len(picked), "of": len(records), "sample_seed": seed, "indices": picked, "time_limit_s": time_limit_s,
        "record_commits": commits, "same_commit": commits == [ours.commit],
        "bit_for_bit": sum(r["bit_for_bit"] for r in rows), "wall_s": round(time.monotonic() - t0, 1),
        "tests": compare_distributions(olds, new_runs), "rows": rows,
        "provenance": ours.model_dump(mode="json"), "runs": new_runs,
    }
    stem = "-".join(Path(f).stem for f in files)[:80]
    jp, mp = write_results(f"verify-{stem}-{time.strftime('%Y%m%d-%H%M%S')}", result, markdown(result), out_dir or VERIFY_DIR)
    result["written"] = {"json": str(jp), "markdown": str(mp)}
    return result


def _read(path: Path) -> list[dict[str, Any]]:
    if not Path(path).is_file():
        raise ValueError(f"no such record file: {path}")
    return read_jsonl(path)


def _row(idx: int, old: dict[str, Any], new: dict[str, Any]) -> dict[str, Any]:
    """One sampled run: the record's and the re-run's numbers, and whether the re-run used the record's parameters."""
    params = lambda r: (r.get("provenance") or {}).get("params")  # noqa: E731
    return {
        "index": idx, "scenario": old["scenario"], "controller": old["controller"], "planner": old["planner"], "seed": old["seed"],
        "arms": old.get("arms") or "ideal", "bit_for_bit": bit_for_bit(old, new), "same_params": params(old) == params(new),
        **{f"{k}_{side}": r.get(k) for k in ("success", "ticks", "error_cm", "duration_s") for side, r in (("old", old), ("new", new))},
        "reason_new": new.get("reason"),
    }


def _p(x: float | None) -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.3g}"


def _num(x: float | None, fmt: str) -> str:
    return "-" if x is None else format(x, fmt)


def markdown(r: dict[str, Any]) -> str:
    """The short table: the runs, the tests and where they were run."""
    t = r["tests"]
    prov = r["provenance"]
    lines = [
        f"# bagit bench verify: {', '.join(f['path'] for f in r['files'])}",
        "",
        f"{r['sample']} of {r['of']} runs (sample seed {r['sample_seed']}), re-run on {prov.get('host')} ({prov.get('cpu')}, {prov.get('cores')} cores) "
        f"at {str(prov.get('commit'))[:10]}{' (dirty)' if prov.get('dirty') else ''}; the records at {', '.join(c[:10] for c in r['record_commits'])}; "
        f"time limit {r['time_limit_s']:g} s; {r['wall_s']:.0f} s of wall time.",
        "",
        f"**Bit for bit: {r['bit_for_bit']}/{r['sample']}** (success, ticks, error, simulated time and final rim all equal). "
        f"**Distribution {'agrees' if t['agrees'] else 'differs'}** (every p >= {t['alpha_per_question']:.4f}: 0.05 over 3 questions).",
        "",
        "| question | record | re-run | test: p |",
        "|---|---|---|---|",
        f"| success | {t['success']['old']}/{t['success']['of']} | {t['success']['new']}/{t['success']['of']} | "
        f"Fisher {_p(t['success']['fisher_p'])}, McNemar {_p(t['success']['mcnemar_p'])} |",
    ]
    for f, unit in (("error_cm", "cm"), ("duration_s", "s")):
        q = t[f]
        lines.append(f"| {f} (n={q['n']}, both succeeded) | {_num(q['old_mean'], '.3f')} {unit} | {_num(q['new_mean'], '.3f')} {unit} | "
                     f"Wilcoxon (paired) {_p(q['wilcoxon_p'])}, Mann-Whitney {_p(q['mannwhitney_p'])} |")
    lines += ["", "| scenario | seed | arms | bit for bit | ticks | error cm | time s |", "|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        lines.append(f"| {x['scenario']} | {x['seed']} | {x['arms']} | {'yes' if x['bit_for_bit'] else 'no'} | {x['ticks_old']} → {x['ticks_new']} | "
                     f"{_num(x['error_cm_old'], '.4f')} → {_num(x['error_cm_new'], '.4f')} | "
                     f"{_num(x['duration_s_old'], '.2f')} → {_num(x['duration_s_new'], '.2f')} |")
    # The re-runs' own numerics (their process: one BLAS thread, PIQP loaded), else this command's.
    numerics = next((n for run in r.get("runs") or [] if (n := (run.get("provenance") or {}).get("numerics"))), prov.get("numerics"))
    if numerics:
        from bagit.common.machine import Numerics

        lines += ["", f"Numerics of the re-runs: {Numerics.model_validate(numerics).summary()}"]
    return "\n".join(lines) + "\n"


def add_verify_arguments(p: argparse.ArgumentParser) -> None:
    """`verify`'s own flags (the record files are `bagit bench`'s `files`; --time-limit-s and --timeout-s the sweep's)."""
    from bagit.commands import _args

    p.add_argument("--sample", type=_args.positive_int, default=None, help="for `verify`: how many of the records' runs to re-run (default all)")
    p.add_argument("--seed", type=_args.seed, default=0, help="for `verify`: the seed that draws the sample")


def run_from_args(a: argparse.Namespace) -> dict[str, Any]:
    from bagit.common.logs import configure_logging

    configure_logging(logging.WARNING)  # the re-runs' own logs stay in their processes; the progress is ours
    log.setLevel(logging.INFO)
    if not a.files:
        raise ValueError("bench verify needs one or more record files (.jsonl), e.g. bench/results/closed-loop-mpc-cr5.jsonl")
    return verify([Path(f) for f in a.files], a.sample, a.seed, a.time_limit_s, a.timeout_s, a.out)
