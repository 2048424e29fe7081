"""The wire contract and the configuration every service shares (fast unit tests, no bus).

shared/messages.py + shared/codec.py: every message kind round-trips through msgpack with its arrays intact
(also with zero rows); anything else is refused with a DecodeError that says why. shared/keys.py: the key
expressions. shared/settings.py + shared/service.py: site files, ROADSIDE_* overrides, `--set` flags and the
one-line exit-2 error of a service that cannot start. shared/bus.py: the Zenoh config and the bad-input counter.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re

import msgpack
import numpy as np
import pytest
import yaml
import zenoh
from pydantic import ValidationError

from shared.bus import BadInput, set_shared_memory, zenoh_config
from shared.codec import MAX_ARRAY_ITEMS, MAX_MESSAGE_BYTES, DecodeError, decode, encode
from shared.geo import GeoFrame, offset_latlon
from shared.keys import (
    alive_key,
    all_alive_key,
    all_cameras_key,
    camera_key,
    camera_of,
    latest_tracks_key,
    observer_alive_key,
    tracks_key,
)
from shared.messages import (
    MAX_FRAME_BYTES,
    MESSAGE_TYPES,
    SCHEMA_VERSION,
    Detections,
    Frame,
    Objects,
    Status,
    Tracks,
    check_name,
    err95_m,
    not_covariances,
)
from shared.position_error import POSITION_SIGMA
from shared.service import parse_sets, run
from shared.settings import BusSettings, load_settings
from shared.tracks_file import parse_covariance

SITE = "state_ellsworth"
T0 = 1_703_001_600_000_000_000


# --- messages -------------------------------------------------------------------------------------------------------


def make_frame(encoding: str = "gray8", width: int = 4, height: int = 3, **kw) -> Frame:
    data = {"gray8": bytes(range(width * height)), "bgr8": bytes(width * height * 3),
            "jpeg": b"\xff\xd8\xff\xe0 pretend jpeg"}[encoding]
    fields = {"site": SITE, "camera": "NE", "seq": 7, "t_capture_ns": T0, "camera_kind": "fisheye",
              "encoding": encoding, "width": width, "height": height, "scale": 0.5, "data": data,
              "stamps": [("ingest", T0 + 5)]}
    return Frame(**{**fields, **kw})


def make_detections(n: int = 3, **kw) -> Detections:
    rng = np.random.default_rng(n)
    f4 = np.float32
    fields = {"site": SITE, "camera": "NE", "seq": 7, "t_capture_ns": T0, "width": 1280, "height": 960,
              "infer_ms": 12.5, "stamps": [("ingest", T0 + 5), ("detect", T0 + 9)],
              "score": rng.random(n).astype(f4), "uv": (rng.random((n, 2)) * 900).astype(f4),
              "box": (rng.random((n, 4)) * 900).astype(f4), "heading_uv": np.tile(np.array([1, 0], f4), (n, 1)),
              "size_lwh": np.tile(np.array([4.5, 1.8, 1.5], f4), (n, 1)), "vtype": np.arange(n, dtype=np.int8) % 5}
    return Detections(**{**fields, **kw})


def make_objects(n: int = 3, **kw) -> Objects:
    rng = np.random.default_rng(n)
    f4 = np.float32
    fields = {"site": SITE, "camera": "NE", "seq": 7, "t_capture_ns": T0, "infer_ms": 12.5,
              "stamps": [("ingest", T0 + 5), ("detect", T0 + 9), ("localize", T0 + 11)],
              "xy": rng.normal(0, 20, (n, 2)),
              "latlon": np.tile([42.2294, -83.739], (n, 1)) + rng.normal(0, 1e-4, (n, 2)),
              "yaw": rng.uniform(-3, 3, n).astype(f4), "size_lwh": np.tile(np.array([4.5, 1.8, 1.5], f4), (n, 1)),
              "vtype": np.zeros(n, np.int8), "score": np.full(n, 0.9, f4), "uv": (rng.random((n, 2)) * 900).astype(f4)}
    return Objects(**{**fields, **kw})


def make_tracks(n: int = 3, **kw) -> Tracks:
    f4 = np.float32
    fields = {"site": SITE, "seq": 3, "t_capture_ns": T0, "tracker": "tracker-abc",
              "stamps": [("tick_closed", T0 + 20), ("fuse_track", T0 + 21)],
              "id": np.arange(1, n + 1, dtype=np.int64), "xy": np.arange(2 * n, dtype=np.float64).reshape(n, 2),
              "latlon": np.tile([42.2294, -83.739], (n, 1)), "velocity": np.ones((n, 2), f4),
              "yaw": np.zeros(n, f4), "size_lwh": np.ones((n, 3), f4), "vtype": np.zeros(n, np.int8),
              "score": np.full(n, 0.8, f4), "age": np.arange(n, dtype=np.int32), "hits": np.arange(n, dtype=np.int32),
              "cameras": [["NE"] for _ in range(n)],
              "xy_cov": np.tile(np.array([[0.09, 0.02], [0.02, 0.16]], f4), (n, 1, 1)),
              "velocity_cov": np.tile(np.array([[0.25, 0.0], [0.0, 0.25]], f4), (n, 1, 1)),
              "yaw_confirmed": np.arange(n) % 2 == 0, "yaw_std": np.full(n, 0.125, f4),
              "frames": [("NE", 7, T0, T0 + 15)]}
    return Tracks(**{**fields, **kw})


def make_status(**kw) -> Status:
    fields = {"site": SITE, "seq": 2, "t_capture_ns": T0 + 2_000_000_000, "service": "detect", "instance": "cab-1",
              "started_ns": T0, "period_s": 2.0, "counts": {"frames_in": 40, "detections_out": 38},
              "rates": {"frames_in": 20.0, "detections_out": 19.0}, "bad": {"not msgpack": 1},
              "gauges": {"infer_ms": 21.5},
              "last_output_ns": T0 + 1_990_000_000, "cpu_s": 3.25, "peak_rss_mb": 250.0}
    return Status(**{**fields, **kw})


MAKERS = {"frame": make_frame, "detections": make_detections, "objects": make_objects, "tracks": make_tracks,
          "status": make_status}


def assert_same(a, b) -> None:
    assert type(a) is type(b)
    for name in type(a).model_fields:
        x, y = getattr(a, name), getattr(b, name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), name
            assert (x.dtype, x.shape) == (y.dtype, y.shape), name
            np.testing.assert_array_equal(x, y, err_msg=name)
        else:
            assert x == y, name


def test_every_message_kind_has_a_maker() -> None:
    assert set(MAKERS) == set(MESSAGE_TYPES)


@pytest.mark.parametrize("kind", ["detections", "objects", "tracks"])
@pytest.mark.parametrize("n", [0, 1, 5])
def test_round_trip_keeps_array_dtype_shape_and_values(kind: str, n: int) -> None:
    msg = MAKERS[kind](n)
    back = decode(encode(msg))
    assert_same(msg, back)
    assert len(back) == n
    assert decode(encode(msg), type(msg)).seq == msg.seq


@pytest.mark.parametrize("encoding", ["gray8", "bgr8", "jpeg"])
def test_frame_round_trip(encoding: str) -> None:
    msg = make_frame(encoding)
    back = decode(encode(msg), Frame)
    assert_same(msg, back)
    assert back.stamp("ingest") == T0 + 5


def test_empty_arrays_travel_with_their_trailing_shape() -> None:
    back = decode(encode(make_objects(0)))
    assert back.xy.shape == (0, 2) and back.xy.dtype == np.float64
    assert back.size_lwh.shape == (0, 3) and back.size_lwh.dtype == np.float32
    assert back.vtype.shape == (0,) and back.vtype.dtype == np.int8


def test_big_endian_arrays_are_sent_little_endian_with_the_same_values() -> None:
    xy = np.array([[1.5, -2.25]], dtype=">f8")
    back = decode(encode(make_objects(1, xy=xy)))
    assert back.xy.dtype == np.dtype("<f8")
    np.testing.assert_array_equal(back.xy, xy)


def test_tracks_rows_are_json_friendly() -> None:
    rows = make_tracks(2).rows()
    assert json.loads(json.dumps(rows)) == rows
    assert rows[1]["id"] == 2 and rows[1]["type"] == "car" and rows[1]["cameras"] == ["NE"]


@pytest.mark.parametrize(("cov", "reason"), [
    ([[0.09, 0.02], [0.03, 0.16]], "not a symmetric"),  # not symmetric
    ([[0.09, 0.2], [0.2, 0.16]], "not a symmetric"),  # |covariance| beyond what the variances allow
    ([[0.0, 0.0], [0.0, 0.16]], "not a symmetric"),
    ([[0.09, 0.0], [0.0, np.nan]], "NaN or infinite"),
])
@pytest.mark.parametrize("field", ["xy_cov", "velocity_cov"])
def test_a_covariance_that_is_not_one_is_refused(field: str, cov, reason: str) -> None:
    t = raw(make_tracks(2))
    t[field] = arr(np.array([[[0.09, 0.0], [0.0, 0.16]], cov], np.float32))
    refused(pack(t), f"{field}.*{reason}" if "not a" in reason else reason)


def test_a_covariance_singular_but_for_rounding_is_refused() -> None:
    """[[0.01, 0.21], [0.21, 4.41]] is (0.1, 2.1)'(0.1, 2.1), rank 1, but 0.01 * 4.41 rounds to just above
    0.21 * 0.21: refused, in a tracks file too. Of matrices at or near rank 1 every one accepted has a Cholesky factor
    (the Rerun sink draws its uncertainty ellipse with it)."""
    assert not_covariances(np.array([[[0.01, 0.21], [0.21, 4.41]]])).tolist() == [True]
    with pytest.raises(ValueError, match="not a symmetric positive definite"):
        parse_covariance([[0.01, 0.21], [0.21, 4.41]])
    rng = np.random.default_rng(0)
    v = rng.uniform(-3.0, 3.0, (20000, 2))
    floor = rng.choice([0.0, 1e-18, 1e-15, 1e-12, 1e-9, 1e-6], len(v))
    near = v[:, :, None] * v[:, None, :] + floor[:, None, None] * np.eye(2)
    accepted = near[~not_covariances(near)]
    assert len(accepted) > 1000
    np.linalg.cholesky(accepted)  # raises LinAlgError if one has none
    assert not not_covariances(np.array([[[0.09, 0.02], [0.02, 0.16]], [[1e-6, 0.0], [0.0, 1e6]]])).any()


def test_yaw_confirmed_is_one_bool_per_track() -> None:
    assert [r["yaw_confirmed"] for r in make_tracks(3).rows()] == [True, False, True]
    for bad, reason in ((np.ones(2, np.float32), "yaw_confirmed has dtype float32, expected kind 'b'"),
                        (np.ones(3, bool), "yaw_confirmed has 3 rows, expected 2")):
        t = raw(make_tracks(2))
        t["yaw_confirmed"] = arr(bad)
        refused(pack(t), reason)


def test_yaw_std_is_one_positive_float_per_track() -> None:
    assert [r["yaw_std"] for r in make_tracks(2).rows()] == [0.125, 0.125]
    for bad, reason in ((np.array([0.1, 0.0], np.float32), r"Tracks.yaw_std\[1\] is not > 0"),
                        (np.array([0.1, np.nan], np.float32), "yaw_std contains NaN"),
                        (np.ones(2, bool), "yaw_std has dtype bool, expected kind 'f'"),
                        (np.ones(3, np.float32), "yaw_std has 3 rows, expected 2")):
        t = raw(make_tracks(2))
        t["yaw_std"] = arr(bad)
        refused(pack(t), reason)


def test_err95_is_the_95_percent_ellipses_longest_half_axis() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(0, 1, (50, 2, 2))
    cov = a @ a.transpose(0, 2, 1) + 0.01 * np.eye(2)
    np.testing.assert_allclose(err95_m(cov), np.sqrt(5.991 * np.linalg.eigvalsh(cov)[:, -1]))
    # a circle of 1 m sigma: 2.448 m holds 95 % of a 2D Gaussian (1 - exp(-r^2 / 2) = 0.95)
    assert float(err95_m(np.eye(2))) == pytest.approx(np.sqrt(-2 * np.log(0.05)), abs=1e-3)
    samples = rng.multivariate_normal([0, 0], cov[0], 20000)
    inside = np.einsum("ni,ij,nj->n", samples, np.linalg.inv(cov[0]), samples) <= 5.991
    assert inside.mean() == pytest.approx(0.95, abs=0.01)


def test_stamped_appends_and_stamp_looks_up() -> None:
    msg = make_detections(1)
    stamps = msg.stamped("localize", T0 + 99)
    assert [s for s, _ in stamps] == ["ingest", "detect", "localize"]
    assert msg.stamp("detect") == T0 + 9
    with pytest.raises(KeyError, match="no 'localize' stamp"):
        msg.stamp("localize")


# --- decode errors --------------------------------------------------------------------------------------------------


def raw(msg) -> dict:
    """The msgpack map of a message, for tampering (bypasses validation when packed again)."""
    return msgpack.unpackb(encode(msg), raw=False)


def pack(d) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def arr(a: np.ndarray) -> dict:
    return {"dtype": a.dtype.str, "shape": list(a.shape), "data": a.tobytes()}


def refused(payload: bytes, match: str, expect=None) -> DecodeError:
    with pytest.raises(DecodeError, match=match) as info:
        decode(payload, expect)
    return info.value


def test_decode_error_is_a_value_error() -> None:
    assert issubclass(DecodeError, ValueError)


@pytest.mark.parametrize("payload", [b"", b"\xc1", b"\xc1\xc1 not msgpack at all", b"\x92\x01"])
def test_garbage_bytes_are_refused(payload: bytes) -> None:
    refused(payload, "not msgpack")


@pytest.mark.parametrize("value", [[1, 2, 3], "frame", 42, None])
def test_a_message_must_be_a_map(value) -> None:
    refused(pack(value), f"expected a map, got {type(value).__name__}")


def test_unknown_or_missing_kind_is_refused() -> None:
    d = raw(make_frame())
    refused(pack({**d, "kind": "pointcloud"}), "unknown message kind 'pointcloud'")
    del d["kind"]
    refused(pack(d), "unknown message kind None")


def test_the_expected_kind_is_enforced() -> None:
    refused(encode(make_frame()), "expected a detections message, got 'frame'", Detections)


@pytest.mark.parametrize("v", [SCHEMA_VERSION + 1, 0, "1", None])
def test_wrong_schema_version_is_refused(v) -> None:
    d = raw(make_detections())
    d["v"] = v
    refused(pack(d), r"schema version .* is not supported")


def test_missing_schema_version_is_refused() -> None:
    d = raw(make_detections())
    del d["v"]
    refused(pack(d), "schema version None is not supported")


@pytest.mark.parametrize("dtype", ["|O", ">f8", "<c16", "<f2", "<U4", "<u8", "float32"])
def test_disallowed_dtype_is_refused(dtype: str) -> None:
    d = raw(make_detections(2))
    d["uv"] = {"dtype": dtype, "shape": [2, 2], "data": bytes(4 * 16)}
    refused(pack(d), f"field 'uv': dtype '{re.escape(dtype)}' is not allowed")


def test_encode_refuses_a_disallowed_dtype() -> None:
    msg = make_detections(1)
    object.__setattr__(msg, "uv", np.zeros((1, 2), np.complex128))  # bypass validation
    with pytest.raises(ValueError, match="not allowed on the wire"):
        encode(msg)


def test_shape_that_does_not_match_the_bytes_is_refused() -> None:
    d = raw(make_detections(2))
    d["uv"] = {"dtype": "<f4", "shape": [3, 2], "data": np.zeros((2, 2), np.float32).tobytes()}
    refused(pack(d), r"field 'uv': shape \[3, 2\] <f4 needs 24 bytes, got 16")


@pytest.mark.parametrize("dtype", [["<f4"], {"a": 1}, 4, None])
def test_a_dtype_that_is_not_a_string_is_refused(dtype) -> None:
    d = raw(make_detections(1))
    d["uv"] = {"dtype": dtype, "shape": [1, 2], "data": bytes(8)}
    refused(pack(d), "field 'uv': dtype .* is not allowed")  # not a TypeError (unhashable) that ends the service


@pytest.mark.parametrize("shape", [[True, 2], [0, 2**62, 2**62], [0, 2**64 - 1]])
def test_boolean_or_giant_dimensions_are_refused(shape) -> None:
    d = raw(make_detections(1))
    d["uv"] = {"dtype": "<f4", "shape": shape, "data": b""}
    refused(pack(d), "field 'uv': (bad shape|shape .* items exceed the limit)")


def test_capture_times_past_2_pow_62_are_a_broken_clock() -> None:
    """Services add ticks and watermarks to capture times in int64: 2**63 - 1 would overflow there."""
    for t in (2**62, 2**63 - 1):
        d = raw(make_objects(1))
        d["t_capture_ns"] = t
        refused(pack(d), "t_capture_ns")
    assert make_objects(1, t_capture_ns=2**62 - 1).t_capture_ns == 2**62 - 1


def test_stamps_are_capped_before_they_are_validated() -> None:
    d = raw(make_detections(1))
    d["stamps"] = [["x", 1]] * 4000
    refused(pack(d), "4000 stamps, more than the 32")
    d["stamps"] = [["x", 1]] * 100_000  # longer than any list a message holds: msgpack stops at its length
    refused(pack(d), "longer than any message holds")
    d["stamps"] = [["ingest", -1]]
    refused(pack(d), "stamps")


@pytest.mark.parametrize(("make", "match"), [  # the payloads are made in the test: megabytes each
    (lambda: b"\xdd" + (4 * 2**20).to_bytes(4, "big") + b"\x90" * (4 * 2**20), "longer than any message holds"),
    (lambda: b"\x81\xa6stamps\xdd" + (2**20).to_bytes(4, "big") + b"\x80" * 2**20, "longer than any message holds"),
    # short lists in lists: each within the length limit, together millions of objects
    (lambda: b"\xdc\x0f\xa0" + (b"\xdc\x10\x00" + b"\x90" * 4096) * 4000, "more than \\d+ entries in lists and maps"),
])
def test_a_payload_of_millions_of_empty_lists_is_refused_before_it_is_built(make, match: str) -> None:
    """An empty list or map is one byte on the wire and tens in memory: msgpack stops at the most a message holds
    (else a 4 MiB payload cost 350 MB before any check ran, one of 48 MiB gigabytes)."""
    import tracemalloc

    payload = make()
    tracemalloc.start()
    try:
        refused(payload, match)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 64 * 2**20, f"{peak / 2**20:.0f} MB to refuse a {len(payload) / 2**20:.0f} MiB payload"


def test_the_largest_messages_still_decode() -> None:
    """The codec's limits on msgpack's lists and maps let through the most a valid message holds: a Tracks message of
    MAX_ROWS rows, each seen by 64 cameras and with a frame, MAX_STAMPS stamps; a Status message's full maps."""
    from shared.messages import MAX_ROWS, MAX_STAMPS, MAX_STATUS_ENTRIES

    n = MAX_ROWS
    most = make_tracks(n, cameras=[[f"C{j}" for j in range(64)] for _ in range(n)],
                       frames=[("NE", i, T0, T0 + 15) for i in range(n)], stamps=[("fuse_track", T0)] * MAX_STAMPS)
    back = decode(encode(most), Tracks)
    assert len(back) == n and back.cameras == most.cameras and len(back.frames) == n
    names = {f"reason {i}": i for i in range(MAX_STATUS_ENTRIES)}
    full = make_status(counts=names, bad=names, rates={k: 1.0 for k in names}, gauges={k: 1.0 for k in names},
                       rss_mb=100.0)
    assert decode(encode(full), Status).bad == names


