"""Perception on Zenoh: the only module of perception that imports zenoh.

    node = PerceptionNode(session, keys, PerceptionServiceConfig(source=SourceConfig(kind="zenoh")))
    node.close()

Frames come from the configured source: `zenoh` (camera/rgbd), `realsense` or `realsense-file`
(`sources.open_source`, read on a thread of their own). Newest wins: a frame that arrives while
the previous one is still being processed replaces the one waiting, and is counted as dropped;
nothing queues, so the SOI is never late by more than one frame's work.

Per frame: the rim cloud (the bag's segmenter: red-edged, or solid with its colour), then
`extract_soi` warm-started from the previous SOI; when that fails, or the rim jumped further than
`max_jump_m` from the previous one, it starts again cold (point 0 nearest the left gripper when
arm/left/state is fresh). Out: `SoiState` on perception/soi (seq, source_stamp = the frame's
stamp, solve_ms, the share of rim-cloud points within `inlier_m` of the SOI) and, at most
`cloud_rate_hz`, a down-sampled coloured `PointCloud` of the scene on perception/cloud (after the
SOI: the display never delays the control loop).
n_x and the bag (kind, colour) come from the config, else from the current run's scenario
(run/state's scenario_doc), else 32 and red-edged; a red-edged bag's binding colour only from the
config (`bag_rim_color`, the lab's bag, set once like the camera pose; else red). A bad frame is counted with its reason and
reported on stderr (rate-limited); it never stops the node.

Which object, and where (as in the paper): at most `marker_rate_hz` (and on the first frame of a
new run taken `marker_settle_s` after its start) a frame also goes to the marker thread, which
finds the ArUco marker, looks its id up in the object library (the bundled scenario files, or
`object_library`, plus the run's own scenario object) and publishes an `ObjectDetection` on
perception/object: the object's V in the world, or ok=False with the reason (no marker, an unknown
id), counted and reported on stderr. Its own thread and its own newest-wins slot: the SOI path
never waits for it.

With `clock="sim"` (a lockstep simulator) every frame is answered: by its SOI itself, which says whether
the frame gave an object detection too and what perception went without (`SoiState.answer`), or, when
the frame gave none, on sim/ack (`soi_seq` None). The marker detection due on that frame runs in the
SOI's thread right after it, so the coordinator has heard both before the world steps on.
Every message a frame's step needs travels reliably in lockstep, so nothing is sent twice; a frame
that came twice all the same would be answered again, not redone. The start hint is waited for
(`common.lockstep.StepWait`, the lockstep time-out), never fitted without on a short wall-clock bound.
The marker's rate is counted on the frames' stamps, i.e. the camera's clock, in both modes.
"""

from __future__ import annotations

import logging
import threading
import time
from typing import Any, Literal

import numpy as np
import zenoh  # noqa: F401 - the node is where the service meets the bus
from pydantic import BaseModel, ConfigDict, Field

from bagit.common.bus import Keys, LatestCache, Publisher, Subscriber
from bagit.common.clock import ClockKind, make_clock
from bagit.common.errors import BagItError
from bagit.common.geometry import transform_points
from bagit.common.lockstep import StepWait
from bagit.common.messages import ArmState, ObjectDetection, PointCloud, RgbdFrame, RunState, SoiState, StepAck
from bagit.common.names import ACTIVE_STAGES, MAX_N_X, MIN_N_X
from bagit.common.rig import CameraConfig
from bagit.common.scenario import Scenario
from bagit.services.perception.marker import MARKER_RATE_HZ, MARKER_SETTLE_S, MarkerSchedule, ObjectLibrary, detect_object, with_run_object
from bagit.services.perception.rgbd import masked_points
from bagit.services.perception.soi import SoiParams
from bagit.services.perception.sources import RealSenseSource, SourceConfig, open_source
from bagit.services.perception.tracker import RimTracker, frame_soi, start_hint

log = logging.getLogger("bagit.perception")

SERVICE_NAME = "perception"
REPORT_EVERY_S = 5.0


