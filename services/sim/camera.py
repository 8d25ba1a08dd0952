"""A depth-camera noise model like a D455's: noise growing with distance, holes at grazing angles
and depth edges, and a few flying pixels between foreground and background."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class DepthNoise:
    sigma_at_1m: float = 0.001  # std of depth noise at 1 m (m); grows with z^2 as for stereo
    max_range_m: float = 4.0
    edge_jump_m: float = 0.05  # a neighbour this much nearer or farther marks a depth edge
    edge_dropout: float = 0.5  # share of edge pixels that come back empty
    grazing_slope: float = 4.0  # depth change per pixel / (z / f) above this: too grazing, empty
    flying_fraction: float = 0.1  # share of the remaining edge pixels that float between the surfaces


def add_depth_noise(depth: np.ndarray, noise: DepthNoise, rng: np.random.Generator, f_px: float = 390.7) -> np.ndarray:
    """Noisy metric depth `(H, W)` from true metric depth `(H, W)` (0 = no return)."""
    z = depth.copy()
    z[(z <= 0) | (z > noise.max_range_m)] = 0.0
    gy, gx = np.gradient(z)
    dz = np.maximum(np.abs(gx), np.abs(gy))
    valid = z > 0
    edge = valid & (dz > noise.edge_jump_m)
    grazing = valid & ~edge & (dz / np.maximum(z / f_px, 1e-9) > noise.grazing_slope * 10)
    out = z + rng.normal(0.0, 1.0, z.shape) * noise.sigma_at_1m * z**2
    u = rng.random(z.shape)
    out[edge & (u < noise.edge_dropout)] = 0.0
    fly = edge & (u >= noise.edge_dropout) & (u < noise.edge_dropout + noise.flying_fraction * (1 - noise.edge_dropout))
    out[fly] = z[fly] + rng.uniform(-1.0, 1.0, int(fly.sum())) * dz[fly]
    out[grazing] = 0.0
    out[~valid] = 0.0
    return out