@pytest.mark.parametrize("scale", [5e-324, 1e-40, 1 / 65])
def test_a_frame_scale_below_one_64th_is_refused(scale) -> None:
    d = raw(make_frame())
    d["scale"] = scale
    refused(pack(d), "scale")  # detect would enlarge such a frame to infinity


@pytest.mark.parametrize("maker", [make_detections, make_objects])
@pytest.mark.parametrize("vtype", [5, 258, -1, 127])
def test_a_vehicle_type_outside_the_list_is_refused(maker, vtype) -> None:
    d = raw(maker(2))
    d["vtype"] = arr(np.array([0, vtype], np.int16))  # an int8 cast would wrap 258 to 2, a "truck"
    refused(pack(d), r"vtype must index VEHICLE_TYPES \(0-4\)")


@pytest.mark.parametrize("shape", [[-1, 2], "2,2", [2.0, 2], [1, 1, 1, 1, 1]])
def test_bad_shape_is_refused(shape) -> None:
    d = raw(make_detections(1))
    d["uv"] = {"dtype": "<f4", "shape": shape, "data": bytes(8)}
    refused(pack(d), "field 'uv': bad shape")


def test_array_map_needs_exactly_dtype_shape_data() -> None:
    d = raw(make_detections(1))
    d["uv"] = {"dtype": "<f4", "shape": [1, 2], "data": bytes(8), "order": "F"}
    refused(pack(d), "exactly dtype, shape, data")
    d["uv"] = {"dtype": "<f4", "shape": [1, 2], "data": [0.0, 0.0]}
    refused(pack(d), "data must be bytes")