class PerceptionServiceConfig(BaseModel):
    """`bagit perception`'s config file (YAML)."""

    model_config = ConfigDict(extra="forbid")

    source: SourceConfig = Field(default_factory=SourceConfig)
    rig_config: str | None = Field(None, description="rig config YAML: camera extrinsics for realsense sources (default: built-in rig)")
    n_x: int | None = Field(None, ge=MIN_N_X, le=MAX_N_X, description="SOI points; None: the run's scenario, else 32")
    bag_kind: Literal["red-edged", "solid"] | None = Field(None, description="None: the run's scenario, else red-edged")
    bag_color: tuple[float, float, float] | None = Field(None, description="solid bag colour, RGB 0..1; None: the run's scenario")
    bag_rim_color: tuple[float, float, float] | None = Field(
        None, description="the binding colour of the lab's red-edged bag, RGB 0..1, set once like the camera pose; None: red")
    max_jump_m: float = Field(0.05, gt=0.0, le=1.0, description="a warm SOI further than this from the last one: refit cold")
    inlier_m: float = Field(0.015, gt=0.0, le=0.2, description="rim-cloud points this close to the SOI count as inliers")
    cloud_rate_hz: float = Field(10.0, ge=0.0, le=60.0, description="perception/cloud at most this often (0: never)")
    cloud_max_points: int = Field(20000, ge=100, le=500_000)
    hint_max_age_s: float = Field(1.0, gt=0.0, description="a left-arm state older than this is not used as start hint")
    soi: SoiParams = Field(default_factory=SoiParams)
    object_source: Literal["marker", "off"] | None = Field(
        None, description="marker: identify and place the object by its ArUco marker; off: never; None: marker when the library has markers")
    object_library: list[str] | None = Field(None, description="scenario files whose objects (with markers) form the library; None: the bundled ones")
    marker_rate_hz: float = Field(MARKER_RATE_HZ, gt=0.0, le=30.0, description="marker detection at most this often")
    marker_settle_s: float = Field(MARKER_SETTLE_S, ge=0.0, le=30.0,
                                   description="a new run's first detection: on a frame this much newer than its start")


def _rgb(color: tuple[float, float, float]) -> tuple[float, float, float]:
    """A bag colour as a plain 3-tuple."""
    r, g, b = color
    return r, g, b


