"""Which object, and where, on the bus: the perception service finds the ArUco marker on a simulated
frame that arrives on camera/rgbd and publishes the object's V on perception/object; a frame without
a marker is a reported, counted failure (ok=False), never a crash, and the SOI path goes on."""

import logging
import time

import numpy as np
import pytest
from bus_support import session_pair, wait_until
from log_support import LogLines

from bagit.common.bus import Keys, Publisher, Subscriber
from bagit.common.messages import ObjectDetection, RgbdFrame, RunState, SoiState
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception.node import PerceptionNode, PerceptionServiceConfig
from bagit.services.perception.sources import SourceConfig
from bagit.services.sim.world import SimWorld


@pytest.fixture(scope="module")
def scene():
    s = Scenario.from_file(find_scenario("exp01-coffee-box"))
    with SimWorld(s, seed=3) as world:
        frame = world.render_rgbd(0)
    return s, frame


def test_a_simulated_frame_on_camera_rgbd_gives_the_object_on_perception_object(scene):
    s, frame = scene
    for a, b in session_pair("probj"):
        keys = Keys("probj")
        lines = LogLines("bagit.perception")
        node = PerceptionNode(a, keys, PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), n_x=24))
        try:
            got: list[ObjectDetection] = []
            sois: list[SoiState] = []
            Subscriber(b, keys.perception_object, ObjectDetection, got.append)
            Subscriber(b, keys.perception_soi, SoiState, sois.append)
            run_pub = Publisher(b, keys.run_state, RunState)
            pub = Publisher(b, keys.camera_rgbd, RgbdFrame, lockstep=True)  # reliable: on a busy machine a best-effort 1.5 MB frame can be dropped
            assert wait_until(lambda: pub.matched and run_pub.matched)
            # a frame with no marker in view: a reported failure, and the next frame is not starved by the rate
            blank = RgbdFrame(seq=1, color=np.full((480, 640, 3), 200, np.uint8), depth=np.zeros((480, 640), np.uint16),
                              camera=frame.camera)
            pub.put(blank)
            assert wait_until(lambda: len(got) >= 1)
            assert got[0].ok is False and "no ArUco marker" in got[0].error and got[0].vertices is None
            assert node.counters["object_failures"] == 1 and any("no object" in r for r in lines.at(logging.WARNING))
            # a new run in perceiving: its first frame after start + settle is looked at at once
            t0 = time.time()
            run_pub.put(RunState(run_id="r-obj", stage="perceiving", stamp=t0, elapsed_s=0.0,
                                 scenario_doc=s.model_dump(mode="json", exclude_none=True)))
            assert wait_until(lambda: node._run_id == "r-obj")
            pub.put(frame.model_copy(update={"seq": 7, "stamp": t0 + 1.0}))
            assert wait_until(lambda: len(got) >= 2)
            assert wait_until(lambda: len(sois) >= 1)  # the SOI path ran on the same frame
        finally:
            st = node.close()
        det = got[1]
        assert det.ok and det.error is None and det.run_id == "r-obj" and det.seq == 7 and det.source_stamp == t0 + 1.0
        assert det.marker_id == s.object.marker.id and det.name == (s.object.name or s.name)
        V = s.object.bottom_vertices()
        assert det.vertices.shape == V.shape
        err = float(np.linalg.norm(det.vertices - V, axis=1).max())
        assert err < 0.005, err
        assert det.height == pytest.approx(s.object.effective_height())
        assert np.linalg.norm(det.T_world_marker[:3, 3] - s.object.T_world_marker()[:3, 3]) < 0.005
        assert det.detect_ms > 0 and det.depth_pixels > 0
        assert st["counters"]["objects"] == 1 and st["counters"]["object_failures"] == 1
        print(f"marker V error on the bus: {err * 1000:.2f} mm")


def test_object_source_off_publishes_nothing_and_no_library_marker_is_reported(tmp_path):
    for a, _b in session_pair("probjoff"):
        node = PerceptionNode(a, Keys("probjoff"), PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), object_source="off"))
        try:
            assert node._library is None and node._object_pub is None
        finally:
            node.close()
        doc = tmp_path / "nomarker.yaml"
        doc.write_text("name: nomarker\nobject:\n  vertices: [[0.4, -0.05, 0.0], [0.5, -0.05, 0.0], [0.5, 0.05, 0.0], [0.4, 0.05, 0.0]]\n"
                       "  height: 0.1\nbag:\n  rim_perimeter: 0.7\n")
        with LogLines("bagit.perception") as lines:
            node = PerceptionNode(a, Keys("probjoff"), PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), object_source="marker",
                                                                             object_library=[str(doc)]))
            try:
                assert node._library is None and any("no object in the library has a marker" in r for r in lines.messages)
            finally:
                node.close()
