"""Training labels from the pipeline's own tracks: vehicles the site's cameras followed together while they moved.

`roadside autolabel` finds a camera's moving vehicles against a background model, one camera at a time; it misses
a vehicle whose blob merges with another or with its shadow, or that the background model absorbed (a vehicle
waiting at the yield line). The pipeline, played over the same training slice, tracks vehicles across all the
cameras at once: a track that moved is a vehicle, and it is one in every frame of every camera that sees its
ground position, including the frames where that camera's detector missed it. `TrackTeacher` reads a tracks file
(as fuse_track's recorder writes it) and gives, for a frame's capture time, the moving tracks there: each
track's position carried to that time by its velocity, with its heading (its direction of motion, for a track
that moves: shared/messages.py, Tracks), footprint size and type. `label_from_track` turns one into a label of a
camera's frame: bottom centre through the camera's masks, image heading through their local Jacobian, 2D box
around the footprint's corners and its roof's (a roof at height h seen where the ray through it meets the
ground: the flat-ground model `training.autolabel` uses for footprints).

A track that never moved faster than `moving_mps` gives no labels: static clutter the detector fires on (lamp
heads, painted words) makes steady tracks too, and a parked car cannot be told from it this way.

With an end time (`t_end_ns`: autolabel gives the end of the slice it labels) the lines at or after it are left out
altogether: whether a track moved is then decided from the training slice alone, so that a car that waits through
the slice and drives off in a held-out slice after it is not labelled while it waits.
"""

from __future__ import annotations

import json
import math
from bisect import bisect_left
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.tracks_file import TrackRow, parse_tracks_message

VEHICLE_HEIGHT_M = {"car": 1.5, "suv_van": 1.8, "truck": 3.0, "bus": 3.2, "motorcycle": 1.3}


@dataclass(frozen=True)
class TrackLabelConfig:
    moving_mps: float = 2.0  # a track is a vehicle once it has moved at least this fast
    max_gap_s: float = 0.15  # a frame takes the tracks line within this of its capture time
    min_lines: int = 5  # a track seen in fewer lines than this gives no labels (a short-lived false track)

    def __post_init__(self) -> None:
        for name in ("moving_mps", "max_gap_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.min_lines < 1:
            raise ValueError(f"min_lines must be >= 1, got {self.min_lines}")


@dataclass(frozen=True)
class TrackedVehicle:
    """A moving track at a frame's capture time: xy (2,) site metres, yaw rad ENU, length, width, height m."""

    key: str
    xy: np.ndarray
    yaw: float
    length: float
    width: float
    height: float
    type: str


class TrackTeacher:
    """The moving tracks of a tracks file, looked up by capture time (module doc); only its lines before `t_end_ns`
    (None: all) are used, `lines_after_end` counts the others."""

    def __init__(self, path: str | Path, cfg: TrackLabelConfig | None = None, t_end_ns: int | None = None) -> None:
        self.cfg = cfg or TrackLabelConfig()
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"tracks file missing: {path}")
        lines: list[tuple[int, str, tuple[TrackRow, ...]]] = []
        after = 0
        with path.open(encoding="utf-8", errors="replace") as f:  # bytes that are not text fail as bad JSON
            for n, text in enumerate(f, 1):
                if not text.strip():
                    continue
                try:
                    msg = parse_tracks_message(json.loads(text))
                except (json.JSONDecodeError, ValueError) as exc:
                    raise ValueError(f"{path}: line {n}: {exc}") from None
                if t_end_ns is not None and msg.t_ns >= t_end_ns:  # after the slice: not even to tell who moved
                    after += 1
                    continue
                lines.append((msg.t_ns, msg.tracker, msg.rows))
        if not lines and after:
            raise ValueError(f"tracks file {path} holds no tracks before {t_end_ns} ns (the end of the frames' slice; "
                             f"{after} lines at or after it): the tracks of a later slice or of another footage, or "
                             "the frames' names read in another time zone than the tracks'?")
        if not lines:
            raise ValueError(f"tracks file {path} holds no tracks")
        lines.sort(key=lambda ln: ln[0])
        seen: dict[str, int] = {}
        fastest: dict[str, float] = {}
        for _, tracker, rows in lines:
            for r in rows:
                key = f"{tracker}/{r.id}"
                seen[key] = seen.get(key, 0) + 1
                if r.vx is not None and r.vy is not None:
                    fastest[key] = max(fastest.get(key, 0.0), math.hypot(r.vx, r.vy))
        self.vehicles = {k for k, n in seen.items()
                         if n >= self.cfg.min_lines and fastest.get(k, 0.0) >= self.cfg.moving_mps}
        self.times = [t for t, _, _ in lines]
        self.lines = lines
        self.tracks_seen = len(seen)
        self.lines_after_end = after

    def at(self, t_ns: int) -> list[TrackedVehicle]:
        """The moving tracks of the line nearest t_ns (within max_gap_s), carried to t_ns by their velocity."""
        i = bisect_left(self.times, t_ns)
        near = [j for j in (i - 1, i) if 0 <= j < len(self.times)]
        if not near:
            return []
        j = min(near, key=lambda k: abs(self.times[k] - t_ns))
        dt = (t_ns - self.times[j]) / 1e9
        if abs(dt) > self.cfg.max_gap_s:
            return []
        _, tracker, rows = self.lines[j]
        out = []
        for r in rows:
            key = f"{tracker}/{r.id}"
            if key not in self.vehicles:
                continue
            v = np.array([r.vx or 0.0, r.vy or 0.0])
            out.append(TrackedVehicle(key, np.array([r.x, r.y]) + v * dt, r.yaw, r.length, r.width,
                                      VEHICLE_HEIGHT_M.get(r.type, 1.5), r.type))
        return out


