"""`python -m bagit.bench.zoo_ablation A.jsonl B.jsonl --labels A,B --out DIR`: two zoo records of the same
bags under two arms of an ablation (the online Broyden J against J frozen at its initial estimate), compared
bag by bag.

Why a report of its own: the adaptation claim is a paired question (each bag, object and seed run under
both arms), so besides each arm's success, error and simulated time per class (`zoo.summary` over the bags
both records hold) it names the bags that bag under one arm only, with the other arm's cause and reason, and
tests those discordant bags with an exact sign test (two-sided binomial at 1/2), as docs/experiments.md
reports the ablation. Bags that only one record holds are left out of everything and counted, so a partial
record says it is partial. Each arm's commits, hosts, dates and `--params` overrides come from its records.
"""

from __future__ import annotations

import argparse
import logging
from collections import Counter
from pathlib import Path
from typing import Any

from bagit.bench import zoo
from bagit.bench.closed_loop import read_jsonl

log = logging.getLogger("bagit.bench.zoo_ablation")


def bag_index(name: str) -> int:
    """The i of zoo bag `zoo-<set>-<seed>-<i>`: the records' order."""
    return int(name.rsplit("-", 1)[1])


def by_bag(records: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """One record per zoo bag (the last, as a resumed sweep appends), non-zoo runs left out."""
    return {r["scenario"]: r for r in records if zoo.is_zoo_name(r["scenario"])}


def arm_provenance(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """What an arm's records say of where they ran: commits (with their run counts), dirty runs, hosts,
    first and last date, the `--params` overrides, and the runs the CR5 driver slowed."""
    prov = [r.get("provenance") or {} for r in runs]
    overrides = sorted({repr(sorted((r.get("overrides") or {}).items())) for r in runs})
    dates = sorted(p["date"] for p in prov if p.get("date"))
    return {"commits": dict(Counter(str(p.get("commit"))[:7] for p in prov)), "dirty": sum(bool(p.get("dirty")) for p in prov),
            "hosts": sorted({str(p.get("host")) for p in prov}), "first": dates[0] if dates else None, "last": dates[-1] if dates else None,
            "overrides": overrides, "slowed_runs": sum(zoo._slowed(r) > 0 for r in runs)}


def sign_test_p(only_a: int, only_b: int) -> float:
    """Exact two-sided sign test on the discordant bags (1.0 when there are none)."""
    from scipy import stats

    n = only_a + only_b
    return float(stats.binomtest(only_b, n, 0.5).pvalue) if n else 1.0


def _failure(r: dict[str, Any]) -> dict[str, Any]:
    """A failed run as the comparison names it: its cause, stage, reason and slowed periods."""
    return {"cause": zoo.cause(r), "stage": r.get("stage_reached"), "reason": r.get("reason"), "slowed": zoo._slowed(r)}


def compare(a_records: list[dict[str, Any]], b_records: list[dict[str, Any]], labels: tuple[str, str],
            bags: dict[str, dict[str, Any]] | None = None) -> dict[str, Any]:
    """The two arms over the bags both hold: per-class summaries, failure causes, the discordant bags and the
    sign test. `bags`: zoo bag name -> its bag (with "classes"); drawn again with `zoo.zoo_scenario` when None."""
    a, b = by_bag(a_records), by_bag(b_records)
    names = sorted(set(a) & set(b), key=bag_index)
    if bags is None:
        bags = {n: zoo.zoo_scenario(n)[1] for n in names}
    ra, rb = [a[n] for n in names], [b[n] for n in names]
    only_a = [{"bag": n, "classes": bags[n]["classes"], "other": _failure(b[n])} for n in names if a[n].get("success") and not b[n].get("success")]
    only_b = [{"bag": n, "classes": bags[n]["classes"], "other": _failure(a[n])} for n in names if b[n].get("success") and not a[n].get("success")]
    return {"kind": "zoo-ablation", "labels": list(labels), "bags": len(names),
            "only_in": {labels[0]: sorted(set(a) - set(b), key=bag_index), labels[1]: sorted(set(b) - set(a), key=bag_index)},
            "provenance": {labels[0]: arm_provenance(ra), labels[1]: arm_provenance(rb)},
            "summary": {labels[0]: zoo.summary(ra, bags), labels[1]: zoo.summary(rb, bags)},
            "causes": {labels[0]: dict(Counter(zoo.cause(r) for r in ra if not r.get("success"))),
                       labels[1]: dict(Counter(zoo.cause(r) for r in rb if not r.get("success")))},
            "bagged_only_with": {labels[0]: only_a, labels[1]: only_b},
            "sign_test_p": sign_test_p(len(only_a), len(only_b))}


def _cell(s: dict[str, Any] | None) -> str:
    """success/of, mean error (cm) and time (s) over the successes; '-' for a class an arm has no bag of."""
    if s is None:
        return "-"
    err = f"{s['error_cm_mean']:.2f}" if s["error_cm_mean"] is not None else "-"
    t = f"{s['time_s_mean']:.1f}" if s["time_s_mean"] is not None else "-"
    return f"{s['success']}/{s['of']}, {err}, {t}"


def markdown(r: dict[str, Any]) -> str:
    """The comparison: where each arm ran, one row per class, the causes, the discordant bags and the test."""
    la, lb = r["labels"]
    lines = [f"# The bag zoo under two arms: {la} against {lb} ({r['bags']} bags both records hold)", ""]
    left_out = {lab: len(v) for lab, v in r["only_in"].items() if v}
    if left_out:
        lines += ["**Partial**: " + ", ".join(f"{n} bags only in the {lab} record" for lab, n in left_out.items())
                  + " are left out of everything below.", ""]
    for lab in (la, lb):
        p = r["provenance"][lab]
        lines.append(f"- {lab}: commits {p['commits']}, {p['dirty']} dirty, hosts {', '.join(p['hosts'])}, {p['first']} to {p['last']}, "
                     f"overrides {', '.join(p['overrides'])}; runs with slowed periods: {p['slowed_runs']}; "
                     f"bags only in this record (left out): {len(r['only_in'][lab])}")
    sa, sb = r["summary"][la], r["summary"][lb]
    lines += ["", f"| class | {la}: success, error cm, time s | {lb}: success, error cm, time s |", "| --- | --- | --- |"]
    for c in sorted(set(sa) | set(sb), key=lambda c: (c != "all", c)):
        lines.append(f"| {c} | {_cell(sa.get(c))} | {_cell(sb.get(c))} |")
    lines.append("")
    for lab in (la, lb):
        causes = ", ".join(f"{k} {v}" for k, v in sorted(r["causes"][lab].items(), key=lambda kv: (-kv[1], str(kv[0])))) or "none"
        lines.append(f"Failures with {lab} by cause: {causes}.")
    for lab, other in ((la, lb), (lb, la)):
        rows = r["bagged_only_with"][lab]
        lines += ["", f"Bagged only with {lab} ({len(rows)}; the {other} run's cause: stage: reason):"]
        for x in rows:
            o = x["other"]
            lines.append(f"- {x['bag']} ({', '.join(x['classes']) or 'no class'}): {o['cause']}: {o['stage']}: {o['reason']}"
                         + (f" (arms slowed {o['slowed']} periods)" if o["slowed"] else ""))
    n_a, n_b = len(r["bagged_only_with"][la]), len(r["bagged_only_with"][lb])
    lines += ["", f"Exact sign test on the {n_a + n_b} discordant bags ({n_a} against {n_b}): p = {r['sign_test_p']:.3g}."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    """Compare two zoo records and write `<stem>.json` and `<stem>.md` into --out."""
    from bagit.bench.common import write_results

    p = argparse.ArgumentParser(prog="python -m bagit.bench.zoo_ablation", description=__doc__.split("\n\n")[0])
    p.add_argument("a", type=Path, help="the first arm's zoo record (.jsonl)")
    p.add_argument("b", type=Path, help="the second arm's zoo record (.jsonl)")
    p.add_argument("--labels", default="A,B", help="the two arms' names, comma-separated (default A,B)")
    p.add_argument("--out", type=Path, required=True, help="folder for the comparison's .json and .md")
    p.add_argument("--stem", default="comparison", help="the files' name (default comparison)")
    a = p.parse_args(argv)
    labels = tuple(s.strip() for s in a.labels.split(","))
    if len(labels) != 2:
        p.error(f"--labels needs two names, got {a.labels!r}")
    result = compare(read_jsonl(a.a), read_jsonl(a.b), (labels[0], labels[1]))
    result["records"] = [str(a.a), str(a.b)]
    jp, mp = write_results(a.stem, result, markdown(result), a.out)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    log.info("written: %s, %s", jp, mp)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
