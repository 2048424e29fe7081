"""The wire contract: the only definition of every message on the bus.

Four messages flow ingest -> detect -> localize -> fuse_track -> vehicles:

| message    | key expression                            | per item |
| ---------- | ----------------------------------------- | -------- |
| Frame      | `roadside/<site>/cam/<camera>/frame`      | one image: encoding, width, height, bytes |
| Detections | `roadside/<site>/cam/<camera>/detections` | bottom centre (px), score, type, size, heading, box |
| Objects    | `roadside/<site>/cam/<camera>/objects`    | x, y (m), lat, lon, yaw (rad, ENU), size, type, score |
| Tracks     | `roadside/<site>/tracks`                  | id, x, y, lat, lon, velocity, yaw, size, type, ... |

and every service reports what it has done on the side (a traffic engineer's view, `roadside status`):

| Status     | `roadside/<site>/status/<service>/<instance>` | counts and rates, bad input by reason, CPU, memory |

Every message carries `v` (schema version), `site`, `seq`, `t_capture_ns` (when the frame was
captured, from the source, not when it was processed) and `stamps`: `[stage, t_ns]` pairs, one
appended by each stage (wall clock, `time.time_ns()`), from which per-stage latency is computed.

Per-item data are struct-of-arrays numpy arrays (validated on construction: shapes, dtypes, finite
values), so a service never loops over Python objects and the codec (shared/codec.py) sends them as
`{dtype, shape, data}` without pickle.
"""

from __future__ import annotations

import math
import re
import time
from collections.abc import Mapping
from typing import Annotated, Any, ClassVar, Literal

import numpy as np
from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, PlainSerializer, field_validator, model_validator

from shared.geo import offset_latlon

SCHEMA_VERSION = 4
VEHICLE_TYPES = ("car", "suv_van", "truck", "bus", "motorcycle")
SERVICES = ("ingest", "detect", "localize", "fuse_track")
# the keys of one track in a tracks-file line (Tracks.rows, fuse_track's recorder; Tracks.from_record reads them back)
RECORD_KEYS = ("id", "x", "y", "lat", "lon", "vx", "vy", "yaw", "length", "width", "height", "type", "score", "age",
               "hits", "cameras", "xy_cov", "velocity_cov", "yaw_confirmed", "yaw_std")
CAMERA_KINDS = ("pinhole", "fisheye")
MAX_FRAME_BYTES = 32 * 1024 * 1024  # larger frames are refused (an oversized frame is bad input)
MAX_ROWS = 4096  # detections, objects or tracks per message: more is bad input (fusion is quadratic)
INT64_END = 2**63  # seq and times are int64 downstream (numpy); larger values are bad input
# capture times are event times that services add ticks and watermarks to: kept below 2**62 ns (the year 2116) so
# that arithmetic stays within int64; a later one is a broken clock, refused as bad input
T_CAPTURE_END = 2**62
# Tracks.predicted: how far (s) tracks may be moved on from their capture time, and the sigma (m/s^2) of the
# acceleration their velocities leave unknown (docs/wire-format.md, "Where a vehicle is now")
MAX_PREDICT_S = 2.0
PREDICT_ACCEL_STD_MPS2 = 1.5
MAX_STAMPS = 32  # a message passes four stages; a longer list is bad input, not something to copy down the line
MIN_FRAME_SCALE = 1 / 64  # ingest decodes at 1/2, 1/4 or 1/8 at most; a smaller scale would blow pixels up
NAME_RE = re.compile(r"^[A-Za-z0-9_\-]{1,64}$")  # site and camera names: one key-expression chunk


def _as_array(value: Any) -> np.ndarray:
    if isinstance(value, np.ndarray):
        return value
    return np.asarray(value)


Array = Annotated[np.ndarray, BeforeValidator(_as_array), PlainSerializer(lambda a: a.tolist(), return_type=list)]


def check_name(kind: str, name: str) -> str:
    if not isinstance(name, str) or not NAME_RE.fullmatch(name):
        raise ValueError(f"{kind} name must be 1-64 letters, digits, '_' or '-' (ASCII letters only: A-Z, a-z), "
                         f"got {name!r}")
    return name


