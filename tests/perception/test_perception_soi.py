"""SOI extraction on generated clouds with a known true rim: accuracy, coverage, order, warm start, bad input."""

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bagit.common.errors import BadCloud
from bagit.common.geometry import closed_polyline_length, points_to_polyline_distance, resample_closed, rpy_to_matrix
from bagit.services.perception import SoiParams, extract_soi
from bagit.services.perception.synthetic import make_rim_cloud, rim_cloud, true_rim

N_X = 32
TILTS = [(0.0, 0.0, 0.0), (0.35, -0.2, 1.0)]


def check_soi(soi: np.ndarray, rim: np.ndarray, visible: np.ndarray, n_x: int = N_X, bridged_max_m: float = 0.012) -> None:
    """The task's acceptance checks, measured against the true rim polyline `rim (m, 3)`."""
    assert soi.shape == (n_x, 3) and np.all(np.isfinite(soi))
    d = points_to_polyline_distance(soi, rim)
    assert d.mean() <= 0.002, f"mean {d.mean() * 1e3:.2f} mm"
    assert np.percentile(d, 95) <= 0.005, f"p95 {np.percentile(d, 95) * 1e3:.2f} mm"
    # Points over a hidden stretch are bridged along the rim, never left in the middle of the gap.
    assert d.max() <= bridged_max_m, f"a point is {d.max() * 1e3:.1f} mm off the rim"
    # Coverage: no visible stretch of the rim farther than 1.2 spacings from an SOI point.
    spacing = closed_polyline_length(rim) / n_x
    gap = cKDTree(soi).query(rim[visible])[0].max()
    assert gap <= 1.2 * spacing, f"a visible stretch is {gap * 1e3:.1f} mm from the SOI (spacing {spacing * 1e3:.1f})"
    check_order(soi, rim)


def check_order(soi: np.ndarray, rim: np.ndarray) -> None:
    """Counter-clockwise seen from above, and consecutive points are neighbours along the rim,
    going once round it. (The synthetic rims run counter-clockwise about +z in index order.)"""
    c = soi.mean(axis=0)
    assert np.cross(soi - c, np.roll(soi, -1, axis=0) - c)[:, 2].sum() > 0, "not counter-clockwise from above"
    arc_idx = cKDTree(rim).query(soi)[1]
    steps = np.diff(np.concatenate([arc_idx, arc_idx[:1]])) % len(rim)
    assert np.all(steps > 0) and np.all(steps < 2.5 * len(rim) / len(soi)), "SOI order jumps along the rim"
    assert steps.sum() == len(rim), "SOI does not go round the rim exactly once"


@pytest.mark.parametrize("kind", ["ellipse", "lens", "wavy", "sagging"])
@pytest.mark.parametrize("rpy", TILTS)
@pytest.mark.parametrize("outliers, occlusion, seed", [(0.1, 0.07, 0), (0.3, 0.15, 1)])
def test_accuracy_noise_outliers_density_occlusion(kind, rpy, outliers, occlusion, seed):
    """2 mm depth noise, a 6 mm band, 5x uneven density, 10-30 % outliers and a 7-15 % hidden stretch."""
    rim = true_rim(kind, rpy=rpy)
    cloud, visible = rim_cloud(
        rim, noise_m=0.002, band_m=0.006, outlier_fraction=outliers, density_ratio=5.0,
        occlusion=occlusion, occlusion_at=0.1 + 0.4 * seed, seed=seed,
    )
    check_soi(extract_soi(cloud, N_X), rim, visible)


@pytest.mark.parametrize("occlusion_at", [0.0, 0.25, 0.5, 0.75])
def test_hidden_tip_of_a_long_ellipse_is_bridged_along_the_rim(occlusion_at):
    """15 % hidden at a tip of a 2:1 ellipse (or a side): the bridge follows the rim within a few mm."""
    rim = true_rim("ellipse", aspect=0.5, rpy=(0.2, 0.0, 0.3))
    cloud, visible = rim_cloud(rim, occlusion=0.15, occlusion_at=occlusion_at, outlier_fraction=0.2, seed=3)
    soi = extract_soi(cloud, N_X)
    check_soi(soi, rim, visible)
    assert points_to_polyline_distance(soi, rim).max() < 0.004


