"""Headless OpenGL for MuJoCo's offscreen renders, chosen once at each entry point.

    headless_gl()                                   # first thing in a main, before anything imports MuJoCo
    env = headless_gl(dict(os.environ, X="1"))      # a child process's environment

MuJoCo picks its OpenGL back-end (`MUJOCO_GL`) when it is first imported, and PyOpenGL its platform
(`PYOPENGL_PLATFORM`) likewise; this machine and CI have no display, so both default to OSMesa. A
value already set (e.g. `MUJOCO_GL=egl` on a machine with a GPU) is kept. The entry points call it:
the CLI's `main`, `bagit.bench` (every bench module is a `python -m` main), the tests' conftest.
A library import without it still renders headless: the camera falls back to OSMesa on a Linux box
without a display (`bagit.services.sim.camera._gl_context`).
"""

from __future__ import annotations

import os
from collections.abc import MutableMapping

HEADLESS_GL: dict[str, str] = {"MUJOCO_GL": "osmesa", "PYOPENGL_PLATFORM": "osmesa"}


def headless_gl(env: MutableMapping[str, str] | None = None) -> MutableMapping[str, str]:
    """`env` (default: this process's `os.environ`, which children inherit) with HEADLESS_GL's values
    where it has none; returns it."""
    target: MutableMapping[str, str] = os.environ if env is None else env
    for key, value in HEADLESS_GL.items():
        target.setdefault(key, value)
    return target
