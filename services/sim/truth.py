"""Ground truth of the simulated world, for tests and benchmarks only (never for perception or control):
the true rim, the object's pose, and whether the fabric has ever passed through the object.

"Passed through" is latched: once any point of the fabric's mid-surface (its vertices and points
inside its triangles) lies deeper than `PENETRATION_TOL_M` inside one of the object's convex parts,
it stays True.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from bagit.common.rig import ArmName
from bagit.services.sim.objects import ConvexPart

PENETRATION_TOL_M = 0.008  # deeper than this inside the object: the fabric went through it (contact keeps it out)


@dataclass
class GroundTruth:
    """What really happened. rim: (N_AROUND, 3) the rim vertices in order; object_pose: (4, 4) world <- object."""

    time: float
    rim: np.ndarray
    rim_centroid: np.ndarray
    rim_perimeter: float
    object_pose: np.ndarray
    object_vertices: np.ndarray  # V (n_v, 3), the bottom outline
    passed_through: bool
    max_penetration_m: float
    clearance_m: float  # now: the fabric mid-surface's gap to the object (a lower bound; inf when far, < 0 inside)
    mount_poses: dict[ArmName, np.ndarray] = field(default_factory=dict)  # 'left'/'right' -> (4, 4) world <- mount


def _barycentric_grid(level: int) -> np.ndarray:
    """(k, 3) barycentric coordinates of a triangle's points on a grid of `level` steps per edge."""
    ij = [(i, j) for i in range(level + 1) for j in range(level + 1 - i)]
    return np.array([[i, j, level - i - j] for i, j in ij], dtype=float) / level


# The object can poke through a fabric triangle between its corners, so the check samples the whole
# fabric surface: 45 points per triangle, under 1.2 cm apart on the bag's 3 x 7 cm triangles.
_BARY = _barycentric_grid(8)


class PenetrationMonitor:
    """Tracks the deepest point of the fabric's mid-surface inside the object since the start.

    The fabric is sampled on a grid over each triangle (corners included); only triangles near a
    part are tested, so it is cheap enough to run every physics step.
    """

    def __init__(self, parts: list[ConvexPart], elements: np.ndarray, tol: float = PENETRATION_TOL_M):
        self.parts = parts
        self.tol = tol
        self._elements = np.asarray(elements, dtype=int)
        self._centres = [p.points.mean(axis=0) for p in parts]
        self._radii = [float(np.linalg.norm(p.points - c, axis=1).max()) for p, c in zip(parts, self._centres, strict=False)]
        self.max_depth = 0.0
        self.passed = False
        self.last_depth: float | None = None  # `depth` at the last `update`: the world's truth now, as long as nothing moved since

    def depth(self, verts: np.ndarray) -> float:
        """Deepest fabric point inside any part (m), for the fabric's vertices `verts (n, 3)`; -inf if none is near."""
        tri = verts[self._elements]  # (m, 3, 3)
        centre = tri.mean(axis=1)
        reach = np.linalg.norm(tri - centre[:, None], axis=2).max(axis=1)  # (m,)
        deepest = -np.inf
        for part, c, r in zip(self.parts, self._centres, self._radii, strict=False):
            near = np.linalg.norm(centre - c, axis=1) <= r + reach
            if not near.any():
                continue
            pts = np.einsum("kj,mjd->mkd", _BARY, tri[near]).reshape(-1, 3)
            deepest = max(deepest, float(part.depth(pts).max()))
        return deepest

    def update(self, verts: np.ndarray) -> None:
        d = self.last_depth = self.depth(verts)
        if d > self.max_depth:
            self.max_depth = d
        if d > self.tol:
            self.passed = True