def test_two_grippers_hide_both_handles():
    rim = true_rim("lens", rpy=(0.1, 0.05, 0.2))
    cloud, visible = rim_cloud(rim, occlusion=0.07, occlusion_at=[0.0, 0.5], outlier_fraction=0.2, seed=8)
    check_soi(extract_soi(cloud, N_X), rim, visible)


@pytest.mark.parametrize("n_x", [4, 8, 16, 48, 64])
def test_other_point_counts(n_x):
    """Few SOI points still lie on the rim (at least 24 Gaussians are fitted), many still cover it."""
    rim = true_rim("lens", rpy=(0.2, 0.0, 0.7))
    cloud, visible = rim_cloud(rim, outlier_fraction=0.2, occlusion=0.07, seed=n_x)
    soi = extract_soi(cloud, n_x)
    assert soi.shape == (n_x, 3)
    d = points_to_polyline_distance(soi, rim)
    assert d.mean() <= 0.002 and d.max() <= 0.006
    if n_x >= 8:
        check_soi(soi, rim, visible, n_x=n_x)
    steps = np.linalg.norm(np.roll(soi, -1, axis=0) - soi, axis=1)
    assert steps.max() / steps.min() < 1.3  # evenly spaced along the rim


@pytest.mark.parametrize(
    "rpy, perimeter, aspect, outliers, occlusion, at, n_x, n_points",
    [
        ((-0.08, 0.33, 0.97), 0.7, 0.49, 0.12, 0.09, 0.92, 24, 3000),
        ((-0.02, 0.3, -2.32), 0.68, 0.55, 0.17, 0.123, 0.4, 24, 12000),
        ((-0.15, 0.05, -2.9), 0.58, 0.55, 0.13, 0.119, 0.96, 16, 3000),
    ],
)
def test_wavy_rims_with_few_points_and_a_hidden_stretch(rpy, perimeter, aspect, outliers, occlusion, at, n_x, n_points):
    """Cases the chain's bending prior is needed for: without it the components near the gap lose
    the rim and the bridge is centimetres off."""
    rim = true_rim("wavy", perimeter=perimeter, rpy=rpy, aspect=aspect)
    cloud, visible = rim_cloud(rim, n_points=n_points, outlier_fraction=outliers, occlusion=occlusion, occlusion_at=at, seed=5)
    check_soi(extract_soi(cloud, n_x), rim, visible, n_x=n_x)


def test_sizes_and_sparse_clouds():
    for perimeter, n_points in [(0.4, 1500), (1.0, 4000), (0.68, 800)]:
        rim = true_rim("ellipse", perimeter=perimeter, rpy=(0.1, 0.1, 0.4))
        cloud, visible = rim_cloud(rim, n_points=n_points, outlier_fraction=0.15, occlusion=0.05, seed=11)
        check_soi(extract_soi(cloud, N_X), rim, visible)


def test_make_rim_cloud_gives_cloud_and_true_rim():
    cloud, rim = make_rim_cloud("sagging", rpy=(0.2, -0.1, 0.3), n_points=5000, outlier_fraction=0.25, seed=4)
    assert cloud.shape == (5000, 3) and rim.shape[1] == 3
    assert abs(closed_polyline_length(rim) - 0.68) < 1e-9
    d = points_to_polyline_distance(extract_soi(cloud, N_X), rim)
    assert d.mean() <= 0.002