def test_too_many_items_are_refused_before_allocating() -> None:
    d = raw(make_detections(1))
    d["score"] = {"dtype": "<f4", "shape": [MAX_ARRAY_ITEMS + 1], "data": b""}
    refused(pack(d), "exceed the limit")


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
@pytest.mark.parametrize(("maker", "field"), [(make_detections, "uv"), (make_detections, "score"), (make_objects, "xy"),
                                              (make_objects, "latlon"), (make_tracks, "velocity")])
def test_nan_or_inf_in_a_float_column_is_refused(maker, field: str, bad: float) -> None:
    d = raw(maker(3))
    a = getattr(maker(3), field).copy()
    a.flat[1] = bad
    d[field] = arr(a)
    refused(pack(d), f"{field}.*contains NaN or infinite values")


@pytest.mark.parametrize(("field", "rows", "reason"), [
    ("score", np.array([0.5, 1.5, 0.25], np.float32), r"Detections.score\[1\] = 1.5 is not within \[0, 1\]"),
    ("score", np.array([0.5, 0.25, -0.125], np.float32), r"Detections.score\[2\] = -0.125 is not within"),
    ("size_lwh", np.array([[4.5, 1.8, 1.5], [0.0, 1.8, 1.5], [4.5, 1.8, 1.5]], np.float32),
     r"Detections.size_lwh\[1\] = \[0.0, 1.8, 1.5\] is not > 0 m"),
    ("size_lwh", np.array([[4.5, 1.8, 1.5], [4.5, 1.8, 1.5], [-4.5, 1.8, 1.5]], np.float32),
     r"Detections.size_lwh\[2\] = \[-4.5, 1.8, 1.5\] is not > 0 m"),
    ("heading_uv", np.array([[1.0, 0.0], [0.0, 0.0], [0.0, 1.0]], np.float32),
     r"Detections.heading_uv\[1\] = \[0.0, 0.0\] is not a direction"),
])
def test_detections_off_the_contracts_ranges_are_refused(field: str, rows: np.ndarray, reason: str) -> None:
    """A score outside [0, 1], a size not > 0 m or a heading (0, 0) in any row refuses the message where it is
    decoded (localize counts and skips it), as NaN does; before, localize passed such a row on and fuse_track
    refused the whole frame of objects for it. Scores 0 and 1 and tiny sizes are within the contract."""
    d = raw(make_detections(3))
    d[field] = arr(rows)
    refused(pack(d), reason, Detections)
    ok = make_detections(3, score=np.array([0.0, 1.0, 0.5], np.float32),
                         size_lwh=np.array([[1e-3, 1e-3, 1e-3]] * 3, np.float32),
                         heading_uv=np.array([[0.0, -1.0], [1e-30, 0.0], [0.6, 0.8]], np.float32))
    assert_same(decode(encode(ok), Detections), ok)


