"""Test-wide settings: headless MuJoCo rendering, no network beyond loopback."""

import os
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


# The files whose tests bring up whole rigs (`bagit up`, the multi-host rig, a Dask cluster) or a browser.
# `make test` runs the suite on two workers, a file whole on one (`--dist loadfile`); these run one after
# another on one worker, so that two rigs or a rig and a Chromium never share the two cores.
ONE_AT_A_TIME = (
    "tests/app/test_up.py",
    "tests/app/test_up_browser.py",
    "tests/dashboard/test_dashboard_browser.py",
    "tests/bench/test_bench_multihost.py",
    "tests/bench/test_bench_cluster.py",
)


def pytest_xdist_make_scheduler(config: Any, log: Any) -> Any:
    """`--dist loadfile`, with the ONE_AT_A_TIME files as one unit of work."""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class OneRigAtATime(LoadFileScheduling):
        def _split_scope(self, nodeid: str) -> str:
            path = super()._split_scope(nodeid)
            return "whole rigs" if path in ONE_AT_A_TIME else path

    return OneRigAtATime(config, log)
