"""What every test folder shares: the repository's root, and how long a test waits for what must happen.

A test asserts that something happens and in what order, never how fast: a busy machine may take far
longer than an idle one. So a wait for an event gives up only after `HANG_S`, a bound that catches a
hang and nothing else; how fast things happen is measured by the benchmarks under bench/.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from bagit.harness import wait_until as _poll

ROOT = Path(__file__).resolve().parents[1]
HANG_S = 60.0  # a wait this long means it hangs; a slow machine answers well within it


def wait_until(pred: Callable[[], bool], timeout: float = HANG_S, step: float = 0.005) -> bool:
    """Poll `pred` until true or `timeout` seconds pass; the default only guards against a hang."""
    return _poll(pred, timeout, step)
