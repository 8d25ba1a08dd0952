"""Synthetic rim clouds with a known true rim, for tests and benchmarks.

A real depth camera sees the rim as a band a few millimetres wide, with depth noise, outliers
through the scene, density that varies with distance and angle, and stretches hidden behind the
grippers. Each of those is a knob here.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from bagit.common.geometry import closed_polyline_length, rpy_to_matrix

RimKind = Literal["ellipse", "lens", "wavy", "sagging"]


def true_rim(
    kind: RimKind = "ellipse",
    perimeter: float = 0.68,
    center: tuple[float, float, float] = (0.0, 0.0, 0.4),
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    aspect: float = 0.7,
    m: int = 2000,
) -> np.ndarray:
    """A dense closed rim polyline `(m, 3)` of the given kind, scaled to `perimeter`, in the world frame."""
    t = np.linspace(0.0, 2 * np.pi, m, endpoint=False)
    x, y, z = np.cos(t), aspect * np.sin(t), np.zeros(m)
    if kind == "lens":  # pinched at the two handles: the intersection of two circular arcs
        y = aspect * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.6 * (1 - 0.25 * np.cos(t) ** 2)
    elif kind == "wavy":
        z = 0.12 * np.sin(3 * t)
    elif kind == "sagging":  # the rim droops between the handles at x = +-1
        z = -0.35 * np.sin(t) ** 2
    pts = np.stack([x, y, z], axis=1)
    pts *= perimeter / closed_polyline_length(pts)
    return pts @ rpy_to_matrix(rpy).T + np.asarray(center)


def rim_cloud(
    rim: np.ndarray,
    n_points: int = 12_000,
    band_m: float = 0.006,
    noise_m: float = 0.002,
    outlier_fraction: float = 0.2,
    density_ratio: float = 5.0,
    occlusion: float = 0.15,
    occlusion_at: float = 0.3,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray]:
    """A noisy cloud `(n_points, 3)` of the rim band and a mask `(len(rim),)` of the rim's visible points.

    `density_ratio`: how much denser the densest part of the rim is than the sparsest; `occlusion`:
    the fraction of the rim's length hidden, centred at arc fraction `occlusion_at`.
    """
    rng = np.random.default_rng(seed)
    m = len(rim)
    s = np.arange(m) / m
    visible = np.abs(((s - occlusion_at + 0.5) % 1.0) - 0.5) > occlusion / 2
    weight = 1.0 + (density_ratio - 1.0) * 0.5 * (1 + np.cos(2 * np.pi * s))
    weight = np.where(visible, weight, 0.0)
    n_out = int(round(outlier_fraction * n_points))
    n_rim = n_points - n_out
    idx = rng.choice(m, size=n_rim, p=weight / weight.sum())
    tangent = np.roll(rim, -1, axis=0) - np.roll(rim, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(tangent, up)
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
    band = rim[idx] + side[idx] * rng.uniform(-band_m / 2, band_m / 2, (n_rim, 1))
    band += rng.normal(0.0, noise_m, (n_rim, 3)) * [0.5, 0.5, 1.0]  # depth noise mostly along the view
    lo, hi = rim.min(axis=0) - 0.15, rim.max(axis=0) + 0.15
    outliers = rng.uniform(lo, hi, (n_out, 3))
    cloud = np.vstack([band, outliers])
    return cloud[rng.permutation(len(cloud))], visible
