"""Benchmarks behind `bagit bench`: each prints numbers, none is a pass/fail test.

Each module is also a `python -m bagit.bench.<name>` main, whose imports run before its `__main__`
block: this package, imported first, is where they all choose headless OpenGL before MuJoCo loads.
"""

from bagit.common.headless import headless_gl

headless_gl()
