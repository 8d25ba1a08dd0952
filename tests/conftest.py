"""Test-wide settings: headless MuJoCo rendering, no network beyond loopback."""

import bagit  # noqa: F401, I001 - first: importing bagit pins the BLAS kernel before numpy loads (common/machine.py)

import functools
import os
import re
from pathlib import Path
from typing import Any

from bus_support import pair  # noqa: F401 - the two-session fixture every bus test takes
from hypothesis import settings

from bagit.common.headless import headless_gl

headless_gl()  # before any test module imports MuJoCo (conftest is imported before them)

# Property tests draw the same examples on every run: CI must not pass or fail by luck.
# BAGIT_HYPOTHESIS=explore draws fresh examples when hunting for new failures by hand.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("BAGIT_HYPOTHESIS", "ci"))


def pytest_collection_modifyitems(items: list) -> None:
    """A test module that brings up `bagit up` (up_support's rig_up or start_up) starts processes: marked
    here, once, so `make test-fast` leaves it out whatever its own marks say."""
    import pytest

    from bagit.harness import rig_up, start_up

    for item in items:
        module = getattr(item, "module", None)
        if module is not None and any(v is rig_up or v is start_up for v in vars(module).values()):
            item.add_marker(pytest.mark.processes)


# `make test` runs the suite on two workers (TEST_WORKERS=2), a file whole on one (`--dist loadfile`). The files whose tests start
# processes (whole rigs, services, a Dask cluster, a browser, simulated CR5s: start_sims, or the stop-time bench's
# driver_trials, which streams to them on the wall clock) or time messages on a bus run one
# after another on one worker, as one unit of work: they never share the two cores with each other, only with
# the other worker's in-process tests, as the serial suite's did with nothing.
ONE_AT_A_TIME = re.compile(r"mark\.processes|mark\.browser|start_sims|driver_trials|rigbus|session_pair|start_up|rig_up|subprocess")


@functools.cache
def _one_at_a_time(path: str) -> bool:
    try:
        return bool(ONE_AT_A_TIME.search((Path(__file__).parent.parent / path).read_text(encoding="utf-8")))
    except OSError:
        return False


def pytest_xdist_make_scheduler(config: Any, log: Any) -> Any:
    """`--dist loadfile`, with the ONE_AT_A_TIME files as one unit of work."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class OneAtATime(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "processes, one at a time" if _one_at_a_time(path) else path

    return OneAtATime(config, log)
