"""One typed settings object for every process: a site YAML file plus environment overrides.

The site folder (`deploy/sites/<site>/site.yaml`, see deploy/sites/README.md) names the site, its
cameras (kind, image size, lookup masks, source, optional fusion region), the bus and each service's
options. Any field can be overridden from the environment with the prefix `ROADSIDE_` and `__`
between levels, e.g. `ROADSIDE_BUS__MODE=client ROADSIDE_BUS__CONNECT='["tcp/zenoh:7447"]'` (the
compose file does this) or `ROADSIDE_DETECT__THREADS=4`. Relative paths in the file are relative to
the site folder.

Bus default: Zenoh peer-to-peer on loopback, multicast scouting off, explicit endpoints. Each service
listens on its own port (`port_base` + its index in SERVICES; clients such as `roadside tracks` use
`port_base` + 4 and up) and connects to the others, so any one of them can restart.

Precedence, lowest first: the defaults, the site file, the environment, the command line (`--set` and flags).
"""

from __future__ import annotations

import difflib
import ipaddress
import json
import os
import re
import types
import typing
from datetime import UTC, datetime, time
from pathlib import Path
from typing import Literal

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator, model_validator
from pydantic_settings import BaseSettings, EnvSettingsSource, SettingsConfigDict, SettingsError

from shared.keys import SERVICES
from shared.messages import check_name
from shared.position_error import POSITION_SIGMA, check_position_sigma

MAX_THREADS = 256  # ONNX Runtime threads per inference (DetectSettings, shared/inference.py)
ENDPOINT_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")
_HOST_PORT = re.compile(r"^(\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):(\d{1,5})$")
# a host name's label: letters, digits and '-' (RFC 1123), and '_', which Docker's service names may hold
_HOST_LABEL = re.compile(r"^[A-Za-z0-9_](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9_])?$")
MIN_STATUS_PERIOD_S = 0.1  # a shorter bus.status_period_s busy-loops an idle service's status reports


def check_endpoint(text: str) -> str:
    """A Zenoh endpoint `<protocol>/<address>[?metadata][#config]`, e.g. tcp/192.168.1.10:7447 (Zenoh's own error for
    a malformed one is a JSON5 parse error of its config); ValueError names the endpoint and what is wrong."""
    if not isinstance(text, str):
        raise ValueError(f"a Zenoh endpoint is text such as tcp/HOST:7447, got {text!r}")
    proto, sep, rest = text.partition("/")
    address = re.split(r"[?#]", rest, maxsplit=1)[0]
    if not sep or proto not in ENDPOINT_PROTOCOLS or not address:
        raise ValueError(f"not a Zenoh endpoint: {text!r} (expected PROTOCOL/ADDRESS such as tcp/192.168.1.10:7447; "
                         f"protocols: {', '.join(ENDPOINT_PROTOCOLS)})")
    if proto in ("tcp", "udp", "tls", "quic", "ws"):
        m = _HOST_PORT.match(address)
        if not m or int(m.group(2)) > 65535:
            raise ValueError(f"not a Zenoh endpoint: {text!r} ({proto} needs HOST:PORT, the port 0-65535)")
    return text


def check_host(text: str) -> str:
    """`bus.host`: an IPv4 or IPv6 address or a host name, without a port (each service's port is bus.port_base plus
    its index); ValueError names the value and what is wrong (load_settings puts the field's name before it)."""
    if not text.strip():
        raise ValueError(f"{text!r} is empty: give the address the services listen on, e.g. 127.0.0.1")
    if any(c.isspace() for c in text):
        raise ValueError(f"{text!r} holds a space: give one address or host name, e.g. 127.0.0.1")
    try:
        ipaddress.ip_address(text.removeprefix("[").removesuffix("]"))
        return text
    except ValueError:
        pass
    if _HOST_PORT.match(text):
        raise ValueError(f"{text!r} holds a port: give the address alone, e.g. 127.0.0.1 (each service's port is "
                         "bus.port_base plus its index)")
    labels = text.removesuffix(".").split(".")
    if len(text) > 253 or not all(_HOST_LABEL.match(label) for label in labels):
        raise ValueError(f"{text!r} is not an IP address or host name (letters, digits, '-' and '_' between dots, e.g. "
                         "127.0.0.1 or cabinet.local)")
    if labels[-1].isdigit():  # 192.168.1.300: no top-level domain is a number
        raise ValueError(f"{text!r} is not an IP address (four numbers 0-255) or host name")
    return text


class Strict(BaseModel):
    # no NaN or infinity in any number of a site file (an infinite heading step dropped every detection)
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    @model_validator(mode="before")
    @classmethod
    def _empty_path_is_none(cls, data: object) -> object:
        """An optional path given empty (`record_dir: ""` in a site file, `--set ingest.record_dir=""`) is none, not
        the current folder (pydantic reads "" as Path(".")). An empty environment variable is not given at all."""
        if not isinstance(data, dict):
            return data
        empty = [name for name, field in cls.model_fields.items()
                 if data.get(name) == "" and {Path, type(None)} <= set(typing.get_args(field.annotation))]
        return {**data, **dict.fromkeys(empty)} if empty else data


