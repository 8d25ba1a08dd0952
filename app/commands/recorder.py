"""`bagit recorder`: record everything on bagit/<rig>/** to MCAP files (one per run, rolling while idle).

Files open in Foxglove (JSON messages with JSON Schemas; arrays as base64 of their wire bytes).
Stops on Ctrl-C or SIGTERM, finishing the open file; a SIGKILL leaves it readable up to its last
complete chunk (at most --flush-s of data lost). If its writer dies, it stops with failure (exit
status 1, the loss and the reason in its summary) after taking its liveliness token down.
"""

from __future__ import annotations

import argparse
import logging
import math
from pathlib import Path
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.recorder")

NAME = "recorder"
HELP = "record every message of a rig to MCAP files (one per run, rolling while idle)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    add_bus_arguments(p)
    p.add_argument("--dir", type=Path, default=Path("recordings"), help="folder of the recordings (default ./recordings)")
    p.add_argument("--max-mb", type=_args.positive_number, default=1024.0,
                   help="close a file before it would exceed this size in MB, and continue in the next part (default 1024)")
    p.add_argument("--chunk-kb", type=_args.positive_number, default=1024.0, help="MCAP chunk size in KB (default 1024)")
    p.add_argument("--flush-s", type=_args.positive_seconds, default=1.0, help="close a chunk at most this long after its first message")
    p.add_argument("--linger-s", type=_args.non_negative_seconds, default=2.0, help="keep a finished run's file open this long (its last states)")
    p.add_argument("--keep-idle", type=_args.positive_int, default=4, help="idle files of the rig kept (older ones deleted)")
    p.add_argument("--compression", choices=["zstd", "lz4", "none"], default="lz4",
                   help="chunk compression (default lz4: keeps up with 30 Hz RGB-D; zstd: ~40%% smaller, ~2x the CPU)")
    p.add_argument("--exclude", action="append", default=[], metavar="KEY",
                   help="key under bagit/<rig>/ not to record, e.g. camera/rgbd (repeatable; wildcards allowed)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until stopped)")


# RecorderConfig's fields, as the flags that set them (its bounds are the flags' bounds)
FLAGS = {"max_bytes": "--max-mb", "chunk_bytes": "--chunk-kb", "flush_s": "--flush-s", "linger_s": "--linger-s",
         "keep_idle": "--keep-idle", "dir": "--dir"}


def _bytes(value: float, unit: float) -> int:
    """`value` units in whole bytes; a product too large for a float stays too large (not an OverflowError)."""
    b = value * unit
    return int(b) if math.isfinite(b) else 1 << 1024


def run(args: argparse.Namespace) -> dict[str, Any]:

    from pydantic import ValidationError

    from bagit import __version__
    from bagit.commands._service import run_service
    from bagit.common.bus import bus_config_from_args
    from bagit.common.errors import BadRecording
    from bagit.services.recorder.node import RecorderNode, outcome
    from bagit.services.recorder.writer import RecorderConfig, RecordingWriter

    try:
        cfg = RecorderConfig(
            dir=args.dir, max_bytes=_bytes(args.max_mb, 1e6), chunk_bytes=_bytes(args.chunk_kb, 1e3), flush_s=args.flush_s,
            linger_s=args.linger_s, keep_idle=args.keep_idle, compression=args.compression,
        )
    except ValidationError as e:
        first = e.errors()[0]
        field = str(first["loc"][0])
        raise BadRecording(f"{FLAGS.get(field, field)}: {first['msg']}{' bytes' if field in ('max_bytes', 'chunk_bytes') else ''}") from None
    bus = bus_config_from_args(args)
    writer = RecordingWriter(cfg, bus.rig, version=__version__)
    # The node declares its own liveliness token and withdraws it when its writer dies (`stopped`).
    r = run_service("recorder", bus, lambda session, keys: RecorderNode(session, keys, writer, exclude=args.exclude), duration=args.duration,
                    banner=lambda node: f"recording {node.keys.all} into {cfg.dir}", alive=False)
    ok, reason = outcome(r)
    return {**r, "success": ok, "reason": reason, "dir": str(cfg.dir)}


def human(r: dict[str, Any]) -> str:
    return (f"recorded {r['messages']} messages into {len(r['files'])} file(s) in {r['dir']} over {r['uptime_s']:.1f} s"
            f" ({r['lost']} lost, {r['overflow']} dropped, {r['malformed']} malformed)")
