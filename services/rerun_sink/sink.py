"""Log Tracks messages (and optionally camera frames with detections) to an explicit Rerun recording.

View layout (the blueprint `TrackSink.blueprint()` builds):

- **site view**, a 3D view of entity `world`, looked at from straight above (north up, east right). The
  3D view is used so that coordinates stay the site ENU frame as they are (x east, y north, z up, metres;
  hovering shows true site metres). A 2D view would need y flipped, because Rerun's 2D views have y down.
  The basemap is a textured sheet at z = 0, and tracks are drawn a little above it. Each tracker's
  tracks are batched in one entity per kind (one log call per message, not per track):
    - `world/basemap`                     Mesh3D, the orthophoto / rendered map (static)
    - `world/tracks/<tracker>/trails`     LineStrips3D, one strip per track: its last positions (bounded)
    - `world/tracks/<tracker>/positions`  Points3D, one point per track, labelled "<id> <type>"
    - `world/tracks/<tracker>/footprints` LineStrips3D, per track the oriented length x width rectangle
      (closed) and, where the track's travel confirmed which way it heads (`yaw_confirmed`; a row without the key
      counts as confirmed), a segment from the centre to the front
    - `world/tracks/<tracker>/uncertainty` LineStrips3D, per track that carries `xy_cov` the ellipse that holds
      its true position with 95 % probability (docs/wire-format.md, "Position uncertainty")
    - `world/tracks/<tracker>/heading` LineStrips3D, per track that carries `yaw_std` a fan from its centre over
      its heading +- 1.96 sigma (the 95 % interval, at most +- 90 deg), reaching `HEADING_REACH_M` beyond its
      front; where its heading is not confirmed (`yaw_confirmed` false) the fan is drawn behind it too, as the
      vehicle may face either way
    - `world/junction`                    LineStrips3D, when the site's junction is given (site.yaml's `movements:`,
      shared/movements.py) and the origin places it: the junction's inner circle and each leg's sector between the
      two radii, labelled with the leg's name (static): where `roadside counts` takes a vehicle to be
  Every track has its own colour, from a stable hash of (tracker, id), and the label "<id> <type>" on all
  three (shown on the point, on hover for the lines). Each message replaces its tracker's drawings, so a
  track that ended leaves the view at the next message but stays in the recording (scrub back to see it); a
  message of another tracker (fuse_track restarted) clears the one before's drawings.
- **plots**: `plots/speed/<tracker>/<id>` (m/s, one series per track, in the track's colour) and
  `plots/tracks/<tracker>` (tracks per message).
- **cameras** (only when frames are logged): `cameras/<name>/image`, `.../boxes` (2D boxes),
  `.../bottom` (bottom centres), each in a 2D view of its own.

Time: the timeline `capture` (a timestamp): a message's `t_ns`, the capture time of its frames.

A tracks file is JSON lines, one Tracks message per line, as `Tracks.rows()` gives it::

    {"site": str, "seq": int, "t_ns": int, "tracker": str,
     "tracks": [{"id", "x", "y", "lat", "lon", "vx", "vy", "yaw", "length", "width", "height", "type",
                 "score", "age", "hits", "cameras", "xy_cov", "yaw_confirmed", "yaw_std"}, ...]}

x, y: metres, site ENU frame; yaw: radians, counter-clockwise from east; length, width, height: metres;
vx, vy: m/s; xy_cov (optional): [[a, b], [b, c]] m^2; yaw_confirmed (optional): true or false; yaw_std (optional):
rad > 0. `t_capture_ns` is accepted for `t_ns`. A row without x, y but with lat, lon is placed
with the site origin, when one is given. Lines that are not such messages (bad JSON, missing keys, NaN or infinite
numbers, a covariance that is none, another site) are skipped and counted.
"""

from __future__ import annotations

import colorsys
import json
import logging
import math
import zlib
from collections import deque
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from shared.geo import GeoFrame
from shared.messages import CHI2_2DOF_95, check_name
from shared.movements import Junction
from shared.tracks_file import REPLAYED_NS, TrackRow, TracksMessage, _int, parse_tracks_message

from .basemap import Basemap

log = logging.getLogger(__name__)

TIMELINE = "capture"
WORLD = "world"
Z_TRAIL_M = 0.05  # heights above the basemap (z = 0) so the drawings are not hidden in it
Z_FOOTPRINT_M = 0.10
Z_POSITION_M = 0.15
Z_JUNCTION_M = 0.02
JUNCTION_COLOR = (235, 235, 235)
HEADING_REACH_M = 2.0  # how far beyond a track's front its heading fan reaches
def track_color(tracker: str, track_id: int) -> tuple[int, int, int]:
    """A stable RGB colour for (tracker, id): the same in every run (crc32, not Python's salted hash)."""
    h = zlib.crc32(f"{tracker}/{track_id}".encode())
    hue = (h * 0.618033988749895) % 1.0
    sat = 0.65 + 0.3 * ((h >> 8) & 0xFF) / 255.0
    r, g, b = colorsys.hsv_to_rgb(hue, sat, 0.95)
    return round(r * 255), round(g * 255), round(b * 255)


