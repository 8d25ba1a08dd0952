"""The fabric bag's rest mesh: an open-top sack whose rim is an ellipse of the scenario's perimeter.

The mesh has `N_AROUND` vertices per ring and `N_RINGS` rings from the rim down, closed by a
bottom vertex. Ring 0 is the rim (vertex ids 0..N_AROUND-1, counter-clockwise seen from above the
rim plane, id 0 on the +e_x side). Each mount clamps the rim vertices within `HANDLE_HALF_ANGLE`
(ellipse parameter) of its side: the left mount the -e_y side, the right mount the +e_y side, e_y
being world y laid into the rim plane. The mounts are rigid, so the arms shape the rim only
through those two stretches.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bagit.common.geometry import ramanujan_perimeter
from bagit.common.mounts import mount_rotation
from bagit.common.rig import ArmName

N_AROUND = 24
N_RINGS = 5
HANDLE_HALF_ANGLE = 0.8  # rad of ellipse parameter: 7 of the 24 rim vertices each, about a quarter of the rim
RIM_ASPECT = 1.3  # rest rim: semi-axis along the handles / semi-axis across
BOTTOM_TAPER = 0.15  # the lowest ring is this much narrower than the rim


@dataclass
class BagLayout:
    """Where the bag starts and which of its vertices are what (all world frame)."""

    vertices: np.ndarray  # (n, 3) at rest
    elements: np.ndarray  # (m, 3) triangles, counter-clockwise seen from outside
    rim: np.ndarray  # (N_AROUND,) vertex ids of the rim, in order
    handles: dict[ArmName, np.ndarray]  # 'left'/'right' -> rim vertex ids clamped by that mount
    mount_home: dict[ArmName, np.ndarray]  # 'left'/'right' -> (4, 4) world <- mount
    frame: np.ndarray  # (4, 4) world <- rim frame: x across the bag, y along the handles, z the rim normal (up)


def bag_layout(perimeter: float, depth: float, frame: np.ndarray, aspect: float = RIM_ASPECT) -> BagLayout:
    """The rest mesh of a bag whose rim (perimeter `perimeter`, m) lies in the plane of `frame (4, 4)`
    as an ellipse with its long axis along the handles, hanging `depth` (m) below it."""
    if not (np.isfinite(perimeter) and perimeter > 0 and np.isfinite(depth) and depth > 0):
        raise ValueError(f"bag needs a positive perimeter and depth, got {perimeter}, {depth}")
    b = perimeter / ramanujan_perimeter(aspect, 1.0)  # semi-axis across (rim-frame x)
    a = aspect * b  # along the handles (rim-frame y)
    t = 2 * np.pi * np.arange(N_AROUND) / N_AROUND
    local = []
    for r in range(N_RINGS):
        f = r / (N_RINGS - 1)
        shrink = 1.0 - BOTTOM_TAPER * f**2
        local.append(np.stack([b * shrink * np.cos(t), a * shrink * np.sin(t), np.full(N_AROUND, -depth * 0.9 * f)], 1))
    local.append(np.array([[0.0, 0.0, -depth]]))
    verts = np.vstack(local) @ frame[:3, :3].T + frame[:3, 3]
    tris = []
    for r in range(N_RINGS - 1):
        for k in range(N_AROUND):
            i, j = r * N_AROUND + k, r * N_AROUND + (k + 1) % N_AROUND
            p, q = i + N_AROUND, j + N_AROUND
            tris += [[i, p, j], [j, p, q]]
    c = len(verts) - 1
    last = (N_RINGS - 1) * N_AROUND
    tris += [[last + k, c, last + (k + 1) % N_AROUND] for k in range(N_AROUND)]
    rim = np.arange(N_AROUND)
    handles: dict[ArmName, np.ndarray] = {}
    home: dict[ArmName, np.ndarray] = {}
    sides: tuple[tuple[ArmName, float], ...] = (("left", -np.pi / 2), ("right", np.pi / 2))
    for name, side in sides:
        ids = rim[np.abs(np.angle(np.exp(1j * (t - side)))) <= HANDLE_HALF_ANGLE + 1e-9]
        handles[name] = ids
        T = np.eye(4)
        T[:3, :3] = mount_rotation(frame, name)
        T[:3, 3] = verts[ids].mean(axis=0)
        home[name] = T
    return BagLayout(verts, np.asarray(tris, dtype=int), rim, handles, home, frame.copy())