def scene_cloud(frame: RgbdFrame, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """A down-sampled coloured cloud of the whole frame: points `(n, 3)` float32 world, colours `(n, 3)` uint8
    (every stride-th pixel with a depth; only those pixels' depths are converted, `masked_points`)."""
    h, w = frame.depth.shape
    valid = frame.depth > 0
    n = int(valid.sum())
    stride = max(1, int(np.ceil(np.sqrt(n / max_points)))) if n > max_points else 1
    mask = np.zeros_like(valid)
    mask[::stride, ::stride] = valid[::stride, ::stride]
    v, u, cam = masked_points(frame, mask)
    pts = transform_points(frame.camera.extrinsics(), cam)
    cols = frame.color[v, u]
    return pts[:max_points].astype(np.float32), np.ascontiguousarray(cols[:max_points], dtype=np.uint8)


class PerceptionNode:
    """RGB-D frames in, SOI and display cloud out (see the module doc)."""

    def __init__(
        self,
        session: zenoh.Session,
        keys: Keys,
        cfg: PerceptionServiceConfig | None = None,
        camera: CameraConfig | None = None,
        clock: ClockKind = "wall",
    ) -> None:
        self.cfg = cfg or PerceptionServiceConfig()
        self.lockstep = clock == "sim"
        self.clock = make_clock(clock)  # stamps and ages: the frames' (lockstep) or this host's
        self._answered: tuple[float, int | None, bool, str | None] | None = None  # lockstep: the last frame's stamp, SOI, detection, late
        self.keys = keys
        self._cond = threading.Condition()
        self._pending: RgbdFrame | None = None
        self._stop = threading.Event()
        self.stopped = threading.Event()  # set when a recording ends or the camera fails
        self.stop_ok = False
        self.stop_reason: str | None = None
        self.counters = {"frames": 0, "processed": 0, "dropped": 0, "bad": 0, "cold": 0, "published": 0, "clouds": 0,
                         "objects": 0, "object_failures": 0}
        self.last_bad: str | None = None
        self._last_report = {"bad": -1e9, "object": -1e9, "hint": -1e9}
        self.last_object_error: str | None = None
        self._rim: RimTracker | None = None  # the SOI over frames (warm starts), for the run's bag
        self._rim_bag: tuple[int, str, tuple[float, float, float], tuple[float, float, float] | None] | None = None
        self._run_id: str | None = None
        self._run_active = False  # run/state shows a run under way (lockstep: its frames wait for their arm state)
        self._runs_seen: set[str] = set()  # lockstep: the runs whose run/state came (a frame of one waits for it)
        self._tracked_run: str | None = None  # lockstep: the run of the last frame fitted
        self._scenario: Scenario | None = None
        self._last_cloud = -1e9
        self.solve_ms: list[float] = []
        # the source first: no camera is an error before anything is declared
        self._source = open_source(self.cfg.source, camera)  # the rig's camera: device, mode, extrinsics
        self._library = self._open_library()
        self._mcond = threading.Condition()
        self._mpending: RgbdFrame | None = None
        self._markers = MarkerSchedule(self.cfg.marker_rate_hz, self.cfg.marker_settle_s)  # which frames go to the detector
        self._soi_pub = Publisher(session, keys.perception_soi, SoiState, lockstep=self.lockstep)
        self._cloud_pub = Publisher(session, keys.perception_cloud, PointCloud)
        self._object_pub = Publisher(session, keys.perception_object, ObjectDetection, lockstep=self.lockstep) if self._library is not None else None
        self._ack = Publisher(session, keys.step_ack(SERVICE_NAME), StepAck) if self.lockstep else None
        self._step_wait = StepWait()  # lockstep: the left arm's state of a frame's step
        self._arm = LatestCache(session, keys.arm_state("left"), ArmState, self._step_wait.notify)
        self._subs: list[Subscriber[Any]] = [Subscriber(session, keys.run_state, RunState, self._on_run_state)]
        if self._source is None:
            self._subs.append(Subscriber(session, keys.camera_rgbd, RgbdFrame, self._offer))
        self._threads = [threading.Thread(target=self._work, name="perception-worker", daemon=True)]
        if self._library is not None and not self.lockstep:
            self._threads.append(threading.Thread(target=self._marker_work, name="perception-marker", daemon=True))
        if self._source is not None:
            self._threads.append(threading.Thread(target=self._read, args=(self._source,), name="perception-reader", daemon=True))
        for t in self._threads:
            t.start()

    # -- in ----------------------------------------------------------------------------------------

    def _offer(self, frame: RgbdFrame) -> None:
        """Newest wins: a frame still waiting is replaced (and counted as dropped)."""
        with self._cond:
            self.counters["frames"] += 1
            if self._pending is not None:
                self.counters["dropped"] += 1
            self._pending = frame
            self._cond.notify()
        if not self.lockstep:
            self._offer_marker(frame)

    def _open_library(self) -> ObjectLibrary | None:
        """The object library, or None when detection is off (by config, or no object has a marker)."""
        if self.cfg.object_source == "off":
            return None
        lib = ObjectLibrary.from_scenarios(self.cfg.object_library)  # a bad library file is a config error
        if len(lib) == 0:
            if self.cfg.object_source == "marker":
                log.warning("object_source is marker but no object in the library has a marker: no detection")
            return None
        return lib

    def _marker_due(self, frame: RgbdFrame) -> bool:
        """The frame goes to the detector (`MarkerSchedule`, as in `bagit run`; under _mcond)."""
        return self._library is not None and self._markers.due(frame.stamp)

    def _offer_marker(self, frame: RgbdFrame) -> None:
        """Newest wins here too (see `_marker_due`)."""
        with self._mcond:
            if not self._marker_due(frame):
                return
            self._mpending = frame
            self._mcond.notify()

    def _marker_work(self) -> None:
        while not self._stop.is_set():
            with self._mcond:
                while self._mpending is None and not self._stop.is_set():
                    self._mcond.wait(0.1)
                frame = self._mpending
                if self._stop.is_set() or frame is None:  # (the wait ends on a frame or on the stop)
                    return
                self._mpending = None
            self._detect(frame)

    def _detect(self, frame: RgbdFrame) -> None:
        """Find the object's marker in `frame` and publish what was found (or why not)."""
        assert self._library is not None and self._object_pub is not None
        det = detect_object(frame, self._library, self._run_id)  # (a detector bug too is a failed detection)
        try:
            self._object_pub.put(det)
        except Exception as e:  # noqa: BLE001 - a closing session
            log.warning(f"could not publish perception/object: {e}")
        if det.ok:
            self.counters["objects"] += 1
            return
        self.counters["object_failures"] += 1
        self.last_object_error = f"frame {frame.seq}: {det.error}"
        self._report_every("object", f"no object ({self.counters['object_failures']} so far): {self.last_object_error}")

    def _add_run_object(self, scen: Scenario) -> None:
        """The run's own object joins the library when its marker id is new; one id for two different
        objects is reported and the library kept."""
        if self._library is None:
            return
        try:
            self._library = with_run_object(self._library, scen)  # swapped whole: the marker thread never sees a half-built one
        except BagItError as e:
            log.warning(f"the run's object is not added to the library: {e}")

    def _read(self, src: RealSenseSource) -> None:
        try:
            while not self._stop.is_set():
                frame = src.read()
                if frame is None:
                    self._finish(True, f"end of recording {self.cfg.source.path}")
                    return
                self._offer(frame)
        except Exception as e:  # noqa: BLE001 - a camera that fails ends the service with the reason
            self._finish(False, f"camera: {type(e).__name__}: {e}")

    def _finish(self, ok: bool, reason: str) -> None:
        # let the worker finish the frame in hand first
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            with self._cond:
                if self._pending is None and not self._busy:
                    break
            time.sleep(0.01)
        self.stop_ok, self.stop_reason = ok, reason
        (log.info if ok else log.error)("%s", reason)
        self.stopped.set()

    _busy = False

    def _on_run_state(self, msg: RunState) -> None:
        self._run_active = msg.run_id is not None and msg.stage in ACTIVE_STAGES
        if msg.run_id == self._run_id:
            return
        scen = None
        if msg.scenario_doc is not None:
            try:
                scen = Scenario.model_validate(msg.scenario_doc)
            except Exception as e:  # noqa: BLE001
                log.warning(f"run {msg.run_id}: scenario not readable, using the config's bag: {str(e).splitlines()[0]}")
        with self._cond:
            self._run_id, self._scenario = msg.run_id, scen
            if self._rim is not None and not self.lockstep:
                self._rim.reset()  # a new run: start cold (lockstep: on the first frame of its world, `_process`)
        if scen is not None:
            self._add_run_object(scen)
        if msg.run_id is not None and msg.stage == "perceiving":
            with self._mcond:
                self._markers.run_started(msg.stamp - msg.elapsed_s)
        if msg.run_id is not None:  # last: a frame of this run waiting for its run/state finds all of it in place
            with self._cond:
                self._runs_seen.add(msg.run_id)
            self._step_wait.notify()

    # -- work --------------------------------------------------------------------------------------

    def _bag(self) -> tuple[int, str, tuple[float, float, float], tuple[float, float, float] | None]:
        s = self._scenario
        n_x = self.cfg.n_x or (s.bag.n_x if s is not None else 32)
        kind = self.cfg.bag_kind or (s.bag.kind if s is not None else "red-edged")
        color = self.cfg.bag_color or (_rgb(s.bag.color) if s is not None else (0.15, 0.35, 0.75))
        return n_x, kind, color, self.cfg.bag_rim_color  # the binding's colour: the rig's, never the scenario's

    def _work(self) -> None:
        while not self._stop.is_set():
            with self._cond:
                while self._pending is None and not self._stop.is_set():
                    self._cond.wait(0.1)
                frame = self._pending
                if self._stop.is_set() or frame is None:  # (the wait ends on a frame or on the stop)
                    return
                self._pending = None
                self._busy = True
            try:
                self._process(frame)
            except Exception as e:  # noqa: BLE001 - a bad frame is counted and reported, never a crash
                self._bad(frame, f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}")
            finally:
                with self._cond:
                    self._busy = False

    def _hint(self, frame: RgbdFrame) -> tuple[np.ndarray | None, str | None]:
        """The left gripper's position to start a cold fit from, and (lockstep) what the wait for it went without.
        Lockstep: the state of this very step, as `bagit run` reads it (its age on the rig's clock); it comes
        on its own key, before or after the frame, so the fit waits for it (`StepWait`: woken by each state)."""
        late = None
        if self.lockstep and self._run_active and frame.run_id is not None:  # between runs: no wait (nor an arm driver needed)
            def ready() -> bool:
                msg = self._arm.get()
                return msg is not None and msg.stamp >= frame.stamp - 1e-6

            if not self._step_wait.wait(ready, self._stop) and not self._stop.is_set():
                late = "the left arm's state of its step"
                self._report_every("hint", f"lockstep: frame {frame.seq} fitted without {late}")
        item = self._arm.get_with_time()
        if item is None:
            return None, late
        return start_hint(item[0], self.clock.age(item[0].stamp, item[1], frame.stamp), self.cfg.hint_max_age_s), late

    def _tracker(self) -> RimTracker:
        """The run's rim tracker (a new one when the bag changes: n_x, kind or colour)."""
        bag = self._bag()
        if self._rim is None or self._rim_bag != bag:
            n_x, kind, color, rim_color = bag
            self._rim, self._rim_bag = RimTracker(n_x, kind, color, self.cfg.soi, self.cfg.max_jump_m, rim_color), bag
        return self._rim

    def _process(self, frame: RgbdFrame) -> None:
        if not self.lockstep:
            self._soi(frame)
            return
        done = self._answered
        if done is not None and done[0] == frame.stamp:  # the same frame again: answered again, not redone
            self._answer(frame, done[1], done[2], done[3])
            return
        seq, late = None, None
        # A frame of a new run's world may come before that run's run/state (they travel on their own
        # links): its bag (n_x, kind, colour) and the tracker's cold start are that run's, so wait for it.
        run = frame.run_id
        if run is not None:
            if not self._step_wait.wait(lambda: run in self._runs_seen, self._stop):
                if self._stop.is_set():
                    return
                late = f"the run/state of run {run}"
            if run != self._tracked_run:  # the first frame of a run's world: a cold start, as `bagit run` begins
                with self._cond:
                    if self._rim is not None:
                        self._rim.reset()
                self._tracked_run = run
        with self._mcond:  # the marker's schedule is on the frames' stamps: asked once, before the SOI that says so
            detected = self._marker_due(frame)
        try:
            seq, hint_late = self._soi(frame, (frame.stamp if detected else None, late))
            late = late or hint_late
        finally:
            if detected:
                self._detect(frame)
            self._answered = (frame.stamp, seq, detected, late)
            if seq is None:  # no SOI to stand for the answer
                self._answer(frame, seq, detected, late)

    def _answer(self, frame: RgbdFrame, soi_seq: int | None, detected: bool = False, late: str | None = None) -> None:
        """Perception is done with `frame`: its SOI (seq), whether it gave an object detection too, and what it
        went without (`late`: the step may differ from `bagit run`'s)."""
        assert self._ack is not None
        self._ack.put(StepAck(service=SERVICE_NAME, run_id=self._run_id, frame=frame.stamp, soi_seq=soi_seq,
                              object_stamp=frame.stamp if detected else None, stamp=frame.stamp, late=late))

    def _soi(self, frame: RgbdFrame, answer: tuple[float | None, str | None] | None = None) -> tuple[int | None, str | None]:
        """The frame's SOI, published (lockstep: as the frame's answer, `answer` = the stamp of the detection it
        also gave and what it went without so far, the start hint's wait added); its seq, or None (the frame
        counted bad with the reason); and what the lockstep wait for the start hint went without (None: nothing)."""
        hint, late = self._hint(frame)
        tracker = self._tracker()
        self.counters["processed"] += 1
        cold = tracker.cold
        try:
            soi, _cloud = frame_soi(tracker, frame, hint, frame.stamp, self.cfg.inlier_m)
            # stamped once made: on the wall clock its age when sent (stamp - source_stamp, both this host's)
            # counts the extraction, which the controller adds to its time since arrival; in lockstep the
            # frame's time, as before (processing takes no simulated time)
            fields = {} if answer is None else {"object_stamp": answer[0], "late": answer[1] or late}
            soi = soi.model_copy(update={"stamp": self.clock.step_time(frame.stamp), **fields})
        except BagItError as e:
            self.counters["cold"] += tracker.cold - cold
            self._bad(frame, f"no SOI: {e}")
            self._maybe_cloud(frame)
            return None, late
        self.counters["cold"] += tracker.cold - cold
        self.solve_ms.append(soi.solve_ms)
        del self.solve_ms[:-1000]
        self._soi_pub.put(soi)
        self.counters["published"] += 1
        self._maybe_cloud(frame)  # after the SOI: the display never delays the control loop
        return frame.seq, late

    def _maybe_cloud(self, frame: RgbdFrame) -> None:
        rate = self.cfg.cloud_rate_hz
        now = time.monotonic()
        if rate <= 0 or now - self._last_cloud < 1.0 / rate or not self._cloud_pub.matched:  # nobody watching: not made
            return
        self._last_cloud = now
        try:
            pts, cols = scene_cloud(frame, self.cfg.cloud_max_points)
        except Exception:  # noqa: BLE001 - the display cloud is optional; the SOI path reports the frame
            return
        self._cloud_pub.put(PointCloud(seq=frame.seq, stamp=frame.stamp, points=pts, colors=cols))
        self.counters["clouds"] += 1

    def _bad(self, frame: RgbdFrame, reason: str) -> None:
        self.counters["bad"] += 1
        self.last_bad = f"frame {frame.seq}: {reason}"
        self._report_every("bad", f"bad frame ({self.counters['bad']} so far): {self.last_bad}")

    def _report_every(self, kind: str, text: str) -> None:
        """Report `text`, at most once per REPORT_EVERY_S for each `kind` (a flood of bad frames is one line)."""
        now = time.monotonic()
        if now - self._last_report[kind] >= REPORT_EVERY_S:
            self._last_report[kind] = now
            log.warning("%s", text)

    # -- out ---------------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        ms = np.array(self.solve_ms) if self.solve_ms else np.zeros(1)
        return {"source": self.cfg.source.kind, "counters": dict(self.counters), "last_bad": self.last_bad,
                "last_object_error": self.last_object_error,
                "solve_ms": {"median": float(np.median(ms)), "p95": float(np.percentile(ms, 95))},
                "reason": None if self.stop_ok else self.stop_reason}

    def close(self) -> dict[str, Any]:
        self._stop.set()
        self._step_wait.notify()
        with self._cond:
            self._cond.notify_all()
        with self._mcond:
            self._mcond.notify_all()
        for s in self._subs:
            s.close()
        for t in self._threads:
            t.join(timeout=10.0)
        if self._source is not None:
            self._source.close()
        self._arm.close()
        self._soi_pub.close()
        self._cloud_pub.close()
        for p in (self._object_pub, self._ack):
            if p is not None:
                p.close()
        return self.status()