def footprints_xy(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray) -> np.ndarray:
    """(N,) centres (m, site frame), yaw (rad, CCW from east), length, width (m) -> (N, 5, 2) float64 metres:
    each oriented rectangle front-left, front-right, rear-right, rear-left, front-left (closed)."""
    f = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1) * (np.asarray(length) / 2)[:, None]
    left = np.stack([-np.sin(yaw), np.cos(yaw)], axis=-1) * (np.asarray(width) / 2)[:, None]
    c = np.stack([x, y], axis=-1)
    return np.stack([c + f + left, c + f - left, c - f - left, c - f + left, c + f + left], axis=1)


def footprint_strips(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray,
                     nose: np.ndarray) -> tuple[list[np.ndarray], np.ndarray]:
    """The footprints' line strips (each (k, 2) metres): every track's rectangle (`footprints_xy`), then a segment
    from the centre to the front of the tracks where `nose` (N,) bool is set; and for each strip the index of its
    track (for its colour and label)."""
    rect = footprints_xy(x, y, yaw, length, width)  # (N, 5, 2)
    front = np.flatnonzero(nose)
    noses = np.stack([np.column_stack([x, y])[front], (rect[front, 0] + rect[front, 1]) / 2], axis=1)  # (M, 2, 2)
    return [*rect, *noses], np.concatenate([np.arange(len(x)), front])


def heading_fans(x: np.ndarray, y: np.ndarray, yaw: np.ndarray, reach: np.ndarray, yaw_std: np.ndarray,
                 both: np.ndarray, points: int = 9) -> tuple[list[np.ndarray], np.ndarray]:
    """The heading fans' line strips (each (points + 2, 2) metres, closed): from each centre out to `reach` (N,)
    metres over yaw +- 1.96 `yaw_std` (rad; capped at +- 90 deg) and back, and a second fan behind the tracks where
    `both` (N,) bool is set; and for each strip the index of its track."""
    half = np.minimum(1.96 * np.asarray(yaw_std, np.float64), math.pi / 2)
    owner = np.concatenate([np.arange(len(x)), np.flatnonzero(both)])
    heading = np.concatenate([yaw, np.asarray(yaw)[owner[len(x):]] + math.pi])
    a = heading[:, None] + half[owner][:, None] * np.linspace(-1.0, 1.0, points)[None, :]  # (M, P)
    centre = np.column_stack([x, y])[owner]  # (M, 2)
    arc = centre[:, None, :] + np.asarray(reach)[owner][:, None, None] * np.stack([np.cos(a), np.sin(a)], axis=-1)
    return [np.vstack([c, r, c]) for c, r in zip(centre, arc, strict=True)], owner


def ellipses_xy(x: np.ndarray, y: np.ndarray, cov: np.ndarray, points: int = 32) -> np.ndarray:
    """(N,) centres (m, site frame) and (N, 2, 2) position covariances (m^2) -> (N, points + 1, 2) float64 metres:
    each one's 95 % ellipse (d' C^-1 d = 5.991), closed."""
    a = np.linspace(0.0, 2 * np.pi, points + 1)
    circle = np.stack([np.cos(a), np.sin(a)], axis=1) * math.sqrt(CHI2_2DOF_95)  # (P, 2)
    root = np.linalg.cholesky(np.asarray(cov, np.float64))  # C = L L': the unit circle through L is the ellipse
    return np.stack([x, y], axis=-1)[:, None, :] + np.einsum("nij,pj->npi", root, circle)


@dataclass
class _TrackState:
    color: tuple[int, int, int]
    trail: deque  # of (x, y) metres, decimated to >= trail_min_step_m apart
    last_t_ns: int
    speed_t_ns: list[int] = field(default_factory=list)  # speeds not yet sent (capture ns, m/s)
    speed_mps: list[float] = field(default_factory=list)


@dataclass
class _Span:
    t_first_ns: int | None = None
    t_last_ns: int | None = None
    bounds: list[float] = field(default_factory=lambda: [math.inf, -math.inf, math.inf, -math.inf])

    def add(self, t_ns: int, x: np.ndarray, y: np.ndarray) -> None:
        self.t_first_ns = t_ns if self.t_first_ns is None else min(self.t_first_ns, t_ns)
        self.t_last_ns = t_ns if self.t_last_ns is None else max(self.t_last_ns, t_ns)
        if len(x):
            b = self.bounds
            b[:] = [min(b[0], x.min()), max(b[1], x.max()), min(b[2], y.min()), max(b[3], y.max())]