class BusSettings(Strict):
    mode: Literal["peer", "client"] = "peer"
    host: str = "127.0.0.1"  # peer mode: the address every service listens on
    port_base: int = Field(7451, ge=1024, le=65000)
    connect: list[str] = Field(default_factory=list)  # client mode: the router(s), e.g. tcp/zenoh:7447
    listen: list[str] = Field(default_factory=list)  # extra listen endpoints
    multicast_scouting: bool = False
    # Zenoh's shared-memory transport between processes of one host (its default since 1.x: a 16 MB pool mapped
    # in every process that sends messages over 3 kB). Off: the demo measured no latency gained by it and 27 MB more
    # resident in ingest and fuse_track (docs/pipeline.md); containers do not share /dev/shm by default anyway
    shared_memory: bool = False
    # every service publishes a Status report this often (`roadside status`, shared/status.py); 0 = never
    status_period_s: float = Field(2.0, ge=0, le=3600, allow_inf_nan=False)
    # Zenoh's send queue per link for data messages, in batches of up to 64 kB (Zenoh's default 2, its maximum 16).
    # A 640x480 frame goes out in about 5 fragments; with 2 batches a sender ahead of its link drops the fragments
    # that find the queue full (congestion control "drop", after waiting 1-50 ms), so whole frames were lost in
    # playback at full speed and the tracker waited for them (docs/pipeline.md). 16 batches: at most 1 MB per link;
    # the services' peak memory did not change measurably. deploy/zenoh/router.json5 sets the router's the same.
    tx_queue_batches: int = Field(16, ge=1, le=16)
    # the CA certificate (PEM) that the certificate of a tls/ endpoint this process connects to must chain to: a
    # vehicle reaching the cabinet over TLS knows it is the cabinet (deploy/sites/README.md); used as given, not
    # relative to the site folder
    tls_root_ca: Path | None = None
    # this process's own certificate and its private key (PEM), for a router that lets only the operator's enrolled
    # vehicles in (mutual TLS, deploy/sites/README.md); both or neither, used as given
    tls_certificate: Path | None = None
    tls_private_key: Path | None = None

    @field_validator("connect", "listen")
    @classmethod
    def _endpoints(cls, v: list[str]) -> list[str]:
        return [check_endpoint(e) for e in v]

    @field_validator("host")
    @classmethod
    def _host(cls, v: str) -> str:
        return check_host(v)

    @field_validator("status_period_s")
    @classmethod
    def _status_period(cls, v: float) -> float:
        if 0 < v < MIN_STATUS_PERIOD_S:
            raise ValueError(f"must be 0 (no status reports) or at least {MIN_STATUS_PERIOD_S} s, got {v}")
        return v

    @model_validator(mode="after")
    def _certificate_and_key(self) -> BusSettings:
        if (self.tls_certificate is None) != (self.tls_private_key is None):
            given, missing = (("tls_certificate", "tls_private_key") if self.tls_private_key is None
                              else ("tls_private_key", "tls_certificate"))
            raise ValueError(f"bus.{given} is given without bus.{missing}: mutual TLS needs both")
        return self

    def service_endpoint(self, service: str) -> str:
        return f"tcp/{self.host}:{self.port_base + SERVICES.index(service)}"


class CameraSettings(Strict):
    name: str
    kind: Literal["pinhole", "fisheye"]
    width: int = Field(gt=0, le=16384)  # a Frame carries at most 16384 x 16384
    height: int = Field(gt=0, le=16384)
    masks: Path | None = None  # lookup masks file (roadside calibrate)
    source: str | None = None  # this camera's own source (folder, video, URL) when not the site source
    region_m: list[tuple[float, float]] | None = None  # fusion region polygon, site metres; default: nearest camera
    # pixel polygons where localize drops detections: things the detector keeps mistaking for a vehicle (a painted
    # word, a lamp head), marked by the installer on the camera's image (deploy/sites/README.md)
    exclude_px: list[list[tuple[float, float]]] = []
    # the rectangle x0, y0, x1, y1 (full-resolution pixels) that the detector looks at, with 32 network pixels of
    # context around it (OnnxDetector.area_crop): a fisheye's image circle, so the black sides beside it cost no
    # inference (the simulated roundabout's cameras: 576x480 network input instead of 640x480); default the whole image
    detect_area_px: tuple[int, int, int, int] | None = None

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        return check_name("camera", v)

    @field_validator("region_m")
    @classmethod
    def _region(cls, v):
        if v is not None and len(v) < 3:
            raise ValueError(f"region_m needs at least 3 points, got {len(v)}")
        if v is not None:  # (NaN and infinity are refused before: allow_inf_nan)
            area = 0.5 * abs(sum(x0 * y1 - x1 * y0 for (x0, y0), (x1, y1) in zip(v, [*v[1:], v[0]], strict=True)))
            if area < 1.0:  # points on a line, or all in one place: nothing would ever be inside it
                raise ValueError(f"region_m encloses {area:.2g} m^2: its points lie on a line or on top of each other")
        return v

    @model_validator(mode="after")
    def _area(self) -> CameraSettings:
        if self.detect_area_px is not None:
            x0, y0, x1, y1 = self.detect_area_px
            if not (0 <= x0 < x1 <= self.width and 0 <= y0 < y1 <= self.height):
                raise ValueError(f"camera {self.name}: detect_area_px {list(self.detect_area_px)} must be x0 < x1, "
                                 f"y0 < y1 within the {self.width}x{self.height} image")
        return self

    @field_validator("exclude_px")
    @classmethod
    def _exclude(cls, v):
        for i, poly in enumerate(v):
            if len(poly) < 3:
                raise ValueError(f"exclude_px[{i}] needs at least 3 points, got {len(poly)}")
            if not all(abs(c) <= MAX_EXCLUDE_PX for pt in poly for c in pt):  # the filling's fixed point overflows
                raise ValueError(f"exclude_px[{i}] reaches beyond {MAX_EXCLUDE_PX} px: keep it near the image")
        return v


MAX_EXCLUDE_PX = 1_000_000  # polygon vertices further off the image are a typo (calibration/masks.py `excluded`)


