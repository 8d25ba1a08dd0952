"""Where perception's RGB-D frames come from: a live RealSense, a RealSense recording, or the bus.

`SourceConfig.kind` picks one:
- `realsense`: a live RealSense (a D455, or any model with depth and colour) through pyrealsense2,
  the rig's camera (`CameraConfig`: its serial, or the only one attached, and its mode, 640x480 at
  30 Hz by default); depth aligned to colour; intrinsics and depth scale read from the device.
- `realsense-file`: a RealSense recording played back through pyrealsense2: the `.db3` (ROS 2 bag)
  files pyrealsense2 2.59 records (`rs_recording.write_recording` writes them from any frames),
  and older `.bag` (ROS 1) files where the library still reads them; at recorded speed or as
  fast as frames are read, looping or not.
- `zenoh`: frames published on `camera/rgbd` (the simulator, `bagit camera` on another machine).
  These come from the bus, so the perception node subscribes itself: `open_source` returns None.

Which camera, its mode and its camera-to-world extrinsics are the rig config's (`CameraConfig`, one
place for every command that opens it; `T_world_camera` estimated by `bagit calibrate`), passed in.
Frames are `RgbdFrame`s: colour RGB uint8 `(H, W, 3)`, depth uint16 `(H, W)` in depth-scale units,
registered to the colour pixels.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from bagit.common.errors import CameraError, refuse_moved
from bagit.common.messages import CameraInfo, RgbdFrame
from bagit.common.rig import CameraConfig

SourceKind = Literal["zenoh", "realsense", "realsense-file"]
RECORDING_SUFFIXES = (".db3", ".bag")
CAMERA_SETTINGS = ("serial", "width", "height", "fps")  # once a source's too; now only the rig config's camera


class SourceConfig(BaseModel):
    """Which frames perception reads, and how."""

    model_config = ConfigDict(extra="forbid")

    kind: SourceKind = "zenoh"
    path: Path | None = Field(None, description="realsense-file: the recording (.db3, or an older .bag)")
    real_time: bool = Field(True, description="realsense-file: at recorded speed (False: as fast as frames are read)")
    loop: bool = Field(False, description="realsense-file: start again at the end")
    align: bool = Field(True, description="register depth to the colour pixels (skipped when they already are)")
    timeout_s: float = Field(5.0, gt=0, le=120, description="no frame for this long: CameraError")

    @model_validator(mode="before")
    @classmethod
    def _refuse_moved(cls, data: Any) -> Any:
        return refuse_moved(data, {key: f"the rig config's camera.{key} (rig_config)" for key in CAMERA_SETTINGS}, "source")

    @model_validator(mode="after")
    def _needs(self) -> SourceConfig:
        if self.kind == "realsense-file":
            if self.path is None:
                raise ValueError("a realsense-file source needs `path`, the recording to play")
            if self.path.suffix.lower() not in RECORDING_SUFFIXES:
                raise ValueError(f"{self.path}: a RealSense recording ends in .db3 (or .bag for older ones)")
        return self


class FrameSource(Protocol):
    """Frames one after another; `read()` gives None at the end of a recording (never for a live camera)."""

    def read(self) -> RgbdFrame | None: ...

    def close(self) -> None: ...


def open_source(cfg: SourceConfig, camera: CameraConfig | None = None) -> RealSenseSource | None:
    """The frame source `cfg` names; None for kind `zenoh` (the node subscribes to camera/rgbd).
    `camera`: the rig's (`RealSenseSource`)."""
    if cfg.kind == "zenoh":
        return None
    return RealSenseSource(cfg, camera)


def _rs():
    try:
        import pyrealsense2 as rs
    except ImportError as e:  # pragma: no cover - a dependency of the package
        raise CameraError(f"pyrealsense2 is not importable ({e}); install it to use a RealSense") from None
    return rs


