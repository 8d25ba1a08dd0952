"""SOI extraction on generated clouds with a known true rim."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial import cKDTree

from bagit.common.errors import BadCloud
from bagit.common.geometry import closed_polyline_length, points_to_polyline_distance
from bagit.services.perception import extract_soi
from bagit.services.perception.synthetic import rim_cloud, true_rim

N_X = 32
TILTS = [(0.0, 0.0, 0.0), (0.35, -0.2, 1.0)]


def check_soi(soi: np.ndarray, rim: np.ndarray, visible: np.ndarray) -> None:
    """Accuracy where the rim is seen; where it is hidden, SOI points are bridged close to it."""
    assert soi.shape == (N_X, 3) and np.all(np.isfinite(soi))
    d_all = points_to_polyline_distance(soi, rim)
    seen = visible[cKDTree(rim).query(soi)[1]]
    d = d_all[seen]
    assert d.mean() <= 0.002, f"mean {d.mean() * 1e3:.2f} mm"
    assert np.percentile(d, 95) <= 0.005, f"p95 {np.percentile(d, 95) * 1e3:.2f} mm"
    assert d_all.max() <= 0.015, f"a bridged point is {d_all.max() * 1e3:.1f} mm off the rim"
    spacing = closed_polyline_length(rim) / N_X
    gap = cKDTree(soi).query(rim[visible])[0].max()
    assert gap <= 1.2 * spacing, f"a visible stretch is {gap * 1e3:.1f} mm from the SOI"
    # Consecutive SOI points are neighbours along the rim: their arc positions advance monotonically.
    arc_idx = cKDTree(rim).query(soi)[1]
    steps = np.diff(np.concatenate([arc_idx, arc_idx[:1]])) % len(rim)
    assert np.all(steps < len(rim) / N_X * 2.5), "SOI order jumps along the rim"


@pytest.mark.parametrize("kind", ["ellipse", "lens", "wavy", "sagging"])
@pytest.mark.parametrize("rpy", TILTS)
@pytest.mark.parametrize("outliers, seed", [(0.1, 0), (0.3, 1)])
def test_accuracy_noise_outliers_density_occlusion(kind, rpy, outliers, seed):
    rim = true_rim(kind, rpy=rpy)
    cloud, visible = rim_cloud(
        rim, noise_m=0.002, outlier_fraction=outliers, density_ratio=5.0, occlusion=0.07, occlusion_at=0.1 + 0.4 * seed, seed=seed
    )
    check_soi(extract_soi(cloud, N_X), rim, visible)


def test_long_occlusion_bridged_on_the_rim():
    """A 15 % stretch hidden: the visible rim stays accurate and the hidden points stay near the rim."""
    rim = true_rim("ellipse", rpy=(0.2, 0.0, 0.3))
    cloud, visible = rim_cloud(rim, occlusion=0.15, occlusion_at=0.4, seed=3)
    soi = extract_soi(cloud, N_X)
    near = cKDTree(rim).query(soi)[1]
    d = points_to_polyline_distance(soi, rim)
    assert d[visible[near]].mean() < 0.002
    assert d.max() < 0.02  # bridged along the curve, never sitting in the middle of the bag


def test_order_convention_ccw_from_above_and_start():
    rim = true_rim("ellipse", center=(0.1, -0.05, 0.4))
    cloud, _ = rim_cloud(rim, occlusion=0.0, seed=4)
    soi = extract_soi(cloud, N_X)
    c = soi.mean(axis=0)
    area_z = np.cross(soi - c, np.roll(soi, -1, axis=0) - c)[:, 2].sum()
    assert area_z > 0  # counter-clockwise seen from above
    ang = np.mod(np.arctan2(soi[:, 1] - c[1], soi[:, 0] - c[0]), 2 * np.pi)
    assert np.argmin(ang) == 0  # smallest angle from +x first
    hint = np.array([0.1, -0.3, 0.4])  # a handle at -y
    soi_h = extract_soi(cloud, N_X, start_hint=hint)
    assert np.argmin(np.linalg.norm(soi_h - hint, axis=1)) == 0


def test_warm_start_tracks_and_keeps_order():
    rim = true_rim("lens", rpy=(0.1, 0.0, 0.2))
    cloud, _ = rim_cloud(rim, seed=5)
    soi = extract_soi(cloud, N_X)
    prev = soi
    for k in range(1, 6):  # the rim slides 4 mm and turns a little per frame
        moved = rim @ np.array([[np.cos(0.01 * k), -np.sin(0.01 * k), 0], [np.sin(0.01 * k), np.cos(0.01 * k), 0], [0, 0, 1]]).T
        moved = moved + [0.004 * k, 0.0, 0.0]
        cloud_k, vis = rim_cloud(moved, seed=10 + k)
        cur = extract_soi(cloud_k, N_X, init=prev)
        assert points_to_polyline_distance(cur, moved).mean() < 0.002
        # point i stays point i: each moved at most a few mm plus its share of the slide
        assert np.linalg.norm(cur - prev, axis=1).max() < 0.012
        prev = cur


def test_warm_start_falls_back_to_cold_when_the_rim_is_elsewhere():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, seed=6)
    far = extract_soi(cloud, N_X) + [0.5, 0.0, 0.0]
    soi = extract_soi(cloud, N_X, init=far)
    assert points_to_polyline_distance(soi, rim).mean() < 0.002


def test_huge_and_uneven_clouds():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, n_points=300_000, seed=7)
    assert points_to_polyline_distance(extract_soi(cloud, N_X), rim).mean() < 0.002


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
        (np.zeros((100, 2)), 32, "shape"),
        ("not a cloud", 32, "numeric"),
    ],
)
def test_bad_clouds(points, n_x, word):
    with pytest.raises(BadCloud, match=word):
        extract_soi(points, n_x)


def test_bad_init():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, seed=0)
    with pytest.raises(BadCloud, match="init"):
        extract_soi(cloud, N_X, init=np.zeros((5, 3)))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
@given(
    arrays(np.float64, st.tuples(st.integers(0, 400), st.integers(1, 4)), elements=st.floats(allow_nan=True, allow_infinity=True, width=64)),
    st.integers(-2, 40),
)
def test_arbitrary_arrays_give_soi_or_bad_cloud(points, n_x):
    try:
        soi = extract_soi(points, n_x)
    except BadCloud:
        return
    assert soi.shape == (n_x, 3) and np.all(np.isfinite(soi))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.integers(0, 10_000), st.floats(0.0, 0.4), st.floats(0.0, 0.2))
def test_random_rims_give_soi_or_bad_cloud(seed, outliers, occlusion):
    rng = np.random.default_rng(seed)
    rim = true_rim(rng.choice(["ellipse", "lens", "wavy", "sagging"]), rpy=tuple(rng.uniform(-0.5, 0.5, 3)))
    cloud, _ = rim_cloud(rim, n_points=int(rng.integers(200, 5000)), outlier_fraction=outliers, occlusion=occlusion, seed=seed)
    try:
        soi = extract_soi(cloud, 16)
    except BadCloud:
        return
    assert np.all(np.isfinite(soi))
    assert points_to_polyline_distance(soi, rim).max() < 0.1
