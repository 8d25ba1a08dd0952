"""Which object, and where: the ArUco marker on a simulated object names it and places its outline V.

Perception sees only the rendered frame and the object library (the scenario files' object
descriptions); the tests compare with the simulator's truth (where the scenario put the object).
"""

import numpy as np
import pytest

from bagit.common.errors import BadScenario, MarkerNotFound
from bagit.common.messages import RgbdFrame
from bagit.common.scenario import MARKER_THICKNESS_M, MarkerSpec, Scenario
from bagit.scenarios import find_scenario, list_scenarios
from bagit.services.perception.marker import LibraryObject, ObjectLibrary, locate_object, locate_objects
from bagit.services.sim.world import SimWorld


def angle_deg(A: np.ndarray, B: np.ndarray) -> float:
    R = A[:3, :3].T @ B[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))))


@pytest.fixture(scope="module")
def library() -> ObjectLibrary:
    return ObjectLibrary.from_scenarios()


# a level box with a 60 mm marker, a sphere (card on a curved top), a tilted bundle with a 36 mm marker
@pytest.mark.parametrize("name", ["exp01-coffee-box", "exp03-grapefruit", "exp12-three-bound-tilted"])
def test_marker_names_the_object_and_places_it_within_5mm_and_2deg(name, library):
    s = Scenario.from_file(find_scenario(name))
    with SimWorld(s, seed=3) as world:
        frame = world.render_rgbd(0)  # noisy depth, as the D455 model gives
    est = locate_object(frame, library)
    assert est.marker_id == s.object.marker.id
    T_true = s.object.T_world_marker()  # simulator truth: where the scenario put the marker
    assert np.linalg.norm(est.T_world_marker[:3, 3] - T_true[:3, 3]) < 0.005
    assert angle_deg(est.T_world_marker, T_true) < 2.0
    # the library's V, placed from the marker, lands on the scenario's V
    assert est.vertices.shape == s.object.bottom_vertices().shape
    assert np.abs(est.vertices - s.object.bottom_vertices()).max() < 0.005
    assert est.height == pytest.approx(s.object.effective_height())


def test_corners_only_pose_without_depth_is_still_close(library):
    s = Scenario.from_file(find_scenario("exp06-work-bin-tilted"))
    with SimWorld(s, seed=0) as world:
        frame = world.render_rgbd(0)
    est = locate_object(frame, library, use_depth=False)
    assert est.marker.depth_pixels == 0
    assert np.linalg.norm(est.T_world_marker[:3, 3] - s.object.T_world_marker()[:3, 3]) < 0.005
    assert angle_deg(est.T_world_marker, s.object.T_world_marker()) < 2.0


def test_no_marker_in_view_is_a_clear_error(library):
    frame = RgbdFrame(color=np.full((480, 640, 3), 128, np.uint8), depth=np.zeros((480, 640), np.uint16))
    assert locate_objects(frame, library) == []
    with pytest.raises(MarkerNotFound, match="no ArUco marker"):
        locate_object(frame, library)


def test_a_marker_not_in_the_library_is_named(library):
    s = Scenario.from_file(find_scenario("exp08-plastic-packing"))
    with SimWorld(s, seed=0) as world:
        frame = world.render_rgbd(0)
    others = ObjectLibrary(o for o in (library.get(i) for i in library.ids()) if o.marker.id != 8)
    with pytest.raises(MarkerNotFound, match=r"markers \[8\] are not in the library"):
        locate_object(frame, others)


def test_library_from_the_bundled_scenarios(library):
    ids = {Scenario.from_file(p).object.marker.id for p in list_scenarios()}
    assert library.ids() == sorted(ids) and len(library) == 12
    box = library.get(1)
    assert box.vertices.shape == (4, 3) and np.allclose(box.vertices[:, 2], 0.0)  # V in the bottom frame
    assert np.allclose(box.T_bottom_marker()[:3, 3], [0, 0, 0.15 + MARKER_THICKNESS_M])
    with pytest.raises(MarkerNotFound, match="not in the object library"):
        library.get(49)


def test_one_id_for_two_different_objects_is_refused():
    a = LibraryObject("a", MarkerSpec(id=5, position=(0, 0, 0.1)), np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]]), 0.1, "a.yaml")
    b = LibraryObject("b", MarkerSpec(id=5, position=(0, 0, 0.1)), np.array([[0, 0, 0], [2, 0, 0], [0, 1, 0.0]]), 0.1, "b.yaml")
    lib = ObjectLibrary([a, a])  # the same object twice is fine
    assert len(lib) == 1
    with pytest.raises(BadScenario, match="marker id 5 names two different objects"):
        lib.add(b)


def test_marker_spec_validation():
    base = {"name": "t", "object": {"shape": {"type": "box", "size": [0.1, 0.1, 0.1]}}}
    s = Scenario.from_dict({**base, "object": {**base["object"], "marker_id": 7}})
    assert s.object.marker.id == 7 and s.object.marker.position == (0.0, 0.0, 0.1 + MARKER_THICKNESS_M)
    assert Scenario.from_text(s.to_yaml()).object.marker == s.object.marker
    for bad, msg in [
        ({"id": 50}, "not in DICT_4X4_50"),
        ({"id": 1, "dictionary": "DICT_9X9_1"}, "unknown ArUco dictionary"),
        ({"id": 1, "size": 0.0}, "size"),
        ({"id": 1, "position": [0, float("nan"), 0]}, "finite"),
    ]:
        with pytest.raises(BadScenario, match=msg):
            Scenario.from_dict({**base, "object": {**base["object"], "marker": bad}})
    with pytest.raises(BadScenario, match="disagrees"):
        Scenario.from_dict({**base, "object": {**base["object"], "marker_id": 2, "marker": {"id": 3}}})