@pytest.mark.parametrize(("field", "value"), [("infer_ms", math.nan), ("infer_ms", math.inf)])
def test_nan_or_inf_in_a_scalar_is_refused(field: str, value: float) -> None:
    d = raw(make_detections(1))
    d[field] = value
    refused(pack(d), f"{field}: Input should be a finite number")
    f = raw(make_frame())
    f["scale"] = value
    refused(pack(f), "scale: Input should be a finite number")


def test_wrong_column_shape_is_refused() -> None:
    d = raw(make_detections(2))
    d["uv"] = arr(np.zeros((2, 3), np.float32))
    refused(pack(d), r"Detections.uv must have shape \(N, 2\) got \(2, 3\)")
    d = raw(make_objects(2))
    d["yaw"] = arr(np.zeros((2, 1), np.float32))
    refused(pack(d), r"Objects.yaw must have shape \(N,\), got \(2, 1\)")


def test_wrong_column_kind_is_refused() -> None:
    d = raw(make_detections(2))
    d["vtype"] = arr(np.zeros(2, np.float32))
    refused(pack(d), "Detections.vtype has dtype float32, expected kind 'iu'")


def test_mismatched_row_counts_are_refused() -> None:
    d = raw(make_detections(3))
    d["score"] = arr(np.zeros(2, np.float32))
    refused(pack(d), "has 3 rows, expected 2|has 2 rows, expected 3")
    t = raw(make_tracks(2))
    t["cameras"] = [["NE"]]
    refused(pack(t), "Tracks.cameras has 1 entries, expected 2")


def test_extra_and_missing_fields_are_refused() -> None:
    d = raw(make_detections(1))
    refused(pack({**d, "colour": "red"}), "colour: Extra inputs are not permitted")
    del d["uv"]
    refused(pack(d), "uv: Field required")


def test_oversized_frame_is_refused() -> None:
    d = raw(make_frame("jpeg"))
    d["data"] = b"\xff\xd8" + bytes(MAX_FRAME_BYTES)
    refused(pack(d), f"exceeds the {MAX_FRAME_BYTES}-byte limit")
    with pytest.raises(ValueError, match="exceeds"):
        make_frame("jpeg", data=b"\xff\xd8" + bytes(MAX_FRAME_BYTES))


def test_oversized_message_is_refused_before_unpacking() -> None:
    refused(bytes(MAX_MESSAGE_BYTES + 1), f"message of {MAX_MESSAGE_BYTES + 1} bytes exceeds")


@pytest.mark.parametrize(("encoding", "factor"), [("gray8", 1), ("bgr8", 3)])
def test_raw_frame_byte_count_must_match_its_size(encoding: str, factor: int) -> None:
    d = raw(make_frame(encoding, width=4, height=3))
    d["data"] = d["data"][:-1]
    refused(pack(d), f"{encoding} frame 4x3 needs {12 * factor} bytes, got {12 * factor - 1}")


@pytest.mark.parametrize(("field", "value", "match"), [
    ("encoding", "png", "encoding: Input should be 'gray8', 'bgr8' or 'jpeg'"),
    ("camera_kind", "lidar", "camera_kind: Input should be"),
    ("width", 0, "width: Input should be greater than 0"),
    ("height", 20000, "height: Input should be less than or equal to 16384"),
    ("seq", -1, "seq: Input should be greater than or equal to 0"),
    ("seq", 2**63, "seq: Input should be less than"),
    ("t_capture_ns", 2**64 - 1, "t_capture_ns: Input should be less than"),
])
def test_frame_field_limits(field: str, value, match: str) -> None:
    d = raw(make_frame())
    d[field] = value
    refused(pack(d), match)


@pytest.mark.parametrize("name", ["a/b", "NE*", "**", "", "x" * 65, "NE\n", "N E", "nö", "a$b", "NE/frame"])
@pytest.mark.parametrize("field", ["site", "camera"])
def test_bad_site_and_camera_names_are_refused(field: str, name: str) -> None:
    d = raw(make_detections(1))
    d[field] = name
    refused(pack(d), f"{field}: Value error, {field} name must be")
    with pytest.raises(ValueError, match=f"{field} name must be"):
        check_name(field, name)


@pytest.mark.parametrize("name", ["NE", "T_SW", "cam-01", "x" * 64])
def test_good_names_pass(name: str) -> None:
    assert check_name("camera", name) == name


# --- keys -----------------------------------------------------------------------------------------------------------


def test_keys_are_the_documented_ones() -> None:
    assert camera_key("s1", "NE", "frame") == "roadside/s1/cam/NE/frame"
    assert camera_key("s1", "NE", "detections") == "roadside/s1/cam/NE/detections"
    assert camera_key("s1", "T_SW", "objects") == "roadside/s1/cam/T_SW/objects"
    assert all_cameras_key("s1", "objects") == "roadside/s1/cam/*/objects"
    assert tracks_key("s1") == "roadside/s1/tracks"
    assert latest_tracks_key("s1") == "roadside/s1/tracks/latest"
    assert alive_key("s1", "detect", "NE") == "roadside/s1/alive/detect/NE"
    assert all_alive_key("s1") == "roadside/s1/alive/**"
    assert observer_alive_key("s1", "demo-collector") == "roadside/s1/alive/observer/demo-collector"
    assert camera_of("roadside/s1/cam/T_SW/objects") == "T_SW"


@pytest.mark.parametrize("stage", ["tracks", "frames", "", "*"])
def test_keys_refuse_bad_stages(stage: str) -> None:
    with pytest.raises(ValueError, match="stage must be one of"):
        camera_key("s1", "NE", stage)
    with pytest.raises(ValueError, match="stage must be one of"):
        all_cameras_key("s1", stage)


@pytest.mark.parametrize("service", ["rerun_sink", "tracks", "", "detect/x"])
def test_alive_key_refuses_bad_services(service: str) -> None:
    with pytest.raises(ValueError, match="service must be one of"):
        alive_key("s1", service, "NE")


