"""`bagit replay FILE`: publish a recording back onto Zenoh with its original timing.

The dashboard then shows the past run as if live. Stamps are moved to now (--keep-stamps keeps
them); commands and e-stops are not replayed unless --with-commands, which is refused while
anything listens to controller/cmd on the target rig.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from bagit.commands import _args

NAME = "replay"
HELP = "publish a recording back onto Zenoh with its original timing"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("file", type=Path, help="an MCAP file written by `bagit recorder`")
    p.add_argument("--speed", type=_args.positive_number, default=1.0, help="playback speed factor (default 1)")
    p.add_argument("--loop", action="store_true", help="start over at the end until stopped")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds")
    p.add_argument("--wait-s", type=_args.non_negative_seconds, default=2.0, help="wait this long for a subscriber before starting (default 2)")
    p.add_argument("--keep-stamps", action="store_true", help="publish the recorded stamps, not restamped to now")
    p.add_argument("--with-commands", action="store_true",
                   help="also replay controller/cmd and estop (refused while something subscribes to controller/cmd)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    import threading
    import time

    import numpy as np

    from bagit.common.bus import bus_config_from_args, open_session
    from bagit.common.errors import BadRecording
    from bagit.services.recorder.node import Replayer
    from bagit.services.recorder.reading import Recording

    if not args.file.is_file():
        raise BadRecording(f"{args.file}: no such recording")
    rig = args.rig
    if rig is None:  # the recording's own rig: from its first record
        first = next(iter(Recording(args.file).records()), None)
        if first is None:
            raise BadRecording(f"{args.file}: holds no BagIt message")
        rig = first.topic.split("/")[1] if first.topic.startswith("bagit/") else "default"
    args.rig = rig
    bus = bus_config_from_args(args)
    stop = threading.Event()
    from bagit.commands._service import stop_on_signals

    restore = stop_on_signals(stop)
    timer = threading.Timer(args.duration, stop.set) if args.duration else None
    t0 = time.monotonic()
    passes: list[dict[str, Any]] = []
    try:
        session = open_session(bus)
        try:
            rep = Replayer(session, rig=rig, speed=args.speed, with_commands=args.with_commands,
                           restamp=not args.keep_stamps, stop=stop)
            try:
                matched = rep.prepare(rig, args.wait_s)
                if timer is not None:
                    timer.start()
                while not stop.is_set():
                    passes.append(rep.play(args.file))
                    if not args.loop or rep.sent == 0:
                        break
            finally:
                rep.close()
        finally:
            session.close()
    finally:
        if timer is not None:
            timer.cancel()
        restore()
    late = np.array(rep.lateness) * 1e3 if rep.lateness else np.zeros(1)
    return {
        "success": rep.sent > 0,
        "reason": None if rep.sent else "nothing was published",
        "file": str(args.file),
        "rig": rig,
        "speed": args.speed,
        "passes": len(passes),
        "sent": rep.sent,
        "skipped": rep.skipped,
        "malformed": rep.bad,
        "subscriber_seen": matched,
        "complete": all(p["complete"] for p in passes),
        "truncated": next((p["truncated"] for p in passes if p["truncated"]), None),
        "wall_s": time.monotonic() - t0,
        "late_ms_p50": float(np.percentile(late, 50)),
        "late_ms_max": float(late.max()),
    }


def human(r: dict[str, Any]) -> str:
    s = (f"replayed {r['sent']} messages of {r['file']} on rig {r['rig']} at x{r['speed']:g} in {r['wall_s']:.1f} s "
         f"({r['passes']} pass(es), {r['skipped']} skipped, late p50 {r['late_ms_p50']:.1f} ms)")
    if r["truncated"]:
        s += f"; file truncated: {r['truncated']}"
    return s