class IngestSettings(Strict):
    source: str | None = None  # simulator recording, image-sequence folder, video file or stream URL
    pace: str = "1"  # "1" real time, "N" N x real time, "max": as fast as detect takes frames
    loop: bool = False
    encoding: Literal["jpeg", "gray8"] = "gray8"
    # each camera's JPEGs are decoded at the largest reduction (1/1, 1/2, 1/4: DCT-domain, cheap) that keeps the
    # longer side at least this long: the detector's input size (`input_long_side` in models/README.md)
    decode_long_side: int = Field(640, ge=32)
    fps: float | None = Field(None, ge=0.001, le=10000)  # capture times from a frame rate where the source has none
    max_frames: int | None = Field(None, gt=0)  # stop after this many frames per camera
    # pace "max": frames published but not yet detected (default: detect.workers, so that no worker idles)
    max_in_flight: int | None = Field(None, ge=1)
    # pace "max": seconds a frame's detections may take before ingest stops waiting for them (a detect restart
    # must not stall playback); a frame published after that may push an undetected one out of detect's ring
    ack_timeout_s: float = Field(2.0, gt=0)
    # liveliness tokens beyond the four services' that ingest waits for before it plays (up to 60 s), e.g. 1 for
    # a recorder that must see the first frame (the demo's collector declares one once it is linked to all four)
    wait_extra_peers: int = Field(0, ge=0)
    # the time zone of date-time file names (`2023-12-19 11-00-00-034395.jpg`): cameras and recorders name files in
    # their local time, and a capture time is UTC on the wire (an IANA name, e.g. America/Detroit). A name in the hour
    # that the autumn clock change repeats is ambiguous and taken in its first pass: name such files in UTC
    timezone: str = "UTC"
    # when the source ends: "exit" (status 0: `roadside up` ends the run) or "idle": stay up, publishing nothing more
    # and reporting status, until told to stop (compose.yaml: compose restarts a service that exits, and each restart
    # would play the source's last frames again, late for fuse_track)
    at_end: Literal["exit", "idle"] = "exit"
    # also write every frame published, at the source's full resolution and its capture time, to
    # RECORD_DIR/<camera>/<t_capture_ns>.jpg (.png, .bmp for such source files): a folder ingest plays back
    # (`roadside up --source RECORD_DIR`; services/ingest/recorder.py); relative to the site folder. Frames decoded
    # from a video or stream are written as JPEGs of record_jpeg_quality; frames that would not fit in
    # record_queue_mb (a disk slower than the cameras) are dropped and counted, and below record_min_free_mb of free
    # space recording pauses until space is freed
    record_dir: Path | None = None
    record_jpeg_quality: int = Field(92, ge=1, le=100)
    record_queue_mb: float = Field(24.0, gt=0, le=4096)  # counts towards ingest's memory
    record_min_free_mb: float = Field(1024.0, ge=0, le=1e9)
    # play only the recorded frames captured from play_from on and before play_until: ISO 8601 dates and times
    # (2023-12-19T11:00:40) or times of day (11:00:40: on the day of the source's first frame; for footage across
    # midnight or a clock change give date-times), in `timezone` unless they carry a UTC offset; the held-out slice of a
    # recording, an hour of a day's footage. With `loop` the slice repeats. Not for a video file, a stream or a folder
    # timed by `fps`, whose capture times are the clock's when they are played
    play_from: datetime | time | None = None
    play_until: datetime | time | None = None

    @field_validator("play_from", "play_until", mode="before")
    @classmethod
    def _moment(cls, v: object) -> object:
        if isinstance(v, int | float) and not isinstance(v, bool):  # YAML reads 11:00:40 unquoted as 39640
            raise ValueError(f"{v!r} is a number: give an ISO 8601 date and time (2023-12-19T11:00:40) or a time of "
                             "day (11:00:40), in quotes in YAML")
        return v

    @model_validator(mode="after")
    def _window(self) -> IngestSettings:
        a, b = self.play_from, self.play_until
        if a is not None and b is not None and type(a) is not type(b):
            raise ValueError(f"play_from {a} and play_until {b}: give both as date-times or both as times of day")
        if a is not None and b is not None:
            start, end = self.window_ns(0)
            if end <= start:
                raise ValueError(f"play_until {b} is not after play_from {a}")
        return self

    def window_ns(self, day_of_ns: int | None = None) -> tuple[int | None, int | None]:
        """(play_from, play_until) in ns since the epoch (None: open), times without an offset in `timezone`; a time
        of day on the day (in `timezone`) of `day_of_ns` (the source's first frame)."""
        tz = self.tzinfo()

        def ns(t: datetime | time | None) -> int | None:
            if t is None:
                return None
            if isinstance(t, time):
                if day_of_ns is None:
                    raise ValueError(f"ingest.play_from / play_until {t}: a time of day needs the day of a recorded "
                                     "source's first frame")
                day = datetime.fromtimestamp(day_of_ns / 1e9, t.tzinfo or tz).date()  # the day where the time is told
                t = datetime.combine(day, t)  # an offset it carries stays
            t = t if t.tzinfo is not None else t.replace(tzinfo=tz)
            return round(t.timestamp() * 1e6) * 1000

        return ns(self.play_from), ns(self.play_until)

    @field_validator("timezone")
    @classmethod
    def _timezone(cls, v: str) -> str:
        from zoneinfo import ZoneInfo, ZoneInfoNotFoundError

        if v == "UTC":  # the default needs no time-zone database
            return v
        try:
            ZoneInfo(v)
        except (ZoneInfoNotFoundError, ValueError):
            raise ValueError(f"unknown time zone {v!r}: an IANA name such as America/Detroit or Europe/Berlin, or "
                             "UTC") from None
        return v

    def tzinfo(self):
        """`timezone` as a tzinfo."""
        from zoneinfo import ZoneInfo

        return UTC if self.timezone == "UTC" else ZoneInfo(self.timezone)

    @field_validator("pace", mode="before")  # before: YAML and --set give `pace: 2` as a number
    @classmethod
    def _pace(cls, v: str | float) -> str:
        v = str(v).strip().lower()
        if v != "max":
            v = v.removesuffix("x")
            try:
                ok = 0.01 <= float(v) <= 1000  # also refuses nan and inf
            except ValueError:
                ok = False
            if not ok:
                raise ValueError(f"pace must be a speed factor from 0.01 to 1000 (1, 2.5, 10x) or 'max', got {v!r}")
        return v


