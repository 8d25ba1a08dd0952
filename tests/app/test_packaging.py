"""The project installs as a built wheel, not only as an editable checkout."""

import os
import subprocess
import sys
import sysconfig
import zipfile

import pytest
from suite_support import ROOT


@pytest.mark.processes
@pytest.mark.slow
def test_wheel_builds_installs_and_imports(tmp_path):
    out = tmp_path / "dist"
    subprocess.run(
        [sys.executable, "-m", "build", "--wheel", "--no-isolation", "--outdir", str(out), str(ROOT)],
        check=True,
        capture_output=True,
        cwd=tmp_path,
    )
    (wheel,) = out.glob("bagit-*.whl")
    names = zipfile.ZipFile(wheel).namelist()
    for must in ["bagit/cli.py", "bagit/common/geometry.py", "bagit/services/perception/__init__.py", "bagit/scenarios/__init__.py"]:
        assert must in names, must
    assert any(n.startswith("bagit/scenarios/") and n.endswith(".yaml") for n in names)
    assert not any(n.startswith("tests/") for n in names)

    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)], check=True)
    # Dependencies come from this environment's site-packages; `bagit` itself must come from the wheel.
    env = dict(os.environ, PYTHONPATH=sysconfig.get_paths()["purelib"])
    code = (
        "import bagit, bagit.common, bagit.services.perception, bagit.services.planner, bagit.scenarios;"
        "print(bagit.__file__); print(len(bagit.scenarios.list_scenarios()))"
    )
    res = subprocess.run([str(py), "-c", code], check=True, capture_output=True, text=True, env=env, cwd=tmp_path)
    first, count = res.stdout.split()
    assert first.startswith(str(venv)), first
    assert int(count) > 0
    res = subprocess.run([str(venv / "bin" / "bagit"), "--help"], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert res.returncode == 0 and "extract" in res.stdout
