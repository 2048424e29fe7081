"""The tracks file (JSON lines, one Tracks message per line, as fuse_track's recorder writes it) parsed
and validated for its readers (the Rerun sink, training.track_labels): see services/rerun_sink/sink.py for the
format."""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from shared.geo import GeoFrame
from shared.messages import not_covariances

REPLAYED_NS = 5 * 10**9  # a message of the same tracker this much older than the last one: a recording played again

_REQUIRED_ROW = ("id", "yaw", "length", "width")
_OPTIONAL_NUMBERS = ("lat", "lon", "vx", "vy", "height", "score", "age", "hits")


@dataclass(frozen=True)
class TrackRow:
    """One validated track of a Tracks message. x, y metres (site ENU frame); yaw rad (CCW from east);
    length, width metres; vx, vy m/s (None when the row has none); xy_cov the position's error covariance,
    ((east², east·north), (north·east, north²)) m² (None when the row has none); yaw_confirmed whether the track's
    travel confirmed which way it heads, yaw_std rad the heading's error on its axis, 1 sigma (each None when the
    row does not say)."""

    id: int
    x: float
    y: float
    yaw: float
    length: float
    width: float
    type: str
    vx: float | None = None
    vy: float | None = None
    xy_cov: tuple[tuple[float, float], tuple[float, float]] | None = None
    yaw_confirmed: bool | None = None
    yaw_std: float | None = None


@dataclass(frozen=True)
class TracksMessage:
    """One validated Tracks message: capture time `t_ns` (ns since epoch), its rows."""

    site: str
    seq: int
    t_ns: int
    tracker: str
    rows: tuple[TrackRow, ...]


def parse_tracks_message(obj: Any, origin: GeoFrame | None = None) -> TracksMessage:
    """A Tracks-like dict (a tracks-file line, parsed) or a `shared.messages.Tracks` -> TracksMessage.

    Raises ValueError naming the first problem (missing key, wrong type, NaN, ...)."""
    if hasattr(obj, "rows") and hasattr(obj, "t_capture_ns"):  # a shared.messages.Tracks
        obj = {"site": obj.site, "seq": obj.seq, "t_ns": obj.t_capture_ns, "tracker": obj.tracker, "tracks": obj.rows()}
    if not isinstance(obj, Mapping):
        raise ValueError(f"expected a JSON object, got {type(obj).__name__}")
    for key in ("site", "tracks"):
        if key not in obj:
            raise ValueError(f"missing key {key!r}")
    t_key = "t_ns" if "t_ns" in obj else "t_capture_ns"
    if t_key not in obj:
        raise ValueError("missing key 't_ns'")
    site = obj["site"]
    if not isinstance(site, str):
        raise ValueError(f"'site' must be a string, got {site!r}")
    t_ns = _int(obj[t_key], t_key)
    if not 0 <= t_ns < 2**63:
        raise ValueError(f"{t_key!r} must be >= 0 and < 2**63 (ns since the epoch), got {t_ns}")
    seq = _int(obj.get("seq", 0), "seq")
    tracker = obj.get("tracker", "")
    if not isinstance(tracker, str):
        raise ValueError(f"'tracker' must be a string, got {tracker!r}")
    tracks = obj["tracks"]
    if not isinstance(tracks, list):
        raise ValueError(f"'tracks' must be a list, got {type(tracks).__name__}")
    rows = []
    for i, row in enumerate(tracks):
        try:
            rows.append(_parse_row(row, origin))
        except ValueError as e:
            raise ValueError(f"track {i}: {e}") from None
    return TracksMessage(site=site, seq=seq, t_ns=t_ns, tracker=tracker, rows=tuple(rows))