class TrackSink:
    """Logs Tracks messages to `recording` (an explicit `rr.RecordingStream`; nothing global is touched).

    Constructing it logs the static scene: the world's axes (ENU, z up), the site (and origin) as a
    recording property, and the basemap. Each message is one log call per entity and tracker (all its
    tracks batched), so a busy site stays cheap. `max_trail_points` bounds each trail (points at least
    `trail_min_step_m` apart); a track not listed for `forget_after_s` of capture time is forgotten, so the
    state holds only current tracks (one that comes back sooner continues its trail). Per-track speeds are
    buffered and sent as columns every `speed_flush_s` of capture time and by `flush()`.
    `jpeg_quality` (1-100, or None for raw pixels) compresses logged camera frames."""

    def __init__(
        self,
        recording: rr.RecordingStream,
        site: str,
        origin: GeoFrame | None = None,
        basemap: Basemap | None = None,
        *,
        max_trail_points: int = 50,
        trail_min_step_m: float = 0.5,
        forget_after_s: float = 2.0,
        speed_flush_s: float = 1.0,
        jpeg_quality: int | None = 80,
        junction: Junction | None = None,
    ) -> None:
        if not isinstance(recording, rr.RecordingStream):
            raise ValueError(f"recording must be an rr.RecordingStream, got {type(recording).__name__}")
        check_name("site", site)
        if origin is not None and not isinstance(origin, GeoFrame):
            raise ValueError(f"origin must be a GeoFrame or None, got {origin!r}")
        if basemap is not None and not isinstance(basemap, Basemap):
            raise ValueError(f"basemap must be a Basemap or None, got {type(basemap).__name__}")
        if max_trail_points < 2:
            raise ValueError(f"max_trail_points must be >= 2, got {max_trail_points}")
        if not trail_min_step_m >= 0:
            raise ValueError(f"trail_min_step_m must be >= 0, got {trail_min_step_m}")
        if not forget_after_s >= 0:
            raise ValueError(f"forget_after_s must be >= 0, got {forget_after_s}")
        if not speed_flush_s >= 0:
            raise ValueError(f"speed_flush_s must be >= 0, got {speed_flush_s}")
        if jpeg_quality is not None and not 1 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality must be in [1, 100] or None, got {jpeg_quality}")
        self.rec = recording
        self.site = site
        self.origin = origin
        self.basemap = basemap
        self.max_trail_points = int(max_trail_points)
        self.trail_min_step_m = float(trail_min_step_m)
        self.forget_after_ns = int(forget_after_s * 1e9)
        self.speed_flush_ns = int(speed_flush_s * 1e9)
        self.jpeg_quality = jpeg_quality
        self.junction = junction
        self._tracks: dict[tuple[str, int], _TrackState] = {}
        self._drew: set[str] = set()  # the optional layers (entity paths) the last message of their tracker drew
        self._tracker: str | None = None  # the tracker of the last message: another one ends it
        self._last_t_ns = 0  # the last message's capture time: the same tracker far back ends it too (a replay)
        self._tracker_end_ns = 0  # the latest capture time the current tracker drew at: its Clear goes just after
        self._last_speed_flush_ns: int | None = None
        self._cameras: set[str] = set()
        self._span = _Span()
        self.messages = 0
        self.rows = 0
        self.tracks_seen = 0
        self.frames = 0
        self._log_static()

    # --- tracks -----------------------------------------------------------------------------------------

    def log_tracks(self, message: Any) -> int:
        """Log one Tracks message (a TracksMessage, a Tracks-like dict or a `shared.messages.Tracks`) at its
        capture time; returns its number of tracks. Raises ValueError for a message that is not valid or
        is from another site (nothing is logged then)."""
        msg = message if isinstance(message, TracksMessage) else parse_tracks_message(message, self.origin)
        if msg.site != self.site:
            raise ValueError(f"message is from site {msg.site!r}, this sink logs site {self.site!r}")
        rec = self.rec
        base = f"{WORLD}/tracks/{_path_part(msg.tracker)}"
        n = len(msg.rows)
        x = np.array([r.x for r in msg.rows], np.float64)
        y = np.array([r.y for r in msg.rows], np.float64)
        yaw = np.array([r.yaw for r in msg.rows], np.float64)
        length = np.array([r.length for r in msg.rows], np.float64)
        width = np.array([r.width for r in msg.rows], np.float64)
        labels = [f"{r.id} {r.type}" for r in msg.rows]
        colors = np.zeros((n, 3), np.uint8)
        # What can still fail is computed before anything is logged or the sink's state changes, so a message
        # refused here leaves no trace: the footprints, the uncertainty ellipses and the heading fans.
        strips, owner = footprint_strips(x, y, yaw, length, width,
                                         np.array([r.yaw_confirmed is not False for r in msg.rows], bool))
        sure = [i for i, r in enumerate(msg.rows) if r.xy_cov is not None]
        cov = np.array([msg.rows[i].xy_cov for i in sure], np.float64).reshape(-1, 2, 2)
        try:
            ring = ellipses_xy(x[sure], y[sure], cov)
        except np.linalg.LinAlgError as e:  # not_covariances lets none through; a TracksMessage built by hand might
            raise ValueError(f"an xy_cov is not a positive definite covariance ({e})") from None
        known = [i for i, r in enumerate(msg.rows) if r.yaw_std is not None]
        fans, fan_owner = heading_fans(
            x[known], y[known], yaw[known], length[known] / 2 + HEADING_REACH_M,
            np.array([msg.rows[i].yaw_std for i in known], np.float64),
            np.array([msg.rows[i].yaw_confirmed is False for i in known], bool))
        replayed = msg.tracker == self._tracker and msg.t_ns < self._last_t_ns - REPLAYED_NS
        if msg.tracker != self._tracker or replayed:
            if self._tracker is not None:
                self._end_tracker(self._tracker)  # its trails are not joined to the new ones
            self._tracker_end_ns = msg.t_ns
        self._tracker, self._last_t_ns = msg.tracker, msg.t_ns
        self._tracker_end_ns = max(self._tracker_end_ns, msg.t_ns)
        rec.set_time(TIMELINE, timestamp=np.datetime64(msg.t_ns, "ns"))
        trails = []
        for i, row in enumerate(msg.rows):
            state = self._track_state(msg.tracker, row, labels[i], msg.t_ns)
            colors[i] = state.color
            trails.append(_at_z(self._trail(state, row.x, row.y), Z_TRAIL_M))
            if row.vx is not None:
                state.speed_t_ns.append(msg.t_ns)
                state.speed_mps.append(math.hypot(row.vx, row.vy))
        rec.log(
            f"{base}/trails",
            rr.LineStrips3D(trails, colors=colors, labels=labels, show_labels=False, radii=rr.Radius.ui_points(1.5)),
        )
        rec.log(
            f"{base}/positions",
            rr.Points3D(_at_z(np.column_stack([x, y]), Z_POSITION_M), colors=colors, labels=labels, radii=0.4),
        )
        rec.log(
            f"{base}/footprints",
            rr.LineStrips3D(
                [_at_z(s, Z_FOOTPRINT_M) for s in strips],
                colors=colors[owner],
                labels=[labels[i] for i in owner],
                show_labels=False,
                radii=rr.Radius.ui_points(2.0),
            ),
        )
        if self._draws(f"{base}/uncertainty", sure):
            rec.log(f"{base}/uncertainty", rr.LineStrips3D(
                [_at_z(r, Z_FOOTPRINT_M) for r in ring], colors=colors[sure], labels=[labels[i] for i in sure],
                show_labels=False, radii=rr.Radius.ui_points(1.0)))
        if self._draws(f"{base}/heading", known):
            whose = np.array(known, np.int64)[fan_owner]
            rec.log(f"{base}/heading", rr.LineStrips3D(
                [_at_z(f, Z_FOOTPRINT_M) for f in fans], colors=colors[whose], labels=[labels[i] for i in whose],
                show_labels=False, radii=rr.Radius.ui_points(1.0)))
        rec.log(f"plots/tracks/{_path_part(msg.tracker)}", rr.Scalars(n))
        self._forget(msg.tracker, msg.t_ns)
        if self._last_speed_flush_ns is None:
            self._last_speed_flush_ns = msg.t_ns
        elif msg.t_ns - self._last_speed_flush_ns >= self.speed_flush_ns:
            self.flush()
            self._last_speed_flush_ns = msg.t_ns
        self.messages += 1
        self.rows += n
        self._span.add(msg.t_ns, x, y)
        return n

    def _draws(self, path: str, rows: list[int]) -> bool:
        """Whether to log the optional layer `path` for these rows (those that carry its field): when some do, or
        when the tracker's last message drew it (an empty batch then clears it); notes which."""
        drew = path in self._drew
        if rows:
            self._drew.add(path)
        else:
            self._drew.discard(path)
        return bool(rows) or drew

    def flush(self) -> None:
        """Send the buffered per-track speeds (`plots/speed/<tracker>/<id>`). Call it when done."""
        for key, state in self._tracks.items():
            self._send_speeds(key, state)

    def _track_state(self, tracker: str, row: TrackRow, label: str, t_ns: int) -> _TrackState:
        key = (tracker, row.id)
        state = self._tracks.get(key)
        if state is None:
            state = _TrackState(track_color(*key), deque(maxlen=self.max_trail_points), t_ns)
            self._tracks[key] = state
            self.tracks_seen += 1
            self.rec.log(_speed_path(key), rr.SeriesLines(colors=[state.color], names=[label]), static=True)
        state.last_t_ns = t_ns
        return state

    def _trail(self, state: _TrackState, x: float, y: float) -> np.ndarray:
        """The track's trail ending at (x, y): (M, 2) float64 metres; stores (x, y) when it moved enough."""
        trail = state.trail
        if not trail or math.hypot(x - trail[-1][0], y - trail[-1][1]) >= self.trail_min_step_m:
            trail.append((x, y))
        pts = np.array(trail, np.float64)
        return pts if trail[-1] == (x, y) else np.vstack([pts, [x, y]])

    def _end_tracker(self, tracker: str) -> None:
        """A tracker that gave way to another (fuse_track restarted, or its capture time went back): its drawings
        cleared from 1 ns after the latest capture time it drew at (they stay in the recording before), its speeds
        sent and its tracks forgotten. The Clear is not put at the new message's time: when the clock stepped back
        (fuse_track starts a new tracker then), that time is before the old tracker's last drawings, which would
        then stay on screen for ever after. The speeds' flush timer starts again with the next message, whose
        capture time may be earlier than the last flush."""
        base = f"{WORLD}/tracks/{_path_part(tracker)}"
        self.rec.set_time(TIMELINE, timestamp=np.datetime64(self._tracker_end_ns + 1, "ns"))
        self.rec.log(base, rr.Clear(recursive=True))
        self._last_speed_flush_ns = None
        self._drew = {p for p in self._drew if not p.startswith(base + "/")}
        for key, state in list(self._tracks.items()):
            if key[0] == tracker:
                self._send_speeds(key, state)
                del self._tracks[key]

    def _forget(self, tracker: str, t_ns: int) -> None:
        for key, state in list(self._tracks.items()):
            if key[0] == tracker and t_ns - state.last_t_ns > self.forget_after_ns:
                self._send_speeds(key, state)
                del self._tracks[key]

    def _send_speeds(self, key: tuple[str, int], state: _TrackState) -> None:
        if state.speed_t_ns:
            self.rec.send_columns(
                _speed_path(key),
                indexes=[rr.TimeColumn(TIMELINE, timestamp=np.array(state.speed_t_ns, dtype="datetime64[ns]"))],
                columns=rr.Scalars.columns(scalars=np.array(state.speed_mps, np.float64)),
            )
            state.speed_t_ns, state.speed_mps = [], []

    @property
    def live_tracks(self) -> int:
        """How many tracks the sink holds state for (current ones, and ones that left < forget_after_s ago)."""
        return len(self._tracks)

    def trail_of(self, tracker: str, track_id: int) -> np.ndarray | None:
        """The stored trail of a track: (M, 2) float64 metres, site frame, oldest first; None if not held."""
        state = self._tracks.get((tracker, int(track_id)))
        return None if state is None else np.array(state.trail, np.float64).reshape(-1, 2)

    # --- camera frames ----------------------------------------------------------------------------------

    def log_frame(self, camera: str, t_ns: int, image: np.ndarray | bytes, detections: Any = None) -> None:
        """Log one camera frame at capture time `t_ns` (ns since epoch) under `cameras/<camera>`.

        image: (H, W) uint8 grey or (H, W, 3) uint8 BGR (the bus's bgr8), or encoded JPEG/PNG bytes.
        detections, in pixels of `image`: None; an object or mapping with `uv` (N, 2) bottom centres and
        `box` (N, 4) x1 y1 x2 y2 (e.g. `shared.messages.Detections`); or a sequence of
        ((u, v), (x1, y1, x2, y2)) pairs."""
        check_name("camera", camera)
        rec = self.rec
        rec.set_time(TIMELINE, timestamp=np.datetime64(_int(t_ns, "t_ns"), "ns"))
        path = f"cameras/{camera}"
        rec.log(f"{path}/image", _image_archetype(image, self.jpeg_quality))
        uv, box = _detection_arrays(detections)
        rec.log(f"{path}/boxes", rr.Boxes2D(array=box, array_format=rr.Box2DFormat.XYXY, colors=[(255, 200, 0)]))
        rec.log(f"{path}/bottom", rr.Points2D(uv, colors=[(255, 60, 60)], radii=rr.Radius.ui_points(3.0)))
        self._cameras.add(camera)
        self.frames += 1

    # --- layout -----------------------------------------------------------------------------------------

    def blueprint(self) -> rrb.Blueprint:
        """The layout described in the module docstring; the site view frames the basemap, else the
        area the tracks covered so far (else 100 m around the origin)."""
        if self.basemap is not None:
            x0, x1, y0, y1 = self.basemap.extent_m
        elif self.rows:
            x0, x1, y0, y1 = self._span.bounds
        else:
            x0, x1, y0, y1 = -50.0, 50.0, -50.0, 50.0
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        span = max(x1 - x0, y1 - y0, 40.0)
        # Straight above, tilted 3 degrees south so that "up" on screen is unambiguously north.
        eye = rrb.EyeControls3D(
            kind=rrb.Eye3DKind.Orbital,
            position=[cx, cy - 0.05 * span, 1.1 * span],
            look_target=[cx, cy, 0.0],
            eye_up=[0.0, 0.0, 1.0],
        )
        site_view = rrb.Spatial3DView(
            origin=WORLD,
            name=f"{self.site} (site ENU, m)",
            eye_controls=eye,
            line_grid=rrb.LineGrid3D(visible=self.basemap is None, spacing=10.0),
        )
        side: list[Any] = [
            rrb.TimeSeriesView(origin="plots/speed", name="speed (m/s)"),
            rrb.TimeSeriesView(origin="plots/tracks", name="tracks per tick"),
        ]
        if self._cameras:
            side.append(rrb.Grid(*(rrb.Spatial2DView(origin=f"cameras/{c}", name=c) for c in sorted(self._cameras))))
        return rrb.Blueprint(rrb.Horizontal(site_view, rrb.Vertical(*side), column_shares=[3, 2]))

    def summary(self) -> dict:
        """messages, rows, tracks (distinct tracks seen; one forgotten and back counts again), frames,
        t_first_ns, t_last_ns, span_s (capture time)."""
        s = self._span
        span_s = (s.t_last_ns - s.t_first_ns) / 1e9 if s.t_first_ns is not None else 0.0
        return {
            "messages": self.messages,
            "rows": self.rows,
            "tracks": self.tracks_seen,
            "frames": self.frames,
            "t_first_ns": s.t_first_ns,
            "t_last_ns": s.t_last_ns,
            "span_s": span_s,
        }

    def _log_static(self) -> None:
        rec = self.rec
        rec.log(WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        props: dict[str, Any] = {"site": [self.site]}
        if self.origin is not None:
            props.update(
                origin_lat_deg=[self.origin.lat0_deg],
                origin_lon_deg=[self.origin.lon0_deg],
                origin_alt_m=[self.origin.alt0_m],
            )
        rec.send_property("site", rr.AnyValues(**props))
        if self.basemap is not None:
            rec.log(f"{WORLD}/basemap", basemap_mesh(self.basemap), static=True)
        if self.junction is not None and self.origin is not None:
            strips, labels = junction_strips(self.junction, self.origin)
            rec.log(f"{WORLD}/junction", rr.LineStrips3D([_at_z(s, Z_JUNCTION_M) for s in strips], labels=labels,
                                                         colors=[JUNCTION_COLOR], radii=[0.08]), static=True)


def junction_strips(junction: Junction, origin: GeoFrame, points: int = 72) -> tuple[list[np.ndarray], list[str]]:
    """The junction in the site frame: its inner circle, then each leg's sector (from the inner radius out along
    one edge, round the outer radius, back along the other), as (N, 2) strips, and their labels."""
    centre = origin.to_enu(np.array([junction.lat_deg]), np.array([junction.lon_deg]))[0, :2]

    def at(bearing_deg: np.ndarray, r: float) -> np.ndarray:
        b = np.radians(bearing_deg)
        return centre + r * np.column_stack([np.sin(b), np.cos(b)])

    strips = [at(np.linspace(0.0, 360.0, points + 1), junction.inner_radius_m)]
    labels = ["junction"]
    hw = junction.half_width_deg
    for name, bearing in junction.legs:
        edge = np.linspace(bearing - hw, bearing + hw, max(int(points * 2 * hw / 360), 2) + 1)
        strips.append(np.vstack([at(edge[:1], junction.inner_radius_m), at(edge, junction.outer_radius_m),
                                 at(edge[-1:], junction.inner_radius_m)]))
        labels.append(f"leg {name}")
    return strips, labels


def basemap_mesh(basemap: Basemap, cells: int = 32) -> rr.Mesh3D:
    """The basemap as a textured sheet at z = 0 (site frame), its outer corners at `basemap.corners_m`.

    The image is placed as calibration/pick.py georeferences an orthophoto (which is how its landmarks, so the
    cameras' calibration and the tracks, were placed): bilinearly between its four outer corners, the image's outer
    edges at texture coordinates 0 and 1 (the corners are the outer corners of the corner pixels, pixel (i, j)'s
    centre at ((i + 0.5) / W, (j + 0.5) / H)). Four corners need not be a parallelogram, and a mesh is mapped
    linearly within each triangle, so the quad is cut into a grid of `cells` x `cells` cells, each vertex placed by
    the bilinear blend: what is left is the blend's curvature within one cell (millimetres for a real orthophoto)."""
    img = basemap.image
    if img.ndim == 2:
        img = np.repeat(img[:, :, None], 3, axis=2)
    n = int(cells)
    if n < 1:
        raise ValueError(f"cells must be >= 1, got {cells}")
    s = np.linspace(0.0, 1.0, n + 1)
    u, v = np.meshgrid(s, s)  # (n + 1, n + 1): u across the image (columns), v down it (rows); row 0 the top
    u, v = u.reshape(-1, 1), v.reshape(-1, 1)
    tl, tr, br, bl = basemap.corners_m
    xy = (1 - u) * (1 - v) * tl + u * (1 - v) * tr + (1 - u) * v * bl + u * v * br
    k = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].reshape(-1)  # each cell's top-left vertex
    a, b, c, d = k, k + 1, k + n + 2, k + n + 1  # the cell's TL, TR, BR, BL
    return rr.Mesh3D(
        vertex_positions=_at_z(xy, 0.0),
        vertex_normals=np.tile([0.0, 0.0, 1.0], (len(xy), 1)),
        vertex_texcoords=np.column_stack([u, v]),  # v down
        triangle_indices=np.concatenate([np.stack([a, c, b], axis=1), np.stack([a, d, c], axis=1)]),
        albedo_texture=img,
    )


