"""`bagit`: the one command-line entry point.

Errors the user can fix (bad files, bad input, infeasible goals, bad flags) print one line on stderr
and exit with status 2; a job that ran but did not succeed exits with 1. Set BAGIT_DEBUG=1 for tracebacks.
The composition root of every process: it chooses headless OpenGL (`bagit.common.headless`) and sets up logging (`bagit.common.logs`, one format on
stderr, level from BAGIT_LOG_LEVEL) before a command runs; stdout carries only the command's result.
"""

from __future__ import annotations

import argparse
import faulthandler
import importlib
import json
import os
import signal
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any, NoReturn

import numpy as np

from bagit import __version__
from bagit.common.errors import BagItError
from bagit.common.headless import headless_gl
from bagit.common.logs import configure_logging

# The subcommands, in the order `bagit --help` lists them.
COMMAND_MODULES: list[str] = [
    "bagit.commands.demo",
    "bagit.commands.extract",
    "bagit.commands.goal",
    "bagit.commands.plan",
    "bagit.commands.run",
    "bagit.commands.sim",
    "bagit.commands.camera",
    "bagit.commands.calibrate",
    "bagit.commands.bench",
    "bagit.commands.perception",
    "bagit.commands.controller",
    "bagit.commands.arm_driver",
    "bagit.commands.router",
    "bagit.commands.dashboard",
    "bagit.commands.planner",
    "bagit.commands.up",
    "bagit.commands.recorder",
    "bagit.commands.replay",
    "bagit.commands.runs",
]


def _load(name: str) -> ModuleType:
    return importlib.import_module(name)


def _to_jsonable(obj: Any) -> Any:
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, (np.floating, np.integer, np.bool_)):
        return obj.item()
    if isinstance(obj, dict):
        return {str(k): _to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_to_jsonable(v) for v in obj]
    return obj


def print_json(result: dict[str, Any]) -> None:
    """Print a result as one JSON document on stdout."""
    print(json.dumps(_to_jsonable(result)))


class OneLineParser(argparse.ArgumentParser):
    """argparse whose usage errors are one line, like every other error of the CLI (exit status 2):
    `bagit run: error: argument --seed: seed must be in [0, 4294967295], got -1 (see bagit run --help)`."""

    def error(self, message: str) -> NoReturn:
        first = message.splitlines()[0] if message else "bad arguments"
        self.exit(2, f"{self.prog}: error: {first} (see {self.prog} --help)\n")


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, ModuleType]]:
    parser = OneLineParser(prog="bagit", description="Dual-arm bagging of objects into fabric bags.")
    parser.add_argument("--version", action="version", version=f"bagit {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    modules: dict[str, ModuleType] = {}
    for modname in COMMAND_MODULES:
        mod = _load(modname)
        p = sub.add_parser(mod.NAME, help=mod.HELP, description=mod.HELP)
        p.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
        mod.add_arguments(p)
        modules[mod.NAME] = mod
    return parser, modules


def _stacks_on_sigusr1() -> None:
    """`kill -USR1 PID` prints every thread's stack to stderr: how a stuck service (or a test waiting on
    one) tells where it waits. Not where stderr is no file (a caller's captured stream)."""
    try:
        faulthandler.register(signal.SIGUSR1, all_threads=True)
    except (OSError, ValueError, AttributeError, RuntimeError):
        pass


def main(argv: Sequence[str] | None = None) -> int:
    headless_gl()  # before any command imports MuJoCo; the services `bagit up` starts inherit it
    parser, modules = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as e:  # --help, --version, or a usage error (already one line on stderr): its status
        return e.code if isinstance(e.code, int) else 0 if e.code is None else 2
    if not args.command:
        parser.print_help()
        return 2
    mod = modules[args.command]
    _stacks_on_sigusr1()
    try:
        configure_logging()
        result = mod.run(args)
    except KeyboardInterrupt:
        print(f"bagit {args.command}: interrupted", file=sys.stderr)
        return 130
    except (BagItError, OSError, ValueError) as e:
        if os.environ.get("BAGIT_DEBUG"):
            raise
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        print(f"bagit {args.command}: error: {msg}", file=sys.stderr)
        return 2
    if result is None:
        return 0
    if args.json:
        print_json(result)
    elif hasattr(mod, "human"):
        print(mod.human(result))
    if result.get("success") is False:
        if not args.json:
            print(f"bagit {args.command}: failed: {result.get('reason', 'unknown reason')}", file=sys.stderr)
        return 1
    recording = result.get("recording")
    if isinstance(recording, dict) and recording.get("ok") is False:  # a run whose recording failed is no silent success
        print(f"bagit {args.command}: the run's recording failed: {recording.get('lost')} messages lost ({recording.get('error')})", file=sys.stderr)
        return 1
    if result.get("exact") is False and not getattr(args, "allow_inexact", False):  # never a silent success
        why = "; ".join(result.get("inexact") or []) or "unknown reason"
        print(f"bagit {args.command}: the run is not exact (it may differ from `bagit run`'s): {why}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
