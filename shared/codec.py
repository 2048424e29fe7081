"""msgpack codec for the wire contract (shared/messages.py); nothing on the wire is ever unpickled.

A message is a msgpack map `{"kind": "<frame|detections|objects|tracks|status>", ...fields}`. A numpy array
travels as `{"dtype": "<f4", "shape": [N, 2], "data": <bytes>}` with its dtype from a small
allow-list and is decoded with `numpy.frombuffer` (little-endian, C order); a field declared as a map (a Status
message's counts) travels as a plain msgpack map. `decode` raises
`DecodeError` with the reason for anything else: garbage bytes, more lists or map entries than any message holds
(refused while msgpack reads them: MAX_LIST_LEN, MAX_MAP_LEN, MAX_ITEMS), an unknown kind, a wrong schema
version, a disallowed dtype, a shape that does not match the bytes, a field that fails validation.
"""

from __future__ import annotations

import functools
import math
import typing

import msgpack
import numpy as np
from pydantic import ValidationError

from shared.messages import MAX_ROWS, MAX_STAMPS, MAX_STATUS_ENTRIES, MESSAGE_TYPES, Message

ALLOWED_DTYPES = frozenset({"|u1", "|i1", "<u2", "<i2", "<i4", "<u4", "<i8", "<f4", "<f8", "|b1"})
MAX_MESSAGE_BYTES = 48 * 1024 * 1024
MAX_ARRAY_ITEMS = 10_000_000
# What msgpack may build of a payload before any check runs: an empty list is one byte on the wire and some 60 in
# memory, so a payload of them (or of short lists nested in lists) would cost gigabytes. Each limit is the most a
# valid message holds. The longest list: a Tracks message's cameras or frames, one per row (stamps: MAX_STAMPS).
MAX_LIST_LEN = MAX_ROWS
# the largest map: a Status message's counts, rates, bad or gauges, or a message's own fields (and its "kind")
MAX_MAP_LEN = max(MAX_STATUS_ENTRIES, *(len(cls.model_fields) + 1 for cls in MESSAGE_TYPES.values()))
# the entries of all the lists and maps of a message (every list or map but the message's own map is one, so nested
# short lists count): a Tracks message of MAX_ROWS rows holds at most 286,720, each row an entry of `cameras` holding
# up to 64 names and one of `frames` holding 4 values; the rest of any message fits in the 4096 over that (a Status
# message's maps hold 1200)
MAX_ITEMS = MAX_ROWS * (1 + 64 + 1 + 4) + 4096


class DecodeError(ValueError):
    """A message that cannot be decoded or does not validate; the text says why."""


def _pack_array(a: np.ndarray) -> dict:
    a = np.ascontiguousarray(a)
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    dt = a.dtype.str
    if dt not in ALLOWED_DTYPES:
        raise ValueError(f"dtype {a.dtype} is not allowed on the wire (allowed: {sorted(ALLOWED_DTYPES)})")
    return {"dtype": dt, "shape": list(a.shape), "data": a.tobytes()}


def _unpack_array(field: str, d: dict) -> np.ndarray:
    if set(d) != {"dtype", "shape", "data"}:
        raise DecodeError(f"field {field!r}: an array needs exactly dtype, shape, data (got {sorted(d)})")
    dt, shape, data = d["dtype"], d["shape"], d["data"]
    if type(dt) is not str or dt not in ALLOWED_DTYPES:  # a list or map is not hashable: test the type first
        raise DecodeError(f"field {field!r}: dtype {dt!r} is not allowed")
    # type() is int, not isinstance: True and False are ints to Python, not dimensions
    if not isinstance(shape, list) or not all(type(s) is int and s >= 0 for s in shape) or len(shape) > 4:
        raise DecodeError(f"field {field!r}: bad shape {shape!r}")
    if not isinstance(data, bytes):
        raise DecodeError(f"field {field!r}: data must be bytes")
    if any(s > MAX_ARRAY_ITEMS for s in shape):  # also keeps a zero-sized shape from reaching numpy's dimension limit
        raise DecodeError(f"field {field!r}: shape {shape}: items exceed the limit of {MAX_ARRAY_ITEMS} in a dimension")
    n = math.prod(shape)
    if n > MAX_ARRAY_ITEMS:
        raise DecodeError(f"field {field!r}: {n} items exceed the limit of {MAX_ARRAY_ITEMS}")
    dtype = np.dtype(dt)
    if len(data) != n * dtype.itemsize:
        raise DecodeError(f"field {field!r}: shape {shape} {dt} needs {n * dtype.itemsize} bytes, got {len(data)}")
    return np.frombuffer(data, dtype=dtype).reshape(shape)