class DetectSettings(Strict):
    model: Path = Path("models/detector_fp32.onnx")  # CPU model
    model_gpu: Path | None = Path("models/detector_fp16.onnx")  # used when a GPU provider is available
    providers: list[str] | None = None  # default: TensorRT -> CUDA -> CPU, what onnxruntime has
    # On a CPU, two single-threaded inferences side by side beat one two-threaded inference: 51.0 against 34.8
    # frames/s at 640x480 on the 2-core development machine (CPU 39 against 57 ms per frame: the threads of one
    # inference wait on each other), at ~37 against ~29 ms per frame. With a GPU provider one worker may do.
    workers: int = Field(2, ge=1, le=16)  # frames inferred at once
    threads: int = Field(1, ge=1, le=MAX_THREADS)  # ONNX Runtime threads per inference
    score_thr: float = Field(0.3, gt=0, lt=1)
    # frames kept waiting per camera; older ones are dropped. 1: a frame waits for at most one of each other
    # camera's, which live (pace 1, a detector slower than the cameras) measured 171 against 268 ms end to end p50
    # and MOTA 0.492 against 0.427 for 2 (frames two cycles old reach fuse_track after their tick has closed)
    ring: int = Field(1, ge=1, le=8)
    # ONNX Runtime's worker threads busy-wait between jobs by default: ~13 % more CPU per frame (measured 50 vs
    # 44 ms at 640x480, 2 threads) that the other services sharing the cabinet's cores then lack, for ~4 ms
    # less latency per frame. Off by default; turn on when detect has cores to itself (a GPU box).
    spin: bool = False
    # test-time flip: infer each frame and its left-right mirror as a batch of two and average the output maps
    # (shared/inference.py `mirror_average`): twice the inference for better placed, surer detections (docs/pipeline.md
    # "Mirror averaging"). For a GPU, or a CPU with cores to spare
    mirror: bool = False
    # a model with a vote head (training/model.py): a peak whose vote points far from it (a bus's near end) is read at
    # the vehicle's centre (shared/decode.py). Off by default: run 15 found the same near-pole buses with and without
    # it (validation recall 0.335 against 0.331) and scored 901 thermal ap50 0.804 against 0.890 (models/README.md)
    votes: bool = False


class LocalizeSettings(Strict):
    heading_step_px: float = Field(6.0, gt=0)  # pixels along the image heading for the yaw Jacobian
    # an object whose ground point lies inside a higher-scoring object's footprint (its length and width times
    # this) of the same frame is dropped as the same vehicle (services/localize/lift.py `footprint_groups`). 0: off.
    # 1.4 with the shipped model's calibrated sizes: the middle of a plateau over 1.35-1.45 on the validation
    # recordings, a cliff at 1.5 (1.5 before the calibration, itself 0.05 from the cliff; docs/pipeline.md)
    footprint_overlap: float = Field(1.4, ge=0)
    # True: the kept object also spans the peaks it suppresses that line up with it (a long vehicle's fragments; its
    # point moves to their middle, its length to theirs: lift.py `merge_along`). Off: with the shipped model it
    # tracked the same (validation MOTA 0.751 against 0.749 and 0.821 against 0.827 on a second one, the demo's 0.837
    # against 0.837; docs/pipeline.md)
    footprint_merge: bool = False