def connected_devices() -> list[dict[str, str]]:
    """The RealSense devices librealsense sees: [{'name', 'serial', 'firmware', 'usb'}]."""
    rs = _rs()
    out = []
    for dev in rs.context().query_devices():
        info = {}
        for key, what in (("name", rs.camera_info.name), ("serial", rs.camera_info.serial_number),
                          ("firmware", rs.camera_info.firmware_version), ("usb", rs.camera_info.usb_type_descriptor)):
            info[key] = dev.get_info(what) if dev.supports(what) else ""
        out.append(info)
    return out


def _color_rgb(frame, rs) -> np.ndarray:
    """A colour frame as RGB uint8 `(H, W, 3)`, whatever format the device or recording used."""
    import cv2

    fmt = frame.get_profile().format()
    a = np.asanyarray(frame.get_data())
    if fmt == rs.format.rgb8:
        return np.array(a, dtype=np.uint8)
    if fmt == rs.format.bgr8:
        return np.ascontiguousarray(a[..., ::-1])
    if fmt == rs.format.rgba8:
        return np.ascontiguousarray(a[..., :3])
    if fmt == rs.format.bgra8:
        return np.ascontiguousarray(a[..., 2::-1])
    if fmt == rs.format.yuyv:
        return cv2.cvtColor(a.reshape(frame.get_height(), frame.get_width(), 2), cv2.COLOR_YUV2RGB_YUYV)
    raise CameraError(f"colour stream format {fmt} is not one BagIt reads (rgb8, bgr8, rgba8, bgra8, yuyv)")


def align_depth_to_color(depth: np.ndarray, K_depth: np.ndarray, K_color: np.ndarray, T_color_depth: np.ndarray,
                         color_size: tuple[int, int], depth_scale: float) -> np.ndarray:
    """Depth `(Hd, Wd)` uint16 re-projected onto the colour pixels: `(Hc, Wc)` uint16, 0 = no return.

    Each depth pixel is moved into the colour camera (`T_color_depth (4, 4)`, metres) and splatted
    over the colour pixels its footprint covers; where several land, the nearest wins (as
    librealsense's align does). Lens distortion is ignored (a D4xx's depth stream has none).
    """
    d = np.asarray(depth)
    v, u = np.nonzero(d)
    if len(u) == 0:
        return np.zeros((color_size[1], color_size[0]), dtype=np.uint16)
    z = d[v, u].astype(np.float64) * depth_scale
    pts = np.column_stack([(u - K_depth[0, 2]) / K_depth[0, 0] * z, (v - K_depth[1, 2]) / K_depth[1, 1] * z, z])
    pc = pts @ T_color_depth[:3, :3].T + T_color_depth[:3, 3]
    ok = pc[:, 2] > 1e-6
    pc = pc[ok]
    uc = K_color[0, 0] * pc[:, 0] / pc[:, 2] + K_color[0, 2]
    vc = K_color[1, 1] * pc[:, 1] / pc[:, 2] + K_color[1, 2]
    zc = np.round(pc[:, 2] / depth_scale)
    wc, hc = color_size
    out = np.full(hc * wc, np.iinfo(np.uint32).max, dtype=np.uint32)
    # the footprint: a colour pixel finer than a depth pixel is covered by several of them
    k = int(np.ceil(max(K_color[0, 0] / K_depth[0, 0], K_color[1, 1] / K_depth[1, 1]) - 1e-9))
    offs = np.arange(k) - (k - 1) / 2
    for dy in offs:
        for dx in offs:
            iu, iv = np.floor(uc + dx + 0.5).astype(np.int64), np.floor(vc + dy + 0.5).astype(np.int64)
            inb = (iu >= 0) & (iu < wc) & (iv >= 0) & (iv < hc) & (zc > 0) & (zc <= 65535)
            np.minimum.at(out, iv[inb] * wc + iu[inb], zc[inb].astype(np.uint32))
    out[out == np.iinfo(np.uint32).max] = 0
    return out.reshape(hc, wc).astype(np.uint16)


def _K(intr) -> np.ndarray:
    return np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]])


