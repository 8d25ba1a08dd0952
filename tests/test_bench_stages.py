"""`bagit bench stages`: every listed stage is a benchmark module, and the arm driver's measures Ruckig alone."""

from __future__ import annotations

import importlib

import numpy as np

from bagit.bench import arm_driver
from bagit.commands.bench import STAGES


def test_every_stage_is_a_benchmark_module_with_run() -> None:
    for name in STAGES:
        mod = importlib.import_module(f"bagit.bench.{name}")
        assert callable(getattr(mod, "run", None)), name


def test_the_arm_driver_benchmark_times_one_12_axis_ruckig_update_and_the_cycle_around_it() -> None:
    r = arm_driver._offline(30)  # noqa: SLF001
    assert {"ruckig", "pipeline", "format", "reach", "cycle"} <= set(r)
    for name, s in r.items():
        assert s["n"] == 30 and np.isfinite(s["median_ms"]) and 0 < s["min_ms"] <= s["median_ms"], name
    # the pipeline runs one Ruckig update per cycle and more besides
    assert r["pipeline"]["median_ms"] > r["ruckig"]["median_ms"]
