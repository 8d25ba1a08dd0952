"""BagIt: dual-arm bagging of objects into fabric bags.

`bagit` is the composition root: the CLI and the in-process pipeline are the only code that
imports several services. The ground floor is `bagit.common`; each stage lives in
`bagit.services.<stage>`.
"""

__version__ = "0.1.0"

from bagit.common.machine import pin_blas_kernel

pin_blas_kernel()  # before anything loads numpy: one BLAS kernel on every AVX2 machine (common/machine.py's PINNED_BLAS_ENV)