# --- file and live entry points ------------------------------------------------------------------------


class _BadLines:
    def __init__(self) -> None:
        self.count = 0
        self.first: tuple[int, str] | None = None

    def add(self, where: int, reason: str) -> None:
        self.count += 1
        if self.first is None:
            self.first = (where, reason)
            log.warning("skipping bad tracks message %d: %s", where, reason)
        else:
            log.debug("skipping bad tracks message %d: %s", where, reason)


def _as_origin(site_origin: GeoFrame | Mapping | None) -> GeoFrame | None:
    if site_origin is None or isinstance(site_origin, GeoFrame):
        return site_origin
    if isinstance(site_origin, Mapping):
        return GeoFrame.from_dict(site_origin)
    raise ValueError(f"site_origin must be a GeoFrame or a {{lat_deg, lon_deg, alt_m}} mapping, got {site_origin!r}")


def _as_basemap(basemap: Basemap | str | Path | None, origin: GeoFrame | None) -> Basemap | None:
    if basemap is None or isinstance(basemap, Basemap):
        return basemap
    if isinstance(basemap, str | Path):
        return Basemap.from_world_file(basemap, origin)
    raise ValueError(f"basemap must be a Basemap or a world-file path, got {type(basemap).__name__}")


def tracks_file_to_rrd(
    tracks_path: str | Path,
    out_rrd: str | Path,
    *,
    site_origin: GeoFrame | Mapping | None = None,
    basemap: Basemap | str | Path | None = None,
    frames: Iterable[Sequence] | None = None,
    application_id: str = "roadside",
    max_trail_points: int = 50,
    junction: Junction | None = None,
    site: str | None = None,
) -> dict:
    """Convert a tracks file (JSON lines, see the module docstring) to a Rerun .rrd file.

    site_origin: the site's GeoFrame (or its dict), for a lat/lon basemap and rows without x, y.
    basemap: a Basemap, or the path of a basemap world file (see basemap.py).
    frames: optional (camera, t_ns, image, detections) tuples, logged with `TrackSink.log_frame`.
    junction: the site's junction (shared/movements.py), drawn when the origin places it.
    site: the site whose tracks are drawn (its origin and junction are the ones given); a line of another site is
    a bad line. Default: the first valid line's site.
    Bad lines are skipped. Returns {"tracks_file", "rrd", "lines" (non-blank lines read), "messages",
    "bad_lines", "first_bad_line" (1-based line number or None), "first_bad_reason", "rows", "tracks",
    "frames", "t_first_ns", "t_last_ns", "span_s"}. Raises FileNotFoundError naming a missing tracks file."""
    tracks_path, out_rrd = Path(tracks_path), Path(out_rrd)
    if not tracks_path.is_file():
        raise FileNotFoundError(f"tracks file not found: {tracks_path}")
    origin = _as_origin(site_origin)
    bm = _as_basemap(basemap, origin)
    if out_rrd.is_dir():
        raise ValueError(f"{out_rrd} is a folder, not an .rrd file")
    if out_rrd.resolve() == tracks_path.resolve():
        raise ValueError(f"the .rrd would replace the tracks file {tracks_path}: give another --out")
    out_rrd.parent.mkdir(parents=True, exist_ok=True)
    tmp = out_rrd.with_name(out_rrd.name + ".partial")  # an existing file is replaced only by a complete one
    rec = rr.RecordingStream(application_id)
    rec.save(tmp)
    bad = _BadLines()
    lines = 0
    sink: TrackSink | None = None
    done = False
    try:
        rec.send_recording_name(tracks_path.name)
        with tracks_path.open(encoding="utf-8", errors="replace") as f:
            for lineno, line in enumerate(f, 1):
                if not line.strip():
                    continue
                lines += 1
                try:
                    msg = parse_tracks_message(json.loads(line), origin)
                    if sink is None:
                        sink = TrackSink(rec, site or msg.site, origin, bm, max_trail_points=max_trail_points,
                                         junction=junction)
                    sink.log_tracks(msg)
                except ValueError as e:  # json.JSONDecodeError is a ValueError too
                    bad.add(lineno, f"{type(e).__name__}: {e}" if isinstance(e, json.JSONDecodeError) else str(e))
        if sink is None:
            sink = TrackSink(rec, site or "unknown", origin, bm, max_trail_points=max_trail_points, junction=junction)
        sink.flush()
        for frame in frames or ():
            sink.log_frame(*frame)
        rec.send_blueprint(sink.blueprint())
        done = True
    finally:
        rec.flush()
        rec.disconnect()
        if done:
            tmp.replace(out_rrd)
        else:
            tmp.unlink(missing_ok=True)
    return {"tracks_file": str(tracks_path), "rrd": str(out_rrd), "lines": lines, **_counts(sink, bad)}


