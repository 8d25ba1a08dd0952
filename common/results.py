"""The result of one bagging run: one model for `bagit run --json`, `bagit up --json`, the
coordinator's run/state, the dashboard's history, the recorder and the benchmark's records.

Two views of a run sit side by side. What the rig itself perceived (its coordinator's stage, the
final SOI's error, the controller's error to g*) is all a real rig has. With the simulator,
`truth` judges the same run on the world's ground truth (the true rim, whether the fabric went
through the object), which no service ever reads; the headline `success` and `error_cm` are then
the truth's, as the paper's numbers are measured on the bag itself.
"""

from __future__ import annotations

import os
import platform
import socket
import subprocess
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.machine import Numerics, cpu_model, numerics
from bagit.common.names import ArmsMode, Stage

# Counters of the arm side every result carries (zero when nothing happened): the increments
# clipped by the envelope or the lead limit, the periods slowed to the joints' speed, the periods whose
# tool rotation lagged near the wrist singularity (the mounts' positions sent whole), the watchdog's
# stops, the commands refused, the controllers' alarms and the driver's faults.
ARM_EVENT_KINDS = ("clipped", "slowed", "lagged", "watchdog_stops", "rejected", "alarms", "faults")


def axis_error_cm(rim: np.ndarray, vertices: np.ndarray, up: np.ndarray) -> float:
    """The paper's error (Table I): how far the rim's centre is from the object's centre, across the
    object's axis `up (3,)`, in cm. rim: (n, 3); vertices: V (m, 3), the object's bottom outline."""
    rel = np.asarray(rim, dtype=float).mean(axis=0) - np.asarray(vertices, dtype=float).mean(axis=0)
    up = np.asarray(up, dtype=float) / np.linalg.norm(up)
    return float(np.linalg.norm(rel - (rel @ up) * up)) * 100.0


class RecordingReport(BaseModel):
    """What the recorder made of a run (`recording_report`): a run whose recording failed says so, and
    how much of it is missing, whatever became of the run itself."""

    model_config = ConfigDict(extra="forbid")

    ok: bool
    messages: int = Field(0, description="messages of the run on disk")
    lost: int = Field(0, description="messages received during the run and not on disk (write errors, the writer behind or dead)")
    errors: int = Field(0, description="write errors during the run")
    error: str | None = Field(None, description="the (last) write error, e.g. disk full")


def recording_report(before: Any, after: Any) -> RecordingReport | None:
    """The recorder's part in a run from its status (`RecorderStatus`) at the start and at the end; None
    without a recorder. A recorder restarted in between (another `started`) counts from its start."""
    if after is None:
        return None
    if before is None or before.started != after.started:
        before = type(after)(started=after.started)
    lost = (after.lost - before.lost) + (after.overflow - before.overflow)
    errors = after.errors - before.errors
    ok = lost == 0 and errors == 0 and after.error is None
    return RecordingReport(ok=ok, messages=after.messages - before.messages, lost=lost, errors=errors,
                           error=None if ok else (after.error or after.last_error))


class RunTruth(BaseModel):
    """The run judged on the simulator's ground truth (None on a real rig)."""

    model_config = ConfigDict(extra="forbid")

    success: bool
    reason: str | None = None
    error_cm: float | None = None
    passed_through: bool = False
    max_penetration_mm: float = 0.0
    lift_margin_cm: float | None = Field(
        None, description="the true rim's margin round V when the lift from g† began (cm; < 0: a vertex outside)")
    realtime_factor: float | None = Field(None, description="simulated over wall seconds, over the whole run (from its reset to its end)")


class Provenance(BaseModel):
    """Where a result comes from: the code, the machine and the effective method parameters."""

    model_config = ConfigDict(extra="forbid")

    commit: str | None = None
    dirty: bool | None = None
    host: str = Field("", description="the machine that ran it (in a sweep: the worker's)")
    worker: str | None = Field(None, description="the sweep's Dask worker that ran it, by address (None: not run by a sweep's worker)")
    cpu: str = ""
    cores: int = 0
    python: str = ""
    params: dict[str, Any] = Field(default_factory=dict, description="every method parameter the run used")
    date: str | None = Field(None, description="when the result was made: UTC, ISO 8601 (None: a record of before the field)")
    numerics: Numerics | None = Field(None, description="the libraries, BLAS, CPU instruction sets behind it (None: a record of before the field)")