def _parse_row(row: Any, origin: GeoFrame | None) -> TrackRow:
    if not isinstance(row, Mapping):
        raise ValueError(f"expected an object, got {type(row).__name__}")
    for key in _REQUIRED_ROW:
        if key not in row:
            raise ValueError(f"missing key {key!r}")
    for key in _OPTIONAL_NUMBERS:
        if row.get(key) is not None:
            _float(row[key], key)
    if "x" in row and "y" in row:
        x, y = _float(row["x"], "x"), _float(row["y"], "y")
    elif row.get("lat") is not None and row.get("lon") is not None and origin is not None:
        x, y = (float(v) for v in origin.to_enu(np.array([row["lat"]]), np.array([row["lon"]]))[0, :2])
    else:
        raise ValueError("missing key 'x'" if "x" not in row else "missing key 'y'")
    length, width = _float(row["length"], "length"), _float(row["width"], "width")
    if length < 0 or width < 0:
        raise ValueError(f"length and width must be >= 0, got {length}, {width}")
    vtype = row.get("type", "unknown")
    if not isinstance(vtype, str):
        raise ValueError(f"'type' must be a string, got {vtype!r}")
    has_v = row.get("vx") is not None and row.get("vy") is not None
    return TrackRow(
        id=_int(row["id"], "id"),
        x=x,
        y=y,
        yaw=_float(row["yaw"], "yaw"),
        length=length,
        width=width,
        type=vtype,
        vx=float(row["vx"]) if has_v else None,
        vy=float(row["vy"]) if has_v else None,
        xy_cov=parse_covariance(row.get("xy_cov")),
        yaw_confirmed=parse_yaw_confirmed(row.get("yaw_confirmed")),
        yaw_std=parse_yaw_std(row.get("yaw_std")),
    )


def parse_covariance(value: Any, where: str = "",
                     name: str = "xy_cov") -> tuple[tuple[float, float], tuple[float, float]] | None:
    """A track row's `xy_cov` ([[a, b], [b, c]], m^2; Tracks.rows()), or another 2 x 2 covariance of it (`name`, e.g.
    `velocity_cov`), validated; None when the row has none. ValueError (prefixed with `where`, naming `name`) unless it
    is a symmetric positive definite 2 x 2 matrix of finite numbers."""
    if value is None:
        return None
    prefix = f"{where}: " if where else ""
    if not (isinstance(value, list | tuple) and len(value) == 2
            and all(isinstance(r, list | tuple) and len(r) == 2 for r in value)
            and all(isinstance(v, int | float) and not isinstance(v, bool) and _finite(v) for r in value for v in r)):
        raise ValueError(f"{prefix}{name} must be [[a, b], [b, c]] of finite numbers, got {value!r:.80}")
    if not_covariances(np.array(value, np.float64)[None])[0]:
        raise ValueError(f"{prefix}{name} {value} is not a symmetric positive definite covariance")
    (a, b), (c, d) = value
    return (float(a), float(b)), (float(c), float(d))


def parse_yaw_confirmed(value: Any, where: str = "") -> bool | None:
    """A track row's `yaw_confirmed` (true or false; None when the row has none). ValueError (prefixed with
    `where`) otherwise."""
    if value is not None and not isinstance(value, bool):
        raise ValueError(f"{where + ': ' if where else ''}yaw_confirmed must be true or false, got {value!r:.40}")
    return value


def parse_yaw_std(value: Any, where: str = "") -> float | None:
    """A track row's `yaw_std` (rad, a finite number > 0; None when the row has none). ValueError (prefixed with
    `where`) otherwise."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float) or not (_finite(value) and value > 0):
        raise ValueError(f"{where + ': ' if where else ''}yaw_std must be a finite number > 0 (rad), got {value!r:.40}")
    return float(value)


def _finite(v: int | float) -> bool:
    """Whether a number is finite as a float: an integer too large for one (1e400 written without its exponent) is
    not (math.isfinite raises OverflowError for it)."""
    try:
        return math.isfinite(v)
    except OverflowError:
        return False


def _float(v: Any, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{key!r} must be a number, got {v!r}")
    try:
        f = float(v)
    except OverflowError:  # an integer too large for a float
        raise ValueError(f"{key!r} is an integer too large for a float") from None
    if not math.isfinite(f):
        raise ValueError(f"{key!r} is {f}")
    return f


def _int(v: Any, key: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{key!r} must be an integer, got {v!r}")
    try:
        whole = float(v).is_integer()
    except OverflowError:  # an integer too large for a float
        raise ValueError(f"{key!r} is an integer too large for a float") from None
    if not whole:
        raise ValueError(f"{key!r} must be an integer, got {v!r}")
    return int(v)


def file_lines(path: Path) -> Iterator[tuple[str, str]]:
    """("file:line", text) of a tracks file's lines that are not blank, streamed (a cabinet's files run to hundreds of
    megabytes); bytes that are not UTF-8 are replaced, so they fail as bad JSON. ValueError for a file that cannot be
    opened."""
    try:
        handle = open(path, encoding="utf-8", errors="replace")  # closed by the with below: lines are streamed
    except OSError as exc:
        raise ValueError(f"tracks file {path}: {exc.strerror or exc}") from None
    with handle:
        for n, line in enumerate(handle, 1):
            if line.strip():
                yield f"{path}:{n}", line
