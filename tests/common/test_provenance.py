"""What a record says made its numbers (bagit.common.machine), and the lock that `make setup` installs from."""

from __future__ import annotations

import json
import re
import tomllib
from pathlib import Path

import numpy as np
from packaging.requirements import Requirement
from packaging.utils import canonicalize_name
from suite_support import ROOT

from bagit.common import machine
from bagit.common.results import RunResult, provenance


def test_provenance_names_the_libraries_the_blas_and_the_cpus_instruction_sets():
    n = provenance().numerics
    assert n is not None
    assert n.libraries["numpy"] == np.__version__ and set(n.libraries) == set(machine.NUMERIC_LIBRARIES)
    assert n.blas and all(b.internal_api and b.num_threads >= 1 for b in n.blas)  # numpy is loaded: its BLAS at least
    assert set(n.cpu_flags) <= set(machine.ISA_FLAGS)
    flags = re.search(r"^(?:flags|Features)\s*:(.*)$", Path("/proc/cpuinfo").read_text(), re.M)
    if flags:
        assert n.cpu_flags == [f for f in machine.ISA_FLAGS if f in flags.group(1).split()]
    assert "numerics" in json.loads(provenance().model_dump_json()) and str(np.__version__) in n.summary()


def test_the_variables_that_steer_the_kernels_are_recorded_when_set(monkeypatch):
    monkeypatch.setenv("OPENBLAS_CORETYPE", "Sandybridge")
    monkeypatch.delenv("OPENBLAS_L2_SIZE", raising=False)
    machine._static_numerics.cache_clear()
    try:
        env = machine.numerics().env
    finally:
        machine._static_numerics.cache_clear()
    assert env["OPENBLAS_CORETYPE"] == "Sandybridge" and "OPENBLAS_L2_SIZE" not in env


def test_the_piqp_build_is_the_one_loaded():
    import piqp  # noqa: F401 - loads the build its package chose

    assert machine.numerics().piqp_build in set(machine.PIQP_BUILDS.values())


def test_records_of_before_the_numerics_still_read():
    line = (ROOT / "bench/results/closed-loop-mpc-cr5.jsonl").read_text().splitlines()[0]
    r = RunResult.model_validate_json(line)
    assert r.provenance is not None and r.provenance.numerics is None and r.provenance.commit


def _lock() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "requirements.lock").read_text().splitlines():
        if line and not line.startswith((" ", "#")):
            name, sep, ver = line.partition("==")
            assert sep, f"requirements.lock: not an exact pin: {line}"
            pins[canonicalize_name(name)] = ver.split(";")[0].strip()
    return pins


def test_the_lock_pins_every_declared_dependency_within_its_range():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    declared = project["dependencies"] + [d for extra in ("dev", "cluster") for d in project["optional-dependencies"][extra]]
    pins = _lock()
    for spec in map(Requirement, declared):
        name = canonicalize_name(spec.name)
        assert name in pins, f"{spec.name} is declared in pyproject.toml but not in requirements.lock: run `make lock`"
        assert spec.specifier.contains(pins[name], prereleases=True), f"requirements.lock pins {spec.name}=={pins[name]}, outside {spec}"


def _blas_kernels(env: dict[str, str], first: str = "import bagit, numpy") -> list[str]:
    """The OpenBLAS kernels a fresh interpreter runs after `first`, with `env` on top of this one's less the pin."""
    import os
    import subprocess
    import sys

    base = {k: v for k, v in os.environ.items() if k not in machine.PINNED_BLAS_ENV}
    code = f"{first}\nfrom threadpoolctl import threadpool_info\nprint(sorted({{i['architecture'] for i in threadpool_info()}}))"
    out = subprocess.run([sys.executable, "-c", code], env={**base, **env}, capture_output=True, text=True, timeout=120, check=True)
    return json.loads(out.stdout.strip().replace("'", '"'))


def test_every_bagit_process_computes_with_one_blas_kernel():
    """A process that imports bagit before numpy runs OpenBLAS's Haswell kernel on any CPU with AVX2 and FMA,
    whatever OpenBLAS would have picked (the records' kernel: a run on another kernel differs in its last bits,
    and the closed loop makes that another run). A kernel set explicitly wins; numpy loaded first, no pin."""
    avx2 = {"avx2", "fma"} <= set(machine._cpu_flags())
    assert machine.pin_blas_kernel({}) is False  # numpy is loaded in this process: too late to choose
    if not avx2:
        return
    assert _blas_kernels({}) == ["Haswell"]
    assert _blas_kernels({"OPENBLAS_CORETYPE": "Sandybridge"}) == ["Sandybridge"]
    unpinned = _blas_kernels({}, "import numpy, bagit")
    assert len(unpinned) == 1  # OpenBLAS's own pick (SkylakeX on an AVX-512 CPU), which the record then names
