"""What computed a number besides the code: the libraries' versions, the BLAS and its kernel, the CPU's
instruction sets and the variables that steer them. Records carry it (`Provenance.numerics`) because the
closed loop grows a last-bit difference into another run: on the same code and scenario, the BLAS kernel
(OpenBLAS picks it from the CPU, or from `OPENBLAS_CORETYPE`), numpy's and PIQP's AVX-512 paths (taken
only on a CPU that has them) each change a run's ticks and error (docs/experiments.md, "Bit for bit").
"""

from __future__ import annotations

import importlib
import os
import platform
import sys
from collections.abc import MutableMapping
from functools import cache
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

from pydantic import BaseModel, ConfigDict, Field

# The distributions whose code computes a run (PyPI names), and threadpoolctl, which reads the BLAS.
NUMERIC_LIBRARIES = ("numpy", "scipy", "mujoco", "piqp", "ruckig", "open3d", "opencv-python-headless", "eclipse-zenoh", "pydantic",
                     "threadpoolctl")
# Environment variables that change which kernels run or how many threads they use (recorded when set).
NUMERIC_ENV = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS",
               "NPY_DISABLE_CPU_FEATURES", "NPY_ENABLE_CPU_FEATURES")
# The CPU's instruction sets that the libraries above choose kernels by (x86 `flags`, Arm `Features` in /proc/cpuinfo).
ISA_FLAGS = ("sse4_2", "avx", "avx2", "fma", "f16c", "avx512f", "avx512dq", "avx512cd", "avx512bw", "avx512vl", "avx512ifma", "avx512vbmi",
             "avx512_vnni", "avx512_bf16", "avx512_fp16", "amx_tile", "asimd", "sve", "sve2")
# The BLAS kernel every BagIt process computes with on an x86-64 CPU with AVX2 and FMA, whatever OpenBLAS would pick
# by itself (SkylakeX on an AVX-512 CPU, Zen, ...) or a machine's image sets: the kernel changes a run's last bits,
# which the closed loop grows into other ticks and errors. Haswell's, with the L2 size its blocking assumes, is what
# the published records were computed with (their `numerics.env`) and runs on every such CPU. Set where unset.
PINNED_BLAS_ENV = {"OPENBLAS_CORETYPE": "Haswell", "OPENBLAS_L2_SIZE": "512"}
# PIQP's builds, one per instruction set; its package loads the widest the CPU runs.
PIQP_BUILDS = {"piqp.piqp_python_avx512": "avx512", "piqp.piqp_python_avx2": "avx2", "piqp.piqp_python": "generic"}


class BlasLibrary(BaseModel):
    """One BLAS loaded in the process (numpy, scipy and OpenCV each bring their own), as threadpoolctl reads it."""

    model_config = ConfigDict(extra="forbid")

    library: str = Field(description="the shared library's file name: which package brought it")
    internal_api: str = Field(description="openblas | mkl | blis | ...")
    version: str | None = None
    architecture: str | None = Field(None, description="the kernel in use (OpenBLAS: its core type, e.g. Haswell, SkylakeX)")
    threading_layer: str | None = None
    num_threads: int = 0


class Numerics(BaseModel):
    """The libraries, BLAS, CPU instruction sets and variables behind a result (see the module docstring)."""

    model_config = ConfigDict(extra="forbid")

    libraries: dict[str, str | None] = Field(default_factory=dict, description="installed version of each of NUMERIC_LIBRARIES (None: absent)")
    blas: list[BlasLibrary] = Field(default_factory=list, description="every BLAS loaded when the record was made")
    env: dict[str, str] = Field(default_factory=dict, description="those of NUMERIC_ENV that were set")
    cpu_flags: list[str] = Field(default_factory=list, description="those of ISA_FLAGS the CPU has")
    numpy_simd: list[str] = Field(default_factory=list, description="numpy's run-time dispatched CPU targets in use (e.g. X86_V3, X86_V4)")
    piqp_build: str | None = Field(None, description="the PIQP build loaded: avx512 | avx2 | generic (None: not loaded)")

    def summary(self) -> str:
        """One line for a report's header."""
        libs = ", ".join(f"{k.removeprefix('eclipse-').removesuffix('-python-headless')} {v}" for k, v in self.libraries.items() if v)
        blas = "; ".join(f"{b.internal_api} {b.version} {b.architecture} x{b.num_threads} ({b.library})" for b in self.blas)
        env = " ".join(f"{k}={v}" for k, v in self.env.items())
        return (f"{libs}; BLAS: {blas or 'none loaded'}; numpy SIMD {'+'.join(self.numpy_simd) or 'baseline'}, PIQP {self.piqp_build or '-'}; "
                f"CPU flags: {' '.join(self.cpu_flags)}" + (f"; {env}" if env else ""))


