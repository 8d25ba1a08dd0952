"""Headless OpenGL is chosen once, at the entry points (`bagit.common.headless`): a process started
without MUJOCO_GL renders, and a child process inherits the choice."""

from __future__ import annotations

import os
import subprocess
import sys

from bagit.common.headless import HEADLESS_GL, headless_gl

GL_KEYS = (*HEADLESS_GL, "DISPLAY")

# A one-camera scene rendered through the simulator's camera; prints MUJOCO_GL and the depth at the centre.
RENDER = """
import os, sys
{entry}
import mujoco
from bagit.common.rig import CameraConfig
from bagit.services.sim.camera import RgbdRenderer
import bagit.services.sim.world  # noqa: F401 - the module that once set MUJOCO_GL on import
xml = '<mujoco><worldbody><camera name="cam" pos="0 0 1" xyaxes="1 0 0 0 1 0"/><geom type="plane" size="1 1 .1"/></worldbody></mujoco>'
model = mujoco.MjModel.from_xml_string(xml)
data = mujoco.MjData(model)
mujoco.mj_forward(model, data)
cam = CameraConfig(width=32, height=24, fx=30.0, fy=30.0)
rgb, depth = RgbdRenderer(model, cam, camera_name="cam").render(data)
print(os.environ.get("MUJOCO_GL"), round(float(depth[12, 16]), 3))
"""


def _bare_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if k not in GL_KEYS}


def _render(entry: str) -> list[str]:
    out = subprocess.run([sys.executable, "-c", RENDER.format(entry=entry)], env=_bare_env(), capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout.split()


def test_an_entry_point_chooses_osmesa_before_mujoco_loads():
    gl, depth = _render("from bagit.common.headless import headless_gl; headless_gl()")
    assert gl == "osmesa"
    assert float(depth) == 1.0  # the plane a metre below the camera


def test_a_bare_import_still_renders_headless():
    """No entry point: MuJoCo picks its default back-end and the camera falls back to OSMesa."""
    gl, depth = _render("")
    assert gl == "None"
    assert float(depth) == 1.0


def test_a_child_gets_the_choice_and_a_set_value_is_kept():
    env = headless_gl({"PATH": "/usr/bin", "MUJOCO_GL": "egl"})
    assert env == {"PATH": "/usr/bin", "MUJOCO_GL": "egl", "PYOPENGL_PLATFORM": "osmesa"}
    child = subprocess.run([sys.executable, "-c", "from bagit.common.headless import headless_gl; headless_gl(); "
                            "import subprocess, sys; subprocess.run([sys.executable, '-c', "
                            "'import os; print(os.environ[\"MUJOCO_GL\"], os.environ[\"PYOPENGL_PLATFORM\"])'])"],
                           env=_bare_env(), capture_output=True, text=True, timeout=60)
    assert child.stdout.split() == ["osmesa", "osmesa"]
