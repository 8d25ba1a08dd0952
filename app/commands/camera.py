"""`bagit camera`: publish a RealSense's frames on camera/rgbd, for a rig whose camera hangs off another machine.

The frames come from a live RealSense (picked by `--serial`, or the rig config's `camera.serial`,
or the only one attached) or from a RealSense recording (`--file`, e.g. one `write_recording`
made). Each frame carries the device's intrinsics and depth scale and the rig config's
camera-to-world extrinsics. The node declares liveliness `alive/camera` while it runs. No camera
attached: a one-line error naming what was looked for. Ctrl-C or SIGTERM stops cleanly.
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from bagit.commands import _args

log = logging.getLogger("bagit.camera")

NAME = "camera"
HELP = "publish a RealSense's (or a RealSense recording's) RGB-D frames on camera/rgbd"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--file", metavar="REC", help="play this RealSense recording (.db3, or an older .bag) instead of a live camera")
    p.add_argument("--serial", help="the RealSense's serial number (default: the rig config's, or the only one attached)")
    p.add_argument("--rig-config", metavar="YAML", help="rig config: camera extrinsics, serial, resolution (default: the built-in rig)")
    p.add_argument("--width", type=_args.positive_int, help="stream width (default: the rig config's, 640)")
    p.add_argument("--height", type=_args.positive_int, help="stream height (default: the rig config's, 480)")
    p.add_argument("--fps", type=_args.positive_int, help="frame rate (default: the rig config's, 30)")
    p.add_argument("--fast", action="store_true", help="--file: as fast as frames are published, not at recorded speed")
    p.add_argument("--loop", action="store_true", help="--file: start again at the end")
    p.add_argument("--frames", type=_args.positive_int, default=None, metavar="N", help="stop after N frames")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    import threading
    import time

    from bagit.commands._service import flagged_camera, stop_on_signals
    from bagit.common.bus import Keys, Publisher, bus_config_from_args, declare_alive, open_session
    from bagit.common.messages import RgbdFrame
    from bagit.common.rig import RigConfig
    from bagit.services.perception.sources import RealSenseSource, SourceConfig

    rig = RigConfig.from_file(args.rig_config) if args.rig_config else RigConfig()
    cam = flagged_camera(rig.camera, serial=args.serial, width=args.width, height=args.height, fps=args.fps)
    cfg = SourceConfig(kind="realsense-file" if args.file else "realsense", path=args.file, real_time=not args.fast, loop=args.loop)
    if args.rig is None:
        args.rig = rig.name
    bus = bus_config_from_args(args)
    keys = Keys(bus.rig)

    stop = threading.Event()
    restore = stop_on_signals(stop)
    n, size, t0 = 0, 0, time.monotonic()
    try:
        with RealSenseSource(cfg, cam) as source:  # no camera: CameraError before the bus opens
            session = open_session(bus)
            try:
                pub = Publisher(session, keys.camera_rgbd, RgbdFrame)
                token = declare_alive(session, keys, "camera")
                what = f"recording {cfg.path}" if args.file else f"RealSense {source.serial}"
                log.info("%s %dx%d -> %s", what, source.info.width, source.info.height, keys.camera_rgbd)
                while not stop.is_set():
                    if args.duration is not None and time.monotonic() - t0 >= args.duration:
                        break
                    frame = source.read()
                    if frame is None:
                        break  # the end of the recording
                    size = pub.put(frame)
                    n += 1
                    if args.frames is not None and n >= args.frames:
                        break
                token.undeclare()
                pub.close()
            finally:
                session.close()
            serial = source.serial
    finally:
        restore()
    wall = time.monotonic() - t0
    return {
        "success": True,
        "source": cfg.kind,
        "serial": serial,
        "key": keys.camera_rgbd,
        "frames": n,
        "frame_bytes": size,
        "wall_s": wall,
        "fps": n / wall if wall > 0 else 0.0,
        "interrupted": stop.is_set(),
    }


def human(r: dict[str, Any]) -> str:
    return f"published {r['frames']} frames ({r['fps']:.1f} Hz, {r['frame_bytes'] / 1e6:.2f} MB each) from {r['source']} {r['serial']} on {r['key']}"
