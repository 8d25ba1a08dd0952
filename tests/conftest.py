"""Test-wide settings: headless MuJoCo rendering, no network beyond loopback."""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")