def pin_blas_kernel(environ: MutableMapping[str, str] = os.environ) -> bool:
    """Set PINNED_BLAS_ENV in `environ` (a variable already set wins: an explicit choice) before OpenBLAS loads;
    children inherit it. False when it cannot apply: not an x86-64 CPU with AVX2 and FMA, or numpy (and its
    OpenBLAS) already loaded; the kernel is then OpenBLAS's own pick, which every record still names."""
    if "numpy" in sys.modules or platform.machine().lower() not in ("x86_64", "amd64") or not {"avx2", "fma"} <= set(_cpu_flags()):
        return False
    for k, v in PINNED_BLAS_ENV.items():
        environ.setdefault(k, v)
    return all(environ.get(k) == v for k, v in PINNED_BLAS_ENV.items())


def cpu_model() -> str:
    """The CPU's model name (Linux's /proc/cpuinfo; else what the platform says)."""
    for key, value in _cpuinfo_fields():
        if key in ("model name", "Model"):
            return value
    return platform.processor() or ""


def numerics() -> Numerics:
    """This process's numerics: what is fixed for its life read once, the BLAS (threads, libraries loaded since) each call (~2 ms)."""
    return _static_numerics().model_copy(update={"blas": blas_libraries(), "piqp_build": _piqp_build()})


def blas_libraries() -> list[BlasLibrary]:
    """Every BLAS loaded now, with its kernel and threads (empty without threadpoolctl)."""
    try:
        from threadpoolctl import threadpool_info
    except ImportError:
        return []
    return [BlasLibrary(library=Path(i.get("filepath") or "").name, internal_api=str(i.get("internal_api")), version=i.get("version"),
                        architecture=i.get("architecture"), threading_layer=i.get("threading_layer"), num_threads=int(i.get("num_threads") or 0))
            for i in threadpool_info() if i.get("user_api") == "blas"]


@cache
def _cpu_flags() -> tuple[str, ...]:
    """The first processor's instruction-set flags (x86 `flags`, Arm `Features` in /proc/cpuinfo), read once a process."""
    return next((tuple(value.split()) for key, value in _cpuinfo_fields() if key in ("flags", "Features")), ())


@cache
def _static_numerics() -> Numerics:
    flags = set(_cpu_flags())
    return Numerics(libraries={d: _version(d) for d in NUMERIC_LIBRARIES}, env={k: os.environ[k] for k in NUMERIC_ENV if k in os.environ},
                    cpu_flags=[f for f in ISA_FLAGS if f in flags], numpy_simd=_numpy_simd())


def _version(dist: str) -> str | None:
    try:
        return version(dist)
    except PackageNotFoundError:
        return None


def _numpy_simd() -> list[str]:
    """numpy's dispatched targets that this CPU runs and no NPY_DISABLE_CPU_FEATURES turned off."""
    try:
        umath = importlib.import_module("numpy._core._multiarray_umath")
    except ImportError:  # numpy 1.x
        umath = importlib.import_module("numpy.core._multiarray_umath")
    features: dict[str, bool] = getattr(umath, "__cpu_features__", {})
    return [t for t in getattr(umath, "__cpu_dispatch__", []) if features.get(t)]


def _piqp_build() -> str | None:
    """Which of PIQP's builds this process loaded (its package chose by the CPU), without importing it."""
    return next((b for m, b in PIQP_BUILDS.items() if m in sys.modules), None)


@cache
def _cpuinfo_fields() -> tuple[tuple[str, str], ...]:
    """The first processor's `key: value` lines of /proc/cpuinfo (empty elsewhere)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return ()
    fields = []
    for line in text.split("\n\n", 1)[0].splitlines():
        key, sep, value = line.partition(":")
        if sep:
            fields.append((key.strip(), value.strip()))
    return tuple(fields)
