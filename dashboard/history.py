"""The runs of this dashboard session: what was started, with which parameters, and how it ended.

A run enters the history when the dashboard starts it (with the parameter overrides it sent) or
when a RunState names a run id not seen before (started by someone else). Bounded, newest first.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Any

from pydantic import ValidationError

from bagit.common.messages import RunState
from bagit.common.names import FINAL_STAGES
from bagit.common.results import RunResult

MAX_RUNS = 200


@dataclass
class RunRecord:
    run_id: str
    scenario: str | None
    params: dict[str, Any] = field(default_factory=dict)
    started_wall: float = field(default_factory=time.time)
    stage: str = "idle"
    progress: float = 0.0
    elapsed_s: float = 0.0
    reason: str | None = None
    result: RunResult | None = None  # the coordinator's, once the run ended
    by_dashboard: bool = False

    @property
    def finished(self) -> bool:
        return self.stage in FINAL_STAGES


class RunHistory:
    """Thread-safe, bounded record of this session's runs."""

    def __init__(self, max_runs: int = MAX_RUNS) -> None:
        self._runs: OrderedDict[str, RunRecord] = OrderedDict()
        self._max = max_runs
        self._lock = threading.Lock()

    def started(self, run_id: str, scenario: str | None, params: dict[str, Any]) -> RunRecord:
        with self._lock:
            rec = self._runs.get(run_id)
            if rec is None:
                rec = self._add(RunRecord(run_id, scenario, dict(params), by_dashboard=True))
            else:  # the first RunState beat the start reply
                rec.params, rec.by_dashboard = dict(params), True
                rec.scenario = rec.scenario or scenario
            return rec

    def update(self, state: RunState) -> RunRecord | None:
        """Fold a RunState into its run's record (None for a state without a run id)."""
        if not state.run_id:
            return None
        with self._lock:
            rec = self._runs.get(state.run_id)
            if rec is None:
                rec = self._add(RunRecord(state.run_id, state.scenario))
            if rec.finished and state.stage not in FINAL_STAGES:
                return rec  # a late republished state never reopens a finished run
            rec.stage = state.stage
            rec.progress = state.progress
            rec.elapsed_s = state.elapsed_s
            rec.scenario = state.scenario or rec.scenario
            if state.reason:
                rec.reason = state.reason
            if state.result:
                try:
                    rec.result = RunResult.model_validate(state.result)
                except ValidationError:
                    rec.result = None  # a coordinator of another version: the stage and reason still show
            return rec

    def _add(self, rec: RunRecord) -> RunRecord:
        self._runs[rec.run_id] = rec
        while len(self._runs) > self._max:
            self._runs.popitem(last=False)
        return rec

    def get(self, run_id: str) -> RunRecord | None:
        with self._lock:
            return self._runs.get(run_id)

    def records(self) -> list[RunRecord]:
        """Newest first."""
        with self._lock:
            return list(reversed(self._runs.values()))


def _params_text(p: dict[str, Any]) -> str:
    return ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in sorted(p.items())) or "scenario's"


def history_markdown(history: RunHistory, limit: int = 20) -> str:
    recs = history.records()[:limit]
    if not recs:
        return "_No runs yet in this session._"
    lines = ["| run | scenario | result | time | params | reason |", "|---|---|---|---|---|---|"]
    for r in recs:
        stage = {"done": "**done**", "failed": "**failed**", "aborted": "**aborted**"}.get(r.stage, f"{r.stage}…")
        if r.result is not None and r.result.perceived_error_cm is not None:
            stage += f", {r.result.perceived_error_cm:.2f} cm"
        clock = time.strftime("%H:%M:%S", time.localtime(r.started_wall))
        reason = (r.reason or "").replace("|", "/")
        lines.append(
            f"| {r.run_id} | {r.scenario or '-'} | {stage} | {clock}, {r.elapsed_s:.1f} s | {_params_text(r.params)} | {reason} |"
        )
    return "\n".join(lines)
