"""Frame sources: a RealSense recording the project writes itself (pyrealsense2's software device and
recorder, from simulated frames) plays back through the `realsense-file` source pixel for pixel, and
perception finds the bag rim in it; no camera attached is a clear error."""

import time

import numpy as np
import pydantic
import pytest

from bagit.common.errors import CameraError
from bagit.common.geometry import make_transform, points_to_polyline_distance
from bagit.common.messages import CameraInfo, RgbdFrame
from bagit.common.rig import CameraConfig
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception import extract_soi, red_rim_mask, rim_cloud
from bagit.services.perception.rs_recording import write_recording
from bagit.services.perception.sources import SourceConfig, align_depth_to_color, connected_devices, open_source
from bagit.services.sim.world import SimWorld

N_FRAMES = 4
FPS = 30


@pytest.fixture(scope="module")
def sim():
    """Four noisy 30 Hz frames of the coffee-box scene, the camera pose and the true rim."""
    s = Scenario.from_file(find_scenario("exp01-coffee-box"))
    with SimWorld(s, seed=2) as world:
        world.step(0.5)
        frames = []
        for k in range(N_FRAMES):
            frames.append(world.render_rgbd(k))
            world.step(1.0 / FPS)
        return frames, world.rig.camera.T_world_camera(), world.true_rim()


@pytest.fixture(scope="module")
def recording(sim, tmp_path_factory):
    path = tmp_path_factory.mktemp("rs") / "sim.db3"
    assert write_recording(sim[0], path, fps=FPS) == N_FRAMES
    return path


def test_playback_gives_back_the_written_frames_and_the_soi(sim, recording):
    frames, T_wc, true_rim = sim
    cfg = SourceConfig(kind="realsense-file", path=recording, real_time=False)
    with open_source(cfg, CameraConfig().with_pose(T_wc)) as src:
        assert src.serial == "BAGIT-SIM"
        got = list(src)
    assert len(got) == N_FRAMES
    for a, b in zip(frames, got, strict=False):
        assert np.array_equal(a.color, b.color) and np.array_equal(a.depth, b.depth)
        # intrinsics and depth scale come from the recording (stored as float32)
        for k in ("width", "height", "fx", "fy", "cx", "cy", "depth_scale"):
            assert getattr(b.camera, k) == pytest.approx(getattr(a.camera, k), rel=1e-6)
        assert np.allclose(b.camera.extrinsics(), T_wc)  # from the rig, not the camera
    assert [f.seq for f in got] == list(range(N_FRAMES))
    # perception on the played-back frame: the rim, where the simulator has it
    soi = extract_soi(rim_cloud(got[0], red_rim_mask), 32)
    # the same as on the written frame, but for the intrinsics rounded to float32 in the file
    assert np.abs(soi - extract_soi(rim_cloud(frames[0], red_rim_mask), 32)).max() < 0.002
    assert points_to_polyline_distance(soi, true_rim).max() < 0.01  # on the binding's visible top, ~5 mm off the fabric's edge


def test_real_time_playback_keeps_the_recorded_spacing_and_loops(sim, recording):
    """Played at the recorded pace, in a loop. Real-time playback drops a frame the reader is late for (as a
    camera does), so each frame read is matched to the recording's by its pixels: their order only goes
    forward or wraps to the start (a reader late by a whole loop reads the same frame of the next pass), and
    the first pass is never read faster than recorded."""
    written = [f.depth for f in sim[0]]
    cfg = SourceConfig(kind="realsense-file", path=recording, real_time=True, loop=True)
    t0 = time.monotonic()  # playback starts as the source opens
    with open_source(cfg) as src:
        read = []
        for _ in range(4 * N_FRAMES):
            f = src.read()
            read.append((time.monotonic() - t0, f.seq, next(i for i, d in enumerate(written) if np.array_equal(d, f.depth))))
    assert [seq for _, seq, _ in read] == list(range(4 * N_FRAMES))
    index = [i for _, _, i in read]
    wraps = [k for k in range(1, len(index)) if index[k] < index[k - 1]]
    assert wraps and index.count(0) >= 2, index  # it looped back to the start
    t_last, _, i_last = read[wraps[0] - 1]  # the first pass's last frame read: frame i_last, recorded i_last/FPS after frame 0
    assert t_last >= 0.9 * i_last / FPS, read  # never faster than recorded (a dropped frame makes it later, not sooner)


def test_no_camera_is_a_clear_error():
    if connected_devices():
        pytest.skip("a RealSense is attached to this machine")
    with pytest.raises(CameraError, match="no RealSense camera found .*serial 123456789012"):
        open_source(SourceConfig(kind="realsense"), CameraConfig(serial="123456789012"))
    with pytest.raises(CameraError, match="any RealSense"):
        open_source(SourceConfig(kind="realsense"))


def test_bad_recordings_and_configs(tmp_path, sim):
    with pytest.raises(CameraError, match="no RealSense recording at"):
        open_source(SourceConfig(kind="realsense-file", path=tmp_path / "missing.db3"))
    for name in ("junk.db3", "junk.bag"):
        (tmp_path / name).write_bytes(b"not a recording\n" * 10)
        with pytest.raises(CameraError, match="cannot read RealSense recording"):
            open_source(SourceConfig(kind="realsense-file", path=tmp_path / name))
    with pytest.raises(pydantic.ValidationError, match="fps is no longer a source setting: it is the rig config's camera.fps"):
        SourceConfig(kind="realsense", fps=15)  # which camera and its mode: the rig config's, one place
    with pytest.raises(pydantic.ValidationError, match="needs `path`"):
        SourceConfig(kind="realsense-file")
    with pytest.raises(pydantic.ValidationError, match=r"\.db3"):
        SourceConfig(kind="realsense-file", path=tmp_path / "x.mp4")
    assert open_source(SourceConfig(kind="zenoh")) is None  # the node subscribes to camera/rgbd itself
    with pytest.raises(CameraError, match="only .db3"):
        write_recording(sim[0][:1], tmp_path / "x.bag")
    with pytest.raises(CameraError, match="no frames"):
        write_recording([], tmp_path / "x.db3")
    odd = RgbdFrame(camera=CameraInfo(fx=500.0), color=sim[0][0].color, depth=sim[0][0].depth)
    with pytest.raises(CameraError, match="intrinsics or size differ"):
        write_recording([sim[0][0], odd], tmp_path / "y.db3", real_time=False)


def test_align_depth_to_color_moves_pixels_by_the_baseline():
    K = np.array([[400.0, 0, 160], [0, 400.0, 120], [0, 0, 1]])
    depth = np.zeros((240, 320), np.uint16)
    depth[100:140, 100:140] = 1000  # a square at 1 m
    same = align_depth_to_color(depth, K, K, np.eye(4), (320, 240), 0.001)
    assert np.array_equal(same, depth)
    # colour camera 5 cm to the right of the depth camera: points appear 400 * 0.05 / 1 = 20 px further left
    moved = align_depth_to_color(depth, K, K, make_transform(None, [-0.05, 0, 0]), (320, 240), 0.001)
    assert np.array_equal(moved[:, 80:120], depth[:, 100:140]) and not moved[:, 120:].any()
    # a colour image twice as fine: every colour pixel of the square is covered, no holes
    K2 = np.array([[800.0, 0, 320], [0, 800.0, 240], [0, 0, 1]])
    fine = align_depth_to_color(depth, K, K2, np.eye(4), (640, 480), 0.001)
    assert (fine[202:278, 202:278] == 1000).all() and fine.sum() > 0.9 * 4 * depth.astype(np.int64).sum()
