"""The perception service on Zenoh: a RealSense recording the project writes itself (from simulated
frames) played back through the `realsense-file` source gives SoiState on perception/soi with the
true rim; frames published on camera/rgbd do too; a bad frame is counted, never a crash; no camera
is a one-line error."""

import logging
import threading
import time

import numpy as np
import pytest
from bus_support import session_pair, wait_until
from log_support import LogLines

from bagit.cli import main
from bagit.common.bus import BusConfig, Keys, LivelinessWatcher, Publisher, Subscriber, locators, open_session
from bagit.common.geometry import points_to_polyline_distance
from bagit.common.messages import ObjectDetection, PointCloud, RgbdFrame, SoiState, StepAck
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception.node import PerceptionNode, PerceptionServiceConfig
from bagit.services.perception.rs_recording import write_recording
from bagit.services.perception.sources import SourceConfig, connected_devices
from bagit.services.sim.world import SimWorld

N_FRAMES = 4


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """Four noisy 30 Hz frames of the coffee-box scene, the true rim, and a .db3 recording of them."""
    s = Scenario.from_file(find_scenario("exp01-coffee-box"))
    with SimWorld(s, seed=2) as world:
        world.step(0.5)
        frames = []
        for k in range(N_FRAMES):
            frames.append(world.render_rgbd(k))
            world.step(1.0 / 30)
        rim = world.true_rim()
    path = tmp_path_factory.mktemp("rs") / "sim.db3"
    assert write_recording(frames, path, fps=30) == N_FRAMES
    return frames, rim, path


@pytest.mark.slow
def test_a_recording_played_through_the_perception_service_gives_the_soi(sim, capsys):
    """#10: play back a recording through the perception service (the CLI, source realsense-file)
    and get the SOI on Zenoh, within a few mm of the true rim."""
    frames, true_rim, path = sim
    s = open_session(BusConfig(rig="pnrec", adminspace=True))
    sois: list[SoiState] = []
    clouds: list[PointCloud] = []
    alive: list[bool] = []
    try:
        Subscriber(s, Keys("pnrec").perception_soi, SoiState, sois.append)
        Subscriber(s, Keys("pnrec").perception_cloud, PointCloud, clouds.append)
        LivelinessWatcher(s, Keys("pnrec"), on_change=lambda n, up: alive.append(up) if n == "perception" else None)
        result: dict = {}
        args = ["perception", "--source", "realsense-file", "--file", str(path), "--loop", "--n-x", "32",
                "--duration", "6", "--rig", "pnrec", "-e", locators(s)[0], "--json"]
        t = threading.Thread(target=lambda: result.setdefault("code", main(args)))
        t.start()
        assert wait_until(lambda: len(sois) >= 3)
        t.join(30)
        assert not t.is_alive() and result["code"] == 0
        assert alive[:1] == [True] and wait_until(lambda: alive[-1] is False)
    finally:
        s.close()
    for soi in sois:
        assert soi.rim.shape == (32, 3)
        d = points_to_polyline_distance(soi.rim, true_rim)
        assert d.max() < 0.01 and np.median(d) < 0.006, (d.max(), np.median(d))  # on the binding's top, ~5 mm off the edge
        assert soi.n_points > 100 and soi.inlier_fraction > 0.8 and soi.solve_ms > 0
        assert abs(soi.source_stamp - time.time()) < 60  # the frame's stamp (read time of a recording)
    assert np.max(np.linalg.norm(sois[-1].rim - sois[0].rim, axis=1)) < 0.01  # warm starts keep point i as point i
    assert clouds and clouds[0].points.shape[1] == 3 and clouds[0].colors.shape == clouds[0].points.shape
    out = capsys.readouterr()
    assert '"bad": 0' in out.out and "realsense-file" in out.out