@functools.cache  # per message type, once: decode runs per message
def map_fields(cls: type[Message]) -> frozenset[str]:
    """The fields of a message type that are maps (a Status message's counts): they travel as msgpack maps, and
    every other map on the wire is an array."""
    return frozenset(name for name, f in cls.model_fields.items() if typing.get_origin(f.annotation) is dict)


def encode(msg: Message) -> bytes:
    """Message -> msgpack bytes."""
    out: dict = {"kind": msg.kind}
    for name in type(msg).model_fields:
        value = getattr(msg, name)
        out[name] = _pack_array(value) if isinstance(value, np.ndarray) else value
    return msgpack.packb(out, use_bin_type=True)


def decode(payload: bytes | bytearray | memoryview, expect: type[Message] | None = None) -> Message:
    """msgpack bytes -> a validated message (of type `expect` when given); DecodeError says why not."""
    if len(payload) > MAX_MESSAGE_BYTES:
        raise DecodeError(f"message of {len(payload)} bytes exceeds the {MAX_MESSAGE_BYTES}-byte limit")
    items = 0

    def counted(container: list | dict) -> list | dict:  # each list and map, once msgpack has built it
        nonlocal items
        items += len(container)
        if items > MAX_ITEMS:
            raise DecodeError(f"more than {MAX_ITEMS} entries in lists and maps, more than any message holds")
        return container

    try:
        # a string or bin costs the bytes it brings: the message's own limit is theirs. Every entry takes a byte of
        # the payload at least, so one of MAX_ITEMS bytes or fewer cannot exceed the count: not counted (a callback
        # per list and map is a tenth of a Tracks message's decoding)
        hooks = {"list_hook": counted, "object_hook": counted} if len(payload) > MAX_ITEMS else {}
        raw = msgpack.unpackb(bytes(payload), raw=False, strict_map_key=True, max_array_len=MAX_LIST_LEN,
                              max_map_len=MAX_MAP_LEN, max_bin_len=MAX_MESSAGE_BYTES, max_str_len=MAX_MESSAGE_BYTES,
                              **hooks)
    except DecodeError:
        raise
    except Exception as exc:  # msgpack raises several unrelated exception types for garbage
        if "exceeds max_" in str(exc):  # msgpack's "5000 exceeds max_array_len(4096)": a limit above
            raise DecodeError(f"a list or map longer than any message holds ({exc})") from None
        raise DecodeError(f"not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(raw, dict):
        raise DecodeError(f"expected a map, got {type(raw).__name__}")
    kind = raw.pop("kind", None)
    cls = MESSAGE_TYPES.get(kind) if isinstance(kind, str) else None
    if cls is None:
        raise DecodeError(f"unknown message kind {kind!r}")
    if expect is not None and cls is not expect:
        raise DecodeError(f"expected a {expect.kind} message, got {kind!r}")
    if raw.get("v") != (v := cls.model_fields["v"].default):
        raise DecodeError(f"schema version {raw.get('v')!r} is not supported (this build speaks v{v})")
    if isinstance(raw.get("stamps"), list) and len(raw["stamps"]) > MAX_STAMPS:  # before validating each one
        raise DecodeError(f"{kind}: {len(raw['stamps'])} stamps, more than the {MAX_STAMPS} a message may carry")
    fields = {}
    maps = map_fields(cls)
    try:
        for name, value in raw.items():
            fields[name] = _unpack_array(name, value) if isinstance(value, dict) and name not in maps else value
    except DecodeError:
        raise
    except Exception as exc:  # whatever else numpy makes of a crafted array: the message is bad, not the service
        raise DecodeError(f"{kind}: field {name!r} is not a valid array ({type(exc).__name__}: {exc})") from None
    try:
        return cls(**fields)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first.get("loc", ())) or kind
        raise DecodeError(f"{kind} does not validate: {where}: {first.get('msg')}"
                          f" ({exc.error_count()} error(s))") from None
    except Exception as exc:  # a validator's arithmetic on a crafted value (OverflowError, ...): still a bad message
        raise DecodeError(f"{kind} does not validate: {type(exc).__name__}: {exc}") from None