def test_order_convention_ccw_from_above_and_start():
    rim = true_rim("ellipse", center=(0.1, -0.05, 0.4))
    cloud, _ = rim_cloud(rim, occlusion=0.0, seed=4)
    soi = extract_soi(cloud, N_X)
    c = soi.mean(axis=0)
    assert np.cross(soi - c, np.roll(soi, -1, axis=0) - c)[:, 2].sum() > 0  # counter-clockwise seen from above
    ang = np.mod(np.arctan2(soi[:, 1] - c[1], soi[:, 0] - c[0]), 2 * np.pi)
    assert np.argmin(ang) == 0  # smallest angle from +x first
    hint = np.array([0.1, -0.3, 0.4])  # a handle at -y
    soi_h = extract_soi(cloud, N_X, start_hint=hint)
    assert np.argmin(np.linalg.norm(soi_h - hint, axis=1)) == 0
    assert np.cross(soi_h - c, np.roll(soi_h, -1, axis=0) - c)[:, 2].sum() > 0


def test_rim_given_clockwise_still_comes_out_counter_clockwise():
    rim = true_rim("lens", rpy=(0.3, 0.0, 0.0))[::-1]  # the polyline runs clockwise
    cloud, _ = rim_cloud(rim, seed=2)
    soi = extract_soi(cloud, N_X)
    c = soi.mean(axis=0)
    assert np.cross(soi - c, np.roll(soi, -1, axis=0) - c)[:, 2].sum() > 0


def test_steep_tilt_orders_about_the_upward_plane_normal():
    """Tilted 60 degrees: counter-clockwise about the rim plane's normal taken with positive z."""
    rim = true_rim("ellipse", rpy=(np.pi / 3, 0.0, 0.2))
    cloud, visible = rim_cloud(rim, occlusion=0.05, seed=6)
    soi = extract_soi(cloud, N_X)
    normal = rpy_to_matrix((np.pi / 3, 0.0, 0.2))[:, 2]
    c = soi.mean(axis=0)
    assert normal[2] > 0 and np.cross(soi - c, np.roll(soi, -1, axis=0) - c).sum(axis=0) @ normal > 0
    assert points_to_polyline_distance(soi, rim).mean() <= 0.002


def test_start_hint_puts_point_zero_at_the_handle():
    rim = true_rim("lens", rpy=(0.0, 0.0, np.pi / 2))  # handles at +-y
    cloud, _ = rim_cloud(rim, seed=9)
    left = rim[np.argmin(rim[:, 1])]
    soi = extract_soi(cloud, N_X, start_hint=left + [0.0, -0.02, 0.03])
    assert np.linalg.norm(soi[0] - left) < 0.006  # on the rim, at the handle


def test_warm_start_tracks_and_keeps_order():
    rim0 = true_rim("lens", rpy=(0.1, 0.0, 0.2))
    prev = extract_soi(rim_cloud(rim0, seed=5)[0], N_X)
    c = rim0.mean(axis=0)
    for k in range(1, 9):  # the rim slides 4 mm, turns and narrows a little per frame
        rim = ((rim0 - c) * [1.0, 1.0 - 0.01 * k, 1.0]) @ rpy_to_matrix((0.0, 0.0, 0.01 * k)).T + c + [0.004 * k, 0.0, 0.0]
        cloud, visible = rim_cloud(rim, occlusion=0.1, occlusion_at=0.3 + 0.01 * k, seed=10 + k)
        cur = extract_soi(cloud, N_X, init=prev)
        check_soi(cur, rim, visible)
        # point i stays point i: each moves no more than the rim did (4 mm slide + turn + noise)
        assert np.linalg.norm(cur - prev, axis=1).max() < 0.008
        prev = cur


def _bean(dent: float, width: float = 0.4) -> np.ndarray:
    """A kidney-shaped rim `(2000, 3)`: an ellipse with a dent `dent` deep (share of its radius) at +x."""
    t = np.linspace(0.0, 2.0 * np.pi, 2000, endpoint=False)
    r = 0.11 * (1.0 - dent * np.exp(-((np.angle(np.exp(1j * t)) / width) ** 2)))
    return resample_closed(np.column_stack([r * np.cos(t), 0.8 * r * np.sin(t), 0.45 + 0.01 * np.cos(2 * t)]), 2000)


