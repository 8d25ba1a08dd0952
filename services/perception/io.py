"""Reading point-cloud files: `.ply` and `.pcd` with open3d, `.npy` with numpy (no pickles)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import open3d as o3d

from bagit.common.errors import BadCloud

SUFFIXES = (".ply", ".pcd", ".npy")


def load_cloud(path: str | Path) -> np.ndarray:
    """The points `(n, 3)` float64 of a cloud file (world frame, metres, as written).

    BadCloud when the file is missing, unreadable, of another format, empty, or not `(n, 3)`
    numbers. Values are not checked here (NaN, size): that is the SOI extractor's job.
    """
    p = Path(path)
    if not p.exists():
        raise BadCloud(f"no cloud file at {p}")
    if not p.is_file():
        raise BadCloud(f"{p} is not a file")
    suffix = p.suffix.lower()
    if suffix not in SUFFIXES:
        raise BadCloud(f"unsupported cloud format {suffix or '(none)'!r} for {p.name}: use .ply, .pcd or .npy")
    try:
        with open(p, "rb") as f:  # open3d only warns on an unreadable file; ask the OS for the reason
            f.read(1)
    except OSError as e:
        raise BadCloud(f"cannot read {p}: {e.strerror or e}") from None
    if suffix == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            reason = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise BadCloud(f"cannot read {p} as a numpy array: {reason}") from None
        if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiu":
            raise BadCloud(f"{p}: expected a numeric array, got dtype {getattr(a, 'dtype', type(a))}")
    else:
        pc = o3d.io.read_point_cloud(str(p), format="auto", print_progress=False)
        a = np.asarray(pc.points)
        if a.size == 0:
            raise BadCloud(f"{p} holds no points (or is not a valid {suffix[1:].upper()} file)")
    if a.ndim != 2 or a.shape[1] != 3:
        raise BadCloud(f"{p}: expected points of shape (n, 3), got {a.shape}")
    if len(a) == 0:
        raise BadCloud(f"{p} holds no points")
    return np.asarray(a, dtype=np.float64)