class RunResult(BaseModel):
    """One run, as every part of BagIt reports it (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    run_id: str | None = None
    scenario: str | None = None
    controller: str | None = None
    planner: str | None = None
    seed: int | None = None
    arms: ArmsMode | None = Field(None, description="cr5: the two CR5s through the arm driver; ideal: floating grippers (ablation)")
    overrides: dict[str, Any] = Field(default_factory=dict, description="method parameters set for this run over the scenario's")
    success: bool = False
    stage_reached: Stage = "idle"
    reason: str | None = None
    error_cm: float | None = Field(None, description="the paper's error: truth's with a simulator, else from the final SOI")
    perceived_error_cm: float | None = Field(None, description="the same measure on the rig's own final SOI")
    error_to_goal_m: float | None = Field(None, description="the controller's RMS distance of the SOI to g* at the end")
    duration_s: float | None = Field(None, description="servoing time, on the rig's clock (simulated seconds in simulation)")
    wall_s: float = 0.0
    planning_time_s: float = 0.0
    path_nodes: int = 0
    ticks: int = 0
    solve_ms_median: float | None = None
    arm_events: dict[str, int] = Field(default_factory=lambda: dict.fromkeys(ARM_EVENT_KINDS, 0))
    final_rim: list[list[float]] | None = Field(None, description="(n_x, 3): the simulator's true rim at the end (else the final SOI)")
    object_vertices: list[list[float]] | None = Field(None, description="V (m, 3) the run's goal used")
    object_from: str | None = Field(None, description="marker | scenario: where V came from")
    object_reason: str | None = None
    marker: dict[str, Any] | None = Field(None, description="the marker detection behind V: id, name, height, V error to the scenario's")
    lift_margin_cm: float | None = None
    truth: RunTruth | None = None
    exact: bool | None = Field(None, description="bagit up in lockstep: every step was answered in full, so the run is "
                               "`bagit run`'s computation; False: see `inexact`; None: not a lockstep run")
    inexact: list[str] = Field(default_factory=list, description="why a lockstep run is not exact (a service dropped, a late answer)")
    recording: RecordingReport | None = Field(None, description="with a recorder on the rig: whether the run's recording failed, what it lost")
    provenance: Provenance | None = None

    def headline(self) -> str:
        """One line for people: verdict, error, time."""
        verdict = "SUCCESS" if self.success else f"FAILED at {self.stage_reached}: {self.reason}"
        err = f"error {self.error_cm:.2f} cm, " if self.error_cm is not None else ""
        dur = f"{self.duration_s:.1f} s servoing, " if self.duration_s is not None else ""
        return (f"{self.scenario} ({self.controller}, {self.planner}, seed {self.seed}, arms {self.arms}): {verdict}\n"
                f"{err}{dur}{self.wall_s:.1f} s wall, {self.ticks} ticks, planning {self.planning_time_s:.2f} s")


def points_list(a: np.ndarray | None, decimals: int = 5) -> list[list[float]] | None:
    """An (n, 3) array as JSON-able rounded lists (None stays None)."""
    if a is None:
        return None
    return np.round(np.asarray(a, dtype=float), decimals).tolist()


_PROVENANCE_CACHE: dict[str, Any] = {}


def provenance(params: dict[str, Any] | None = None) -> Provenance:
    """This code's commit (and whether the tree had changes), the host, its CPU and numerics, `params`, and now."""
    if not _PROVENANCE_CACHE:
        root = Path(__file__).resolve().parent.parent
        commit, dirty = None, None
        try:
            commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=5).stdout.strip() or None
            if commit:
                st = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=5)
                dirty = bool(st.stdout.strip())
        except (OSError, subprocess.SubprocessError):
            pass
        _PROVENANCE_CACHE.update(commit=commit, dirty=dirty, host=socket.gethostname(), cpu=cpu_model(),
                                 cores=os.cpu_count() or 0, python=platform.python_version())
    date = datetime.now(UTC).isoformat(timespec="seconds")
    return Provenance(**_PROVENANCE_CACHE, params=dict(params or {}), date=date, numerics=numerics())