@pytest.mark.parametrize("call", [lambda: camera_key("s/1", "NE", "frame"), lambda: camera_key("s1", "*", "frame"),
                                  lambda: tracks_key("**"), lambda: alive_key("s1", "detect", "a/b"),
                                  lambda: observer_alive_key("s1", "x/y")])
def test_keys_refuse_bad_names(call) -> None:
    with pytest.raises(ValueError, match="name must be"):
        call()


@pytest.mark.parametrize("key", ["roadside/s1/tracks", "roadside/s1/cam/NE", "other/s1/cam/NE/frame"])
def test_camera_of_refuses_other_keys(key: str) -> None:
    with pytest.raises(ValueError, match="not a camera key"):
        camera_of(key)


# --- settings -------------------------------------------------------------------------------------------------------


SITE_YAML = {
    "site": SITE,
    "origin": {"lat_deg": 42.2294, "lon_deg": -83.739, "alt_m": 265.0},
    "cameras": [{"name": "NE", "kind": "fisheye", "width": 1280, "height": 960, "masks": "masks/NE.npz"},
                {"name": "T_SW", "kind": "pinhole", "width": 640, "height": 512, "masks": "/abs/T_SW.npz"}],
    "bus": {"port_base": 24000},
    "ingest": {"source": "recording", "pace": "max"},
    "detect": {"threads": 3},
}


def write_site(tmp_path, data: dict) -> object:
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.fixture(autouse=True)
def _no_roadside_env(monkeypatch) -> None:
    for k in list(os.environ):
        if k.startswith("ROADSIDE_"):
            monkeypatch.delenv(k)


def test_load_a_site_file(tmp_path) -> None:
    s = load_settings(write_site(tmp_path, SITE_YAML))
    assert s.site == SITE and [c.name for c in s.cameras] == ["NE", "T_SW"]
    assert s.bus.port_base == 24000 and s.bus.mode == "peer" and s.detect.threads == 3
    assert s.site_dir == tmp_path.resolve()
    assert s.path(s.camera("NE").masks) == tmp_path.resolve() / "masks/NE.npz"
    assert str(s.path(s.camera("T_SW").masks)) == "/abs/T_SW.npz"
    assert s.bus.service_endpoint("localize") == "tcp/127.0.0.1:24002"
    assert load_settings(tmp_path).site == SITE  # a folder holding site.yaml
    with pytest.raises(KeyError, match="no camera 'SW'"):
        s.camera("SW")


