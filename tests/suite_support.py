"""What every test folder shares: the repository's root, and how long a test waits for what must happen.

A test asserts that something happens and in what order, never how fast: a busy machine may take far
longer than an idle one. So a wait for an event gives up only after `HANG_S`, a bound that catches a
hang and nothing else; how fast things happen is measured by the benchmarks under bench/.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from bagit.harness import wait_until as _poll

if TYPE_CHECKING:
    from bagit.common.scenario import Scenario

ROOT = Path(__file__).resolve().parents[1]
HANG_S = 60.0  # a wait this long means it hangs; a slow machine answers well within it


def wait_until(pred: Callable[[], bool], timeout: float = HANG_S, step: float = 0.005) -> bool:
    """Poll `pred` until true or `timeout` seconds pass; the default only guards against a hang."""
    return _poll(pred, timeout, step)


def exp12_in_a_bag_too_small() -> Scenario:
    """exp12 with its start rim shrunk to 0.568 m round: the bag's ellipse holds the object's bottom under C1,
    barely, and g* then touches the object, so the object does not fit (`check_scenario_goal`)."""
    from bagit.common.geometry import closed_polyline_length
    from bagit.common.scenario import Scenario
    from bagit.scenarios import find_scenario

    s = Scenario.from_file(find_scenario("exp12"))
    rim = s.bag.g0()
    c = rim.mean(axis=0)
    doc = s.model_dump(mode="json", exclude_none=True)
    doc["bag"].update(initial_rim=(c + (rim - c) * (0.568 / closed_polyline_length(rim))).tolist(), rim_perimeter=0.568)
    return Scenario.from_dict(doc)
