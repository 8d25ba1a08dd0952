"""argparse types for the numbers a user gives on the command line: one refusal rule per kind.

A flag of one of these types refuses NaN, infinities, negatives where they mean nothing and values
that would overflow later (`--max-mb inf`, `--duration 1e300` waits past what the OS can time), at
parse time, with the flag's name in a one-line error. Bounds that belong to a service's config stay
in its pydantic model, which the command validates after parsing.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from typing import Any

from bagit.common.names import MAX_N_X, MIN_N_X

MAX_SEED = 2**32 - 1  # numpy's legacy seed range; also exact in every JSON reader (the dashboard's included)
MAX_SECONDS = 366 * 24 * 3600.0  # a year: far under threading.TIMEOUT_MAX; longer: run without --duration
MAX_PORT = 65535
MAX_COUNT = 2**31 - 1  # a count (a width, frames, points, workers) fits the C int it may be handed to


def _float(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None


def positive_number(text: str) -> float:
    """A finite number > 0 (a rate, a speed factor, a size)."""
    v = _float(text)
    if not (math.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


def non_negative_number(text: str) -> float:
    """A finite number >= 0 (a rate where 0 means never)."""
    v = _float(text)
    if not (math.isfinite(v) and v >= 0):
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return v


def positive_seconds(text: str) -> float:
    """A duration in (0, MAX_SECONDS] seconds: `Event.wait` overflows on a huge one."""
    v = positive_number(text)
    if v > MAX_SECONDS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SECONDS:.0f} s (a year), got {text}")
    return v


def non_negative_seconds(text: str) -> float:
    """A duration in [0, MAX_SECONDS] seconds."""
    v = non_negative_number(text)
    if v > MAX_SECONDS:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_SECONDS:.0f} s (a year), got {text}")
    return v


def int_in(lo: int, hi: int | None = None, what: str = "") -> Callable[[str], int]:
    """An argparse type: a whole number in [lo, hi] (no upper bound with hi None)."""

    def parse(text: str) -> int:
        v = _int(text)
        if v < lo or (hi is not None and v > hi):
            span = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
            raise argparse.ArgumentTypeError(f"{what + ' ' if what else ''}must be {span}, got {v}")
        return v

    parse.__name__ = what.replace(" ", "_") or f"int_from_{lo}"  # argparse names the type in some errors
    return parse


non_negative_int = int_in(0, MAX_COUNT, "count")
positive_int = int_in(1, MAX_COUNT, "count")
seed = int_in(0, MAX_SEED, "seed")
port = int_in(0, MAX_PORT, "port")
soi_points = int_in(MIN_N_X, MAX_N_X, "SOI points")


def json_object(text: str) -> dict[str, Any]:
    """A JSON object (e.g. method parameters)."""
    try:
        v = json.loads(text)
    except (json.JSONDecodeError, RecursionError) as e:
        raise argparse.ArgumentTypeError(f"not JSON: {e}") from None
    if not isinstance(v, dict):
        raise argparse.ArgumentTypeError("must be a JSON object of method parameters")
    return v


def moved(where: str) -> Callable[[str], Any]:
    """The type of a flag that no longer exists: refused, whatever its value, saying where the setting is now."""

    def refuse(text: str) -> Any:
        raise argparse.ArgumentTypeError(f"no longer a flag of this command: the setting is {where}")

    return refuse