def footprint_corners(v: TrackedVehicle) -> np.ndarray:
    """(4, 2) ground corners of a vehicle's footprint, site metres."""
    c, s = math.cos(v.yaw), math.sin(v.yaw)
    along, across = np.array([c, s]) * v.length / 2, np.array([-s, c]) * v.width / 2
    return np.array([v.xy + along + across, v.xy + along - across, v.xy - along - across, v.xy - along + across])


def label_from_track(v: TrackedVehicle, view) -> dict | None:
    """A label of one frame (working pixels of `view`, a training.autolabel.GroundView) for a tracked vehicle:
    {"uv", "box", "heading_uv"}; None where its bottom centre is off the calibrated ground or outside the ROI, or
    fewer than four of its corners are on the ground."""
    hs, ws = view.valid.shape
    uv = view.to_pixel(v.xy, (0, 0, ws - 1, hs - 1))
    if uv is None or not (0 <= uv[0] <= ws - 1 and 0 <= uv[1] <= hs - 1) or not view.roi[round(uv[1]), round(uv[0])]:
        return None
    jac = view.jacobian(uv)
    if jac is None:
        return None
    corners = footprint_corners(v)
    h_cam = view.height_m
    roof = view.foot + (corners - view.foot) * (h_cam / max(h_cam - v.height, 0.5))
    near = (int(uv[0]) - 160, int(uv[1]) - 160, int(uv[0]) + 160, int(uv[1]) + 160)
    pts = [p for p in (view.to_pixel(c, near) for c in np.vstack([corners, roof])) if p is not None]
    if len(pts) < 4:
        return None
    pts = np.array(pts)
    box = np.concatenate([np.clip(pts.min(axis=0), 0, [ws - 1, hs - 1]), np.clip(pts.max(axis=0), 0, [ws - 1, hs - 1])])
    if box[2] - box[0] < 2 or box[3] - box[1] < 2:
        return None
    duv = np.linalg.solve(jac, np.array([math.cos(v.yaw), math.sin(v.yaw)]))
    return {"uv": uv, "box": box, "heading_uv": duv / np.linalg.norm(duv)}
