"""The SOI extractor's parts: clean-up, ring ordering, chain EM, bridging, the rim curve, the sample file."""

from importlib import resources

import numpy as np
import pytest
from scipy.spatial import cKDTree

from bagit.common.errors import BadCloud
from bagit.common.geometry import closed_polyline_length, points_to_polyline_distance
from bagit.services.perception import extract_soi, load_cloud
from bagit.services.perception.cleanup import SUBSAMPLE_POINTS, _chance_count, clean_cloud, dense_cells, gate_near, subsample, voxel_down
from bagit.services.perception.curve import ClosedCurve, following_phase, polar_fill
from bagit.services.perception.em import bending_matrix, bridge, chain_em
from bagit.services.perception.ring import is_counter_clockwise, rim_plane, ring_init
from bagit.services.perception.synthetic import rim_cloud, sample_cloud, true_rim


def ellipse(n: int, a: float = 0.15, b: float = 0.08, z: float = 0.4, phase: float = 0.0) -> np.ndarray:
    t = phase + np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([a * np.cos(t), b * np.sin(t), np.full(n, z)])


# --- clean-up -----------------------------------------------------------------------------------


def test_dense_cells_drop_scattered_outliers_and_keep_the_rim():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, n_points=12_000, outlier_fraction=0.3, seed=0)
    keep = dense_cells(cloud)
    d = cKDTree(rim).query(cloud)[0]  # the rim polyline is dense (0.3 mm steps)
    assert np.mean(d[keep] < 0.01) > 0.99  # what is kept is rim
    assert keep[d < 0.006].mean() > 0.95  # and the rim is kept


def test_cell_threshold_grows_with_outlier_density():
    counts = [_chance_count(lam, 65_000) for lam in (1e-4, 1e-2, 0.05, 0.12, 0.3)]
    assert counts[0] == 3 and counts == sorted(counts) and counts[-1] > counts[0]


def test_clean_cloud_evens_density_and_thins_huge_clouds():
    rim = true_rim("ellipse")
    cloud, _ = rim_cloud(rim, n_points=100_000, outlier_fraction=0.2, density_ratio=5.0, seed=1)
    assert len(subsample(cloud)) == SUBSAMPLE_POINTS and np.array_equal(subsample(cloud), subsample(cloud))
    cleaned = clean_cloud(cloud)
    assert len(cleaned) < 3000
    # density along the rim after voxelisation: dense and sparse ends within 2x, not 5x
    s = np.arange(len(rim)) / len(rim)
    idx = np.argmin(np.linalg.norm(cleaned[:, None] - rim[None, ::20], axis=2), axis=1) * 20
    dense = np.sum(np.abs(((s[idx] + 0.5) % 1.0) - 0.5) < 0.1)
    sparse = np.sum(np.abs(s[idx] - 0.5) < 0.1)
    assert dense < 2.0 * sparse


def test_voxel_down_averages_per_voxel():
    pts = np.array([[0.0001, 0.0001, 0.0001], [0.0003, 0.0003, 0.0003], [0.1, 0.1, 0.1]])
    out = voxel_down(pts, 0.004)
    assert len(out) == 2 and np.any(np.all(np.isclose(out, 0.0002), axis=1))


def test_gate_keeps_points_near_the_curve_between_its_vertices():
    rim = ellipse(32)
    mid = 0.5 * (rim + np.roll(rim, -1, axis=0))  # half-way between vertices
    outward = (mid - [0.0, 0.0, 0.4]) / np.linalg.norm(mid - [0.0, 0.0, 0.4], axis=1, keepdims=True)
    near = mid + 0.03 * outward
    up = mid + [0.0, 0.0, 0.035]
    far = mid + 0.06 * outward
    kept = gate_near(np.vstack([near, up, far, [[1.0, 1.0, 1.0]]]), rim, radius=0.04)
    assert len(kept) == 64 and np.allclose(kept, np.vstack([near, up]))


# --- ring ordering ------------------------------------------------------------------------------


def test_ring_init_is_counter_clockwise_and_even():
    rim = true_rim("lens", rpy=(0.2, 0.1, 2.0))
    cloud, _ = rim_cloud(rim, outlier_fraction=0.2, occlusion=0.0, seed=2)
    cleaned = clean_cloud(cloud)
    centroid, normal = rim_plane(cleaned)
    mu0 = ring_init(cleaned, 32, centroid, normal)
    assert normal[2] > 0 and is_counter_clockwise(mu0, normal)
    steps = np.linalg.norm(np.roll(mu0, -1, axis=0) - mu0, axis=1)
    assert steps.max() / steps.min() < 1.5
    assert np.median(points_to_polyline_distance(mu0, rim)) < 0.005


def test_rim_plane_refuses_lines_and_points():
    with pytest.raises(BadCloud, match="degenerate"):
        rim_plane(np.outer(np.linspace(0, 1, 50), [1.0, 0.5, 0.0]))
    with pytest.raises(BadCloud, match="degenerate"):
        rim_plane(np.zeros((2, 3)))


# --- chain EM -----------------------------------------------------------------------------------


