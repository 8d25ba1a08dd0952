"""Reading point-cloud files: `.ply` and `.pcd` with open3d, `.npy` with numpy."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from bagit.common.errors import BadCloud


def load_cloud(path: str | Path) -> np.ndarray:
    """The points `(n, 3)` of a cloud file. BadCloud when missing, unreadable or of the wrong shape."""
    p = Path(path)
    if not p.is_file():
        raise BadCloud(f"no cloud file at {p}")
    suffix = p.suffix.lower()
    if suffix == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except (ValueError, OSError) as e:
            raise BadCloud(f"cannot read {p} as a numpy array: {e}") from None
    elif suffix in (".ply", ".pcd"):
        pc = o3d.io.read_point_cloud(str(p), format="auto", print_progress=False)
        a = np.asarray(pc.points)
        if a.size == 0:
            raise BadCloud(f"{p} holds no points (or is not a valid {suffix[1:].upper()} file)")
    else:
        raise BadCloud(f"unsupported cloud format {suffix!r}: use .ply, .pcd or .npy")
    if a.ndim != 2 or a.shape[1] != 3:
        raise BadCloud(f"{p}: expected points of shape (n, 3), got {a.shape}")
    return np.asarray(a, dtype=float)