@pytest.mark.parametrize("occlusion_at", [0.25, 0.5, 0.75])
def test_warm_start_keeps_a_kidney_shaped_rims_length_over_a_hidden_stretch(occlusion_at):
    """A pinched rim is far from the ellipse the polar bridge models: bridged that way, a hidden
    stretch bulged out by centimetres and the SOI jumped. Warm, the bridge that keeps the last
    rim's length is taken."""
    rim = _bean(0.6)
    prev = resample_closed(rim, N_X)  # the rim as last seen, whole
    cloud, _ = rim_cloud(rim, occlusion=0.15, occlusion_at=occlusion_at, seed=3)
    cur = extract_soi(cloud, N_X, init=prev)
    assert abs(closed_polyline_length(cur) / closed_polyline_length(rim) - 1.0) < 0.04
    assert np.linalg.norm(cur - prev, axis=1).max() < 0.015


def test_warm_start_keeps_init_indexing_whatever_it_is():
    """An init that starts elsewhere and runs clockwise: the result keeps exactly that indexing."""
    rim = true_rim("ellipse", rpy=(0.2, 0.1, 0.0))
    cloud, _ = rim_cloud(rim, seed=12)
    cold = extract_soi(cloud, N_X)
    init = np.roll(cold, 7, axis=0)[::-1]
    warm = extract_soi(cloud, N_X, init=init)
    assert np.linalg.norm(warm - init, axis=1).max() < 0.004
    cloud2, _ = rim_cloud(rim + [0.0, 0.003, 0.0], seed=13)
    warm2 = extract_soi(cloud2, N_X, init=warm)
    assert np.linalg.norm(warm2 - warm, axis=1).max() < 0.006


def test_warm_start_does_not_creep_round_a_still_rim():
    rim = true_rim("wavy", rpy=(0.1, 0.0, 0.4))
    prev = first = extract_soi(rim_cloud(rim, occlusion=0.07, seed=20)[0], N_X)
    for k in range(20):
        prev = extract_soi(rim_cloud(rim, occlusion=0.07, seed=21 + k)[0], N_X, init=prev)
    assert np.linalg.norm(prev - first, axis=1).max() < 0.004


def test_warm_start_falls_back_to_cold_when_the_rim_is_elsewhere():
    rim = true_rim("ellipse")
    cloud, visible = rim_cloud(rim, seed=6)
    cold = extract_soi(cloud, N_X)
    far = cold + [0.5, 0.0, 0.0]
    soi = extract_soi(cloud, N_X, init=far)
    check_soi(soi, rim, visible)
    # ... and is indexed like init as far as it can be: the same cyclic order as the cold result
    assert np.linalg.norm(soi - cold, axis=1).max() < 0.004


@pytest.mark.parametrize("distance", [0.02, 0.06, 0.12, 0.25])
def test_warm_start_from_a_far_init_never_fits_the_wrong_thing(distance):
    """An init displaced by 2-25 cm (a dropped frame, a jolt), with 30 % outliers and a hidden
    stretch: the SOI is on the rim whether the warm start holds or it falls back to cold."""
    rim = true_rim("lens", rpy=(0.1, 0.0, 0.3))
    cloud, visible = rim_cloud(rim, outlier_fraction=0.3, occlusion=0.15, seed=15)
    cold = extract_soi(cloud, N_X)
    for angle in (0.0, 2.0, 4.0):
        init = cold + distance * np.array([np.cos(angle), np.sin(angle), 0.3])
        check_soi(extract_soi(cloud, N_X, init=init), rim, visible)


def test_huge_cloud_is_thinned_first():
    rim = true_rim("ellipse")
    cloud, visible = rim_cloud(rim, n_points=400_000, outlier_fraction=0.3, seed=7)
    check_soi(extract_soi(cloud, N_X), rim, visible)


