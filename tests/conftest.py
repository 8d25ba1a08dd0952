"""Test-wide settings: headless MuJoCo rendering, no network beyond loopback."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

from bus_support import pair  # noqa: E402, F401 - the two-session fixture every bus test takes
from hypothesis import settings  # noqa: E402

# Property tests draw the same examples on every run: CI must not pass or fail by luck.
# BAGIT_HYPOTHESIS=explore draws fresh examples when hunting for new failures by hand.
settings.register_profile("ci", derandomize=True, database=None, print_blob=True)
settings.register_profile("explore", derandomize=False)
settings.load_profile(os.environ.get("BAGIT_HYPOTHESIS", "ci"))
