"""Reading point-cloud files: `.ply` and `.pcd` with open3d, `.npy` with numpy (no pickles)."""

from __future__ import annotations

from pathlib import Path
from tokenize import TokenError

import numpy as np
import open3d as o3d

from bagit.common.errors import BadCloud

SUFFIXES = (".ply", ".pcd", ".npy")

# A cloud may hold at most this many points: ten whole 1280x720 depth frames (the D455's largest),
# 240 MB as float64. A header that declares more, or more than its file's bytes can hold, is refused
# before anything is allocated (a 128-byte file could otherwise ask for terabytes).
MAX_CLOUD_POINTS = 10_000_000
HEADER_BYTES = 1 << 16  # how much of a PLY or PCD file is read to find its header
MIN_ASCII_VALUE_BYTES = 2  # a value in an ASCII cloud takes at least a digit and a separator
LZF_MAX_RATIO = 100  # PCD's binary_compressed (LZF) shrinks data at most ~90-fold
PLY_TYPE_BYTES = {
    "char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
    "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8,
}


def _too_many(p: Path, declared: int, need: int, have: int) -> None:
    """BadCloud when a header declares more than MAX_CLOUD_POINTS points, or more bytes than the file holds."""
    if declared > MAX_CLOUD_POINTS:
        raise BadCloud(f"{p}: its header declares {declared} points, over the {MAX_CLOUD_POINTS} a cloud may have")
    if need > have:
        raise BadCloud(f"{p}: its header declares {declared} points, which need at least {need} bytes, "
                       f"but the file has {have} after the header (truncated, or a corrupt header)")


def _check_npy_header(p: Path, size: int) -> None:
    """The .npy header's shape and dtype against MAX_CLOUD_POINTS and the file's size, before np.load."""
    try:
        with open(p, "rb") as f:
            version = np.lib.format.read_magic(f)
            read = np.lib.format.read_array_header_1_0 if version == (1, 0) else np.lib.format.read_array_header_2_0
            shape, _, dtype = read(f)
            offset = f.tell()
    except (ValueError, OSError, EOFError, SyntaxError, TypeError, TokenError, RecursionError, MemoryError) as e:
        # numpy parses the header's dict with the tokenizer and ast.literal_eval: any of these on junk
        reason = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise BadCloud(f"cannot read {p} as a numpy array: {reason}") from None
    if dtype.hasobject:
        return  # np.load refuses it (no pickles) with its own reason
    if dtype.kind not in "fiu":
        raise BadCloud(f"{p}: expected a numeric array, got dtype {dtype}")
    if len(shape) != 2 or shape[1] != 3:
        raise BadCloud(f"{p}: expected points of shape (n, 3), got {shape}")
    _too_many(p, int(shape[0]), int(np.prod(shape, dtype=object)) * dtype.itemsize, size - offset)


def _check_ply_header(p: Path, head: bytes, size: int) -> None:
    """The element counts of a PLY header against MAX_CLOUD_POINTS and the file's size (open3d would
    allocate them all first). A file without a PLY header is left to open3d, which refuses it."""
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        return
    nl = head.find(b"\n", end)
    body = size - (nl + 1 if nl >= 0 else len(head))
    fmt = ""
    elements: list[list] = []  # [name, count, bytes per item (binary), values per item]
    for line in head[:end].decode("ascii", "replace").splitlines():
        tok = line.split()
        if len(tok) >= 2 and tok[0] == "format":
            fmt = tok[1]
        elif len(tok) >= 3 and tok[0] == "element":
            try:
                count = int(tok[2])
            except ValueError:
                raise BadCloud(f"{p}: PLY element {tok[1]!r} has a count that is not a whole number: {tok[2]!r}") from None
            if count < 0:
                raise BadCloud(f"{p}: PLY element {tok[1]!r} has a negative count {count}")
            elements.append([tok[1], count, 0, 0])
        elif tok and tok[0] == "property" and elements:
            kind = tok[2] if len(tok) > 2 and tok[1] == "list" else (tok[1] if len(tok) > 1 else "")
            if kind not in PLY_TYPE_BYTES:  # a list takes at least its count's bytes
                raise BadCloud(f"{p}: PLY property of unknown type: {line.strip()!r}")
            elements[-1][2] += PLY_TYPE_BYTES[kind]
            elements[-1][3] += 1
    points = sum(e[1] for e in elements if e[0] == "vertex")
    if fmt == "ascii":
        need = sum(count * n for _, count, _, n in elements) * MIN_ASCII_VALUE_BYTES - 1
    else:
        need = sum(count * b for _, count, b, _ in elements)
    _too_many(p, points, need, body)


