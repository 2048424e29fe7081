"""Ground truth for the tracking evaluation (eval/tracking.py): every vehicle's trajectory from a recording, and
which vehicles must be tracked when (the GT objects), by the evaluation policy `TrackingEvalConfig`.

Ground truth
------------
`GroundTruth` merges every camera's `gt/<camera>.jsonl` of the recording into one trajectory per vehicle id
(bottom centre `xyz` over time; the cameras capture at slightly different times, so the merged trajectory is
denser than any one camera's). `Trajectory.position_at(t)` interpolates linearly; it answers None outside the
observed span (beyond `max_extrapolation_s`, where it extrapolates the end segment) and inside a gap between
samples longer than `max_gap_s` (the vehicle was out of every camera's view: a straight line there could cut a
curve; a gap of up to 1.05 frame intervals is always bridged, for low-rate recordings).

GT objects (which vehicles must be tracked at time t), for a set of chosen cameras
----------------------------------------------------------------------------------
A vehicle is a GT object at t when all hold:
1. seen: at least one chosen camera has a frame with capture time within +-`visibility_window_frames` frame
   intervals of t in which the vehicle's bottom centre is `in_image` and `visible_fraction` >=
   `min_visible_fraction`;
2. its ground-truth position at t is defined (see above);
3. that position lies in the evaluation area: for at least one chosen camera, within that camera's evaluation
   radius of its ground position (recording.json `pose.position_m`, x and y) and in that same camera's field of
   view. The evaluation radius of a camera is its ROI radius (the paper's: 25 m around a fisheye camera,
   `roi_radius_fisheye_m`; "< 200 m within its field of view" for a long-range pinhole/thermal camera,
   `roi_radius_pinhole_m`), or `eval_radius_m` when that is set and larger (then trajectory errors are split into
   in-ROI and out-ROI). A fisheye camera's field of view holds its whole disc; a pinhole or thermal camera's is
   its image: the camera has the vehicle's bottom centre `in_image` in a frame within +-`visibility_window_frames`
   frame intervals of t, however little of the vehicle shows (how much shows is condition 1, which another chosen
   camera may meet). A vehicle behind a pinhole camera, or beside its image, is in no area of that camera.
The ROI of a vehicle is decided the same way with the ROI radius (`GroundTruth.objects_in_roi`). Parked vehicles
are GT objects like the others when they are seen. For one camera's own tracks the chosen cameras are that camera
alone: its GT objects are the vehicles *it* sees in *its* area (or, with `seen_by`, that any of those cameras sees:
a pinhole or thermal camera alone is still charged only for the vehicles in its own image).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from sim.recording import Recording


@dataclass(frozen=True)
class TrackingEvalConfig:
    """The evaluation policy (see the module docstring). Distances in metres, times in seconds."""

    match_gate_m: float = 1.5  # a track and a GT object farther apart on the ground never match
    min_visible_fraction: float = 0.3  # a camera "sees" a vehicle: bottom centre in image and this much visible
    visibility_window_frames: float = 1.0  # ... in a frame within +- this many frame intervals of the tick
    roi_radius_fisheye_m: float = 25.0  # the paper's fisheye ROI
    roi_radius_pinhole_m: float = 200.0  # the paper's long-range (thermal) ROI: < 200 m in the field of view
    roi_radius_m: float | None = None  # one ROI radius for every camera (overrides the two above)
    eval_radius_m: float | None = None  # larger evaluation area (out-ROI part); None: the area is the ROI
    # how far ahead of their capture time tracks are scored moved on (`Tracks.predicted`) and as they were (stale):
    # where a vehicle that receives them that much later finds them
    predict_horizons_s: tuple[float, ...] = (0.1, 0.3)
    max_extrapolation_s: float = 0.2  # GT positions beyond the observed span by more than this are undefined
    max_gap_s: float = 0.5  # no interpolation across longer gaps in a vehicle's merged trajectory
    traj_window_s: float = 1.0  # the part of the GT trajectory a tracked position is projected on: tick +- this
    ignore_unscored_tracks: bool = True  # tracks on non-GT vehicles / outside the area are not false positives
    fill_silent_ticks: bool = True  # frame times without any tracks line count as empty ticks
    handoff_window_s: float = 1.0  # a crossing is tracked if matched within this time before and after it
    moving_mps: float = 1.0  # the tracked heading's error is also given for vehicles at least this fast, and slower


@dataclass
class Trajectory:
    """One vehicle's merged ground-truth trajectory: sample times (ns, increasing) and bottom centres (m)."""

    vehicle_id: int | str
    t_ns: np.ndarray  # (N,) int64
    xyz: np.ndarray  # (N, 3) float64
    parked: bool = False
    type: str = ""
    yaw: np.ndarray | None = None  # (N,) float64 rad ENU, the heading at each sample; None: not known

    def heading_at(self, t_ns: int) -> tuple[float, float]:
        """(yaw rad, speed m/s) at the sample nearest t_ns (NaN yaw when not known); the speed from the samples
        either side of it."""
        ts, n = self.t_ns, len(self.t_ns)
        if n == 0:
            return math.nan, math.nan
        j = int(np.clip(np.searchsorted(ts, int(t_ns)), 0, n - 1))
        if j > 0 and abs(int(ts[j - 1]) - int(t_ns)) < abs(int(ts[j]) - int(t_ns)):
            j -= 1
        a, b = max(j - 1, 0), min(j + 1, n - 1)
        dt = (int(ts[b]) - int(ts[a])) / 1e9
        speed = float(np.linalg.norm(self.xyz[b, :2] - self.xyz[a, :2]) / dt) if dt > 0 else math.nan
        return (float(self.yaw[j]) if self.yaw is not None else math.nan), speed

    def _extrapolate(self, t: int, i: int, j: int, max_gap_ns: int) -> np.ndarray:
        """Position at t on the line through samples i and j (constant at i when that segment is a gap)."""
        ti, tj = self.t_ns[i], self.t_ns[j]
        if i == j or abs(int(tj) - int(ti)) > max_gap_ns or ti == tj:
            return self.xyz[i].copy()
        f = (t - int(ti)) / (int(tj) - int(ti))
        return self.xyz[i] + f * (self.xyz[j] - self.xyz[i])

    def position_at(self, t_ns: int, max_extrapolation_ns: int, max_gap_ns: int) -> np.ndarray | None:
        """Bottom centre (3,) at t_ns, linearly interpolated; None where undefined (see the module docstring)."""
        ts, n, t = self.t_ns, len(self.t_ns), int(t_ns)
        if n == 0 or t < int(ts[0]) - max_extrapolation_ns or t > int(ts[-1]) + max_extrapolation_ns:
            return None
        i = int(np.searchsorted(ts, t, side="right"))  # ts[i-1] <= t < ts[i]
        if i == 0:
            return self._extrapolate(t, 0, min(1, n - 1), max_gap_ns)
        if i == n:  # at or after the last sample
            if int(ts[-1]) == t:
                return self.xyz[-1].copy()
            return self._extrapolate(t, n - 1, max(n - 2, 0), max_gap_ns)
        a, b = i - 1, i
        ta, tb = int(ts[a]), int(ts[b])
        if tb - ta <= max_gap_ns:
            return self.xyz[a] + (t - ta) / (tb - ta) * (self.xyz[b] - self.xyz[a])
        if t - ta <= max_extrapolation_ns:  # just after the last sample before a gap
            return self._extrapolate(t, a, a - 1, max_gap_ns) if a > 0 else self.xyz[a].copy()
        if tb - t <= max_extrapolation_ns:  # just before the first sample after a gap
            return self._extrapolate(t, b, b + 1, max_gap_ns) if b + 1 < n else self.xyz[b].copy()
        return None

    def distance_to_path(self, xy: np.ndarray, t_ns: int, window_ns: int, max_gap_ns: int) -> float:
        """Ground distance from xy to the trajectory polyline of the samples within t_ns +- window_ns (plus the
        samples bracketing that window; no segment across a gap longer than max_gap_ns)."""
        ts = self.t_ns
        lo = max(int(np.searchsorted(ts, int(t_ns) - window_ns, side="left")) - 1, 0)
        hi = min(int(np.searchsorted(ts, int(t_ns) + window_ns, side="right")) + 1, len(ts))
        if hi <= lo:
            return float("nan")
        pts = self.xyz[lo:hi, :2]
        p = np.asarray(xy, float)[:2]
        best = float(np.min(np.linalg.norm(pts - p, axis=1)))
        if len(pts) >= 2:
            ok = np.diff(ts[lo:hi]) <= max_gap_ns
            a, b = pts[:-1][ok], pts[1:][ok]
            if len(a):
                ab = b - a
                den = np.maximum(np.sum(ab * ab, axis=1), 1e-12)
                f = np.clip(np.sum((p - a) * ab, axis=1) / den, 0.0, 1.0)
                best = min(best, float(np.min(np.linalg.norm(a + f[:, None] * ab - p, axis=1))))
        return best


