"""`bagit runs [DIR]`: the runs recorded in a folder, with their results.

A run's result is its last run state: from the `bagit.run` metadata of a closed file, or, for a
file whose recorder was killed, from the last run/state message that could be recovered.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

NAME = "runs"
HELP = "list the runs recorded in a folder, with their results"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("dir", nargs="?", type=Path, default=Path("recordings"), help="folder of recordings (default ./recordings)")


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.services.recorder.reading import list_runs

    return list_runs(args.dir)


def human(r: dict[str, Any]) -> str:
    lines = [f"{len(r['runs'])} run(s) in {r['dir']} ({r['idle_files']} idle file(s), {r['idle_bytes'] / 1e6:.1f} MB)"]
    for x in r["runs"]:
        when = time.strftime("%Y-%m-%d %H:%M:%S", time.localtime(x["start_ns"] / 1e9)) if x["start_ns"] else "?"
        res = x["result"]
        outcome = x["stage"] or "?"
        if x["reason"]:
            outcome += f" ({x['reason']})"
        if isinstance(res, dict) and res:
            outcome += " " + _result_text(res)
        tail = "" if x["complete"] else "  [truncated: recovered up to its last complete chunk]"
        lines.append(f"  {x['run_id']:<20} {when}  {x['duration_s']:7.1f} s  {x['scenario'] or '-':<14} {outcome}"
                     f"  {x['messages']} msgs, {x['bytes'] / 1e6:.1f} MB, {len(x['files'])} file(s){tail}")
    for u in r["unreadable"]:
        lines.append(f"  unreadable: {u['file']}: {u['reason']}")
    return "\n".join(lines)


def _result_text(res: dict[str, Any]) -> str:
    """A recorded run's result in a few words: the RunResult's error and ticks (older recordings: their first fields)."""
    from pydantic import ValidationError

    from bagit.common.results import RunResult

    try:
        r = RunResult.model_validate(res)
    except ValidationError:
        return ", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in list(res.items())[:5])
    err = f"error {r.error_cm:.2f} cm, " if r.error_cm is not None else ""
    return f"{err}{r.ticks} ticks, planning {r.planning_time_s:.2f} s"