def _check_pcd_header(p: Path, head: bytes, size: int) -> None:
    """POINTS (and WIDTH x HEIGHT) of a PCD header against MAX_CLOUD_POINTS and the file's size.
    A file without a DATA line in its first HEADER_BYTES is left to open3d, which refuses it."""
    fields: dict[str, list[str]] = {}
    offset = 0
    for raw in head.split(b"\n"):
        offset += len(raw) + 1
        tok = raw.decode("ascii", "replace").split()
        if not tok or tok[0].startswith("#"):
            continue
        fields[tok[0].upper()] = tok[1:]
        if tok[0].upper() == "DATA":
            break
    else:
        return

    def ints(key: str, default: list[int]) -> list[int]:
        try:
            return [int(t) for t in fields[key]] if key in fields else default
        except ValueError:
            raise BadCloud(f"{p}: PCD header's {key} is not whole numbers: {' '.join(fields[key])!r}") from None

    width, height, points = ((ints(k, [0]) or [0])[0] for k in ("WIDTH", "HEIGHT", "POINTS"))
    if min(width, height, points) < 0:
        raise BadCloud(f"{p}: PCD header has a negative WIDTH, HEIGHT or POINTS")
    declared = max(points, width * height)
    sizes = ints("SIZE", [])
    counts = ints("COUNT", [1] * len(sizes))
    point_bytes = sum(s * c for s, c in zip(sizes, counts, strict=False))
    mode = (fields.get("DATA") or ["ascii"])[0].lower()
    if mode == "binary":
        need = declared * point_bytes
    elif mode == "binary_compressed":
        need = declared * point_bytes // LZF_MAX_RATIO
    else:
        need = declared * max(len(sizes), 1) * MIN_ASCII_VALUE_BYTES - 1
    _too_many(p, declared, need, size - min(offset, size))


def load_cloud(path: str | Path) -> np.ndarray:
    """The points `(n, 3)` float64 of a cloud file (world frame, metres, as written).

    BadCloud when the file is missing, unreadable, of another format, empty, or not `(n, 3)`
    numbers, and before anything is allocated when its header declares more than MAX_CLOUD_POINTS
    points or more than the file's bytes hold. Values are not checked here (NaN, size): that is the
    SOI extractor's job.
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
            head = f.read(HEADER_BYTES)
        size = p.stat().st_size
    except OSError as e:
        raise BadCloud(f"cannot read {p}: {e.strerror or e}") from None
    if suffix == ".npy":
        _check_npy_header(p, size)
    elif suffix == ".ply":
        _check_ply_header(p, head, size)
    else:
        _check_pcd_header(p, head, size)
    if suffix == ".npy":
        try:
            a = np.load(p, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            reason = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise BadCloud(f"cannot read {p} as a numpy array: {reason}") from None
        if not isinstance(a, np.ndarray) or a.dtype.kind not in "fiu":
            raise BadCloud(f"{p}: expected a numeric array, got dtype {getattr(a, 'dtype', type(a))}")
    else:
        pc = o3d.io.read_point_cloud(p, format="auto", print_progress=False)
        a = np.asarray(pc.points)
        if a.size == 0:
            raise BadCloud(f"{p} holds no points (or is not a valid {suffix[1:].upper()} file)")
    if a.ndim != 2 or a.shape[1] != 3:
        raise BadCloud(f"{p}: expected points of shape (n, 3), got {a.shape}")
    if len(a) == 0:
        raise BadCloud(f"{p} holds no points")
    return np.asarray(a, dtype=np.float64)