class FuseTrackSettings(Strict):
    # at most 1 s: a tick's objects lie within tick/2 of its time, and the tracker takes objects up to its
    # max_coast_s (1 s) from a tick's time
    tick_ms: float = Field(100.0, gt=0, le=1000.0)
    watermark_ms: float = Field(150.0, ge=0)  # event time a tick waits for late cameras
    max_wait_ms: float = Field(300.0, gt=0)  # wall time a tick waits after its first batch
    camera_timeout_ms: float = Field(1000.0, gt=0)  # wall time without frames before a camera is not waited for
    merge_gate_m: float = Field(3.0, gt=0)  # objects of two cameras this close are one vehicle
    # weight of an object outside its camera's region in a fused position, against 1 inside (a far view places a
    # vehicle worse; chosen over the validation recordings, docs/pipeline.md "Along and across the line of sight":
    # 0.5 with position_sigma, 0.1 without it)
    out_of_region_weight: float = Field(0.5, gt=0, le=1)
    # a fused position weighs each member by its error along and across the line from its camera, rows of
    # (range m, sigma along m, sigma across m) by range (shared/position_error.py); null: a scalar weighted mean
    position_sigma: tuple[tuple[float, float, float], ...] | None = POSITION_SIGMA
    # with position_sigma: a member with another object of its frame just in front of it (1-8 m nearer its camera,
    # within 4 m of the line from it) counts with its sigmas times this (services/fuse_track/fusion.py). 1: off
    crowded_sigma_factor: float = Field(2.0, ge=1, allow_inf_nan=False)
    occlusion_fallback: bool = False  # keep out-of-region objects nobody else saw (services/fuse_track/fusion.py)
    # without occlusion_fallback: such an object within this distance of its own camera may still extend a confirmed
    # track, never start one (a vehicle hidden from its region's camera keeps its track while a neighbour sees it;
    # chosen on the validation recording, docs/pipeline.md "Hidden from its own camera"). 0: dropped, the paper's rule
    extend_range_m: float = Field(50.0, ge=0)
    # a fused object's heading and size weigh each camera's by yaw_size_range_m^2 / (yaw_size_range_m^2 + r^2), r the
    # vehicle's distance from that camera: a detector's are the worse the farther (docs/pipeline.md, "Far headings and
    # sizes"). 0: off
    yaw_size_range_m: float = Field(20.0, ge=0)
    # a camera that delivered no frame for this long (event time, s) is down: the ground its region held goes to the
    # nearest camera that is up, whose objects there scoring at least handover_min_score start tracks, until it
    # delivers again (fusion.py, 5; chosen on the validation recordings: docs/pipeline.md, "A camera down"). 0: never
    handover_s: float = Field(1.0, ge=0)
    handover_min_score: float = Field(0.6, ge=0, le=1)
    # a fused object inside the footprint (length and width times long_footprint) of a longer fused object at least
    # long_vehicle_m long is dropped: another camera's peak on the same bus or truck (fusion.py, 6; 0 = off)
    long_vehicle_m: float = Field(7.0, ge=0, le=30)
    long_footprint: float = Field(1.4, gt=0, le=4)
    gate_m: float = Field(3.0, gt=0)  # largest track-to-measurement distance
    max_age_ticks: int = Field(3, ge=1)
    min_hits: int = Field(3, ge=1)
    # objects scoring at least this start tracks; lower ones (down to detect.score_thr) only extend confirmed
    # tracks left unmatched (ByteTrack's second round; services/fuse_track/tracker.py). 0: every object alike
    high_score: float = Field(0.0, ge=0, le=1)
    # with high_score: a lower-scoring object may start a track too, confirmed after this many consecutive ticks
    # (a parked or queued vehicle the detector is unsure of; static clutter goes in cameras[].exclude_px). 0: off
    standing_hits: int = Field(0, ge=0)
    # a track confirmed within relink_s of a confirmed track's loss takes its id when the lost track's motion brings
    # it within relink_gate_m (a vehicle lost for a moment keeps its identity; services/fuse_track/tracker.py). 0: off
    relink_s: float = Field(3.0, ge=0, le=30)
    relink_gate_m: float = Field(3.0, gt=0)
    # what each track reports of its position's error (Tracks.xy_cov; services/fuse_track/tracker.py): the share of a
    # measurement's error variance that persists from frame to frame (not averaged away by the filter), and the sigma
    # along the vehicle, as a share of its length, of where on its body the detector puts it. Chosen for the shipped
    # detector (docs/pipeline.md, "How sure a track is"); another detector may need its own
    bias_share: float = Field(0.6, ge=0, le=1)
    along_length_share: float = Field(0.07, ge=0, le=1)
    # a track's heading counts as confirmed (Tracks.yaw_confirmed) once it has travelled this far (m) from where it was
    # first seen, moving; a confirmed heading is turned round only by this long (s) of motion against it, not by a
    # standing vehicle's jittering detections (docs/pipeline.md, "Front or back")
    yaw_confirm_travel_m: float = Field(3.0, ge=0, le=100)
    yaw_reverse_s: float = Field(1.0, ge=0, le=30)
    # how far off (deg, 1 sigma, on its axis) the detector's heading of a vehicle is: what a standing track reports as
    # its heading's error (Tracks.yaw_std; a moving track's comes from its velocity's). Chosen for the shipped detector
    # (docs/pipeline.md, "How sure a heading is"); another detector may need its own
    yaw_std_deg: float = Field(14.0, gt=0, le=90)
    record: Path | None = None  # append every Tracks message to this JSON-lines file
    # at this size the recording is renamed <stem>.<n>.jsonl and a new one started (services/fuse_track/recorder.py);
    # 0: one file that grows for ever (about 4 MB a minute with the demo's four cameras)
    record_rotate_mb: float = Field(0.0, ge=0)
    record_keep: int = Field(0, ge=0)  # rotated files kept, the oldest deleted beyond it; 0: all

    @field_validator("position_sigma")
    @classmethod
    def _position_sigma(cls, v):
        return None if v is None else check_position_sigma(v)


class LegSettings(Strict):
    name: str = Field(min_length=1, max_length=64)
    bearing_deg: float = Field(ge=-360, le=360)  # from the junction's centre along the leg, from north, clockwise


class MovementSettings(Strict):
    """The junction whose turning movements `roadside counts` counts (shared/movements.py): its centre, its legs
    and the radii between which a vehicle is on a leg (inside inner_radius_m it is in the junction)."""

    center: dict[str, float]  # {lat_deg, lon_deg}
    legs: list[LegSettings] = Field(min_length=2, max_length=16)
    inner_radius_m: float = Field(gt=0, le=500)
    outer_radius_m: float = Field(gt=0, le=2000)
    half_width_deg: float = Field(35.0, gt=0, le=90)

    @model_validator(mode="after")
    def _junction(self) -> MovementSettings:
        if set(self.center) != {"lat_deg", "lon_deg"}:
            raise ValueError(f"movements.center needs lat_deg and lon_deg, got {sorted(self.center)}")
        self.junction()  # names what is wrong: radii, overlapping or duplicate legs, the centre
        return self

    def junction(self):
        from shared.movements import Junction

        return Junction(self.center["lat_deg"], self.center["lon_deg"],
                        tuple((leg.name, leg.bearing_deg) for leg in self.legs), self.inner_radius_m,
                        self.outer_radius_m, self.half_width_deg)


