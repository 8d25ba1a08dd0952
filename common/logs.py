"""The one logging set-up of every BagIt process: one format, on stderr.

`bagit.cli.main` (the composition root) calls `configure_logging()` once per command; every module
logs through `logging.getLogger("bagit.<service>")` and never configures handlers itself.

    2025-05-01 14:03:07.412 WARNING bagit.controller: hold: no SOI for 0.5 s

BagIt's level is INFO unless BAGIT_LOG_LEVEL names another (DEBUG, INFO, WARNING, ERROR); other
libraries log their warnings and errors only. What a
command prints as its result (a `--json` document, a table) is not a log line and stays a print.
`bagit up` prefixes each child's lines with `[service]`, so a line says who, when, how bad and what.
"""

from __future__ import annotations

import logging
import os
import sys
from typing import TextIO

LOG_FORMAT = "%(asctime)s.%(msecs)03d %(levelname)s %(name)s: %(message)s"
DATE_FORMAT = "%Y-%m-%d %H:%M:%S"
LEVEL_ENV = "BAGIT_LOG_LEVEL"


class _StderrHandler(logging.StreamHandler):
    """A stream handler that writes to whatever sys.stderr is at the time of each record (so a
    handler set up once still writes where stderr is redirected later, e.g. by a test's capture)."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:
        pass


def _level(level: int | str | None) -> int:
    name = level if level is not None else os.environ.get(LEVEL_ENV, "INFO")
    if isinstance(name, int):
        return name
    value = logging.getLevelName(name.strip().upper())
    if not isinstance(value, int):
        raise ValueError(f"{LEVEL_ENV}={name!r} is not a logging level (DEBUG, INFO, WARNING, ERROR)")
    return value


def configure_logging(level: int | str | None = None) -> None:
    """Log BagIt's records at `level` or above (default: BAGIT_LOG_LEVEL, else INFO), and other
    libraries' at WARNING or above, to stderr in LOG_FORMAT.

    Idempotent: a second call replaces the handler of the first instead of adding one.
    """
    root = logging.getLogger()
    for h in list(root.handlers):
        if isinstance(h, _StderrHandler):
            root.removeHandler(h)
    handler = _StderrHandler()
    handler.setFormatter(logging.Formatter(LOG_FORMAT, DATE_FORMAT))
    root.addHandler(handler)
    ours = _level(level)
    root.setLevel(max(ours, logging.WARNING))
    logging.getLogger("bagit").setLevel(ours)
