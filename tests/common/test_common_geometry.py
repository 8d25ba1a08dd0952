import numpy as np
import pytest
from scipy.integrate import quad

from bagit.common import geometry as g


def test_ramanujan_matches_integral():
    for a, b, rel in [(0.12, 0.08, 1e-9), (0.15, 0.03, 1e-6), (0.2, 0.01, 1e-4), (0.1, 0.1, 1e-12)]:
        exact, _ = quad(lambda t: np.sqrt((a * np.sin(t)) ** 2 + (b * np.cos(t)) ** 2), 0, 2 * np.pi)
        assert g.ramanujan_perimeter(a, b) == pytest.approx(exact, rel=rel)


def test_fps_spreads_points():
    t = np.linspace(0, 2 * np.pi, 1000, endpoint=False) ** 1.5  # uneven sampling
    t = t / t.max() * 2 * np.pi
    pts = np.stack([np.cos(t), np.sin(t), 0 * t], axis=1)
    idx = g.farthest_point_sampling(pts, 16)
    assert len(set(idx.tolist())) == 16
    chosen = pts[idx]
    d = np.linalg.norm(chosen[:, None] - chosen[None], axis=2) + np.eye(16) * 9
    assert d.min() > 0.3  # an even 16-gon on the unit circle has side 0.39


def test_pca_axis_and_plane():
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(500, 3)) * [0.3, 0.05, 0.001]
    ax = g.pca_axis(pts)
    assert abs(ax[0]) > 0.99
    _, n, rms = g.fit_plane(pts)
    assert abs(n[2]) > 0.99 and rms < 0.002


def test_chamfer_zero_for_same_set_and_grows():
    a = np.random.default_rng(1).normal(size=(50, 3))
    assert g.chamfer_distance(a, a) == 0.0
    assert g.chamfer_distance(a, a + [0.1, 0, 0]) > 0.05


def test_transforms_round_trip():
    T = g.pose_to_matrix([0.1, -0.2, 0.3], [0.3, -0.2, 1.1])
    p = np.random.default_rng(2).normal(size=(10, 3))
    back = g.transform_points(g.invert_transform(T), g.transform_points(T, p))
    assert np.allclose(back, p)
    assert np.allclose(g.matrix_to_rpy(T[:3, :3]), [0.3, -0.2, 1.1])


def test_align_cyclic_recovers_shift_and_direction():
    t = np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ref = np.stack([np.cos(t), 0.5 * np.sin(t), 0 * t], axis=1)
    scrambled = np.roll(ref[::-1], 5, axis=0)
    assert np.allclose(g.align_cyclic(scrambled, ref), ref)


def test_resample_and_length_and_polyline_distance():
    sq = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float)
    assert g.closed_polyline_length(sq) == pytest.approx(4.0)
    r = g.resample_closed(sq, 8)
    assert np.allclose(np.linalg.norm(np.roll(r, -1, 0) - r, axis=1), 0.5)
    d = g.points_to_polyline_distance(np.array([[0.5, 0.5, 0], [2, 0, 0], [0.5, -0.1, 0]]), sq)
    assert np.allclose(d, [0.5, 1.0, 0.1])


def test_enclosure_signs_distances_and_points_the_way_out():
    t = np.linspace(0, 2 * np.pi, 64, endpoint=False)
    rim = np.stack([0.1 * np.cos(t), 0.1 * np.sin(t), np.full(64, 0.5)], 1)
    pts = np.array([[0.05, 0.0, 0.7], [0.0, 0.12, 0.7], [0.0, 0.0, 0.7]])
    frame = g.make_transform(None, [0, 0, 0.6])
    d, out = g.enclosure(rim, pts, frame)
    assert d == pytest.approx([0.05, -0.02, 0.1], abs=2e-3)  # inside > 0, outside < 0, heights ignored
    assert out[0] == pytest.approx([1, 0, 0], abs=0.05) and out[1] == pytest.approx([0, 1, 0], abs=0.05)
    # seen along a tilted axis: the frame's z, not the world's
    R = g.rpy_to_matrix([0.0, np.pi / 2, 0.0])  # F's z along world x
    d2, out2 = g.enclosure(rim, pts, g.make_transform(R, [0, 0, 0.6]))
    assert np.all(d2 < 0) and np.allclose(out2 @ R[:, 2], 0.0)  # the rim is a line in that view; pushes stay in F's plane
    for bad in (rim[:2], np.full_like(rim, np.nan)):
        with pytest.raises(ValueError):
            g.enclosure(bad, pts, frame)


def test_nearest_on_polyline_is_the_plain_formula_bit_for_bit():
    # Computed coordinate by coordinate for speed; every SOI error and inlier fraction published
    # so far came from the plain (n, m, d) formula, so the numbers must be exactly its numbers.
    rng = np.random.default_rng(7)
    for d in (2, 3):
        for closed in (True, False):
            q = rng.normal(size=(200, d)) * 0.3
            line = rng.normal(size=(17, d)) * 0.2
            a = line
            b = np.roll(a, -1, axis=0) if closed else a[1:]
            a = a if closed else a[:-1]
            ab = b - a
            denom = np.einsum("ij,ij->i", ab, ab)
            t = np.clip(np.einsum("nmj,mj->nm", q[:, None, :] - a[None], ab) / np.where(denom > 0, denom, 1.0), 0.0, 1.0)
            proj = a[None] + t[..., None] * ab[None]
            dist = np.linalg.norm(q[:, None, :] - proj, axis=2)
            j = dist.argmin(axis=1)
            near, got = g.nearest_on_polyline(q, line, closed)
            assert np.array_equal(got, dist[np.arange(len(q)), j]) and np.array_equal(near, proj[np.arange(len(q)), j])
