"""BagIt messages as MCAP JSON: one JSON Schema per message model, and the message <-> JSON record.

Foxglove opens JSON channels (message encoding `json`, schema encoding `jsonschema`) and shows
binary data given as base64 strings with `"contentEncoding": "base64"`. So a record is the
model's non-array fields as JSON (exactly what the wire header carries) and every array field as

    {"dtype": "<f8", "shape": [32, 3], "data": "<base64 of the raw little-endian bytes>"}

i.e. the array payload as it travels (same dtype, same bytes, no float -> text round trip), only
base64-wrapped so the message stays JSON. The schema is the pydantic model's own JSON Schema with
each array field given as that `NdArray` object (inline, titled NdArray). Decoding checks dtype, shape and length exactly as
`bagit.common.wire` does, so a hostile recording raises BadRecording and never over-allocates.
"""

from __future__ import annotations

import base64
import binascii
import json
from functools import cache
from typing import Any

import numpy as np
from pydantic import ValidationError
from pydantic.json_schema import GenerateJsonSchema, JsonSchemaValue
from pydantic_core import core_schema

from bagit.common.errors import BadRecording
from bagit.common.messages import MESSAGE_TYPES, SCHEMA_VERSION, Message
from bagit.common.wire import ALLOWED_DTYPES

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
SCHEMA_PREFIX = "bagit."

NDARRAY_SCHEMA: dict[str, Any] = {
    "type": "object",
    "title": "NdArray",
    "description": "an array as it travels on the wire: raw little-endian bytes (base64) with dtype and shape",
    "properties": {
        "dtype": {"type": "string", "enum": sorted(ALLOWED_DTYPES)},
        "shape": {"type": "array", "items": {"type": "integer", "minimum": 0}, "maxItems": 4},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
    "required": ["dtype", "shape", "data"],
    "additionalProperties": False,
}


class _WithArrays(GenerateJsonSchema):
    """pydantic's generator, taught that a numpy array field is an NdArray."""

    def is_instance_schema(self, schema: core_schema.IsInstanceSchema) -> JsonSchemaValue:
        if schema["cls"] is np.ndarray:
            return dict(NDARRAY_SCHEMA)
        return super().is_instance_schema(schema)


def schema_name(cls: type[Message]) -> str:
    """The MCAP schema name of a message model, e.g. `bagit.SoiState`."""
    return f"{SCHEMA_PREFIX}{cls.__name__}"


@cache
def json_schema_bytes(cls: type[Message]) -> bytes:
    """The JSON Schema (draft 2020-12) of a message model's MCAP record, as UTF-8 bytes."""
    s = cls.model_json_schema(schema_generator=_WithArrays, mode="validation")
    s["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    s["$comment"] = f"BagIt message kind {cls.KIND!r}, schema version {SCHEMA_VERSION}"
    return json.dumps(s, sort_keys=True).encode()


@cache
def array_fields(cls: type[Message]) -> frozenset[str]:
    """Names of a model's numpy-array fields (those its schema gives as NdArray)."""
    props = json.loads(json_schema_bytes(cls))["properties"]
    return frozenset(name for name, p in props.items() if '"title": "NdArray"' in json.dumps(p))


def class_for_schema(name: str) -> type[Message]:
    """The message model a schema name stands for; BadRecording if it is not a BagIt one."""
    for cls in MESSAGE_TYPES.values():
        if schema_name(cls) == name:
            return cls
    raise BadRecording(f"schema {name!r} is not a BagIt message schema")


def to_json(msg: Message) -> bytes:
    """The MCAP record of a message: non-array fields as JSON, arrays as base64 NdArray objects."""
    names = array_fields(type(msg))
    record: dict[str, Any] = msg.model_dump(mode="json", exclude=set(names))
    for name in names:
        a = getattr(msg, name)
        if a is None:
            record[name] = None
            continue
        a = np.ascontiguousarray(a)
        a = a.astype(a.dtype.newbyteorder("<"), copy=False)
        record[name] = {"dtype": a.dtype.str, "shape": list(a.shape), "data": base64.b64encode(a.data).decode("ascii")}
    return json.dumps(record, separators=(",", ":")).encode()


def from_json(cls: type[Message], data: bytes | memoryview) -> Message:
    """Parse an MCAP record back into its message; BadRecording on anything malformed."""
    try:
        record = json.loads(bytes(data))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise BadRecording(f"{cls.KIND}: record is not JSON: {e}") from None
    if not isinstance(record, dict):
        raise BadRecording(f"{cls.KIND}: record is not a JSON object")
    for name in array_fields(cls):
        spec = record.get(name)
        if spec is not None:
            record[name] = _array(cls.KIND, name, spec)
    try:
        return cls.model_validate(record)
    except ValidationError as e:
        first = e.errors()[0]
        raise BadRecording(f"{cls.KIND}: {'.'.join(map(str, first['loc']))}: {first['msg']}") from None


def _array(kind: str, name: str, spec: object) -> np.ndarray:
    where = f"{kind}.{name}"
    if not isinstance(spec, dict):
        raise BadRecording(f"{where}: not an NdArray object")
    dtype, shape, text = spec.get("dtype"), spec.get("shape"), spec.get("data")
    if dtype not in ALLOWED_DTYPES:
        raise BadRecording(f"{where}: dtype {dtype!r} not allowed")
    if not (isinstance(shape, list) and len(shape) <= 4 and all(isinstance(s, int) and 0 <= s < 2**31 for s in shape)):
        raise BadRecording(f"{where}: bad shape {shape!r}")
    if not isinstance(text, str):
        raise BadRecording(f"{where}: data is not a base64 string")
    dt = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dt.itemsize
    if len(text) > 4 * (nbytes // 3 + 1) + 4:
        raise BadRecording(f"{where}: {len(text)} base64 characters is more than shape {shape} of {dtype} needs")
    try:
        raw = base64.b64decode(text, validate=True)
    except (binascii.Error, ValueError):
        raise BadRecording(f"{where}: data is not valid base64") from None
    if len(raw) != nbytes:
        raise BadRecording(f"{where}: {len(raw)} bytes do not match shape {shape} of {dtype}")
    return np.frombuffer(raw, dtype=dt).reshape(shape).copy()