def live(
    messages: Iterable[Any],
    recording: rr.RecordingStream,
    *,
    site_origin: GeoFrame | Mapping | None = None,
    basemap: Basemap | str | Path | None = None,
    max_trail_points: int = 50,
    junction: Junction | None = None,
) -> dict:
    """Log Tracks messages as they come: `messages` yields Tracks-like dicts (a tracks-file line, parsed)
    or `shared.messages.Tracks`, e.g. from the caller's Zenoh subscriber; `recording` is the caller's
    stream (connected to a viewer, or saving). The site is the first valid message's. Bad messages are
    skipped and counted; the layout is sent once, right after the first message that parses has been logged or
    refused (so it frames that message's tracks when there is no basemap). Returns the summary of
    `tracks_file_to_rrd` (line numbers are message numbers) when `messages` ends."""
    origin = _as_origin(site_origin)
    bm = _as_basemap(basemap, origin)
    bad = _BadLines()
    sink: TrackSink | None = None
    n = 0
    for n, obj in enumerate(messages, 1):
        try:
            msg = parse_tracks_message(obj, origin)
            if sink is None:
                sink = TrackSink(recording, msg.site, origin, bm, max_trail_points=max_trail_points,
                                 junction=junction)
                try:
                    sink.log_tracks(msg)
                finally:  # also when the sink refuses the message: the sink exists, this branch is not taken again
                    recording.send_blueprint(sink.blueprint())
            else:
                sink.log_tracks(msg)
        except ValueError as e:
            bad.add(n, str(e))
    if sink is not None:
        sink.flush()
    return {"lines": n, **_counts(sink, bad)}


