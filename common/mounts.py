"""How the two bag mounts hold the rim: the rim's frame, and each mount's orientation in it.

The left mount clamps the rim's -e_y side and the right mount its +e_y side, e_y being world y laid
into the rim's plane (the arms stand along world y, left at -y). Shared by the simulator, which
starts the mounts there (`services/sim/bag.py`), and the planner, which checks that the arms can hold
the rim where the goal puts it (`services/planner/reach.py`).
"""

from __future__ import annotations

import numpy as np


def rim_frame(center: np.ndarray, normal: np.ndarray | None = None) -> np.ndarray:
    """(4, 4) world <- rim frame: origin `center (3,)`, z `normal` (turned upward), y world y laid into the plane."""
    n = np.array([0.0, 0.0, 1.0]) if normal is None else np.asarray(normal, dtype=float)
    n = n / np.linalg.norm(n)
    if n[2] < 0:
        n = -n
    ey = np.array([0.0, 1.0, 0.0]) - n[1] * n
    if np.linalg.norm(ey) < 1e-6:  # rim plane across world y: any in-plane direction will do
        ey = np.cross(n, [1.0, 0.0, 0.0])
    ey /= np.linalg.norm(ey)
    ex = np.cross(ey, n)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([ex, ey, n])
    T[:3, 3] = center
    return T


def mount_rotation(frame: np.ndarray, side: str) -> np.ndarray:
    """(3, 3) world <- mount of the mount on `side`: z points from the handle into the bag (the tool axis,
    so the flange sits outside the rim), y points down the rim normal, x completes the frame."""
    ex, ey, n = frame[:3, 0], frame[:3, 1], frame[:3, 2]
    s = -1.0 if side == "left" else 1.0
    z = -s * ey  # left handle is on -e_y: its tool points +e_y, into the bag
    x = -s * ex
    y = np.cross(z, x)  # == -n for both sides
    assert np.allclose(y, -n)
    return np.column_stack([x, y, z])