def _T_to(src_profile, dst_profile) -> np.ndarray:
    """4x4 dst <- src from librealsense extrinsics (rotation stored column-major)."""
    ex = src_profile.get_extrinsics_to(dst_profile)
    T = np.eye(4)
    T[:3, :3] = np.asarray(ex.rotation, dtype=float).reshape(3, 3).T
    T[:3, 3] = ex.translation
    return T


def _same_pixels(depth_profile, color_profile) -> bool:
    """Is depth already registered to colour (same intrinsics, identity extrinsics)? Then align is a no-op."""
    di = depth_profile.as_video_stream_profile().get_intrinsics()
    ci = color_profile.as_video_stream_profile().get_intrinsics()
    same_k = (di.width, di.height) == (ci.width, ci.height) and np.allclose(
        [di.fx, di.fy, di.ppx, di.ppy], [ci.fx, ci.fy, ci.ppx, ci.ppy], atol=1e-6
    )
    try:
        T = _T_to(depth_profile, color_profile)
    except RuntimeError:
        return False
    return bool(same_k and np.allclose(T, np.eye(4), atol=1e-9))


class RealSenseSource:
    """A live RealSense (a pyrealsense2 pipeline, depth aligned by librealsense) or a RealSense
    recording (its playback device's sensors, depth and colour paired by timestamp here)."""

    def __init__(self, cfg: SourceConfig, camera: CameraConfig | None = None):
        """`camera`: the rig's: which device (serial), its mode (width, height, fps) and the extrinsics
        stamped on every frame; None: a camera in no rig, the only one attached at the default mode,
        frames in its own frame."""
        if cfg.kind not in ("realsense", "realsense-file"):
            raise CameraError(f"a RealSenseSource reads kind realsense or realsense-file, not {cfg.kind!r}")
        rs = _rs()
        self.cfg = cfg
        self.camera = camera or CameraConfig()
        self._rs = rs
        self._T = np.eye(4) if camera is None else camera.T_world_camera()
        if self._T.shape != (4, 4) or not np.all(np.isfinite(self._T)):
            raise CameraError("T_world_camera must be a finite 4x4 transform")
        self.live = cfg.kind == "realsense"
        self._seq = 0
        self._started = False
        if self.live:
            self._open_live()
        else:
            self._open_file()

    # -- a live camera ------------------------------------------------------------------------

    def _open_live(self) -> None:
        rs, cfg = self._rs, self.cfg
        self.serial = self._pick_device()
        self._pipe = rs.pipeline()
        config = rs.config()
        config.enable_device(self.serial)
        cam = self.camera
        fps = int(round(cam.fps))
        config.enable_stream(rs.stream.depth, cam.width, cam.height, rs.format.z16, fps)
        config.enable_stream(rs.stream.color, cam.width, cam.height, rs.format.rgb8, fps)
        try:
            profile = self._pipe.start(config)
        except RuntimeError as e:
            raise CameraError(f"cannot start RealSense {self.serial} at {cam.width}x{cam.height}@{fps} (depth z16 + colour rgb8): {e}") from None
        self._started = True
        try:
            dev = profile.get_device()
            self.depth_scale = float(dev.first_depth_sensor().get_depth_scale())
            dprof, cprof = profile.get_stream(rs.stream.depth), profile.get_stream(rs.stream.color)
            self._align = rs.align(rs.stream.color) if cfg.align and not _same_pixels(dprof, cprof) else None
            self._set_info(cprof.as_video_stream_profile().get_intrinsics())
        except BaseException:
            self.close()
            raise
        self._last: tuple[int, int] = (-1, -1)

    def _pick_device(self) -> str:
        devices = connected_devices()
        want = self.camera.serial
        if not devices:
            raise CameraError(
                f"no RealSense camera found (looked for {'serial ' + want if want else 'any RealSense'} over USB with librealsense); "
                "is it plugged in, and readable by this user (udev rules)?"
            )
        serials = [d["serial"] for d in devices]
        if want is None:
            if len(devices) > 1:
                raise CameraError(f"{len(devices)} RealSense cameras attached ({', '.join(serials)}): say which with its serial")
            return serials[0]
        if want not in serials:
            seen = ", ".join(f"{d['name']} {d['serial']}" for d in devices)
            raise CameraError(f"no RealSense with serial {want} (attached: {seen})")
        return want

    def _read_live(self) -> RgbdFrame:
        rs = self._rs
        deadline = time.monotonic() + self.cfg.timeout_s
        while True:
            ok, frames = self._pipe.try_wait_for_frames(100)
            if not ok:
                if time.monotonic() > deadline:
                    raise CameraError(f"no frame from RealSense {self.serial} for {self.cfg.timeout_s:.1f} s")
                continue
            depth, color = frames.get_depth_frame(), frames.get_color_frame()
            if not depth or not color:
                continue
            key = (depth.get_frame_number(), color.get_frame_number())
            if key[0] == self._last[0] or key[1] == self._last[1]:  # a frame handed on again beside its partner's next
                continue
            self._last = key
            if self._align is not None:
                frames = self._align.process(frames)
                depth, color = frames.get_depth_frame(), frames.get_color_frame()
            stamp = time.time()
            if color.get_frame_timestamp_domain() == rs.timestamp_domain.global_time:
                stamp = color.get_timestamp() / 1000.0  # capture time on the host clock (ms)
            return self._message(np.array(np.asanyarray(depth.get_data()), dtype=np.uint16), _color_rgb(color, rs), stamp)

    # -- a recording ----------------------------------------------------------------------------

    def _open_file(self) -> None:
        import queue

        rs, cfg = self._rs, self.cfg
        if cfg.path is None:
            raise CameraError("no RealSense recording given (the camera config's path is empty)")
        path = Path(cfg.path)
        if not path.is_file():
            raise CameraError(f"no RealSense recording at {path}")
        try:
            self._dev = rs.context().load_device(str(path))
        except RuntimeError as e:
            raise CameraError(f"cannot read RealSense recording {path}: {e}") from None
        self._playback = self._dev.as_playback()
        self._playback.set_real_time(cfg.real_time)
        self.serial = self._dev.get_info(rs.camera_info.serial_number) if self._dev.supports(rs.camera_info.serial_number) else ""
        picks: dict = {}
        for sensor in self._dev.query_sensors():
            for prof in sensor.get_stream_profiles():
                st = prof.stream_type()
                if st in (rs.stream.depth, rs.stream.color) and st not in picks:
                    picks[st] = (sensor, prof)
        if rs.stream.depth not in picks or rs.stream.color not in picks:
            have = ", ".join(str(p.stream_type()) for s in self._dev.query_sensors() for p in s.get_stream_profiles()) or "none"
            raise CameraError(f"recording {path} has no depth and colour streams (has {have})")
        dprof, cprof = picks[rs.stream.depth][1], picks[rs.stream.color][1]
        try:
            self.depth_scale = float(picks[rs.stream.depth][0].as_depth_sensor().get_depth_scale())
        except RuntimeError:
            self.depth_scale = 0.001  # the RealSense default, for recordings that did not keep the option
        di = dprof.as_video_stream_profile().get_intrinsics()
        ci = cprof.as_video_stream_profile().get_intrinsics()
        self._align_args = None
        if cfg.align and not _same_pixels(dprof, cprof):
            self._align_args = (_K(di), _K(ci), _T_to(dprof, cprof), (ci.width, ci.height), self.depth_scale)
        self._set_info(ci)
        self._pair_tol_ms = 500.0 / max(cprof.fps(), 1)
        self._sensors: dict[int, tuple[Any, list[Any]]] = {}  # id(sensor) -> (sensor, its profiles to open)
        for st in (rs.stream.depth, rs.stream.color):
            sensor, prof = picks[st]
            self._sensors.setdefault(id(sensor), (sensor, []))[1].append(prof)
        self._queue: queue.Queue = queue.Queue(maxsize=8)
        self._pending: dict = {}
        self._start_sensors()

    def _on_frame(self, f) -> None:
        """Playback thread: copy the pixels out (librealsense recycles its frames) and hand them on;
        when not real-time, waiting here holds playback back until the reader catches up."""
        rs = self._rs
        st = f.get_profile().stream_type()
        if st == rs.stream.depth:
            item = ("depth", f.get_timestamp(), np.array(np.asanyarray(f.get_data()), dtype=np.uint16))
        elif st == rs.stream.color:
            item = ("color", f.get_timestamp(), _color_rgb(f, rs))
        else:
            return
        import queue

        while self._started:
            try:
                self._queue.put(item, timeout=0.05)
                return
            except queue.Full:
                if self.cfg.real_time:
                    return  # real time: a reader that falls behind misses frames, as with a live camera

    def _start_sensors(self) -> None:
        # Paused while the sensors start: playing, the first sensor started would play its first
        # frames before the second one listens, losing their partners.
        self._playback.pause()
        for sensor, profs in self._sensors.values():
            sensor.open(profs)
        self._started = True
        for sensor, _ in self._sensors.values():
            sensor.start(self._on_frame)
        self._playback.resume()

    def _stop_sensors(self) -> None:
        import queue

        self._started = False
        for sensor, _ in self._sensors.values():
            try:
                sensor.stop()
                sensor.close()
            except RuntimeError:
                pass
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break

    def _read_file(self) -> RgbdFrame | None:
        import queue

        deadline = time.monotonic() + self.cfg.timeout_s
        while True:
            try:
                kind, t_ms, data = self._queue.get(timeout=0.1)
            except queue.Empty:
                if self._playback.current_status() == self._rs.playback_status.stopped and self._queue.empty():
                    if not self.cfg.loop:
                        return None
                    self._stop_sensors()  # from the start again
                    self._pending.clear()
                    self._start_sensors()
                    deadline = time.monotonic() + self.cfg.timeout_s
                elif time.monotonic() > deadline:
                    raise CameraError(f"no frame from recording {self.cfg.path} for {self.cfg.timeout_s:.1f} s") from None
                continue
            other = "color" if kind == "depth" else "depth"
            self._pending[kind] = (t_ms, data)
            if other in self._pending and abs(self._pending[other][0] - t_ms) <= self._pair_tol_ms:
                (_, depth), (_, color) = self._pending.pop("depth"), self._pending.pop("color")
                if self._align_args is not None:
                    depth = align_depth_to_color(depth, *self._align_args)
                return self._message(depth, color, time.time())

    # -- both ---------------------------------------------------------------------------------

    def _set_info(self, ci) -> None:
        self.info = CameraInfo(width=ci.width, height=ci.height, fx=ci.fx, fy=ci.fy, cx=ci.ppx, cy=ci.ppy,
                               depth_scale=self.depth_scale, T_world_camera=self._T.tolist())

    def _message(self, depth: np.ndarray, color: np.ndarray, stamp: float) -> RgbdFrame:
        seq = self._seq
        self._seq += 1
        return RgbdFrame(seq=seq, stamp=stamp, camera=self.info, color=color, depth=depth)

    def read(self) -> RgbdFrame | None:
        """The next frame (depth registered to colour); None at the end of a recording that does not
        loop; CameraError when no frame comes within `timeout_s`. Stamps: a live camera's capture
        time, or when a recording's frame was read."""
        if not self._started:
            raise CameraError("the source is closed")
        return self._read_live() if self.live else self._read_file()

    def __iter__(self) -> Iterator[RgbdFrame]:
        while (f := self.read()) is not None:
            yield f

    def close(self) -> None:
        if not self._started:
            return
        if self.live:
            self._started = False
            try:
                self._pipe.stop()
            except RuntimeError:
                pass
        else:
            self._stop_sensors()

    def __enter__(self) -> RealSenseSource:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