def test_bending_matrix_is_the_closed_second_difference():
    P = bending_matrix(8)
    assert np.allclose(P, P.T) and np.allclose(P @ np.ones(8), 0.0)
    assert np.allclose(np.diag(P), 6.0) and np.isclose(P[0, 2], 1.0) and np.isclose(P[0, 1], -4.0)
    assert not P.flags.writeable


def test_chain_em_fits_a_noisy_ring_and_estimates_the_outlier_share():
    rng = np.random.default_rng(3)
    ring = ellipse(3000) + rng.normal(0.0, 0.0015, (3000, 3))
    outliers = rng.uniform([-0.3, -0.3, 0.2], [0.3, 0.3, 0.6], (750, 3))  # 20 %
    mu0 = ellipse(24, a=0.12, b=0.06, phase=0.05)  # too small, turned a little
    fit = chain_em(np.vstack([ring, outliers]), mu0, iterations=60, bending=0.3, sigma0=0.01)
    d = points_to_polyline_distance(fit.mu, ellipse(2000))
    assert d.max() < 0.002
    assert 0.15 < fit.outlier_weight < 0.25
    assert np.all(fit.support > 0.5 * np.median(fit.support))
    assert is_counter_clockwise(fit.mu, np.array([0.0, 0.0, 1.0]))


def test_chain_em_carries_components_through_a_gap():
    ring = ellipse(4000)
    t = np.arctan2(ring[:, 1] / 0.08, ring[:, 0] / 0.15)
    seen = ring[np.abs(np.angle(np.exp(1j * (t - np.pi / 2)))) > 0.5]  # a gap at the top
    fit = chain_em(seen, ellipse(24), iterations=40, bending=0.3, sigma0=0.01)
    starved = fit.support < 0.2 * np.median(fit.support)
    assert 1 <= starved.sum() <= 4
    # the starved ones are bridged near the rim (bending continuation), not pulled onto the chord
    assert points_to_polyline_distance(fit.mu[starved], ellipse(2000)).max() < 0.01


def test_bridge_replaces_the_dropped_means_smoothly():
    mu = ellipse(32)
    keep = np.ones(32, dtype=bool)
    keep[10:14] = False
    moved = mu.copy()
    moved[10:14] += 0.05  # strays
    out = bridge(moved, keep)
    assert np.allclose(out[keep], mu[keep])
    assert points_to_polyline_distance(out[~keep], ellipse(2000)).max() < 0.003


# --- the rim curve ------------------------------------------------------------------------------


def test_closed_curve_even_points_and_length():
    curve = ClosedCurve.through(ellipse(24, a=0.1, b=0.1))
    assert abs(curve.length - 2 * np.pi * 0.1) < 1e-4
    pts = curve.even(40, phase=0.013)
    steps = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
    assert steps.max() - steps.min() < 1e-4
    assert np.allclose(curve.at(np.array([curve.length + 0.01])), curve.at(np.array([0.01])))


def test_following_phase_recovers_a_known_shift():
    curve = ClosedCurve.through(ellipse(32))
    prev = curve.even(16, phase=0.0123)
    assert abs(following_phase(curve, prev) - 0.0123) < 0.002


def test_polar_fill_restores_a_hidden_tip_of_an_ellipse():
    mu = ellipse(32, a=0.16, b=0.07)  # 2.3 : 1
    keep = np.ones(32, dtype=bool)
    keep[-3:] = keep[:3] = False  # the +x tip hidden
    knots = polar_fill(mu + [0.01, -0.02, 0.0], keep, np.array([0.0, 0.0, 1.0]))
    assert knots is not None and len(knots) > keep.sum()
    truth = ellipse(4000, a=0.16, b=0.07) + [0.01, -0.02, 0.0]
    assert cKDTree(truth).query(knots)[0].max() < 1e-3  # truth is dense: 0.2 mm steps
    chord = ClosedCurve.through(mu, keep)  # the arc-length spline alone cuts the tip
    assert cKDTree(ellipse(4000, a=0.16, b=0.07)).query(chord.points)[0].max() > 0.003


def test_polar_fill_declines_a_rim_that_is_not_star_shaped():
    """A rim that folds back (seen from its centre, one stretch runs clockwise): no polar model."""
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    t[3] = 0.5 * (t[1] + t[2])  # this knot turns back past its predecessor
    loop = np.column_stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros(12)])
    loop[3] *= 0.5
    keep = np.ones(12, dtype=bool)
    keep[8] = False
    assert polar_fill(loop, keep, np.array([0.0, 0.0, 1.0])) is None
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)  # the same without the fold is bridged
    assert polar_fill(np.column_stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.zeros(12)]), keep, np.array([0.0, 0.0, 1.0])) is not None


# --- the bundled sample -------------------------------------------------------------------------


def test_bundled_sample_is_the_generated_one_and_gives_its_rim():
    with resources.as_file(resources.files("bagit.common") / "data" / "sample_rim.ply") as path:
        points = load_cloud(path)
    generated, colors, rim = sample_cloud()
    assert points.shape == (12_000, 3) and np.allclose(points, generated, atol=1e-9)
    assert colors.shape == (12_000, 3) and colors.min() >= 0 and colors.max() <= 1
    soi = extract_soi(points, 32)
    d = points_to_polyline_distance(soi, rim)
    assert d.mean() < 0.002 and abs(closed_polyline_length(soi) - closed_polyline_length(rim)) < 0.02
