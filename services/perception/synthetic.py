"""Synthetic rim clouds with a known true rim, for tests and benchmarks.

A real depth camera sees the rim as a band a few millimetres wide, with depth noise, outliers
through the scene, density that varies with distance and angle, and stretches hidden behind the
grippers. Each of those is a knob here. Everything is seeded, so a cloud is reproducible.

    cloud, rim = make_rim_cloud("lens", rpy=(0.3, 0.0, 0.5), outlier_fraction=0.3, occlusion=0.15)
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Literal, TypedDict, Unpack

import numpy as np

from bagit.common.geometry import closed_polyline_length, rpy_to_matrix

RimKind = Literal["ellipse", "lens", "wavy", "sagging"]
RIM_KINDS: tuple[RimKind, ...] = ("ellipse", "lens", "wavy", "sagging")


def true_rim(
    kind: RimKind = "ellipse",
    perimeter: float = 0.68,
    center: tuple[float, float, float] = (0.0, 0.0, 0.4),
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    aspect: float = 0.7,
    m: int = 2000,
) -> np.ndarray:
    """A dense closed rim polyline `(m, 3)` of the given kind, scaled to `perimeter`, in the world frame.

    Counter-clockwise about its own +z before the rotation `rpy` (roll, pitch, yaw) tilts it;
    the handles sit at its local +-x ends. Kinds: "ellipse"; "lens", pinched to corners at the
    handles; "wavy", three waves up and down around the rim; "sagging", drooping between the
    handles as a bag held by two grippers does.
    """
    t = np.linspace(0.0, 2 * np.pi, m, endpoint=False)
    x, y, z = np.cos(t), aspect * np.sin(t), np.zeros(m)
    if kind == "lens":  # pinched at the two handles, like the intersection of two circular arcs
        y = aspect * np.sign(np.sin(t)) * np.abs(np.sin(t)) ** 0.6 * (1 - 0.25 * np.cos(t) ** 2)
    elif kind == "wavy":
        z = 0.12 * np.sin(3 * t)
    elif kind == "sagging":  # the rim droops between the handles at x = +-1
        z = -0.35 * np.sin(t) ** 2
    elif kind != "ellipse":
        raise ValueError(f"unknown rim kind {kind!r}: use one of {RIM_KINDS}")
    pts = np.stack([x, y, z], axis=1)
    pts *= perimeter / closed_polyline_length(pts)
    return pts @ rpy_to_matrix(rpy).T + np.asarray(center)


class RimCloudOptions(TypedDict, total=False):
    """`rim_cloud`'s options, for the functions that pass them on."""

    n_points: int
    band_m: float
    noise_m: float
    outlier_fraction: float
    density_ratio: float
    occlusion: float
    occlusion_at: float | Sequence[float]
    seed: int
    margin_m: float