def _counts(sink: TrackSink | None, bad: _BadLines) -> dict:
    first = bad.first or (None, None)
    out = {"bad_lines": bad.count, "first_bad_line": first[0], "first_bad_reason": first[1]}
    if sink is None:
        return {
            "messages": 0,
            **out,
            "rows": 0,
            "tracks": 0,
            "frames": 0,
            "t_first_ns": None,
            "t_last_ns": None,
            "span_s": 0.0,
        }
    s = sink.summary()
    return {"messages": s.pop("messages"), **out, **s}


# --- helpers -------------------------------------------------------------------------------------------


def _speed_path(key: tuple[str, int]) -> str:
    return f"plots/speed/{_path_part(key[0])}/{key[1]}"


def _path_part(name: str) -> str:
    return rr.escape_entity_path_part(name) if name else "default"


def _at_z(xy: np.ndarray, z: float) -> np.ndarray:
    xy = np.asarray(xy, dtype=np.float64)
    return np.column_stack([xy, np.full(len(xy), z)])


def _image_archetype(image: np.ndarray | bytes, jpeg_quality: int | None) -> rr.Image | rr.EncodedImage:
    if isinstance(image, bytes | bytearray | memoryview):
        data = bytes(image)
        media = "image/png" if data[:4] == b"\x89PNG" else "image/jpeg"
        return rr.EncodedImage(contents=data, media_type=media)
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise ValueError(f"frame image must be (H, W) or (H, W, 3) uint8, got {img.shape} {img.dtype}")
    arch = rr.Image(img, color_model="L" if img.ndim == 2 else "BGR")
    return arch.compress(jpeg_quality) if jpeg_quality is not None else arch


def _detection_arrays(detections: Any) -> tuple[np.ndarray, np.ndarray]:
    """-> uv (N, 2) float32 px, box (N, 4) float32 x1 y1 x2 y2 px."""
    if detections is None:
        return np.zeros((0, 2), np.float32), np.zeros((0, 4), np.float32)
    if isinstance(detections, Mapping) or hasattr(detections, "uv"):
        get = detections.get if isinstance(detections, Mapping) else lambda k: getattr(detections, k)
        uv, box = np.asarray(get("uv"), np.float32), np.asarray(get("box"), np.float32)
    else:
        pairs = list(detections)
        uv = np.array([p[0] for p in pairs], np.float32).reshape(-1, 2)
        box = np.array([p[1] for p in pairs], np.float32).reshape(-1, 4)
    if uv.ndim != 2 or uv.shape[1] != 2 or box.ndim != 2 or box.shape[1] != 4 or len(uv) != len(box):
        raise ValueError(f"detections need uv (N, 2) and box (N, 4), got {uv.shape} and {box.shape}")
    return uv, box
