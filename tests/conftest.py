"""Test-wide settings: headless MuJoCo rendering, no network beyond loopback."""

import os

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