class Settings(BaseSettings):
    """Everything a process needs; build with `load_settings(path)`."""

    # an empty variable is not given (compose's `${RECORD_FRAMES:-}` when unset): the site file's value stands
    model_config = SettingsConfigDict(env_prefix="ROADSIDE_", env_nested_delimiter="__", extra="forbid",
                                      allow_inf_nan=False, env_ignore_empty=True)

    site: str
    site_dir: Path = Path(".")
    origin: dict[str, float] | None = None  # {lat_deg, lon_deg, alt_m} of the site frame
    cameras: list[CameraSettings]
    bus: BusSettings = BusSettings()
    ingest: IngestSettings = IngestSettings()
    detect: DetectSettings = DetectSettings()
    localize: LocalizeSettings = LocalizeSettings()
    fuse_track: FuseTrackSettings = FuseTrackSettings()
    movements: MovementSettings | None = None  # the junction's legs, for turning-movement counts
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"] = "INFO"

    @field_validator("log_level", mode="before")
    @classmethod
    def _log_level(cls, v: object) -> object:
        if not isinstance(v, str):
            return v
        v = v.upper()  # debug is DEBUG; logging's other names of two levels are theirs; anything else is refused
        return {"WARN": "WARNING", "FATAL": "CRITICAL"}.get(v, v)

    @field_validator("origin")
    @classmethod
    def _origin(cls, v: dict[str, float] | None) -> dict[str, float] | None:
        if v is None:
            return v
        if not {"lat_deg", "lon_deg"} <= set(v) <= {"lat_deg", "lon_deg", "alt_m"}:
            raise ValueError(f"origin needs lat_deg and lon_deg (and optionally alt_m), got {sorted(v)}")
        if abs(v["lat_deg"]) > 90 or abs(v["lon_deg"]) > 180:
            raise ValueError(f"origin must be a finite latitude (-90..90) and longitude (-180..180), got {v}")
        return v

    @classmethod
    def settings_customise_sources(cls, settings_cls, init_settings, env_settings, dotenv_settings,
                                   file_secret_settings):
        return (init_settings,)  # load_settings merges the file, the environment and the overrides, in that order

    @field_validator("site")
    @classmethod
    def _site(cls, v: str) -> str:
        return check_name("site", v)

    @field_validator("cameras")
    @classmethod
    def _cameras(cls, v: list[CameraSettings], info: ValidationInfo) -> list[CameraSettings]:
        names = [c.name for c in v]
        if not names:
            raise ValueError("at least one camera is needed")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"duplicate camera names {dup}")
        # a copied camera entry that keeps the other's masks lifts its detections with the other's lookup and puts
        # both cameras in one place (fuse_track's nearest-camera regions): refused, naming both. A file that is not
        # there is left to the services that read it (a missing file is their error; ingest reads none)
        site_dir = Path(info.data.get("site_dir") or ".")
        seen: dict[tuple[int, int], CameraSettings] = {}
        for cam in v:
            key = None if cam.masks is None else _file_id(site_dir / cam.masks.expanduser())
            if key is None:
                continue
            if key in seen:
                first = seen[key]
                same = cam.masks if cam.masks == first.masks else f"({first.masks} and {cam.masks})"
                raise ValueError(f"cameras {first.name} and {cam.name} name the same masks file {same}: each camera "
                                 "needs its own (roadside calibrate)")
            seen[key] = cam
        return v

    def path(self, p: Path | str | None) -> Path | None:
        """A path from the file, resolved against the site folder."""
        if p is None:
            return None
        p = Path(p).expanduser()
        return p if p.is_absolute() else (self.site_dir / p)

    def camera(self, name: str) -> CameraSettings:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(f"no camera {name!r} at site {self.site} (cameras: {[c.name for c in self.cameras]})")


def load_settings(path: str | Path, **overrides) -> Settings:
    """Read a site YAML file (or a site folder holding site.yaml), then the environment's ROADSIDE_ variables over
    it, then `overrides` (top-level keys, e.g. from command-line flags and `--set`) over both: a flag given on the
    command line wins over the container's environment. ValueError names the file and field."""
    path = Path(path)
    if path.is_dir():
        path = path / "site.yaml"
    if not path.is_file():
        raise ValueError(f"site file not found: {path}")
    try:
        loader = yaml.SafeLoader(path.read_text())
        try:  # composed once: its keys checked as written, then built
            document = loader.get_single_node()
            if document is not None:
                _check_keys_once(document)
            data = (loader.construct_document(document) if document is not None else None) or {}
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        raise ValueError(_yaml_error(path, exc)) from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a text file ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    odd = [k for k in data if not isinstance(k, str)]
    if odd:
        raise ValueError(f"{path}: top-level keys must be names, got {odd[0]!r}")
    data.setdefault("site_dir", str(path.parent.resolve()))
    unknown = unknown_environment()
    if unknown:
        raise ValueError(f"{path}: the environment: {', '.join(unknown)} {'is' if len(unknown) == 1 else 'are'} no "
                         "setting (ROADSIDE_<FIELD> or ROADSIDE_<SECTION>__<FIELD>, e.g. ROADSIDE_FUSE_TRACK__RECORD; "
                         "deploy/sites/README.md)")
    not_json = _environment_not_json()
    if not_json:
        raise ValueError(f"{path}: the environment: {not_json}")
    try:
        data = _deep_merge(data, EnvSettingsSource(Settings)())  # fields it does not name keep the file's values
    except SettingsError as exc:  # an environment variable that is not the JSON its field needs
        names = sorted(k for k in os.environ if k.upper().startswith("ROADSIDE_"))
        raise ValueError(f"{path}: the environment: {exc} (ROADSIDE_ variables set: {', '.join(names)})") from None
    for key, value in overrides.items():
        if value is None:
            continue
        if isinstance(value, dict):
            base = data.get(key) or {}
            if not isinstance(base, dict):
                raise ValueError(f"{path}: {key} is not a section of fields, cannot override {key}.{next(iter(value))}")
            data[key] = _deep_merge(base, value)  # as the environment is merged in
        else:
            data[key] = value
    try:
        return Settings(**data)
    except ValidationError as exc:
        raise ValueError(f"{path}: {_validation_errors(exc, data, overrides)}") from None


