"""A red-edged bag with a binding of another colour: the rig's perception config names the colour,
and the SOI is found through the real path (the simulator's camera renders, perception segments by
the binding's hue and fits the SOI)."""

import numpy as np
import pytest
import yaml

from bagit.common.bag import RIM_COLOR
from bagit.common.geometry import points_to_polyline_distance
from bagit.common.scenario import Scenario
from bagit.scenarios import find_scenario
from bagit.services.perception.rgbd import RED_HUE_BANDS, hue_bands, red_rim_mask, rim_cloud
from bagit.services.perception.tracker import RimTracker, segmenter_for
from bagit.services.sim.world import SimWorld
from bagit.up import lab_perception_config

GREEN, BLUE = (0.1, 0.75, 0.2), (0.1, 0.2, 0.85)


def _bag_scenario(binding, fabric) -> Scenario:
    doc = yaml.safe_load(find_scenario("exp02").read_text())
    doc["bag"].update({"rim": {"color": list(binding)}, "color": list(fabric)})
    return Scenario.from_dict(doc)


def test_hue_bands_of_the_default_red_are_the_red_segmenters():
    assert hue_bands(RIM_COLOR) == RED_HUE_BANDS
    assert hue_bands((1.0, 0.0, 0.1)) == ((0, 7), (167, 179))  # hue 177, just under 180: wraps the other way
    (lo, hi), = hue_bands(GREEN)
    assert lo < 60 < hi and hi - lo == 20


@pytest.mark.parametrize("binding, fabric", [(GREEN, (0.75, 0.45, 0.7)), (BLUE, (0.8, 0.75, 0.35))])
def test_a_green_or_blue_binding_gives_the_soi(binding, fabric):
    s = _bag_scenario(binding, fabric)
    w = SimWorld(s, seed=0)
    w.step(0.5)
    frame = w.render_rgbd(0)
    assert len(rim_cloud(frame, red_rim_mask)) < 50  # no red edge: the default segmenter finds nothing
    cloud = rim_cloud(frame, segmenter_for("red-edged", s.bag.color, binding))
    assert len(cloud) > 500
    rim, _ = RimTracker(32, "red-edged", s.bag.color, rim_color=binding).update(frame, hint=w.true_rim()[0])
    d = points_to_polyline_distance(rim, w.true_rim())
    assert d.mean() < 0.01 and d.max() < 0.025
    w.close()


def test_bagit_up_tells_perception_the_simulated_bags_binding(tmp_path):
    assert lab_perception_config("exp02") == {"bag_rim_color": list(RIM_COLOR)}
    f = tmp_path / "green.yaml"
    f.write_text(_bag_scenario(GREEN, (0.75, 0.45, 0.7)).to_yaml())
    assert lab_perception_config(str(f)) == {"bag_rim_color": list(GREEN)}
    assert np.allclose(lab_perception_config(str(f))["bag_rim_color"], GREEN)


def test_bagit_up_writes_the_binding_into_perceptions_config(tmp_path):
    import argparse
    from pathlib import Path

    from bagit.commands._service import load_service_config
    from bagit.services.perception.node import PerceptionServiceConfig
    from bagit.up import Up, UpOptions

    f = tmp_path / "blue.yaml"
    f.write_text(_bag_scenario(BLUE, (0.8, 0.75, 0.35)).to_yaml())
    up = Up(UpOptions(scenario=str(f), workdir=tmp_path / "up"))
    zpath, rpath = up._write_configs()
    argv = up._argv("perception", zpath, rpath)
    cfg, _ = load_service_config(PerceptionServiceConfig, Path(argv[argv.index("--config") + 1]), {}, argparse.Namespace(rig="sim"))
    assert cfg.bag_rim_color == BLUE and cfg.bag_kind is None  # the rest still from the run's scenario


def test_the_perception_node_segments_the_binding_its_config_names():
    """The node's `bag_rim_color` is the colour it segments: with it, frames of a green-bound bag give SOIs
    on the true rim; with the default (red), the same frames give none."""
    import time

    from bus_support import session_pair, wait_until

    from bagit.common.bus import Keys, Publisher, Subscriber
    from bagit.common.messages import RgbdFrame, SoiState
    from bagit.services.perception.node import PerceptionNode, PerceptionServiceConfig
    from bagit.services.perception.sources import SourceConfig

    s = _bag_scenario(GREEN, (0.75, 0.45, 0.7))
    with SimWorld(s, seed=0) as w:
        w.step(0.5)
        frames = [w.render_rgbd(k) for k in range(2)]
        true_rim = w.true_rim()
    got: dict[str, list[SoiState]] = {}
    for rim_color in (GREEN, None):
        for a, b in session_pair(f"pnbind{'g' if rim_color else 'r'}"):
            keys = Keys(f"pnbind{'g' if rim_color else 'r'}")
            node = PerceptionNode(a, keys, PerceptionServiceConfig(source=SourceConfig(kind="zenoh"), n_x=32, bag_rim_color=rim_color))
            try:
                sois: list[SoiState] = []
                Subscriber(b, keys.perception_soi, SoiState, sois.append)
                pub = Publisher(b, keys.camera_rgbd, RgbdFrame, lockstep=True)  # reliable: on a busy machine a best-effort 1.5 MB frame can be dropped
                assert wait_until(lambda: pub.matched)
                for k, f in enumerate(frames):  # each sent again until the node has it (a put before its subscriber is up is lost)
                    seen = node.counters["processed"] + node.counters["dropped"]
                    for _ in range(30):
                        pub.put(f.model_copy(update={"stamp": time.time(), "seq": 10 + k}))
                        if wait_until(lambda: node.counters["processed"] + node.counters["dropped"] > seen, timeout=5.0):
                            break
                assert wait_until(lambda: node._pending is None and not node._busy, timeout=60)
                time.sleep(0.2)
                assert node.counters["bad"] == (0 if rim_color else node.counters["processed"])
            finally:
                node.close()
            got["green" if rim_color else "red"] = sois
    assert got["green"] and all(points_to_polyline_distance(x.rim, true_rim).max() < 0.025 for x in got["green"])
    assert got["red"] == []
