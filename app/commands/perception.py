"""`bagit perception`: the bag's rim (the SOI) from RGB-D frames, on the rig's bus.

Frames from camera/rgbd (`--source zenoh`, the default), a live RealSense (`--source realsense`)
or a RealSense recording (`--source realsense-file --file REC.db3`). Publishes perception/soi per
frame and a down-sampled perception/cloud for display. No camera attached: a one-line error.
A recording played without `--loop` ends the command when it ends.
"""

from __future__ import annotations

import argparse
from typing import Any

from bagit.commands import _args

NAME = "perception"
HELP = "find the bag rim (SOI) in RGB-D frames from the bus, a RealSense or a recording"


def add_arguments(p: argparse.ArgumentParser) -> None:
    from bagit.common.bus import add_bus_arguments

    p.add_argument("--config", metavar="YAML", help="service config (source, n_x, bag_kind, bag_color, cloud_rate_hz, soi, bus, ...)")
    p.add_argument("--source", choices=["zenoh", "realsense", "realsense-file"], help="where frames come from (default zenoh)")
    p.add_argument("--file", metavar="REC", help="realsense-file: the recording (.db3, or an older .bag)")
    p.add_argument("--serial", help="realsense: the camera's serial number (default: the rig config's camera.serial, else the only one attached)")
    p.add_argument("--fast", action="store_true", default=None, help="realsense-file: as fast as frames are processed, not at recorded speed")
    p.add_argument("--loop", action="store_true", default=None, help="realsense-file: start again at the end")
    p.add_argument("--rig-config", metavar="YAML", help="rig config: the camera (serial, mode, extrinsics) for realsense sources (default: built-in rig)")
    p.add_argument("--n-x", type=_args.soi_points, help="SOI points (default: the run's scenario, else 32)")
    p.add_argument("--bag-kind", choices=["red-edged", "solid"], help="the bag (default: the run's scenario, else red-edged)")
    p.add_argument("--cloud-rate", type=_args.non_negative_number, metavar="HZ", help="display cloud rate (default 10 Hz; 0: none)")
    p.add_argument("--duration", type=_args.positive_seconds, default=None, metavar="S", help="stop after S seconds (default: until Ctrl-C)")
    add_bus_arguments(p)


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bagit.commands._service import flagged_camera, load_service_config, run_service, service_rig
    from bagit.services.perception.node import PerceptionNode, PerceptionServiceConfig

    source = {"kind": args.source or ("realsense-file" if args.file else None), "path": args.file,
              "real_time": None if args.fast is None else not args.fast, "loop": args.loop}
    overrides = {"source": source, "rig_config": args.rig_config, "n_x": args.n_x, "bag_kind": args.bag_kind,
                 "cloud_rate_hz": args.cloud_rate}
    cfg, bus = load_service_config(PerceptionServiceConfig, args.config, overrides, args)
    camera = flagged_camera(service_rig(cfg.rig_config, args.rig_config, args.config).camera, serial=args.serial)

    def banner(node) -> str:
        what = {"zenoh": node.keys.camera_rgbd, "realsense": "a live RealSense", "realsense-file": str(cfg.source.path)}[cfg.source.kind]
        return f"frames from {what} -> {node.keys.perception_soi}"

    return run_service("perception", bus, lambda session, keys: PerceptionNode(session, keys, cfg, camera, clock=bus.clock),
                       duration=args.duration, banner=banner)


def human(r: dict[str, Any]) -> str:
    c = r["counters"]
    return (f"perception stopped after {r['uptime_s']:.1f} s: {c['published']} SOIs from {c['frames']} frames "
            f"({c['dropped']} dropped stale, {c['bad']} bad), median {r['solve_ms']['median']:.0f} ms per frame")