def test_an_exclusion_polygon_reaching_far_beyond_the_image_is_refused(tmp_path) -> None:
    cams = [{**SITE_YAML["cameras"][0], "exclude_px": [[[0, 0], [1e9, 0], [0, 1e9]]]}, *SITE_YAML["cameras"][1:]]
    with pytest.raises(ValueError, match=r"exclude_px\[0\] reaches beyond 1000000 px"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": cams}))


@pytest.mark.parametrize(("origin", "match"), [
    ({"lat": 42.2, "lon": -83.7}, "origin needs lat_deg and lon_deg"),
    ({"lat_deg": 42.2, "lon_deg": -83.7, "height": 3.0}, "origin needs lat_deg and lon_deg"),
    ({"lat_deg": -83.7, "lon_deg": 242.2}, "origin must be a finite latitude"),
    ({"lat_deg": float("nan"), "lon_deg": -83.7}, "origin.lat_deg: Input should be a finite number")])
def test_a_misspelt_or_impossible_origin_is_refused_at_load(tmp_path, origin, match) -> None:
    with pytest.raises(ValueError, match=match):
        load_settings(write_site(tmp_path, {**SITE_YAML, "origin": origin}))


@pytest.mark.parametrize(("region", "match"), [([[0, 0], [10, 10], [20, 20]], "on a line"),
                                               ([[5, 5], [5, 5], [5, 5]], "on top of each other"),
                                               ([[0, 0], [10, 0], [float("nan"), 5]],
                                                "region_m.2.0: Input should be a finite number")])
def test_a_degenerate_fusion_region_is_refused(tmp_path, region, match) -> None:
    cams = [{**SITE_YAML["cameras"][0], "region_m": region}, *SITE_YAML["cameras"][1:]]
    with pytest.raises(ValueError, match=match):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": cams}))


@pytest.mark.parametrize(("variable", "field"), [("ROADSIDE_LOCALIZE__HEADING_STEP_PX", "localize.heading_step_px"),
                                               ("ROADSIDE_INGEST__FPS", "ingest.fps"),
                                               ("ROADSIDE_FUSE_TRACK__GATE_M", "fuse_track.gate_m")])
@pytest.mark.parametrize("value", ["inf", "nan"])
def test_an_infinite_or_nan_setting_is_refused_naming_it(tmp_path, monkeypatch, variable, field, value) -> None:
    """An infinite heading step passed `gt=0` and dropped every detection as outside the calibrated area."""
    monkeypatch.setenv(variable, value)
    with pytest.raises(ValueError, match=rf"{field}: Input should be a finite number"):
        load_settings(write_site(tmp_path, SITE_YAML))


def test_environment_overrides_nested_fields_and_keeps_the_rest(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("ROADSIDE_BUS__PORT_BASE", "31000")
    monkeypatch.setenv("ROADSIDE_DETECT__SCORE_THR", "0.2")
    monkeypatch.setenv("ROADSIDE_FUSE_TRACK__TICK_MS", "50")
    s = load_settings(write_site(tmp_path, SITE_YAML))
    assert s.bus.port_base == 31000 and s.bus.host == "127.0.0.1"
    assert s.detect.score_thr == 0.2 and s.detect.threads == 3  # threads from the file survives
    assert s.fuse_track.tick_ms == 50.0
    assert s.ingest.pace == "max"


@pytest.mark.parametrize(("name", "default", "other", "bad"), [
    ("extend_range_m", 50.0, 0.0, ("-5",)),
    ("out_of_region_weight", 0.5, 0.2, ("0", "1.5", "nan")),
    ("position_sigma", POSITION_SIGMA, ((0.0, 0.5, 0.3), (40.0, 2.0, 0.6)),
     ("[[0, 0.5, 0.3], [0, 2, 0.6]]", "[[0, 0, 0.3]]", "[[0, 0.5]]", "[]", "7")),
    ("position_sigma", POSITION_SIGMA, None, ()),
    ("crowded_sigma_factor", 2.0, 1.0, ("0.5", "nan", "inf")),
])
def test_fuse_track_fusion_settings_reach_the_services_fusion(tmp_path, monkeypatch, name, default, other,
                                                              bad) -> None:
    import services.fuse_track.__main__ as fuse_track

    monkeypatch.setattr(fuse_track, "camera_positions", lambda s: ({"NE": (0.0, 0.0), "T_SW": (50.0, 0.0)}, None))
    s = load_settings(write_site(tmp_path, SITE_YAML))
    assert getattr(s.fuse_track, name) == default and getattr(fuse_track.build(s)[0].config, name) == default
    env = f"ROADSIDE_FUSE_TRACK__{name.upper()}"
    monkeypatch.setenv(env, json.dumps(other))
    assert getattr(fuse_track.build(load_settings(write_site(tmp_path, SITE_YAML)))[0].config, name) == other
    for value in bad:
        monkeypatch.setenv(env, value)
        with pytest.raises(ValueError, match=rf"fuse_track\.{name}"):
            load_settings(write_site(tmp_path, SITE_YAML))


def test_environment_override_is_validated(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("ROADSIDE_BUS__MODE", "broker")
    with pytest.raises(ValueError, match=r"site.yaml: bus.mode"):
        load_settings(write_site(tmp_path, SITE_YAML))


@pytest.mark.parametrize("name", ["ROADSIDE_FUSE_TRACK_RECORD", "ROADSIDE_FUSETRACK__RECORD", "ROADSIDE_SITE_DIR",
                                  "ROADSIDE_BUS__MDOE", "ROADSIDE_LOG_LEVEL__X"])
def test_an_environment_variable_that_names_no_setting_is_refused(tmp_path, monkeypatch, name) -> None:
    """A misspelt ROADSIDE_ variable would be ignored (a cabinet's recording silently off): it is named."""
    monkeypatch.setenv(name, "/data/tracks.jsonl")
    with pytest.raises(ValueError, match=f"the environment: {name} is no setting"):
        load_settings(write_site(tmp_path, SITE_YAML))
    monkeypatch.delenv(name)
    monkeypatch.setenv("ROADSIDE_FUSE_TRACK__RECORD", "/data/tracks.jsonl")
    monkeypatch.setenv("roadside_log_level", "warn")  # the names are case-insensitive, as pydantic-settings reads them
    monkeypatch.setenv("ROADSIDE_ORIGIN__ALT_M", "12.5")  # a mapping's key
    settings = load_settings(write_site(tmp_path, {**SITE_YAML, "origin": {"lat_deg": 42.2, "lon_deg": -83.7}}))
    assert str(settings.fuse_track.record) == "/data/tracks.jsonl" and settings.log_level == "WARNING"
    assert settings.origin["alt_m"] == 12.5


@pytest.mark.parametrize("pace", ["0", "-1", "fast", "nan", "", "1e-7", "inf", "5000x"])
def test_bad_pace_is_refused(tmp_path, pace: str) -> None:
    with pytest.raises(ValueError, match=r"ingest\.pace: .*pace must be a speed factor from 0\.01 to 1000"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "ingest": {"pace": pace}}))


@pytest.mark.parametrize(("pace", "stored"), [("max", "max"), ("MAX", "max"), ("10x", "10"), ("2.5", "2.5"), (1, "1"),
                                             (2.5, "2.5")])
def test_good_pace_is_normalised(tmp_path, pace, stored: str) -> None:
    assert load_settings(write_site(tmp_path, {**SITE_YAML, "ingest": {"pace": pace}})).ingest.pace == stored


def test_duplicate_camera_names_are_refused(tmp_path) -> None:
    cams = [SITE_YAML["cameras"][0], {**SITE_YAML["cameras"][1], "name": "NE"}]
    with pytest.raises(ValueError, match=r"duplicate camera names \['NE'\]"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": cams}))


def test_no_cameras_and_bad_camera_names_are_refused(tmp_path) -> None:
    with pytest.raises(ValueError, match="at least one camera"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": []}))
    with pytest.raises(ValueError, match="camera name must be"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": [{**SITE_YAML["cameras"][0], "name": "N/E"}]}))


def test_exclusion_polygons_are_checked(tmp_path) -> None:
    cam = SITE_YAML["cameras"][0]
    triangle = [[1, 2], [5, 2], [5, 6]]
    ok = load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": [{**cam, "exclude_px": [triangle]}]}))
    assert ok.cameras[0].exclude_px == [[(1, 2), (5, 2), (5, 6)]]
    assert load_settings(write_site(tmp_path, SITE_YAML)).cameras[0].exclude_px == []
    with pytest.raises(ValueError, match=r"exclude_px\[0\] needs at least 3 points, got 2"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": [{**cam, "exclude_px": [[[1, 2], [5, 2]]]}]}))
    with pytest.raises(ValueError, match=r"cameras.0.exclude_px.1.1.1: Input should be a finite number"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": [
            {**cam, "exclude_px": [[[1, 2], [5, 2], [5, 6]], [[1, 2], [5, float("nan")], [5, 6]]]}]}))


def test_unknown_field_is_named(tmp_path) -> None:
    with pytest.raises(ValueError, match=r"site.yaml: detect.treads: Extra inputs are not permitted"):
        load_settings(write_site(tmp_path, {**SITE_YAML, "detect": {"treads": 2}}))


def test_missing_site_file_names_the_file(tmp_path) -> None:
    missing = tmp_path / "nowhere" / "site.yaml"
    with pytest.raises(ValueError, match=f"site file not found: {re.escape(str(missing))}"):
        load_settings(missing)
    with pytest.raises(ValueError, match="site file not found"):
        load_settings(tmp_path)  # a folder without site.yaml


def test_bad_yaml_and_non_mapping_name_the_file(tmp_path) -> None:
    path = tmp_path / "site.yaml"
    path.write_text("site: [unclosed\n")
    with pytest.raises(ValueError, match=f"{re.escape(str(path))}: not valid YAML"):
        load_settings(path)
    path.write_text("- a\n- b\n")
    with pytest.raises(ValueError, match="expected a mapping at the top level"):
        load_settings(path)


def test_parse_sets_builds_nested_overrides_with_yaml_values() -> None:
    got = parse_sets(["ingest.pace=max", "ingest.max_frames=2", "detect.score_thr=0.05",
                      "bus.connect=[tcp/a:1, tcp/b:2]", "fuse_track.record=/tmp/x.jsonl", "ingest.loop=true",
                      "log_level=DEBUG", "detect.model_gpu=null", "ingest.source=a=b"])
    assert got == {"ingest": {"pace": "max", "max_frames": 2, "loop": True, "source": "a=b"},
                   "detect": {"score_thr": 0.05, "model_gpu": None}, "bus": {"connect": ["tcp/a:1", "tcp/b:2"]},
                   "fuse_track": {"record": "/tmp/x.jsonl"}, "log_level": "DEBUG"}


@pytest.mark.parametrize("items", [["ingest.pace"], ["=1"], ["ingest.pace=max", "ingest=fast", "ingest.loop=true"],
                                   ["detect.score_thr=[0.1"]])
def test_parse_sets_refuses_malformed_items(items: list[str]) -> None:
    with pytest.raises(ValueError, match="--set"):
        parse_sets(items)


def test_set_overrides_merge_into_the_file_sections(tmp_path) -> None:
    path = write_site(tmp_path, SITE_YAML)
    s = load_settings(path, **parse_sets(["detect.score_thr=0.05", "bus.port_base=25000", "ingest.max_frames=2"]))
    assert s.detect.score_thr == 0.05 and s.detect.threads == 3
    assert s.bus.port_base == 25000 and s.ingest.pace == "max" and s.ingest.max_frames == 2
    assert load_settings(path, **parse_sets(["ingest.pace=10"])).ingest.pace == "10"  # a YAML number
    with pytest.raises(ValueError, match=r"detect\.score_thr"):
        load_settings(path, **parse_sets(["detect.score_thr=2"]))
    with pytest.raises(ValueError, match="cameras is not a section"):
        load_settings(path, **parse_sets(["cameras.0.masks=x.npz"]))


def test_a_service_that_cannot_start_exits_2_with_one_error_line(tmp_path, capsys) -> None:
    def main(settings, stopper):
        raise ValueError(f"detector model not found: {tmp_path / 'm.onnx'}")

    assert run("detect", main, ["--site", str(tmp_path / "none.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("detect: error: site file not found") and "none.yaml" in err[0]
    path = write_site(tmp_path, SITE_YAML)
    assert run("detect", main, ["--site", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"detect: error: detector model not found: {tmp_path / 'm.onnx'}"]
    assert run("detect", main, ["--site", str(path), "--set", "detect.score_thr=[0.1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not valid YAML" in err[0]


# --- bus helpers ----------------------------------------------------------------------------------------------------


def test_zenoh_config_peer_service_listens_on_its_port_and_connects_to_the_others() -> None:
    conf = zenoh_config(BusSettings(port_base=30000), "detect")
    assert json.loads(conf.get_json("mode")) == "peer"
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:30001"]
    assert json.loads(conf.get_json("connect/endpoints")) == [
        "tcp/127.0.0.1:30000", "tcp/127.0.0.1:30002", "tcp/127.0.0.1:30003"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    client = zenoh_config(BusSettings(port_base=30000), None, client_index=2)
    assert json.loads(client.get_json("listen/endpoints")) == ["tcp/127.0.0.1:30005"]
    assert len(json.loads(client.get_json("connect/endpoints"))) == 4
    assert json.loads(zenoh_config(BusSettings(port_base=30000), None).get_json("listen/endpoints")) == []


def test_zenoh_config_client_mode_needs_a_router() -> None:
    with pytest.raises(ValueError, match=r"bus\.connect names no router"):
        zenoh_config(BusSettings(mode="client"), "detect")
    conf = zenoh_config(BusSettings(mode="client", connect=["tcp/zenoh:7447"]), "detect")
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/zenoh:7447"]
    assert json.loads(conf.get_json("listen/endpoints")) == []


def test_zenoh_config_shared_memory_is_off_unless_asked() -> None:
    # Zenoh turns its shared-memory transport on by default: a pool mapped in each process, no latency gained here
    assert json.loads(zenoh_config(BusSettings(port_base=30000), "ingest").get_json(
        "transport/shared_memory/enabled")) is False
    on = zenoh_config(BusSettings(port_base=30000, shared_memory=True), "ingest")
    assert json.loads(on.get_json("transport/shared_memory/enabled")) is True


def test_zenoh_config_data_send_queue_is_bus_tx_queue_batches() -> None:
    # Zenoh's default 2 batches dropped fragments of camera frames in full-speed playback (docs/pipeline.md)
    key = "transport/link/tx/queue/size/data"
    assert json.loads(zenoh_config(BusSettings(port_base=30000), "ingest").get_json(key)) == 16
    assert json.loads(zenoh_config(BusSettings(port_base=30000, tx_queue_batches=4), "ingest").get_json(key)) == 4
    for bad in (0, 17):  # Zenoh refuses more than 16
        with pytest.raises(ValidationError, match="tx_queue_batches"):
            BusSettings(tx_queue_batches=bad)


def test_shared_memory_setting_on_a_zenoh_without_it() -> None:
    class NoSharedMemory:  # a Zenoh built without the feature knows no such key
        def insert_json5(self, key: str, value: str) -> None:
            raise zenoh.ZError("unknown key")

    set_shared_memory(NoSharedMemory(), False)  # off is what it is anyway
    with pytest.raises(ValueError, match=r"bus\.shared_memory is true but this Zenoh has no shared-memory transport"):
        set_shared_memory(NoSharedMemory(), True)


def test_bad_input_logs_each_reason_once_and_counts_them(caplog) -> None:
    bad = BadInput("detect")
    with caplog.at_level(logging.WARNING, logger="roadside.bus"):
        for seq in range(5):
            bad(f"camera NE seq {seq}: corrupt JPEG ({100 + seq} bytes)", "NE")
        bad("frame does not validate: scale: Input should be a finite number (1 error(s))", "NE")
        bad("frame does not validate: data: Value error, gray8 frame 4x3 needs 12 bytes, got 11 (1 error(s))", "NE")
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 3, lines
    assert "dropped NE message" in lines[0] and "corrupt JPEG" in lines[0]
    assert "finite number" in lines[1] and "needs 12 bytes" in lines[2]
    assert bad.total == 7 and sorted(bad.counts.values()) == [1, 1, 5]


def test_a_receiver_that_falls_behind_drops_the_oldest_and_reports_them(caplog) -> None:
    from shared.bus import BadInput, Receiver

    class Session:  # stands in for Zenoh: keeps the subscriber's callback
        def declare_subscriber(self, key, callback):
            self.callback = callback

    class Sample:
        def __init__(self, payload: bytes) -> None:
            self.key_expr, self.payload = "k", type("P", (), {"to_bytes": lambda _: payload})()

    session, bad = Session(), BadInput("test")
    receiver = Receiver(session, "k", Detections, bad, fifo=5, fifo_bytes=10**9)
    payloads = [encode(make_detections(1, seq=s)) for s in range(12)]
    for p in payloads:
        session.callback(Sample(p))
    with caplog.at_level("WARNING"):
        got = receiver.poll()
    assert [m.seq for m in got] == [7, 8, 9, 10, 11] and receiver.overflow == 7 and bad.total == 7
    assert "7 messages dropped unread: the service fell behind" in caplog.text
    assert receiver.poll() == [] and bad.total == 7  # reported once
    small = Receiver(session, "k", Detections, bad, fifo=100, fifo_bytes=3 * len(payloads[0]))
    for p in payloads:
        session.callback(Sample(p))
    assert len(small.buffer) == 3 and small.bytes == 3 * len(payloads[0]) and small.overflow == 9


def test_bad_input_keeps_a_bounded_number_of_reasons() -> None:
    bad = BadInput("fuse_track")
    for i in range(1000):
        bad(f"objects from camera 'cam{chr(65 + i % 26)}{chr(65 + i // 26 % 26)}x', not at this site")
    assert len(bad.counts) <= 257 and bad.total == 1000


# --- small edges of the services that need no bus ------------------------------------------------------------------


def test_client_stream_gives_the_current_tracks_then_only_newer_ones() -> None:
    from shared.client import TrackClient

    class Queue:
        def __init__(self, batches: list[list[Tracks]]) -> None:
            self.batches = batches

        def poll(self) -> list[Tracks]:
            return self.batches.pop(0) if self.batches else []

        def wait(self, timeout_s: float) -> None:  # the real Receiver sleeps until a message arrives
            pass

    client = TrackClient.__new__(TrackClient)  # no Zenoh session: latest() and the receiver are stand-ins
    client.latest = lambda timeout_s=2.0: make_tracks(1, seq=5, tracker="tracker-a")
    queued = [make_tracks(1, seq=s, tracker=t) for t, s in [("tracker-a", 4), ("tracker-a", 5), ("tracker-a", 6),
                                                            ("tracker-b", 0), ("tracker-b", 5)]]
    client.receiver = Queue([queued[:3], queued[3:]])
    got = [(t.tracker, t.seq) for t in client.stream(timeout_s=0.05, poll_s=0.001, latest=False)]
    # a restarted fuse_track (another tracker) starts again at seq 0 and is followed at once
    assert got == [("tracker-a", 5), ("tracker-a", 6), ("tracker-b", 0), ("tracker-b", 5)]
    # after the current one, duplicates and stragglers of the tracker followed are skipped too
    client.receiver = Queue([[make_tracks(1, seq=s, tracker="tracker-b") for s in (6, 6, 4, 7)]])
    assert [t.seq for t in client.stream(timeout_s=0.05, poll_s=0.001, latest=False)] == [5, 6, 7]
    # a recording played again (`roadside play`: its tracker, seq and capture time from their start again) is
    # followed from its start; a stale message a few ticks old is not a replay
    s_ns = 10**9

    def tick(seq, t_s):
        return make_tracks(1, seq=seq, tracker="tracker-b", t_capture_ns=T0 + round(t_s * s_ns))

    client.latest = lambda timeout_s=2.0: tick(5, 60.5)
    client.receiver = Queue([[tick(3, 60.3), tick(6, 60.6), tick(7, 60.7), tick(0, 0.0), tick(1, 0.1), tick(1, 0.1),
                              tick(2, 0.2)]])
    assert [t.seq for t in client.stream(timeout_s=0.05, poll_s=0.001, latest=False)] == [5, 6, 7, 0, 1, 2]


def test_client_stream_gives_a_slow_loop_the_newest_tracks() -> None:
    """A vehicle's loop slower than the tick: of the messages that came while it was busy only the newest is given
    (after the duplicate check) and the others counted in `skipped`; `latest=False` gives every one, in order."""
    from shared.client import TrackClient

    class Queue:
        def __init__(self, batches: list[list[Tracks]]) -> None:
            self.batches = batches

        def poll(self) -> list[Tracks]:
            return self.batches.pop(0) if self.batches else []

        def wait(self, timeout_s: float) -> None:
            pass

    def batches() -> list[list[Tracks]]:  # what the loop finds waiting after each message it worked on
        return [[make_tracks(1, seq=s, tracker="tracker-a") for s in batch]
                for batch in ([6, 7, 8], [9], [8, 9], [10, 11, 10])]

    client = TrackClient.__new__(TrackClient)  # no Zenoh session: latest() and the receiver are stand-ins
    client.skipped = 0
    client.latest = lambda timeout_s=2.0: make_tracks(1, seq=5, tracker="tracker-a")
    client.receiver = Queue(batches())
    assert [t.seq for t in client.stream(timeout_s=0.05, poll_s=0.001)] == [5, 8, 9, 11]
    assert client.skipped == 3  # 6, 7 and 10: the duplicates 8, 9 and 10 are not counted
    client.skipped = 0
    client.receiver = Queue(batches())
    assert [t.seq for t in client.stream(timeout_s=0.05, poll_s=0.001, latest=False)] == [5, 6, 7, 8, 9, 10, 11]
    assert client.skipped == 0


def test_client_stream_ends_when_told_to_stop() -> None:
    import threading

    from shared.client import TrackClient

    class Quiet:  # no message ever comes
        def poll(self) -> list[Tracks]:
            return []

        def wait(self, timeout_s: float) -> None:
            pass

    client = TrackClient.__new__(TrackClient)
    client.latest = lambda timeout_s=2.0: make_tracks(1, seq=5, tracker="tracker-a")
    client.receiver = Quiet()
    stop = threading.Event()
    stream = client.stream(timeout_s=None, poll_s=0.001, stop=stop)
    assert next(stream).seq == 5  # the current tracks at once
    stop.set()
    assert list(stream) == []  # without a timeout it would wait for ever


def test_fuse_track_refuses_implausible_objects() -> None:
    from services.fuse_track.__main__ import implausible

    assert implausible(make_objects(2)) is None and implausible(make_objects(0)) is None
    assert "beyond" in implausible(make_objects(1, xy=np.array([[1e300, 0.0]])))
    assert "outside" in implausible(make_objects(1, size_lwh=np.array([[4.0, 1e-300, 1.5]])))
    assert "outside" in implausible(make_objects(1, size_lwh=np.array([[4.0, 1.8, 3e38]], np.float32)))


def test_fuse_track_names_a_masks_file_without_camera_metadata(tmp_path) -> None:
    from services.fuse_track.__main__ import camera_positions

    path = tmp_path / "masks" / "NE.npz"
    path.parent.mkdir()
    np.savez(path, meta=np.array(json.dumps({"format": "roadside-lookup-masks", "version": 1})))
    s = load_settings(write_site(tmp_path, {**SITE_YAML, "cameras": SITE_YAML["cameras"][:1]}))
    with pytest.raises(ValueError, match=rf"{re.escape(str(path))}: not a lookup masks file \(KeyError"):
        camera_positions(s)


def test_too_many_rows_are_refused():
    import numpy as np

    from shared.messages import MAX_ROWS, Objects

    n = MAX_ROWS + 1
    f4 = np.float32
    with pytest.raises(ValueError, match="more than the"):
        Objects(site="s", camera="c", seq=0, t_capture_ns=0, infer_ms=0.0, xy=np.zeros((n, 2)),
                latlon=np.zeros((n, 2)), yaw=np.zeros(n, f4), size_lwh=np.ones((n, 3), f4),
                vtype=np.zeros(n, np.int8), score=np.zeros(n, f4), uv=np.zeros((n, 2), f4))


def test_tracks_predicted_move_on_at_their_velocity_with_their_uncertainty_grown() -> None:
    """Tracks 0.5 s later: positions moved by velocity x dt, latitude and longitude with them (as the site frame
    has them), covariances grown by dt^2 velocity_cov and the acceleration term; a valid message (it encodes and
    decodes); backwards works too; too far, a non-integer time or a bad sigma is refused, named."""
    geo = GeoFrame(42.2294, -83.739)
    tracks = make_tracks(3, velocity=np.array([[10.0, 0.0], [0.0, -4.0], [0.0, 0.0]], np.float32))
    tracks = tracks.model_copy(update={"latlon": geo.to_geodetic(tracks.xy)[:, :2]})
    later = tracks.predicted(T0 + 500_000_000, accel_std_mps2=2.0)
    np.testing.assert_allclose(later.xy, tracks.xy + np.array([[5.0, 0.0], [0.0, -2.0], [0.0, 0.0]]))
    np.testing.assert_allclose(later.latlon, geo.to_geodetic(later.xy)[:, :2], rtol=0, atol=1e-9)  # ~0.1 mm
    grown = tracks.xy_cov[0] + 0.25 * tracks.velocity_cov[0] + (2.0 * 0.25 / 2) ** 2 * np.eye(2)
    np.testing.assert_allclose(later.xy_cov[0], grown, rtol=1e-6)
    np.testing.assert_allclose(later.velocity_cov[0], tracks.velocity_cov[0] + np.eye(2), rtol=1e-6)
    assert later.t_capture_ns == T0 + 500_000_000 and later.stamps[-1][0] == "predict"
    assert later.frames == tracks.frames and (later.id == tracks.id).all() and (later.yaw == tracks.yaw).all()
    again = decode(encode(later))
    np.testing.assert_array_equal(again.xy_cov, later.xy_cov)
    np.testing.assert_allclose(tracks.predicted(T0 - 200_000_000).xy[0], tracks.xy[0] - [2.0, 0.0])
    assert tracks.predicted(T0).xy_cov.tolist() == tracks.xy_cov.tolist()
    with pytest.raises(ValueError, match=r"cannot be predicted .* \+2\.500 s away, more than 2\.0 s"):
        tracks.predicted(T0 + 2_500_000_000)
    with pytest.raises(ValueError, match="t_ns must be an integer"):
        tracks.predicted(float(T0))
    with pytest.raises(ValueError, match="accel_std_mps2 must be a finite number >= 0"):
        tracks.predicted(T0, accel_std_mps2=math.nan)


def test_offset_latlon_agrees_with_the_ellipsoid() -> None:
    """Small ground offsets through the radii of curvature: within a millimetre of pymap3d's exact conversion at
    50 m, at the site's latitude and far north."""
    for lat0 in (42.2294, 70.0):
        geo = GeoFrame(lat0, -83.739)
        east, north = np.array([50.0, -30.0, 0.0]), np.array([0.0, 40.0, -50.0])
        lat, lon = offset_latlon(np.full(3, lat0), np.full(3, -83.739), east, north)
        np.testing.assert_allclose(geo.to_enu(lat, lon)[:, :2], np.column_stack([east, north]), atol=1e-3)
