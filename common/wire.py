"""The wire format of messages: a JSON header plus raw little-endian array bytes. No pickle.

    b"BGT1" | uint32 LE header length | header (UTF-8 JSON) | array bytes ...

The header holds the message kind, its schema version, its non-array fields, and for each array
field its dtype, shape, offset and length in the byte section. Decoding checks every one of these
against the payload, so a malformed or hostile payload raises `BadMessage` and never allocates
more than it carries.
"""

from __future__ import annotations

import json
import struct
from typing import TypeVar

import numpy as np
from pydantic import ValidationError

from bagit.common.errors import BadMessage
from bagit.common.messages import MESSAGE_TYPES, SCHEMA_VERSION, Message

MAGIC = b"BGT1"
MAX_HEADER_BYTES = 1 << 20
ALLOWED_DTYPES = {"<f8", "<f4", "|u1", "<u2", "<i4", "<i8", "<u4"}

M = TypeVar("M", bound=Message)


def encode(msg: Message) -> bytearray:
    """Serialise a message into one buffer: its arrays are copied once, straight into place. A frame is
    1.5 MB; each fresh buffer that size costs the page faults of new memory, so there is only the one."""
    arrays: dict = {}
    parts: list[np.ndarray] = []
    offset = 0
    for name in type(msg).model_fields:
        value = getattr(msg, name)
        if isinstance(value, np.ndarray):
            a = value.astype(value.dtype.newbyteorder("<"), copy=False)
            arrays[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "offset": offset, "nbytes": a.nbytes}
            parts.append(a)
            offset += a.nbytes
    fields = msg.model_dump(mode="json", exclude=set(arrays))
    header = json.dumps({"kind": msg.KIND, "v": msg.schema_version, "fields": fields, "arrays": arrays}).encode()
    start = 8 + len(header)
    out = bytearray(start + offset)
    out[:8] = MAGIC + struct.pack("<I", len(header))
    out[8:start] = header
    for a, spec in zip(parts, arrays.values(), strict=True):
        np.frombuffer(out, a.dtype, a.size, start + spec["offset"]).reshape(a.shape)[...] = a
    return out


def decode(payload: bytes | bytearray | memoryview, expected: type[M] | None = None) -> M:
    """Parse bytes back into a message; `expected` pins the type. Raises BadMessage on anything malformed."""
    buf = memoryview(payload).cast("B") if not isinstance(payload, bytes) else memoryview(payload)
    if len(buf) < 8 or bytes(buf[:4]) != MAGIC:
        raise BadMessage("not a BagIt message (bad magic)")
    (hlen,) = struct.unpack("<I", bytes(buf[4:8]))
    if hlen > MAX_HEADER_BYTES or 8 + hlen > len(buf):
        raise BadMessage(f"header length {hlen} does not fit the {len(buf)}-byte payload")
    try:
        header = json.loads(bytes(buf[8 : 8 + hlen]).decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BadMessage(f"header is not JSON: {e}") from None
    except RecursionError:  # e.g. 100,000 nested '[': json's C parser hits the interpreter's recursion limit
        raise BadMessage("header is nested too deeply to parse") from None
    if not isinstance(header, dict):
        raise BadMessage("header is not a JSON object")
    kind = header.get("kind")
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise BadMessage(f"unknown message kind {kind!r}")
    if expected is not None and cls is not expected:
        raise BadMessage(f"expected a {expected.KIND!r} message, got {kind!r}")
    if header.get("v") != SCHEMA_VERSION:
        raise BadMessage(f"{kind}: schema version {header.get('v')!r}, this build speaks {SCHEMA_VERSION}")
    fields = header.get("fields")
    arrays = header.get("arrays")
    if not isinstance(fields, dict) or not isinstance(arrays, dict):
        raise BadMessage(f"{kind}: header lacks fields or arrays")
    body = buf[8 + hlen :]
    data = dict(fields)
    for name, spec in arrays.items():
        data[name] = _array_from(body, name, spec)
    try:
        return cls.model_validate(data)  # type: ignore[return-value]
    except ValidationError as e:
        first = e.errors()[0]
        raise BadMessage(f"{kind}: {'.'.join(map(str, first['loc']))}: {first['msg']}") from None
    except RecursionError:
        raise BadMessage(f"{kind}: fields nested too deeply to validate") from None


def _array_from(body: memoryview, name: str, spec: object) -> np.ndarray:
    if not isinstance(spec, dict):
        raise BadMessage(f"array {name!r}: bad spec")
    dtype, shape, off, nbytes = spec.get("dtype"), spec.get("shape"), spec.get("offset"), spec.get("nbytes")
    if dtype not in ALLOWED_DTYPES:
        raise BadMessage(f"array {name!r}: dtype {dtype!r} not allowed")
    if not (isinstance(shape, list) and all(isinstance(s, int) and 0 <= s < 2**31 for s in shape) and len(shape) <= 4):
        raise BadMessage(f"array {name!r}: bad shape {shape!r}")
    if not (isinstance(off, int) and isinstance(nbytes, int) and off >= 0 and nbytes >= 0):
        raise BadMessage(f"array {name!r}: bad offset/length")
    dt = np.dtype(dtype)
    if int(np.prod(shape, dtype=np.int64)) * dt.itemsize != nbytes or off + nbytes > len(body):
        raise BadMessage(f"array {name!r}: {nbytes} bytes at {off} do not match shape {shape} of {dtype}")
    return np.frombuffer(body[off : off + nbytes], dtype=dt).reshape(shape).copy()