@pytest.mark.slow
def test_frames_on_camera_rgbd_give_the_soi_and_a_bad_frame_is_counted(sim):
    frames, true_rim, _ = sim
    for a, b in session_pair("pnzenoh"):
        keys = Keys("pnzenoh")
        lines = LogLines("bagit.perception")
        node = PerceptionNode(a, keys, PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), n_x=24))
        try:
            sois: list[SoiState] = []
            Subscriber(b, keys.perception_soi, SoiState, sois.append)
            pub = Publisher(b, keys.camera_rgbd, RgbdFrame, lockstep=True)  # reliable: on a busy machine a best-effort 1.5 MB frame can be dropped
            assert wait_until(lambda: pub.matched)
            bad = frames[0].model_copy(update={"color": frames[0].color[:, :-1]})  # colour and depth disagree
            pub.put(bad)
            assert wait_until(lambda: node.counters["bad"] == 1)
            assert "does not match" in node.last_bad and any("bad frame" in m for m in lines.at(logging.WARNING))
            sent = []
            for k, f in enumerate(frames):
                f = f.model_copy(update={"stamp": time.time(), "seq": 100 + k})
                sent.append(f.stamp)
                pub.put(f)
                assert wait_until(lambda: node.counters["processed"] >= 2 + k - node.counters["dropped"])
            assert wait_until(lambda: len(sois) >= 1 and node._pending is None and not node._busy)
            time.sleep(0.2)
        finally:
            st = node.close()
        assert st["counters"]["bad"] == 1 and st["counters"]["published"] == len(sois) >= 1
        assert st["counters"]["published"] + st["counters"]["dropped"] == N_FRAMES  # newest wins, nothing queued
        for soi in sois:
            assert soi.rim.shape == (24, 3) and soi.seq >= 100 and soi.source_stamp in sent
            assert points_to_polyline_distance(soi.rim, true_rim).max() < 0.01


@pytest.mark.slow
def test_in_lockstep_a_frames_soi_is_its_answer_and_a_frame_without_one_is_answered_on_sim_ack(sim):
    frames, _, _ = sim
    for a, b in session_pair("pnlock"):
        keys = Keys("pnlock")
        node = PerceptionNode(a, keys, PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), n_x=24), clock="sim")
        try:
            sois: list[SoiState] = []
            acks: list[StepAck] = []
            dets: list[ObjectDetection] = []
            Subscriber(b, keys.perception_soi, SoiState, sois.append)
            Subscriber(b, keys.step_ack("perception"), StepAck, acks.append)
            Subscriber(b, keys.perception_object, ObjectDetection, dets.append)
            pub = Publisher(b, keys.camera_rgbd, RgbdFrame, lockstep=True)
            assert wait_until(lambda: pub.matched)
            pub.put(frames[0].model_copy(update={"stamp": 5.0, "seq": 7}))
            assert wait_until(lambda: len(sois) == 1 and len(dets) == 1)
            pub.put(frames[1].model_copy(update={"stamp": 5.1, "seq": 8, "color": frames[1].color[:, :-1]}))  # gives no SOI
            assert wait_until(lambda: len(acks) == 1)
            time.sleep(0.2)  # nothing more comes
        finally:
            node.close()
    assert len(sois) == 1 and [(x.frame, x.soi_seq) for x in acks] == [(5.1, None)]  # the frame with an SOI: no StepAck
    answer = sois[0].answer()  # what the coordinator takes the SOI for: the frame's detection (due at the first frame) to wait for
    assert (answer.service, answer.frame, answer.soi_seq, answer.object_stamp, answer.late) == ("perception", 5.0, 7, 5.0, None)
    assert [d.source_stamp for d in dets] == [5.0] and acks[0].object_stamp is None  # the marker's rate: none due 0.1 s later


def test_no_camera_is_a_one_line_error(capsys):
    if connected_devices():
        pytest.skip("a RealSense is attached to this machine")
    assert main(["perception", "--source", "realsense", "--serial", "000111222333", "--rig", "pnnone"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no RealSense camera found" in err and "serial 000111222333" in err
