"""Write RGB-D frames into a RealSense recording that pyrealsense2 plays back like a real camera's.

A pyrealsense2 software device with a depth sensor and a colour sensor takes the frames; a
pyrealsense2 recorder attached to it writes what the sensors emit. pyrealsense2 2.59 writes ROS 2
bags and insists on the `.db3` extension. The recording keeps the streams' intrinsics, the depth
units and the depth-to-colour extrinsics (identity: the frames are already registered), so a
`realsense-file` source reads back the same pixels, intrinsics and depth scale.

Used to make test recordings from simulated frames, and to turn any frames into a file the
RealSense Viewer opens.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from bagit.common.errors import CameraError
from bagit.common.messages import CameraInfo, RgbdFrame

DEFAULT_SERIAL = "BAGIT-SIM"


def _intrinsics(rs, info: CameraInfo):
    k = rs.intrinsics()
    k.width, k.height = info.width, info.height
    k.fx, k.fy, k.ppx, k.ppy = info.fx, info.fy, info.cx, info.cy
    k.model = rs.distortion.none
    k.coeffs = [0.0] * 5
    return k


def _stream(rs, kind, uid: int, info: CameraInfo, fps: int, bpp: int, fmt):
    s = rs.video_stream()
    s.type, s.index, s.uid = kind, 0, uid
    s.width, s.height, s.fps, s.bpp, s.fmt = info.width, info.height, fps, bpp, fmt
    s.intrinsics = _intrinsics(rs, info)
    return s


def write_recording(frames: Iterable[RgbdFrame], path: str | Path, fps: int = 30, serial: str = DEFAULT_SERIAL,
                    compress: bool = False, real_time: bool = True) -> int:
    """Record `frames` (all of one size and intrinsics) to `path` (`.db3`); returns how many were written.

    The recorder files frames on its own clock as they arrive, so `real_time` feeds them at the
    spacing of their `stamp`s (a 30 Hz run takes its own length to write) and playback at recorded
    speed keeps it; False writes at once (playback "at recorded speed" is then instantaneous).
    Each frame's `stamp` is also its RealSense timestamp (ms). `compress`: lossless compression.
    """
    import pyrealsense2 as rs

    p = Path(path)
    if p.suffix.lower() != ".db3":
        raise CameraError(f"{p}: pyrealsense2 {rs.__version__} records only .db3 files")
    if not p.parent.is_dir():
        raise CameraError(f"cannot record to {p}: no folder {p.parent}")
    it = iter(frames)
    first = next(it, None)
    if first is None:
        raise CameraError("no frames to record")
    info = first.camera
    dev = rs.software_device()
    dev.register_info(rs.camera_info.name, "BagIt software camera")
    dev.register_info(rs.camera_info.serial_number, serial)
    dsens, csens = dev.add_sensor("Depth"), dev.add_sensor("Color")
    dsens.add_read_only_option(rs.option.depth_units, float(info.depth_scale))
    dprof = dsens.add_video_stream(_stream(rs, rs.stream.depth, 0, info, fps, 2, rs.format.z16)).as_video_stream_profile()
    cprof = csens.add_video_stream(_stream(rs, rs.stream.color, 1, info, fps, 3, rs.format.rgb8)).as_video_stream_profile()
    ident = rs.extrinsics()
    ident.rotation = [1.0, 0, 0, 0, 1.0, 0, 0, 0, 1.0]
    ident.translation = [0.0, 0.0, 0.0]
    dprof.register_extrinsics_to(cprof, ident)
    try:
        recorder = rs.recorder(str(p), dev, compress)
    except RuntimeError as e:
        raise CameraError(f"cannot record to {p}: {e}") from None
    keep: list[np.ndarray] = []  # the sensors read the pixels after on_video_frame returns
    n = 0
    t0_wall, t0_stamp = time.monotonic(), float(first.stamp)
    dsens.open(dprof)
    csens.open(cprof)
    dsens.start(lambda f: None)
    csens.start(lambda f: None)
    try:
        for frame in _chain(first, it):
            c = frame.camera
            if (c.width, c.height, c.fx, c.fy, c.cx, c.cy, c.depth_scale) != (info.width, info.height, info.fx, info.fy, info.cx, info.cy, info.depth_scale):
                raise CameraError(f"frame {frame.seq}: intrinsics or size differ from the first frame's; one recording holds one camera")
            if frame.color.shape != (info.height, info.width, 3) or frame.depth.shape != (info.height, info.width):
                raise CameraError(f"frame {frame.seq}: images are not {info.width}x{info.height}")
            if real_time:
                wait = (float(frame.stamp) - t0_stamp) - (time.monotonic() - t0_wall)
                if wait > 0:
                    time.sleep(min(wait, 10.0))
            depth = np.ascontiguousarray(frame.depth, dtype=np.uint16)
            color = np.ascontiguousarray(frame.color, dtype=np.uint8)
            keep += [depth, color]
            for sensor, profile, pixels, bpp in ((dsens, dprof, depth, 2), (csens, cprof, color, 3)):
                f = rs.software_video_frame()
                f.pixels = pixels
                f.bpp = bpp
                f.stride = info.width * bpp
                f.timestamp = float(frame.stamp) * 1000.0
                f.domain = rs.timestamp_domain.system_time
                f.frame_number = n
                f.profile = profile
                sensor.on_video_frame(f)
            n += 1
    finally:
        for s in (dsens, csens):
            s.stop()
            s.close()
        recorder.pause()
        del recorder  # the file is complete once the recorder is gone
    return n


def _chain(first: RgbdFrame, rest) -> Iterable[RgbdFrame]:
    yield first
    yield from rest