MAX_ERRORS = 10  # a site file's validation errors reported at once; the rest counted


def _validation_errors(exc: ValidationError, data: dict, overrides: dict) -> str:
    """Every mistake pydantic found in a site file, in one line joined by "; " (fixing them one run at a time took as
    many runs as mistakes): each as `location: pydantic's words`, with where the value came from (_given_by). An
    unknown key is named so, with the field it most likely misspells (`heigth`: did you mean height?), and that
    field's own "Field required" at the same place is then left out: the typo is the one mistake. A camera's
    mistakes keep its index in the location and add its name (`cameras.0.height: Field required (camera NE)`)."""
    errors = exc.errors()
    given_for: dict[tuple, str] = {}  # an unknown key's close match: its place -> the suggested field
    for e in errors:
        if e.get("type") == "extra_forbidden" and e.get("loc"):
            loc = tuple(e["loc"])
            close = _close_field(loc, data)
            if close:
                given_for[loc] = close
    suggested = {(*loc[:-1], close) for loc, close in given_for.items()}
    lines = []
    for e in errors:
        loc = tuple(e.get("loc", ()))
        if e.get("type") == "missing" and loc in suggested:
            continue  # said as the unknown key that misspells it
        parts = [str(p) for p in loc]
        where = f"{'.'.join(parts)}: " if parts else ""  # nothing for a rule over the whole file
        msg = str(e.get("msg")).removeprefix("Value error, ")  # pydantic's words for a validator's ValueError
        camera = _camera_name(loc, data)
        if e.get("type") == "extra_forbidden":
            msg += ": unknown field" + (f" of camera {camera}" if camera else "")
            msg += f" (did you mean {given_for[loc]}?)" if loc in given_for else ""
        elif camera:
            msg += f" (camera {camera})"
        lines.append(f"{where}{msg}{_given_by(parts, overrides)}")
    more = len(lines) - MAX_ERRORS
    return "; ".join(lines[:MAX_ERRORS] + ([f"and {more} more"] if more > 0 else []))


def _given_at(data: object, loc: tuple) -> object:
    """What the merged site data holds at pydantic's location `loc` (None where nothing is)."""
    for part in loc:
        if isinstance(data, dict):
            data = data.get(part)
        elif isinstance(data, list) and isinstance(part, int) and 0 <= part < len(data):
            data = data[part]
        else:
            return None
    return data


def _close_field(loc: tuple, data: dict) -> str | None:
    """The field of the section at loc[:-1] that the unknown key loc[-1] most likely misspells, None when none is
    close (fields already given there are no candidates)."""
    model: type[BaseModel] | None = Settings
    for part in loc[:-1]:
        if isinstance(part, int):  # an item of a list of sections (cameras, movements.legs)
            continue
        field = model.model_fields.get(part) if model is not None else None
        model = _section_model(field.annotation) if field is not None else None
        if model is None:
            return None
    given = _given_at(data, loc[:-1])
    taken = set(given) if isinstance(given, dict) else set()
    fields = [f for f in model.model_fields if f not in taken and f != "site_dir"]
    close = difflib.get_close_matches(str(loc[-1]), fields, n=1)
    return close[0] if close else None


def _camera_name(loc: tuple, data: dict) -> str | None:
    """The name of the camera a location inside `cameras` is in (cameras.0.height: NE), None outside a camera, for
    a camera without a name, or where the name itself is the mistake (its message quotes it)."""
    if len(loc) < 2 or loc[0] != "cameras" or not isinstance(loc[1], int) or loc[2:3] == ("name",):
        return None
    name = _given_at(data, (*loc[:2], "name"))
    return name if isinstance(name, str) and name else None


def _file_id(path: Path) -> tuple[int, int] | None:
    """The device and inode of the file at `path` (the same for a link to it or another spelling of its path), or
    None where there is none."""
    try:
        st = path.stat()
    except (OSError, ValueError):
        return None
    return (st.st_dev, st.st_ino) if path.is_file() else None


class DuplicateKeyError(yaml.YAMLError):
    """A key given twice in one mapping of a site file, with the marks of both."""

    def __init__(self, key, first_mark, mark) -> None:
        super().__init__(f"{key} is given twice (first at line {first_mark.line + 1})")
        self.key, self.first_mark, self.mark = key, first_mark, mark


def _check_keys_once(node: yaml.Node, done: set[int] | None = None) -> None:
    """DuplicateKeyError for a key given twice in one mapping of a composed YAML document (PyYAML keeps the last: a
    section appended at the end of a site file silently replaced the whole earlier one). Checked on the nodes as
    written, before PyYAML's merges rewrite them: keys a merge (`<<: *base`) brings in may be given again, at any
    depth, as a merge is for. Keys compare by their resolved tag and text (1 and '1' are two keys)."""
    done = set() if done is None else done
    if id(node) in done:  # an alias: checked where its anchor stands
        return
    done.add(id(node))
    if isinstance(node, yaml.MappingNode):
        seen: dict = {}
        for key_node, value_node in node.value:
            if key_node.tag != "tag:yaml.org,2002:merge" and isinstance(key_node, yaml.ScalarNode):
                first = seen.setdefault((key_node.tag, key_node.value), key_node)
                if first is not key_node:
                    raise DuplicateKeyError(key_node.value, first.start_mark, key_node.start_mark)
            _check_keys_once(key_node, done)
            _check_keys_once(value_node, done)
    elif isinstance(node, yaml.SequenceNode):
        for item in node.value:
            _check_keys_once(item, done)


