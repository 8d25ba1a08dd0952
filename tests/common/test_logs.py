"""The one log format: what `bagit.cli.main` sets up for every command."""

from __future__ import annotations

import logging
import re

import pytest

from bagit.common.logs import LEVEL_ENV, configure_logging

LINE = re.compile(r"^\d{4}-\d\d-\d\d \d\d:\d\d:\d\d\.\d{3} (?P<level>[A-Z]+) (?P<name>[\w.]+): (?P<msg>.*)$")


@pytest.fixture
def restore_logging():
    root, ours = logging.getLogger(), logging.getLogger("bagit")
    saved = (list(root.handlers), root.level, ours.level)
    yield
    root.handlers[:], (root.level, ours.level) = saved[0], saved[1:]


def test_one_line_per_record_in_the_one_format_and_a_second_call_adds_no_handler(restore_logging, capsys, monkeypatch):
    monkeypatch.delenv(LEVEL_ENV, raising=False)
    configure_logging()
    configure_logging()
    logging.getLogger("bagit.controller").warning("hold: %s", "no SOI")
    logging.getLogger("bagit.planner").info("run r1: bagging")
    logging.getLogger("bagit.planner").debug("not at INFO")
    logging.getLogger("somelib").info("a library's chatter stays out")
    lines = capsys.readouterr().err.splitlines()
    parsed = [LINE.match(ln) for ln in lines]
    assert all(parsed) and len(lines) == 2, lines
    assert [(m["level"], m["name"], m["msg"]) for m in parsed if m] == [
        ("WARNING", "bagit.controller", "hold: no SOI"), ("INFO", "bagit.planner", "run r1: bagging")]


def test_the_level_comes_from_the_environment_and_a_bad_one_is_refused(restore_logging, capsys, monkeypatch):
    monkeypatch.setenv(LEVEL_ENV, "debug")
    configure_logging()
    logging.getLogger("bagit.sim").debug("step 3")
    assert "DEBUG bagit.sim: step 3" in capsys.readouterr().err
    monkeypatch.setenv(LEVEL_ENV, "loud")
    with pytest.raises(ValueError, match="BAGIT_LOG_LEVEL"):
        configure_logging()


def test_a_bad_level_is_one_line_from_the_cli(restore_logging, capsys, monkeypatch):
    from bagit.cli import main

    monkeypatch.setenv(LEVEL_ENV, "loud")
    assert main(["goal", "exp02"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "BAGIT_LOG_LEVEL='loud' is not a logging level" in err[0], err