def rim_cloud(
    rim: np.ndarray,
    n_points: int = 12_000,
    band_m: float = 0.006,
    noise_m: float = 0.002,
    outlier_fraction: float = 0.2,
    density_ratio: float = 5.0,
    occlusion: float = 0.15,
    occlusion_at: float | Sequence[float] = 0.3,
    seed: int = 0,
    margin_m: float = 0.15,
) -> tuple[np.ndarray, np.ndarray]:
    """A noisy cloud `(n_points, 3)` of the rim band and a mask `(len(rim),)` of the rim's visible points.

    band_m: the band's width across the rim (in the horizontal); noise_m: depth noise (standard
    deviation along z; half that across); outlier_fraction: share of points spread uniformly
    through the rim's bounding box grown by `margin_m`; density_ratio: how much denser the
    densest part of the rim is than the sparsest; occlusion: fraction of the rim's length hidden
    around each arc fraction in `occlusion_at` (one gripper, or one per entry).
    """
    rng = np.random.default_rng(seed)
    m = len(rim)
    s = np.arange(m) / m
    visible = np.ones(m, dtype=bool)
    for at in np.atleast_1d(np.asarray(occlusion_at, dtype=float)):
        visible &= np.abs(((s - at + 0.5) % 1.0) - 0.5) > occlusion / 2
    weight = 1.0 + (density_ratio - 1.0) * 0.5 * (1 + np.cos(2 * np.pi * s))
    weight = np.where(visible, weight, 0.0)
    n_out = int(round(outlier_fraction * n_points))
    n_rim = n_points - n_out
    idx = rng.choice(m, size=n_rim, p=weight / weight.sum())
    tangent = np.roll(rim, -1, axis=0) - np.roll(rim, 1, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    side = np.cross(tangent, [0.0, 0.0, 1.0])
    side /= np.maximum(np.linalg.norm(side, axis=1, keepdims=True), 1e-9)
    band = rim[idx] + side[idx] * rng.uniform(-band_m / 2, band_m / 2, (n_rim, 1))
    band += rng.normal(0.0, noise_m, (n_rim, 3)) * [0.5, 0.5, 1.0]  # depth noise mostly along the view
    lo, hi = rim.min(axis=0) - margin_m, rim.max(axis=0) + margin_m
    outliers = rng.uniform(lo, hi, (n_out, 3))
    cloud = np.vstack([band, outliers])
    return cloud[rng.permutation(len(cloud))], visible


def make_rim_cloud(
    kind: RimKind = "ellipse",
    *,
    perimeter: float = 0.68,
    center: tuple[float, float, float] = (0.0, 0.0, 0.4),
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0),
    aspect: float = 0.7,
    **cloud_options: Unpack[RimCloudOptions],
) -> tuple[np.ndarray, np.ndarray]:
    """A rim of `kind` and a noisy cloud of it: (cloud `(n, 3)`, true rim polyline `(m, 3)`).

    `cloud_options` go to `rim_cloud` (n_points, band_m, noise_m, outlier_fraction, density_ratio,
    occlusion, occlusion_at, seed, margin_m).
    """
    rim = true_rim(kind, perimeter=perimeter, center=center, rpy=rpy, aspect=aspect)
    cloud, _ = rim_cloud(rim, **cloud_options)
    return cloud, rim


def sample_cloud() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The bundled sample (common/data/sample_rim.ply): points `(12000, 3)`, colours `(12000, 3)`
    in [0, 1] (the red rim band, outliers in scene colours) and the true rim `(m, 3)`.

    A tilted, pinched rim seen with 2 mm noise, 20 % outliers, 5x uneven density and 8 % hidden
    behind the gripper at the left handle (world -y, where the rig holds it).
    """
    rim = true_rim("lens", perimeter=0.68, center=(0.02, -0.01, 0.42), rpy=(0.12, -0.05, np.pi / 2 + 0.1), aspect=0.65)
    n_points, outlier_fraction = 12_000, 0.2
    cloud, _ = rim_cloud(rim, n_points=n_points, outlier_fraction=0.0, occlusion=0.08, occlusion_at=0.5, seed=2024)
    rng = np.random.default_rng(2025)
    n_out = int(outlier_fraction * n_points)
    lo, hi = rim.min(axis=0) - 0.15, rim.max(axis=0) + 0.15
    band = cloud[: n_points - n_out]
    outliers = rng.uniform(lo, hi, (n_out, 3))
    colors = np.vstack([
        np.clip(rng.normal([0.8, 0.08, 0.1], 0.04, (len(band), 3)), 0.0, 1.0),  # the red edge
        rng.uniform(0.2, 0.8, (n_out, 1)) * np.ones((1, 3)) + rng.normal(0.0, 0.05, (n_out, 3)),  # grey-ish scene
    ])
    order = rng.permutation(n_points)
    return np.vstack([band, outliers])[order], np.clip(colors, 0.0, 1.0)[order], rim


def write_sample_cloud(path: str | Path) -> Path:
    """Write `sample_cloud()` as a PLY file (open3d) and return its path; regenerates the bundled sample."""
    import open3d as o3d

    points, colors, _ = sample_cloud()
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    pc.colors = o3d.utility.Vector3dVector(colors)
    p = Path(path)
    if not o3d.io.write_point_cloud(p, pc, write_ascii=False):
        raise OSError(f"could not write {p}")
    return p


if __name__ == "__main__":  # python -m bagit.services.perception.synthetic [PATH]
    import sys

    default = Path(__file__).resolve().parents[2] / "common" / "data" / "sample_rim.ply"
    print(write_sample_cloud(sys.argv[1] if len(sys.argv) > 1 else default))
