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