def test_outlier_clumps_are_not_taken_for_rim():
    """Clumps of outliers (a red object in the scene) near the rim: no SOI point sits on them."""
    rim = true_rim("ellipse", rpy=(0.1, 0.0, 0.0))
    cloud, visible = rim_cloud(rim, outlier_fraction=0.2, occlusion=0.1, occlusion_at=0.25, seed=14)
    rng = np.random.default_rng(14)
    c = rim.mean(axis=0)
    clumps = [c + [0.0, 0.16, 0.03], c + [0.2, -0.05, 0.0], c + [-0.05, 0.0, 0.05]]
    extra = np.vstack([p + rng.normal(0.0, 0.004, (150, 3)) for p in clumps])
    soi = extract_soi(np.vstack([cloud, extra]), N_X)
    check_soi(soi, rim, visible)


def test_params_are_validated_and_used():
    with pytest.raises(ValueError):
        SoiParams(bending=-1.0)
    with pytest.raises(ValueError):
        SoiParams(unknown=1)
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, seed=3)
    few = extract_soi(cloud, N_X, params=SoiParams(cold_iterations=1))
    assert few.shape == (N_X, 3)


@pytest.mark.parametrize(
    "points, n_x, word",
    [
        (np.zeros((0, 3)), 32, "empty"),
        (np.full((100, 3), np.nan), 32, "NaN"),
        (np.r_[np.random.default_rng(0).normal(size=(99, 3)), [[np.inf, 0, 0]]], 8, "NaN or infinite"),
        (np.random.default_rng(0).normal(size=(10, 3)), 32, "fewer"),
        (np.zeros((500, 3)), 32, "degenerate"),
        (np.outer(np.linspace(0, 1, 500), [1, 2, 3]), 32, "degenerate"),
        (np.random.default_rng(0).normal(size=(100, 3)), 3, "n_x"),
        (np.random.default_rng(0).normal(size=(100, 3)), 32.0, "n_x"),
        (np.random.default_rng(0).normal(size=(100, 3)), True, "n_x"),
        (np.zeros((100, 2)), 32, "shape"),
        (np.zeros((10, 3, 1)), 4, "shape"),
        (np.zeros(3), 4, "shape"),
        ("not a cloud", 32, "numeric"),
        ([[1, 2, "x"]], 4, "numeric"),
        (np.full((100, 3), 1e300), 4, "beyond"),
    ],
)
def test_bad_clouds(points, n_x, word):
    with pytest.raises(BadCloud, match=word):
        extract_soi(points, n_x)


def test_bad_init_and_hint():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, seed=0)
    for init in (np.zeros((5, 3)), np.full((N_X, 3), np.nan), np.zeros((N_X, 3)), "x"):
        with pytest.raises(BadCloud, match="init"):
            extract_soi(cloud, N_X, init=init)
    for hint in (np.zeros(2), [np.nan, 0, 0], "left"):
        with pytest.raises(BadCloud, match="start_hint"):
            extract_soi(cloud, N_X, start_hint=hint)


def test_a_blob_is_not_a_rim():
    """Points filling a ball: whatever comes out is finite, or BadCloud says there is no rim."""
    pts = np.random.default_rng(3).normal(0.0, 0.05, (5000, 3))
    try:
        soi = extract_soi(pts, N_X)
    except BadCloud:
        return
    assert soi.shape == (N_X, 3) and np.all(np.isfinite(soi))


def test_a_half_hidden_rim_is_refused_for_what_it_is_not_as_a_numerical_failure():
    """A rim cloud of 117 points from a simulated run (exp09, the bag's rim mostly out of view):
    cold EM leaves half its components without points, the median support is ~1e-10, and one
    component with a trace of support but no mean of its own used to count as fed and put NaN
    into the bridge ("failed numerically"). Now the cloud is refused because it shows too little rim."""
    case = np.load(Path(__file__).parent / "data" / "half-hidden-rim.npz")
    for init in (case["init"], None):
        with pytest.raises(BadCloud, match="not show enough of a rim"):
            extract_soi(case["points"], N_X, init=init)