class Message(BaseModel):
    """Fields every message carries."""

    model_config = ConfigDict(arbitrary_types_allowed=True, extra="forbid", frozen=False)
    kind: ClassVar[str] = "message"

    v: int = SCHEMA_VERSION
    site: str
    seq: int = Field(ge=0, lt=INT64_END)
    t_capture_ns: int = Field(ge=0, lt=T_CAPTURE_END)
    stamps: list[tuple[Annotated[str, Field(max_length=64)], Annotated[int, Field(ge=0, lt=INT64_END)]]] = Field(
        default_factory=list, max_length=MAX_STAMPS)

    @field_validator("v")
    @classmethod
    def _version(cls, v: int) -> int:
        if v != SCHEMA_VERSION:
            raise ValueError(f"schema version {v} is not supported (this build speaks v{SCHEMA_VERSION})")
        return v

    @field_validator("site")
    @classmethod
    def _site(cls, v: str) -> str:
        return check_name("site", v)

    def stamped(self, stage: str, t_ns: int | None = None) -> list[tuple[str, int]]:
        """This message's stamps plus `(stage, now)`, for the message the stage publishes next."""
        return [*self.stamps, (stage, time.time_ns() if t_ns is None else int(t_ns))]

    def stamp(self, stage: str) -> int:
        """The time `stage` stamped this message (ns), KeyError if it did not."""
        for name, t in reversed(self.stamps):
            if name == stage:
                return t
        raise KeyError(f"{type(self).__name__} has no {stage!r} stamp (has {[s for s, _ in self.stamps]})")


class CameraMessage(Message):
    camera: str

    @field_validator("camera")
    @classmethod
    def _camera(cls, v: str) -> str:
        return check_name("camera", v)


def _check_columns(name: str, arrays: dict[str, tuple[np.ndarray, tuple, str]]) -> int:
    """Validate struct-of-arrays columns: {field: (array, trailing shape, dtype kind)}; returns N."""
    n = None
    for field, (a, trailing, kinds) in arrays.items():
        if a.dtype.kind not in kinds:
            raise ValueError(f"{name}.{field} has dtype {a.dtype}, expected kind {kinds!r}")
        if a.ndim != 1 + len(trailing) or tuple(a.shape[1:]) != trailing:
            raise ValueError(f"{name}.{field} must have shape (N, {', '.join(map(str, trailing))}) got {a.shape}"
                             if trailing else f"{name}.{field} must have shape (N,), got {a.shape}")
        if n is None:
            n = len(a)
        elif len(a) != n:
            raise ValueError(f"{name}.{field} has {len(a)} rows, expected {n} like the other fields")
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ValueError(f"{name}.{field} contains NaN or infinite values")
        if field == "vtype" and len(a) and not (0 <= a.min() and a.max() < len(VEHICLE_TYPES)):
            raise ValueError(f"{name}.vtype must index VEHICLE_TYPES (0-{len(VEHICLE_TYPES) - 1}), got "
                             f"{int(a.min()) if a.min() < 0 else int(a.max())}")
    if (n or 0) > MAX_ROWS:
        raise ValueError(f"{name} has {n} rows, more than the {MAX_ROWS} a message may carry")
    return n or 0


def _check_rows(name: str, bad: np.ndarray, values: np.ndarray, why: str) -> None:
    """ValueError naming the first row of `values` that `bad` ((N,) bool) marks, and why it is refused."""
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{i}] = {np.asarray(values[i], np.float64).round(6).tolist()} {why}")


class Frame(CameraMessage):
    """One camera image. `data`: the encoded bytes (jpeg) or raw pixels (gray8: H*W, bgr8: H*W*3).
    `scale`: this image's pixels per original-sensor pixel (ingest may decode a JPEG at reduced size);
    detect reports detections in original-sensor pixels."""

    kind: ClassVar[str] = "frame"
    camera_kind: Literal["pinhole", "fisheye"]
    encoding: Literal["gray8", "bgr8", "jpeg"]
    width: int = Field(gt=0, le=16384)
    height: int = Field(gt=0, le=16384)
    scale: float = Field(default=1.0, ge=MIN_FRAME_SCALE, le=1.0, allow_inf_nan=False)
    data: bytes

    @model_validator(mode="after")
    def _size(self) -> Frame:
        if len(self.data) > MAX_FRAME_BYTES:
            raise ValueError(f"frame of {len(self.data)} bytes exceeds the {MAX_FRAME_BYTES}-byte limit")
        expected = {"gray8": self.width * self.height, "bgr8": self.width * self.height * 3}.get(self.encoding)
        if expected is not None and len(self.data) != expected:
            raise ValueError(f"{self.encoding} frame {self.width}x{self.height} needs {expected} bytes, "
                             f"got {len(self.data)}")
        return self