@dataclass
class _CameraFrames:
    name: str
    kind: str
    xy: np.ndarray  # (2,) ground position
    t_ns: np.ndarray  # (F,) frame capture times
    ids: list[list]  # per frame: vehicle ids listed
    in_image: list[np.ndarray]  # per frame: bool per listed vehicle
    visible_fraction: list[np.ndarray]  # per frame: float per listed vehicle
    _seen_cache: dict[float, list[frozenset]] = field(default_factory=dict)
    _view_cache: list[frozenset] | None = None

    def in_view(self) -> list[frozenset]:
        """Per frame, the ids of the vehicles whose bottom centre is in this camera's image, however hidden."""
        if self._view_cache is None:
            self._view_cache = [frozenset(v for v, ok in zip(ids, inim, strict=True) if ok)
                                for ids, inim in zip(self.ids, self.in_image, strict=True)]
        return self._view_cache

    def seen(self, min_visible_fraction: float) -> list[frozenset]:
        """Per frame, the ids of the vehicles this camera sees (bottom centre in image, visible enough)."""
        key = float(min_visible_fraction)
        if key not in self._seen_cache:
            self._seen_cache[key] = [
                frozenset(v for v, ok in zip(ids, inim & (vf >= key), strict=True) if ok)
                for ids, inim, vf in zip(self.ids, self.in_image, self.visible_fraction, strict=True)
            ]
        return self._seen_cache[key]


