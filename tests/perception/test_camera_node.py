"""`bagit camera`: a RealSense recording's frames arrive on camera/rgbd over Zenoh, with the rig's
extrinsics, while alive/camera is declared; no camera attached is a one-line error."""

import threading

import numpy as np
import pytest
from bus_support import wait_until

from bagit.cli import main
from bagit.common.bus import BusConfig, Keys, LivelinessWatcher, Subscriber, locators, open_session
from bagit.common.messages import CameraInfo, RgbdFrame
from bagit.common.rig import RigConfig
from bagit.services.perception.rs_recording import write_recording
from bagit.services.perception.sources import connected_devices


def test_camera_publishes_a_recording_with_liveliness(tmp_path, capsys):
    rng = np.random.default_rng(0)
    frames = [RgbdFrame(seq=k, stamp=k / 30, camera=CameraInfo(width=64, height=48, fx=40.0, fy=40.0, cx=31.5, cy=23.5),
                        color=rng.integers(0, 255, (48, 64, 3), dtype=np.uint8),
                        depth=rng.integers(0, 3000, (48, 64), dtype=np.uint16)) for k in range(3)]
    write_recording(frames, tmp_path / "r.db3", fps=30)
    rig = RigConfig(name="camtest")
    (tmp_path / "rig.yaml").write_text(rig.to_yaml())
    keys = Keys("camtest")
    sub_session = open_session(BusConfig(rig="camtest", adminspace=True))
    got: list[RgbdFrame] = []
    alive: list[bool] = []
    try:
        sub = Subscriber(sub_session, keys.camera_rgbd, RgbdFrame, got.append)  # noqa: F841
        watcher = LivelinessWatcher(sub_session, keys, on_change=lambda s, up: alive.append(up) if s == "camera" else None)
        result: dict = {}
        args = ["camera", "--file", str(tmp_path / "r.db3"), "--loop", "--frames", "45", "--rig-config", str(tmp_path / "rig.yaml"),
                "-e", locators(sub_session)[0], "--json"]
        t = threading.Thread(target=lambda: result.setdefault("code", main(args)))
        t.start()
        t.join(20)
        assert not t.is_alive() and result["code"] == 0
        assert wait_until(lambda: len(got) >= 10)  # the first puts may go before the peers meet
        assert alive[:1] == [True] and wait_until(lambda: alive[-1] is False)
        assert watcher.alive() == set()
    finally:
        sub_session.close()
    by_depth = {f.depth.tobytes(): f for f in frames}
    for f in got:
        assert f.depth.tobytes() in by_depth and np.array_equal(f.color, by_depth[f.depth.tobytes()].color)
        assert np.allclose(f.camera.extrinsics(), rig.camera.T_world_camera())  # the rig's extrinsics
        assert f.camera.fx == pytest.approx(40.0)
    assert '"frames": 45' in capsys.readouterr().out


def test_no_camera_is_a_one_line_error(capsys):
    if connected_devices():
        pytest.skip("a RealSense is attached to this machine")
    assert main(["camera", "--serial", "000111222333"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no RealSense camera found" in err and "serial 000111222333" in err
