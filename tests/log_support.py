"""Collect what a logger (and its children) logs, from any thread, while a test runs."""

from __future__ import annotations

import logging


class LogLines(logging.Handler):
    """Attached to `logger` (at DEBUG) until `close()`: `messages` (a list that grows as records come) and
    the records themselves."""

    def __init__(self, logger: str) -> None:
        super().__init__(logging.DEBUG)
        self.records: list[logging.LogRecord] = []
        self.messages: list[str] = []
        self._logger = logging.getLogger(logger)
        self._level = self._logger.level
        self._logger.setLevel(logging.DEBUG)
        self._logger.addHandler(self)

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)
        self.messages.append(record.getMessage())

    def at(self, level: int) -> list[str]:
        """The messages logged at exactly `level`."""
        return [r.getMessage() for r in list(self.records) if r.levelno == level]

    def close(self) -> None:
        self._logger.removeHandler(self)
        self._logger.setLevel(self._level)
        super().close()

    def __enter__(self) -> LogLines:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()