class Detections(CameraMessage):
    """Detections of one frame, in original-sensor pixels of the camera.

    score (N,) float32 in [0, 1]; uv (N, 2) float32 bottom centre px; box (N, 4) float32 x1 y1 x2 y2 px;
    heading_uv (N, 2) float32 image-space unit vector rear -> front (not (0, 0)); size_lwh (N, 3) float32 metres,
    each > 0; vtype (N,) int8 index into VEHICLE_TYPES. `infer_ms`: the detector's own time for this frame.
    A message with a row outside these ranges is refused whole, as one with NaN is (localize would pass the row on,
    and fuse_track refuse the whole frame for it).
    """

    kind: ClassVar[str] = "detections"
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    infer_ms: float = Field(ge=0, allow_inf_nan=False)
    score: Array
    uv: Array
    box: Array
    heading_uv: Array
    size_lwh: Array
    vtype: Array

    @model_validator(mode="after")
    def _columns(self) -> Detections:
        _check_columns("Detections", {
            "score": (self.score, (), "f"), "uv": (self.uv, (2,), "f"), "box": (self.box, (4,), "f"),
            "heading_uv": (self.heading_uv, (2,), "f"), "size_lwh": (self.size_lwh, (3,), "f"),
            "vtype": (self.vtype, (), "iu")})
        _check_rows("Detections.score", (self.score < 0) | (self.score > 1), self.score, "is not within [0, 1]")
        _check_rows("Detections.size_lwh", np.any(self.size_lwh <= 0, axis=1), self.size_lwh, "is not > 0 m")
        _check_rows("Detections.heading_uv", np.all(self.heading_uv == 0, axis=1), self.heading_uv,
                    "is not a direction")
        return self

    def __len__(self) -> int:
        return len(self.score)


class Objects(CameraMessage):
    """Detections lifted to the ground by the camera's lookup masks.

    xy (N, 2) float64 metres, site ENU frame; latlon (N, 2) float64 degrees; yaw (N,) float32 radians,
    counter-clockwise from east; size_lwh (N, 3) float32 metres; vtype (N,) int8; score (N,) float32;
    uv (N, 2) float32 the bottom centre in the camera's pixels (for drawing).
    `infer_ms` is carried over from Detections (latency accounting).
    """

    kind: ClassVar[str] = "objects"
    infer_ms: float = Field(ge=0, allow_inf_nan=False)
    xy: Array
    latlon: Array
    yaw: Array
    size_lwh: Array
    vtype: Array
    score: Array
    uv: Array

    @model_validator(mode="after")
    def _columns(self) -> Objects:
        _check_columns("Objects", {
            "xy": (self.xy, (2,), "f"), "latlon": (self.latlon, (2,), "f"), "yaw": (self.yaw, (), "f"),
            "size_lwh": (self.size_lwh, (3,), "f"), "vtype": (self.vtype, (), "iu"),
            "score": (self.score, (), "f"), "uv": (self.uv, (2,), "f")})
        return self

    def __len__(self) -> int:
        return len(self.score)


CHI2_2DOF_95 = 5.991  # chi-square with 2 degrees of freedom, 95th percentile: a 2D Gaussian's 95 % ellipse


COV_MIN_RELATIVE_DET = 1e-12  # a covariance's determinant must exceed this share of a*d (its diagonal's product)


def not_covariances(c: np.ndarray) -> np.ndarray:
    """(N, 2, 2) finite matrices -> (N,) bool: those that are not a covariance, symmetric (exactly: the project
    symmetrises what it computes) and positive definite. The one rule for Tracks, the fusion's objects and tracks
    files. Positive definite with a margin: the determinant a*d - b*b must be more than `COV_MIN_RELATIVE_DET` times
    a*d, so a matrix that is singular but for rounding (b*b rounds to just under a*d) is refused, and every one
    accepted has a Cholesky factor (the Rerun sink draws its ellipse with it). Computed in float64 (the products of
    float32 entries are exact there)."""
    c = np.asarray(c, np.float64)
    a, d, b = c[:, 0, 0], c[:, 1, 1], c[:, 0, 1]
    return (a <= 0) | (a * d * (1.0 - COV_MIN_RELATIVE_DET) <= b * c[:, 1, 0]) | (b != c[:, 1, 0])