class GroundTruth:
    """The ground-truth trajectory model and visibility of a recording (config-independent; build it once)."""

    def __init__(self, recording: Recording | str | Path) -> None:
        self.recording = recording if isinstance(recording, Recording) else Recording(recording)
        meta = self.recording.meta
        self.cameras: dict[str, _CameraFrames] = {}
        samples: dict[Any, list[tuple[int, list[float]]]] = {}
        info: dict[Any, tuple[bool, str]] = {}
        yaws: dict[Any, list[float]] = {}
        for entry in meta["cameras"]:
            name = entry["name"]
            try:
                pos = entry["pose"]["position_m"]
                xy = np.array([float(pos[0]), float(pos[1])])
            except (KeyError, IndexError, TypeError, ValueError):
                raise ValueError(f"{self.recording.path}: camera {name!r} has no pose.position_m") from None
            times, ids_l, inim_l, vf_l = [], [], [], []
            for n, frame in enumerate(self.recording.ground_truth(name), 1):
                try:
                    t = int(frame["t_ns"])
                    ids, inim, vf = [], [], []
                    for v in frame["vehicles"]:
                        vid = v["id"]
                        ids.append(vid)
                        inim.append(bool(v.get("in_image", False)))
                        vf.append(float(v.get("visible_fraction") or 0.0))
                        samples.setdefault(vid, []).append((t, [float(c) for c in v["xyz"][:3]]))
                        yaws.setdefault(vid, []).append(float(v.get("yaw", math.nan)))
                        info.setdefault(vid, (bool(v.get("parked", False)), str(v.get("type", ""))))
                except (KeyError, TypeError, ValueError) as exc:
                    raise ValueError(f"{self.recording.path / entry['gt']}:{n}: bad ground truth: {exc!r}") from None
                times.append(t)
                ids_l.append(ids)
                inim_l.append(np.array(inim, bool))
                vf_l.append(np.array(vf, float))
            order = np.argsort(np.array(times, np.int64), kind="stable")
            self.cameras[name] = _CameraFrames(
                name=name, kind=str(entry.get("kind", "pinhole")), xy=xy,
                t_ns=np.array(times, np.int64)[order], ids=[ids_l[i] for i in order],
                in_image=[inim_l[i] for i in order], visible_fraction=[vf_l[i] for i in order])
        self.trajectories: dict[Any, Trajectory] = {}
        for vid, s in samples.items():
            t = np.array([a for a, _ in s], np.int64)
            xyz = np.array([b for _, b in s], float).reshape(-1, 3)
            ut, inv = np.unique(t, return_inverse=True)  # several cameras at one instant: average
            acc = np.zeros((len(ut), 3))
            np.add.at(acc, inv, xyz)
            acc /= np.bincount(inv, minlength=len(ut))[:, None]
            yaw = np.full(len(ut), np.nan)
            yaw[inv] = yaws[vid]  # several cameras at one instant: one vehicle, one heading
            parked, vtype = info[vid]
            self.trajectories[vid] = Trajectory(vid, ut, acc, parked, vtype, yaw)
        self._ids = list(self.trajectories)
        self._start = np.array([self.trajectories[v].t_ns[0] for v in self._ids], np.int64)
        self._end = np.array([self.trajectories[v].t_ns[-1] for v in self._ids], np.int64)
        hz = meta.get("hz")
        if isinstance(hz, int | float) and hz > 0:
            self.frame_interval_ns = round(1e9 / float(hz))
        else:
            diffs = [np.diff(c.t_ns) for c in self.cameras.values() if len(c.t_ns) > 1]
            self.frame_interval_ns = int(np.median(np.concatenate(diffs))) if diffs else 100_000_000
        all_t = [c.t_ns for c in self.cameras.values() if len(c.t_ns)]
        self.t_min_ns = int(min(t[0] for t in all_t)) if all_t else 0
        self.t_max_ns = int(max(t[-1] for t in all_t)) if all_t else -1

    # -- queries -------------------------------------------------------------------------------------------

    def check_cameras(self, cameras: str | Sequence[str] | None) -> list[str]:
        if cameras is None:
            return list(self.cameras)
        names = [c.strip() for c in cameras.split(",") if c.strip()] if isinstance(cameras, str) else list(cameras)
        bad = [c for c in names if c not in self.cameras]
        if bad or not names:
            raise ValueError(f"unknown camera(s) {bad or names!r}; the recording has {', '.join(self.cameras)}")
        return names

    def roi_radius_m(self, camera: str, config: TrackingEvalConfig) -> float:
        if config.roi_radius_m is not None:
            return float(config.roi_radius_m)
        kind = self.cameras[camera].kind
        return float(config.roi_radius_fisheye_m if kind == "fisheye" else config.roi_radius_pinhole_m)

    def area_radius_m(self, camera: str, config: TrackingEvalConfig) -> float:
        return max(self.roi_radius_m(camera, config), float(config.eval_radius_m or 0.0))

    def max_gap_ns(self, config: TrackingEvalConfig) -> int:
        """The longest gap between trajectory samples that is interpolated (at least 1.05 frame intervals)."""
        return max(round(config.max_gap_s * 1e9), round(1.05 * self.frame_interval_ns))

    def _within(self, xy: np.ndarray, cameras: Sequence[str], radius) -> np.ndarray:
        xy = np.asarray(xy, float).reshape(-1, 2)
        cam = np.array([self.cameras[c].xy for c in cameras]).reshape(-1, 2)
        rad = np.array([radius(c) for c in cameras], float)
        d = np.linalg.norm(xy[:, None, :] - cam[None, :, :], axis=2)
        return np.any(d <= rad[None, :], axis=1)

    def in_roi(self, xy: np.ndarray, cameras: Sequence[str], config: TrackingEvalConfig) -> np.ndarray:
        """(N,) bool: ground points (a track's positions) within the ROI radius of at least one of the cameras, the
        whole disc (a point has no `in_image`; a vehicle's ROI: `objects_in_roi`)."""
        return self._within(xy, cameras, lambda c: self.roi_radius_m(c, config))

    def in_area(self, xy: np.ndarray, cameras: Sequence[str], config: TrackingEvalConfig) -> np.ndarray:
        """(N,) bool: ground points (a track's positions) within the evaluation radius of at least one of the
        cameras, the whole disc (a vehicle's area: `objects_in_area`)."""
        return self._within(xy, cameras, lambda c: self.area_radius_m(c, config))

    def positions_at(self, t_ns: int, config: TrackingEvalConfig) -> dict[Any, np.ndarray]:
        """Every vehicle whose ground-truth position at t_ns is defined -> its bottom centre (3,)."""
        ext = round(config.max_extrapolation_s * 1e9)
        gap = self.max_gap_ns(config)
        cand = np.nonzero((self._start - ext <= t_ns) & (self._end + ext >= t_ns))[0]
        out = {}
        for k in cand:
            vid = self._ids[k]
            p = self.trajectories[vid].position_at(t_ns, ext, gap)
            if p is not None:
                out[vid] = p
        return out

    def _in_frames(self, t_ns: int, camera: str, config: TrackingEvalConfig,
                   per_frame: list[frozenset]) -> set:
        w = round(config.visibility_window_frames * self.frame_interval_ns)
        cf = self.cameras[camera]
        lo = int(np.searchsorted(cf.t_ns, t_ns - w, side="left"))
        hi = int(np.searchsorted(cf.t_ns, t_ns + w, side="right"))
        return set().union(*per_frame[lo:hi])

    def seen_by(self, t_ns: int, cameras: Sequence[str], config: TrackingEvalConfig) -> set:
        """Ids of the vehicles that a camera sees in a frame within +- the visibility window of t_ns."""
        out: set = set()
        for c in cameras:
            out |= self._in_frames(t_ns, c, config, self.cameras[c].seen(config.min_visible_fraction))
        return out

    def in_view(self, t_ns: int, camera: str, config: TrackingEvalConfig) -> set | None:
        """Ids of the vehicles in the camera's field of view at t_ns (see the module docstring): those whose bottom
        centre is in its image in a frame within +- the visibility window; None for a fisheye camera, whose field of
        view holds its whole disc."""
        if self.cameras[camera].kind == "fisheye":
            return None
        return self._in_frames(t_ns, camera, config, self.cameras[camera].in_view())

    def _objects_within(self, t_ns: int, positions: Mapping[Any, np.ndarray], cameras: Sequence[str],
                        config: TrackingEvalConfig, radius) -> np.ndarray:
        ids = list(positions)
        xy = np.array([np.asarray(positions[v], float)[:2] for v in ids]).reshape(-1, 2)
        out = np.zeros(len(ids), bool)
        for c in cameras:
            near = self._within(xy, [c], radius)
            view = self.in_view(t_ns, c, config) if near.any() else None
            if view is not None:
                near &= np.array([v in view for v in ids], bool)
            out |= near
        return out

    def objects_in_area(self, t_ns: int, positions: Mapping[Any, np.ndarray], cameras: Sequence[str],
                        config: TrackingEvalConfig) -> np.ndarray:
        """(N,) bool per vehicle of `positions` (id -> its position at t_ns): within the evaluation area of a camera
        of `cameras` whose field of view holds it (condition 3 of the module docstring)."""
        return self._objects_within(t_ns, positions, cameras, config, lambda c: self.area_radius_m(c, config))

    def objects_in_roi(self, t_ns: int, positions: Mapping[Any, np.ndarray], cameras: Sequence[str],
                       config: TrackingEvalConfig) -> np.ndarray:
        """(N,) bool per vehicle of `positions` (id -> its position at t_ns): within the ROI of a camera of
        `cameras` whose field of view holds it (as `objects_in_area`, with the ROI radius)."""
        return self._objects_within(t_ns, positions, cameras, config, lambda c: self.roi_radius_m(c, config))

    def gt_objects(self, t_ns: int, cameras: Sequence[str], config: TrackingEvalConfig,
                   positions: Mapping[Any, np.ndarray] | None = None,
                   seen_by: Sequence[str] | None = None) -> dict[Any, np.ndarray]:
        """The GT objects at t_ns (see the module docstring) -> their bottom centres (3,): in the area of one of
        `cameras` and in that camera's field of view, seen by one of `cameras` (or of `seen_by`: a camera tracked
        alone is charged for every vehicle of its area that any camera sees, as the fused tracks are)."""
        pos = self.positions_at(t_ns, config) if positions is None else positions
        ids = [v for v in self.seen_by(t_ns, seen_by or cameras, config) if v in pos]
        if not ids:
            return {}
        inside = self.objects_in_area(t_ns, {v: pos[v] for v in ids}, cameras, config)
        return {v: pos[v] for v, ok in zip(ids, inside, strict=True) if ok}


def _ground_truth(recording: Recording | GroundTruth | str | Path) -> GroundTruth:
    return recording if isinstance(recording, GroundTruth) else GroundTruth(recording)