def _yaml_error(path: Path, exc: yaml.YAMLError) -> str:
    """One line for a site file PyYAML cannot read: the file, the line and column, the problem (PyYAML's own
    message spans five lines and names no file)."""
    if isinstance(exc, DuplicateKeyError):
        return f"{path}: line {exc.mark.line + 1}: {exc}"
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or getattr(exc, "context", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    if context and problem != context and not context.startswith("while "):  # "expected a single document ..."
        problem = f"{context}, {problem}"
    where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
    hint = " (a tab cannot indent YAML: use spaces)" if "'\\t'" in problem else ""
    return f"{path}: not valid YAML{where}: {problem}{hint}"


def _environment_not_json() -> str | None:
    """The first ROADSIDE_ variable for a list, a mapping or a section whose value is not JSON, with an example of
    what it needs (pydantic-settings' own error names the section, not the variable, and not that it must be JSON)."""
    for name in sorted(os.environ):
        if not name.upper().startswith("ROADSIDE_"):
            continue
        value, annotation, model = os.environ[name], None, Settings
        if value == "":  # not given (Settings' env_ignore_empty)
            continue
        for part in name[len("ROADSIDE_"):].lower().split("__"):
            field = model.model_fields.get(part) if model is not None else None
            if field is None:  # an unknown name (unknown_environment), or one inside a list or a mapping
                annotation = None
                break
            annotation = field.annotation
            model = _section_model(annotation)
        kind = _json_kind(annotation)
        if kind is None:
            continue
        try:
            json.loads(value)
        except ValueError:
            if kind == "list of text":
                example = json.dumps([v.strip() for v in value.split(",")] if value.strip() else [])
            elif kind == "list":
                example = "[...]"
            else:
                example = '{"%s": ...}' % (next(iter(model.model_fields)) if model is not None else "KEY")
            what = "an object" if kind == "mapping" else "a list"
            return f"{name} must be JSON ({what}), e.g. {name}='{example}'; got {value!r}"
    return None


def _json_kind(annotation) -> str | None:
    """"list of text", "list" or "mapping" for a field that the environment must give as JSON, else None."""
    if annotation is None:
        return None
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    kinds = set()
    for t in [a for a in typing.get_args(annotation) if a is not type(None)] if union else [annotation]:
        origin = typing.get_origin(t) or t
        if origin in (list, tuple, set, frozenset):
            kinds.add("list of text" if typing.get_args(t) in ((str,), (str, ...)) else "list")
        elif origin is dict or (isinstance(origin, type) and issubclass(origin, BaseModel)):
            kinds.add("mapping")
        else:
            return None  # a plain value is one of its choices: pydantic-settings takes the text as it is
    return kinds.pop() if len(kinds) == 1 else None


def _deep_merge(base: dict, over: dict) -> dict:
    """`base` with `over`'s values put in, mappings merged key by key (a list or a value replaces)."""
    out = dict(base)
    for key, value in over.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def _section_model(annotation) -> type[BaseModel] | None:
    """The settings section a field's annotation holds (`BusSettings`, `MovementSettings | None`), None for a plain
    value (unknown_environment and _environment_not_json both walk the `__` paths of ROADSIDE_ variables with it)."""
    models = [t for t in (annotation, *typing.get_args(annotation)) if isinstance(t, type) and issubclass(t, BaseModel)]
    return models[0] if models else None


def unknown_environment() -> list[str]:
    """The ROADSIDE_ environment variables that name no setting (a misspelt one would be ignored: a cabinet's
    recording silently off): the part after the prefix must be a field, and after a section's `__` one of its."""

    bad = []
    for name in sorted(os.environ):
        if not name.upper().startswith("ROADSIDE_"):
            continue
        parts = name[len("ROADSIDE_"):].lower().split("__")
        field = Settings.model_fields.get(parts[0])
        if field is None or parts[0] == "site_dir":
            bad.append(name)
            continue
        if len(parts) > 1:
            types = (field.annotation, *typing.get_args(field.annotation))
            if any(typing.get_origin(t) is dict for t in types):
                continue  # a mapping (origin: ROADSIDE_ORIGIN__ALT_M) takes any key
            model = _section_model(field.annotation)
            if model is None or parts[1] not in model.model_fields:
                bad.append(name)
    return bad


def _given_by(loc: list[str], overrides: dict) -> str:
    """Where a bad value came from when not from the site file: an override (`--set section.field=...`, a
    command-line flag, which wins over the rest) or an environment variable (ROADSIDE_SECTION__FIELD, which wins
    over the file)."""
    if not loc:  # a rule over the whole file
        return ""
    node: object = overrides
    for part in loc:
        if not isinstance(node, dict) or part not in node:
            break
        node = node[part]
    else:
        return " (given on the command line: --set or a flag)"
    for n in range(len(loc), 0, -1):
        name = "ROADSIDE_" + "__".join(loc[:n]).upper()
        if any(k.upper() == name for k in os.environ):
            return f" (given by the environment: {name})"
    return ""


def env_overrides() -> dict[str, str]:
    """The ROADSIDE_* variables in effect (for logging what overrode the file)."""
    return {k: v for k, v in os.environ.items() if k.startswith("ROADSIDE_")}