def predict_motion(xy: np.ndarray, velocity: np.ndarray, xy_cov: np.ndarray, velocity_cov: np.ndarray, dt_s: float,
                   accel_std_mps2: float = PREDICT_ACCEL_STD_MPS2) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracked positions moved on by `dt_s` seconds at their velocities (m, m/s, (N, 2)), with their covariances
    grown to match: xy + v dt, xy_cov + dt^2 velocity_cov + (a dt^2 / 2)^2 I and velocity_cov + (a dt)^2 I, a the
    unknown acceleration's sigma (`accel_std_mps2`: braking, speeding up, the turn of a roundabout). Returns
    (xy, xy_cov, velocity_cov), float64. Tracks.predicted and docs/wire-format.md ("Where a vehicle is now")."""
    dt = float(dt_s)
    eye = np.eye(2)
    xy = np.asarray(xy, np.float64) + np.asarray(velocity, np.float64) * dt
    vel_cov = np.asarray(velocity_cov, np.float64)
    xy_cov = np.asarray(xy_cov, np.float64) + dt * dt * vel_cov + (accel_std_mps2 * dt * dt / 2) ** 2 * eye
    return xy, xy_cov, vel_cov + (accel_std_mps2 * dt) ** 2 * eye


def err95_m(xy_cov: np.ndarray) -> np.ndarray:
    """(..., 2, 2) position covariances (m^2) -> (...) the longest half-axis (m) of each one's 95 % ellipse: the
    true position lies within that ellipse with 95 % probability, and within this distance along its worst axis."""
    c = np.asarray(xy_cov, np.float64)
    mean, half = (c[..., 0, 0] + c[..., 1, 1]) / 2, (c[..., 0, 0] - c[..., 1, 1]) / 2
    return np.sqrt(CHI2_2DOF_95 * (mean + np.sqrt(half * half + c[..., 0, 1] * c[..., 1, 0])))


class Tracks(Message):
    """The tracked vehicles at event time `t_capture_ns` (the tick's capture time).

    id (N,) int64 unique per tracker instance; xy (N, 2) float64 m, site frame; latlon (N, 2) float64 deg;
    velocity (N, 2) float32 m/s (east, north); yaw (N,) float32 rad ENU; size_lwh (N, 3) float32 m;
    vtype (N,) int8; score (N,) float32; age (N,) int32 ticks since the track started; hits (N,) int32
    ticks with a measurement; cameras: per track, the cameras whose objects updated it this tick; xy_cov (N, 2, 2)
    float32 m^2: the covariance of the position's error (east, north), velocity_cov (N, 2, 2) float32 (m/s)^2 the
    velocity's, each symmetric positive definite; yaw_confirmed (N,) bool: whether the vehicle's own travel has
    confirmed which way it heads; yaw_std (N,) float32 rad > 0: the heading's error on its axis, 1 sigma (how far
    the axis may be off; front and back are yaw_confirmed's).
    An id that drops out and comes back within a few seconds where the lost track was heading is the same vehicle
    (fuse_track's `relink_s`). yaw: of a moving track, its direction of motion (from 4 m/s; drawn towards it from
    1.5 m/s); of a track that stopped, the heading it had; of a vehicle not seen travelling (yaw_confirmed false),
    the detector's, whose front and back may be reversed (read it as an axis).
    `frames`: (camera, seq, t_capture_ns, t_arrival_ns at fuse_track) of every frame whose objects went
    into this tick (latency accounting).
    """

    kind: ClassVar[str] = "tracks"
    tracker: str = ""  # the tracker instance's id: track ids are unique per instance
    id: Array
    xy: Array
    latlon: Array
    velocity: Array
    yaw: Array
    size_lwh: Array
    vtype: Array
    score: Array
    age: Array
    hits: Array
    cameras: list[Annotated[list[str], Field(max_length=64)]]
    xy_cov: Array
    velocity_cov: Array
    yaw_confirmed: Array
    yaw_std: Array
    frames: list[tuple[str, int, int, int]] = Field(default_factory=list, max_length=MAX_ROWS)

    @model_validator(mode="after")
    def _columns(self) -> Tracks:
        n = _check_columns("Tracks", {
            "id": (self.id, (), "iu"), "xy": (self.xy, (2,), "f"), "latlon": (self.latlon, (2,), "f"),
            "velocity": (self.velocity, (2,), "f"), "yaw": (self.yaw, (), "f"),
            "size_lwh": (self.size_lwh, (3,), "f"), "vtype": (self.vtype, (), "iu"),
            "score": (self.score, (), "f"), "age": (self.age, (), "iu"), "hits": (self.hits, (), "iu"),
            "xy_cov": (self.xy_cov, (2, 2), "f"), "velocity_cov": (self.velocity_cov, (2, 2), "f"),
            "yaw_confirmed": (self.yaw_confirmed, (), "b"), "yaw_std": (self.yaw_std, (), "f")})
        if len(self.cameras) != n:
            raise ValueError(f"Tracks.cameras has {len(self.cameras)} entries, expected {n}")
        for name in ("xy_cov", "velocity_cov"):
            bad = not_covariances(getattr(self, name))
            if bad.any():
                raise ValueError(f"Tracks.{name}[{int(np.flatnonzero(bad)[0])}] is not a symmetric positive definite "
                                 "covariance")
        if np.any(self.yaw_std <= 0):
            raise ValueError(f"Tracks.yaw_std[{int(np.flatnonzero(self.yaw_std <= 0)[0])}] is not > 0")
        return self

    def __len__(self) -> int:
        return len(self.id)

    def predicted(self, t_ns: int, accel_std_mps2: float = PREDICT_ACCEL_STD_MPS2) -> Tracks:
        """These tracks moved on to `t_ns` (ns, the capture times' clock: the cabinet's, which a vehicle shares
        through GNSS or PTP; within MAX_PREDICT_S of `t_capture_ns`, either way) at their velocities, their
        positions' and velocities' covariances grown as `predict_motion` says, latitude and longitude moved with
        them; `t_capture_ns` becomes `t_ns`, a "predict" stamp is added and the rest is kept (`frames` still
        says when the images were taken). A message reaches a vehicle tens of milliseconds after its capture, in
        which a vehicle at 50 km/h moves more than a metre: docs/wire-format.md, "Where a vehicle is now"."""
        if isinstance(t_ns, bool) or not isinstance(t_ns, int | np.integer):
            raise ValueError(f"t_ns must be an integer time in ns, got {t_ns!r}")
        dt = (int(t_ns) - self.t_capture_ns) / 1e9
        if not abs(dt) <= MAX_PREDICT_S:
            raise ValueError(f"tracks captured at {self.t_capture_ns} ns cannot be predicted to {int(t_ns)} ns: "
                             f"{dt:+.3f} s away, more than {MAX_PREDICT_S} s (is the clock the cabinet's?)")
        if not (isinstance(accel_std_mps2, int | float) and math.isfinite(accel_std_mps2) and accel_std_mps2 >= 0):
            raise ValueError(f"accel_std_mps2 must be a finite number >= 0, got {accel_std_mps2!r}")
        xy, xy_cov, vel_cov = predict_motion(self.xy, self.velocity, self.xy_cov, self.velocity_cov, dt,
                                             accel_std_mps2)
        lat, lon = offset_latlon(self.latlon[:, 0], self.latlon[:, 1], xy[:, 0] - self.xy[:, 0],
                                 xy[:, 1] - self.xy[:, 1])
        fields = {name: getattr(self, name) for name in type(self).model_fields}
        return Tracks(**{**fields, "t_capture_ns": int(t_ns), "stamps": self.stamped("predict"), "xy": xy,
                         "latlon": np.column_stack([lat, lon]).reshape(-1, 2), "xy_cov": xy_cov.astype(np.float32),
                         "velocity_cov": vel_cov.astype(np.float32)})  # symmetric as they were: the same sums

    @classmethod
    def from_record(cls, line: Mapping) -> Tracks:
        """The message a tracks-file line holds (fuse_track's recorder: site, seq, t_ns, tracker and `rows()`; no
        stamps); ValueError naming the first problem (a key missing, a value of the wrong kind or out of its column's
        range, a row off the contract, a file recorded before a field it needs: xy_cov, velocity_cov, yaw_confirmed
        and yaw_std came with schema version 3)."""
        if not isinstance(line, Mapping):
            raise ValueError(f"a tracks record must be a JSON object, got {type(line).__name__}")
        missing = [k for k in ("site", "seq", "t_ns", "tracker", "tracks") if k not in line]
        if missing:
            raise ValueError(f"tracks record without {', '.join(missing)}")
        rows = line["tracks"]
        if not isinstance(rows, list) or not all(isinstance(r, Mapping) for r in rows):
            raise ValueError("tracks record: 'tracks' must be a list of objects")
        for i, r in enumerate(rows):
            gone = [k for k in RECORD_KEYS if k not in r]
            if gone:
                raise ValueError(f"tracks record: track {i} has no {', '.join(gone)} (a file of an older schema "
                                 "version?)")
            if r["type"] not in VEHICLE_TYPES:
                raise ValueError(f"tracks record: track {i} has type {r['type']!r}, not one of {VEHICLE_TYPES}")

        def column(keys: tuple[str, ...], dtype) -> np.ndarray:
            values = [r[k] for r in rows for k in keys]
            integer = np.issubdtype(dtype, np.integer)
            if not all(isinstance(v, int | float) and not isinstance(v, bool) for v in values) or (
                    integer and not all(isinstance(v, int) for v in values)):
                raise ValueError(f"tracks record: {'/'.join(keys)} must be {'integers' if integer else 'numbers'}")
            out_of_range = f"tracks record: {'/'.join(keys)} out of the range of {np.dtype(dtype).name}"
            if integer and values and not (np.iinfo(dtype).min <= min(values) and max(values) <= np.iinfo(dtype).max):
                raise ValueError(out_of_range)
            try:
                return np.array(values, dtype).reshape(len(rows), len(keys))
            except OverflowError:  # an integer too large for a float (1e400 written without its exponent)
                raise ValueError(out_of_range) from None

        def matrices(key: str) -> np.ndarray:
            if not all(isinstance(m, list) and len(m) == 2 and all(
                    isinstance(row, list) and len(row) == 2 and all(
                        isinstance(v, int | float) and not isinstance(v, bool) for v in row) for row in m)
                       for m in (r[key] for r in rows)):
                raise ValueError(f"tracks record: {key} must be 2x2 matrices of numbers")
            try:
                return np.array([r[key] for r in rows], np.float32).reshape(len(rows), 2, 2)
            except OverflowError:  # an integer too large for a float
                raise ValueError(f"tracks record: {key} out of the range of float32") from None

        if not all(isinstance(r["cameras"], list) and all(isinstance(c, str) for c in r["cameras"]) for r in rows):
            raise ValueError("tracks record: cameras must be lists of names")
        if not all(isinstance(r["yaw_confirmed"], bool) for r in rows):
            raise ValueError("tracks record: yaw_confirmed must be true or false")
        return cls(site=line["site"], seq=line["seq"], t_capture_ns=line["t_ns"], tracker=line["tracker"],
                   id=column(("id",), np.int64)[:, 0],
                   xy=column(("x", "y"), np.float64), latlon=column(("lat", "lon"), np.float64),
                   velocity=column(("vx", "vy"), np.float32), yaw=column(("yaw",), np.float32)[:, 0],
                   size_lwh=column(("length", "width", "height"), np.float32),
                   vtype=np.array([VEHICLE_TYPES.index(r["type"]) for r in rows], np.int8),
                   score=column(("score",), np.float32)[:, 0], age=column(("age",), np.int32)[:, 0],
                   hits=column(("hits",), np.int32)[:, 0], cameras=[list(r["cameras"]) for r in rows],
                   xy_cov=matrices("xy_cov"), velocity_cov=matrices("velocity_cov"),
                   yaw_confirmed=np.array([r["yaw_confirmed"] for r in rows], bool),
                   yaw_std=column(("yaw_std",), np.float32)[:, 0])

    def rows(self) -> list[dict]:
        """One plain dict per track (JSON-friendly), as the recorder writes and clients print."""
        # whole columns to Python lists first: one conversion per column, not one per value
        def rounded(a: np.ndarray, digits: int) -> list:
            return np.round(a.astype(np.float64), digits).tolist()

        xy, vel, size = rounded(self.xy, 3), rounded(self.velocity, 3), rounded(self.size_lwh, 3)
        yaw, score = rounded(self.yaw, 4), rounded(self.score, 3)
        latlon = self.latlon.astype(np.float64).tolist()
        names = [VEHICLE_TYPES[t] if 0 <= t < len(VEHICLE_TYPES) else "unknown" for t in self.vtype.tolist()]
        cov, vcov, yaw_sd = rounded(self.xy_cov, 5), rounded(self.velocity_cov, 5), rounded(self.yaw_std, 5)
        return [{"id": i, "x": p[0], "y": p[1], "lat": ll[0], "lon": ll[1], "vx": v[0], "vy": v[1], "yaw": a,
                 "length": s[0], "width": s[1], "height": s[2], "type": t, "score": sc, "age": age, "hits": hits,
                 "cameras": list(cams), "xy_cov": c, "velocity_cov": vc, "yaw_confirmed": sure,
                 "yaw_std": sd}
                for i, p, ll, v, a, s, t, sc, age, hits, cams, c, vc, sure, sd in zip(
                    self.id.tolist(), xy, latlon, vel, yaw, size, names, score, self.age.tolist(), self.hits.tolist(),
                    self.cameras, cov, vcov, self.yaw_confirmed.tolist(), yaw_sd, strict=True)]


MAX_STATUS_ENTRIES = 300  # names in one of a Status message's maps (BadInput keeps at most 256 reasons, + 1)
StatusName = Annotated[str, Field(min_length=1, max_length=160)]
Count = Annotated[int, Field(ge=0, lt=INT64_END)]
Reading = Annotated[float, Field(allow_inf_nan=False)]


class Status(Message):
    """What one running service has done so far, published every `bus.status_period_s` (shared/status.py).

    `seq`: the report's number since the service started; `t_capture_ns`: when the report was taken (wall clock,
    ns). `service`: one of SERVICES; `instance`: which of them (e.g. fuse_track's tracker, or "main");
    `started_ns`: when the service started (wall clock). `counts`: messages by what they were, since the start
    (e.g. frames_in, detections_out); `rates`: the same per second over the last `period_s`; `bad`: messages
    dropped since the start, by reason (the reasons the service logs); `gauges`: readings of now (e.g. tracks
    held, mean inference ms over the period); `last_output_ns`: when the service last published its output (0:
    not yet); `cpu_s`: the process's CPU time; `rss_mb`: its resident memory now, `peak_rss_mb` its peak; `final`: the
    report of a service that is stopping."""

    kind: ClassVar[str] = "status"
    service: Literal[SERVICES]  # type: ignore[valid-type]
    instance: str
    started_ns: int = Field(ge=0, lt=T_CAPTURE_END)
    period_s: float = Field(gt=0, allow_inf_nan=False)
    counts: dict[StatusName, Count] = Field(default_factory=dict, max_length=MAX_STATUS_ENTRIES)
    rates: dict[StatusName, Annotated[float, Field(ge=0, allow_inf_nan=False)]] = Field(
        default_factory=dict, max_length=MAX_STATUS_ENTRIES)
    bad: dict[StatusName, Count] = Field(default_factory=dict, max_length=MAX_STATUS_ENTRIES)
    gauges: dict[StatusName, Reading] = Field(default_factory=dict, max_length=MAX_STATUS_ENTRIES)
    last_output_ns: int = Field(0, ge=0, lt=T_CAPTURE_END)
    cpu_s: float = Field(ge=0, allow_inf_nan=False)
    rss_mb: float = Field(ge=0, allow_inf_nan=False)
    peak_rss_mb: float = Field(ge=0, allow_inf_nan=False)
    final: bool = False

    @field_validator("instance")
    @classmethod
    def _instance(cls, v: str) -> str:
        return check_name("instance", v)


MESSAGE_TYPES: dict[str, type[Message]] = {m.kind: m for m in (Frame, Detections, Objects, Tracks, Status)}

