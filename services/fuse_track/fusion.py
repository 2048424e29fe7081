"""Multi-camera fusion of one tick's ground objects, before tracking (no transport here).

The paper divides the map into regions by camera location and keeps each camera's detections in
its own region. Here each camera has a region: a polygon in site metres, or by default its Voronoi
cell (the points nearer to its ground position than to any other camera's that also uses the
default), optionally cut at `max_range_m`. Then, for the objects of one tick:

1. every object is brought to the tick's reference time with its velocity hint (optional, (N, 2)
   m/s, e.g. `Tracker.velocity_hints`): cameras capture up to +-tick/2 apart, ~0.75 m at 15 m/s;
2. objects inside their own camera's region seed groups; objects of different frames within
   `merge_gate_m` join a group (Hungarian assignment per source frame, at most one object per frame);
3. an object outside its camera's region joins a group within the gate with the low weight
   `out_of_region_weight`, else it is dropped (the paper's rule). With `occlusion_fallback` it is kept
   on its own when no camera whose region contains it saw anything within `merge_gate_m`; that also keeps
   every far-off false positive of a camera wherever the region's own camera saw nothing: on the demo
   (four fisheye cameras, the shipped detector) MOTA -0.11 with the fallback and 0.48 without, so it is
   off by default. Instead, such an object within `extend_range_m` of its own camera is kept as
   *extend-only* (`ObjectBatch.extend_only`): the tracker lets it extend a confirmed track that nothing
   else matched, never start one, so a vehicle hidden from its region's camera behind another keeps its
   track while a neighbour sees it, and a far-off false positive finds no track to extend. Objects of a
   camera without a region are always kept;
4. each group becomes one object: position the weighted mean (weight = score x region weight), and
   with `position_sigma` (the default) each member's weight a 2x2 information matrix rather than a number:
   a camera places a vehicle well across its line of sight and poorly along it, the more so the farther
   (the shipped fisheye detector, beyond 35 m: 0.5-0.7 m across, 1.2-2.5 m along), so two cameras that see
   a vehicle from different sides pin it down where neither alone does (a member with another object of its frame
   just in front of it, between it and its camera, counts with `crowded_sigma_factor` times its sigmas: the
   detector places such a vehicle, in a queue or beside a neighbour, worse, above all across the line of sight);
   yaw the weighted circular mean after
   aligning 180-degree reversals to the member heaviest in heading weight (below), turned to point the way the
   heaviest member's heading points, size the weighted mean, each member's weight in both times
   yaw_size_range_m^2 / (yaw_size_range_m^2 + r^2), r its distance from its camera (the detector's heading and size
   of a vehicle are the worse the farther it is: the shipped fisheye detector's heading is off by 9-11 deg rms within
   20 m, 22-27 deg at 20-45 m and 39 deg at 45-70 m; docs/pipeline.md, "Far headings and sizes"), type the weighted
   vote, score the maximum; `sources` lists its cameras; with `position_sigma`, `xy_cov` is the covariance of its
   position's error that its members' error model implies, an out-of-region member's variances 1 /
   out_of_region_weight times its range model's, the ratio that weight stands for (the tracker turns it into each
   track's, to report);
5. a camera that has delivered no frame for `handover_s` of event time (dead, unplugged, its stream stalled) is down:
   the ground its region held goes to the nearest camera that is up (`contains(xy, down)`), whose objects there
   scoring at least `handover_min_score` then seed groups and start tracks as in their own region (a far view's
   weaker objects are more often false), until it delivers again. Without it the other cameras' far
   views of a dead camera's ground were extend-only, so no vehicle that entered it was tracked (the demo's recording
   with NE's objects dropped: 0.08 of the vehicles in NE's ROI; docs/pipeline.md, "A camera down"). A camera not
   heard from since the start counts as down from handover_s after the first tick; `fuse` learns which cameras
   delivered from its `delivered` argument.

6. a fused object that lies inside the footprint of a longer one at least `long_vehicle_m` long (its length and
   width times `long_footprint`, along its heading) is dropped: the other cameras' peaks on the same bus or truck
   (the longest first; a dropped one drops nothing).
   The detector places a long vehicle at one end and another camera places it at the other, or reads its front as a
   car of its own, farther apart than `merge_gate_m`; localize drops such second peaks within one frame
   (`localize.footprint_overlap`), this across cameras. Without it the stray peak started a track, or pulled a car's
   track beside the truck onto it and swapped their ids (docs/pipeline.md, "Long vehicles across cameras").

A fused object is stated at its members' weighted mean capture time `t_ns` (each member shifted
there with its hint), not at the tick time: the tracker does the last shift with its own velocity,
so an object without a hint is never claimed to be at a time it was not seen.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import linear_sum_assignment

from shared.geo import FOOTPRINT_ROWS, in_footprints
from shared.messages import not_covariances
from shared.position_error import POSITION_SIGMA, check_position_sigma, position_information

log = logging.getLogger(__name__)

NS_PER_S = 1_000_000_000
MAX_VTYPE = 127  # vtype travels as int8
COLUMNS = ("camera", "t_ns", "xy", "yaw", "size_lwh", "vtype", "score")  # ObjectBatch's per-row arrays


def check_columns(owner: str, columns: dict[str, tuple[np.ndarray, tuple[int, ...]]]) -> int:
    """Shapes (N, *trailing), equal N and finite floats of struct-of-arrays columns; returns N.

    Raises ValueError naming `owner.field` and the bad shape or value.
    """
    n = None
    for name, (a, trailing) in columns.items():
        if a.shape[1:] != trailing or a.ndim != 1 + len(trailing):
            want = "(N" + "".join(f", {t}" for t in trailing) + ")"
            raise ValueError(f"{owner}.{name} must have shape {want}, got {a.shape}")
        if n is None:
            n = len(a)
        elif len(a) != n:
            raise ValueError(f"{owner}.{name} has {len(a)} rows, expected {n} like the other fields")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            bad = a[~np.isfinite(a)].ravel()[0]
            raise ValueError(f"{owner}.{name} contains a non-finite value ({bad})")
    return n or 0


def as_column(owner: str, name: str, value: object, dtype: type) -> np.ndarray:
    """`value` as a numpy array of `dtype` (int64 or float64); ValueError naming the field when it is not
    numeric (or, for int64, not integer)."""
    a = value if isinstance(value, np.ndarray) else np.asarray(value)
    if a.dtype.kind not in ("iub" if dtype is np.int64 else "iuf"):
        raise ValueError(f"{owner}.{name} has dtype {a.dtype}, expected a {np.dtype(dtype).name} array")
    return a.astype(dtype, copy=False)


def frame_labels(camera: np.ndarray, t_ns: np.ndarray) -> np.ndarray:
    """(N,) int: one label per (camera, capture time) pair, numbered in that pair's sorted order (camera name,
    then time), as `np.unique` over the pairs would number them, without its slow structured sort."""
    if len(t_ns) == 0:
        return np.zeros(0, np.int64)
    _, cam_code = np.unique(camera, return_inverse=True)
    cam_code = cam_code.reshape(-1)
    order = np.lexsort((t_ns, cam_code))
    c, t = cam_code[order], t_ns[order]
    new = np.r_[True, (c[1:] != c[:-1]) | (t[1:] != t[:-1])]
    labels = np.empty(len(t_ns), np.int64)
    labels[order] = np.cumsum(new) - 1
    return labels


def check_covariance(name: str, value: object, n: int) -> np.ndarray:
    """`value` as (n, 2, 2) float64 covariances; ValueError naming `name` unless each is finite, symmetric and
    positive definite."""
    a = as_column(name.rpartition(".")[0] or name, name.rpartition(".")[2], value, np.float64)
    if a.shape != (n, 2, 2):
        raise ValueError(f"{name} must have shape ({n}, 2, 2), got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} contains a non-finite value ({a[~np.isfinite(a)][0]})")
    bad = not_covariances(a)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{i}] must be a symmetric positive definite 2x2 matrix, got {a[i].tolist()}")
    return a


def symmetric(a: np.ndarray) -> np.ndarray:
    """(..., n, n) matrices made exactly symmetric (what rounding in the products left over averaged away)."""
    return 0.5 * (a + np.swapaxes(a, -1, -2))


def inverse_2x2(a: np.ndarray) -> np.ndarray:
    """(G, 2, 2) -> (G, 2, 2) inverses in closed form (for 2 x 2 a batched LAPACK solve costs more than the
    arithmetic); inf or NaN where a matrix is singular."""
    det = a[:, 0, 0] * a[:, 1, 1] - a[:, 0, 1] * a[:, 1, 0]
    inv = np.stack([a[:, 1, 1], -a[:, 0, 1], -a[:, 1, 0], a[:, 0, 0]], axis=1).reshape(-1, 2, 2)
    with np.errstate(divide="ignore", invalid="ignore"):
        return inv / det[:, None, None]


def wrap_angle(a: np.ndarray) -> np.ndarray:
    """Angles (rad) wrapped to [-pi, pi)."""
    return (a + np.pi) % (2 * np.pi) - np.pi


@dataclass(frozen=True)
class ObjectBatch:
    """Ground objects of one tick, struct of arrays, N rows (N = 0 is fine).

    camera (N,) str: the camera that saw it (for fused objects: the heaviest member's camera);
    t_ns (N,) int64: capture time of the object's frame, ns; xy (N, 2) float64 metres, site ENU
    frame; yaw (N,) float64 rad ENU, counter-clockwise from east; size_lwh (N, 3) float64 metres,
    all > 0; vtype (N,) int64 index into VEHICLE_TYPES (0..127); score (N,) float64 in [0, 1];
    sources: per object the cameras whose objects went into it; None (the default) means each
    object's own camera; read it with `sources_of(i)`. extend_only: (N,) bool, objects that may extend a
    confirmed track but never start one (the fusion's occlusion fallback, module docstring 3); None (the
    default) means none; read it with `extend_mask()`. xy_cov: (N, 2, 2) float64 m^2, the covariance of each
    row's position error (the fusion's, from its cameras' error model, module docstring 4); None (the default)
    means unknown, and a batch joined from batches of which one has none has none.
    Validated on construction: ValueError naming the field.
    """

    camera: np.ndarray
    t_ns: np.ndarray
    xy: np.ndarray
    yaw: np.ndarray
    size_lwh: np.ndarray
    vtype: np.ndarray
    score: np.ndarray
    sources: list[list[str]] | None = None
    extend_only: np.ndarray | None = None
    xy_cov: np.ndarray | None = None

    def __post_init__(self) -> None:
        cam = np.asarray(self.camera)
        if cam.dtype.kind not in "UO" and cam.size:
            raise ValueError(f"ObjectBatch.camera must hold camera names (str), got dtype {cam.dtype}")
        cam = cam.astype(str) if cam.size else cam.astype("U1").reshape(cam.shape)
        cols = {
            "camera": cam,
            "t_ns": as_column("ObjectBatch", "t_ns", self.t_ns, np.int64),
            "xy": as_column("ObjectBatch", "xy", self.xy, np.float64),
            "yaw": as_column("ObjectBatch", "yaw", self.yaw, np.float64),
            "size_lwh": as_column("ObjectBatch", "size_lwh", self.size_lwh, np.float64),
            "vtype": as_column("ObjectBatch", "vtype", self.vtype, np.int64),
            "score": as_column("ObjectBatch", "score", self.score, np.float64),
        }
        shapes = {"xy": (2,), "size_lwh": (3,)}
        n = check_columns("ObjectBatch", {k: (v, shapes.get(k, ())) for k, v in cols.items()})
        if n and not (cols["size_lwh"] > 0).all():
            raise ValueError(f"ObjectBatch.size_lwh must be > 0 m, got {cols['size_lwh'].min()}")
        if n and (cols["score"].min() < 0 or cols["score"].max() > 1):
            bad = cols["score"][(cols["score"] < 0) | (cols["score"] > 1)][0]
            raise ValueError(f"ObjectBatch.score must be within [0, 1], got {bad}")
        if n and (cols["vtype"].min() < 0 or cols["vtype"].max() > MAX_VTYPE):
            bad = cols["vtype"][(cols["vtype"] < 0) | (cols["vtype"] > MAX_VTYPE)][0]
            raise ValueError(f"ObjectBatch.vtype must be within [0, {MAX_VTYPE}] (int8 on the wire), got {bad}")
        sources = self.sources
        if sources is not None and (len(sources) != n or not all(isinstance(s, list) and s for s in sources)):
            raise ValueError(f"ObjectBatch.sources must be {n} non-empty lists of camera names, got {sources!r}")
        if self.extend_only is not None:
            ext = np.asarray(self.extend_only)
            if ext.dtype != bool or ext.shape != (n,):
                raise ValueError(f"ObjectBatch.extend_only must be ({n},) bool, got {ext.shape} {ext.dtype}")
            object.__setattr__(self, "extend_only", ext)
        if self.xy_cov is not None:
            object.__setattr__(self, "xy_cov", check_covariance("ObjectBatch.xy_cov", self.xy_cov, n))
        for k, v in cols.items():
            object.__setattr__(self, k, v)

    def __len__(self) -> int:
        return len(self.t_ns)

    def sources_of(self, i: int) -> list[str]:
        """The cameras whose objects went into row i."""
        return list(self.sources[i]) if self.sources is not None else [str(self.camera[i])]

    def extend_mask(self) -> np.ndarray:
        """(N,) bool: the rows that may only extend a confirmed track."""
        return self.extend_only if self.extend_only is not None else np.zeros(len(self), bool)

    @classmethod
    def empty(cls) -> ObjectBatch:
        return cls(np.zeros(0, "U1"), np.zeros(0, np.int64), np.zeros((0, 2)), np.zeros(0), np.zeros((0, 3)),
                   np.zeros(0, np.int64), np.zeros(0))

    @classmethod
    def from_frame(cls, camera: str, t_ns: int, xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray,
                   vtype: np.ndarray, score: np.ndarray) -> ObjectBatch:
        """The objects of one camera frame (one camera name and capture time for all rows)."""
        n = len(np.asarray(score).reshape(-1))
        return cls(np.full(n, camera), np.full(n, int(t_ns), np.int64), xy, yaw, size_lwh, vtype, score)

    @classmethod
    def concat(cls, batches: Sequence[ObjectBatch]) -> ObjectBatch:
        """The rows of several batches, in order."""
        batches = [b for b in batches if len(b)]
        if not batches:
            return cls.empty()
        cat = {k: np.concatenate([getattr(b, k) for b in batches]) for k in COLUMNS}
        ext = None
        if any(b.extend_only is not None for b in batches):
            ext = np.concatenate([b.extend_mask() for b in batches])
        cov = np.concatenate([b.xy_cov for b in batches]) if all(b.xy_cov is not None for b in batches) else None
        sources = None
        if any(b.sources is not None for b in batches):
            sources = [b.sources_of(i) for b in batches for i in range(len(b))]
        return cls._validated(**cat, sources=sources, extend_only=ext, xy_cov=cov)

    def select(self, index: np.ndarray) -> ObjectBatch:
        """The rows at `index` (integer indices or a boolean mask)."""
        rows = np.arange(len(self))[index]
        sources = None if self.sources is None else [self.sources[i] for i in rows]
        ext = None if self.extend_only is None else self.extend_only[rows]
        cov = None if self.xy_cov is None else self.xy_cov[rows]
        return ObjectBatch._validated(**{k: getattr(self, k)[rows] for k in COLUMNS}, sources=sources,
                                      extend_only=ext, xy_cov=cov)

    @classmethod
    def _validated(cls, sources: list[list[str]] | None = None, extend_only: np.ndarray | None = None,
                   xy_cov: np.ndarray | None = None, **columns: np.ndarray) -> ObjectBatch:
        """A batch of rows taken from batches that were validated on construction (`select`, `concat`): the
        columns already have their dtypes and shapes, so the checks are not run again on the per-tick path."""
        batch = object.__new__(cls)
        for k in COLUMNS:
            object.__setattr__(batch, k, columns[k])
        object.__setattr__(batch, "sources", sources)
        object.__setattr__(batch, "extend_only", extend_only)
        object.__setattr__(batch, "xy_cov", xy_cov)
        return batch


@dataclass(frozen=True)
class CameraRegion:
    """Where a camera's objects are preferred. position_xy: the camera's ground position (2,) m, site
    frame. polygon_xy: (K, 2) m, K >= 3, site frame; None means the Voronoi cell among the cameras
    that use the default. max_range_m: optionally also within this distance of position_xy."""

    name: str
    position_xy: tuple[float, float]
    polygon_xy: np.ndarray | None = None
    max_range_m: float | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"CameraRegion.name must be a non-empty string, got {self.name!r}")
        pos = np.asarray(self.position_xy, np.float64)
        if pos.shape != (2,) or not np.all(np.isfinite(pos)):
            raise ValueError(f"CameraRegion.position_xy of {self.name} must be 2 finite metres, got {self.position_xy}")
        object.__setattr__(self, "position_xy", (float(pos[0]), float(pos[1])))
        if self.polygon_xy is not None:
            poly = np.asarray(self.polygon_xy, np.float64)
            if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3 or not np.all(np.isfinite(poly)):
                raise ValueError(f"CameraRegion.polygon_xy of {self.name} must be (K >= 3, 2) finite metres, "
                                 f"got shape {poly.shape}")
            object.__setattr__(self, "polygon_xy", poly)
        if self.max_range_m is not None and not (np.isfinite(self.max_range_m) and self.max_range_m > 0):
            raise ValueError(f"CameraRegion.max_range_m of {self.name} must be > 0, got {self.max_range_m}")


@dataclass(frozen=True)
class FusionConfig:
    """merge_gate_m: objects of different frames closer than this (at the tick's reference time) are
    one vehicle; out_of_region_weight: weight of an object outside its camera's region relative to
    one inside (the variance ratio of in- and out-of-region localization, (0.22 / 0.49)^2 = 0.2 in the
    paper; chosen over the validation recordings, docs/pipeline.md: 0.5 with position_sigma, 0.1 without);
    min_score: objects below it are ignored (the paper fuses high-certainty detections only);
    position_sigma: rows (range m, sigma along the line from the camera m, sigma across it m), ranges increasing:
    each member of a group weighs in its position with the inverse of that covariance times its weight (module
    doc, 4; objects of a camera without a region as 1 m either way); None = a scalar weighted mean (the paper's);
    crowded_sigma_factor: with position_sigma, the sigmas of a member that has another object of its own frame in
    front of it (nearer its camera by crowd_ahead_m = (at least, at most) m, within crowd_across_m of the line from
    the camera) are multiplied by this (module doc, 4; 1 = off);
    occlusion_fallback: keep an object outside its camera's region that no region owner saw (module doc, 3);
    extend_range_m: without occlusion_fallback, keep such an object as extend-only when it lies within this distance
    of its own camera (module doc, 3; 0 = drop it, the paper's rule);
    split_score: objects below it are fused only with each other, those at or above it only with each other
    (for the tracker's two rounds, `TrackerConfig.high_score`: a low-score object inside its camera's region
    would otherwise let a high-score one from outside it join its group and start a track; 0 = one pool);
    yaw_size_range_m: a member's weight in its group's heading and size falls with its distance r from its camera as
    yaw_size_range_m^2 / (yaw_size_range_m^2 + r^2) (module doc, 4; 0 = the same weight as in its position);
    handover_s: a camera that delivered no frame for this long (event time, s; `Fusion.fuse`'s `delivered`) is down,
    and the ground its region held goes to the nearest camera that is up (module doc, 5; 0 = never);
    handover_min_score: there, only that camera's objects scoring at least this count as in its region (the others
    as outside it: extend-only within extend_range_m);
    long_vehicle_m, long_footprint: a fused object inside the footprint of a longer one at least long_vehicle_m long,
    its length and width times long_footprint, is dropped (module doc, 6; long_vehicle_m 0 = off)."""

    merge_gate_m: float = 3.0
    out_of_region_weight: float = 0.5
    position_sigma: tuple[tuple[float, float, float], ...] | None = POSITION_SIGMA
    # 2 within (1-8 m ahead, 4 m across): a plateau over 1.7-2.4 and 3-6 m (validation; docs/pipeline.md, "Crowded")
    crowded_sigma_factor: float = 2.0
    crowd_ahead_m: tuple[float, float] = (1.0, 8.0)
    crowd_across_m: float = 4.0
    min_score: float = 0.0
    occlusion_fallback: bool = False
    extend_range_m: float = 0.0
    split_score: float = 0.0
    # 20 m: the far end of a plateau over 5-20 m of the validation recordings' median heading errors, a mean 2.9 deg
    # lower than without, and as good as 10 m for the sizes (docs/pipeline.md, "Far headings and sizes")
    yaw_size_range_m: float = 20.0
    # 1 s: ten of a 10 Hz camera's frames, three of a 5 Hz real one's gaps at its worst (docs/pipeline.md, "A camera
    # down"); 0.6: the top of a plateau over 0.5-0.6 of the validation recordings' MOTA with each camera down in turn
    handover_s: float = 1.0
    handover_min_score: float = 0.6
    # 7 m and 1.4: the middle of a plateau over 6.5-8 m and 1.3-1.5 of the validation recordings' MOTA and IDF1
    # (docs/pipeline.md, "Long vehicles across cameras")
    long_vehicle_m: float = 7.0
    long_footprint: float = 1.4

    def __post_init__(self) -> None:
        if not (np.isfinite(self.long_vehicle_m) and self.long_vehicle_m >= 0):
            raise ValueError(f"long_vehicle_m must be >= 0 (0: off), got {self.long_vehicle_m}")
        if not (np.isfinite(self.long_footprint) and self.long_footprint > 0):
            raise ValueError(f"long_footprint must be > 0, got {self.long_footprint}")
        if not (np.isfinite(self.merge_gate_m) and self.merge_gate_m > 0):
            raise ValueError(f"merge_gate_m must be > 0, got {self.merge_gate_m}")
        if not 0 < self.out_of_region_weight <= 1:
            raise ValueError(f"out_of_region_weight must be within (0, 1], got {self.out_of_region_weight}")
        if self.position_sigma is not None:
            object.__setattr__(self, "position_sigma", check_position_sigma(self.position_sigma))
        if not (np.isfinite(self.crowded_sigma_factor) and self.crowded_sigma_factor >= 1):
            raise ValueError(f"crowded_sigma_factor must be >= 1, got {self.crowded_sigma_factor}")
        ahead = np.asarray(self.crowd_ahead_m, np.float64)
        if ahead.shape != (2,) or not (np.all(np.isfinite(ahead)) and 0 <= ahead[0] < ahead[1]):
            raise ValueError(f"crowd_ahead_m must be (least, most) m with 0 <= least < most, got {self.crowd_ahead_m}")
        object.__setattr__(self, "crowd_ahead_m", (float(ahead[0]), float(ahead[1])))
        if not (np.isfinite(self.crowd_across_m) and self.crowd_across_m > 0):
            raise ValueError(f"crowd_across_m must be > 0, got {self.crowd_across_m}")
        for name in ("extend_range_m", "yaw_size_range_m", "handover_s"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("min_score", "split_score", "handover_min_score"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"{name} must be within [0, 1], got {getattr(self, name)}")


def points_in_polygon(xy: np.ndarray, polygon: np.ndarray) -> np.ndarray:
    """xy (N, 2), polygon (K, 2), same frame -> (N,) bool inside (even-odd rule)."""
    a = polygon
    b = np.roll(polygon, -1, axis=0)
    x, y = xy[:, :1], xy[:, 1:]
    crosses = (a[:, 1] > y) != (b[:, 1] > y)
    with np.errstate(divide="ignore", invalid="ignore"):
        x_at = a[:, 0] + (y - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
    return np.count_nonzero(crosses & (x < x_at), axis=1) % 2 == 1


def crowded(xy: np.ndarray, camera_xy: np.ndarray, frame: np.ndarray, ahead_m: tuple[float, float],
            across_m: float, block: int = 256) -> np.ndarray:
    """(N,) bool: object n has another object of its own frame (`frame`: (N,) labels) in front of it, between it and
    its camera (camera_xy: (N, 2), the same within a frame): nearer along the line from the camera by ahead_m[0] to
    ahead_m[1] m, within across_m of that line and on the camera's side the object is on (not behind the camera).
    All pairs at once, `block` objects at a time (memory)."""
    n = len(xy)
    out = np.zeros(n, bool)
    v = xy - camera_xy
    rng = np.hypot(v[:, 0], v[:, 1])
    u = v / np.maximum(rng, 1e-9)[:, None]
    normal = np.stack([-u[:, 1], u[:, 0]], axis=1)
    u_at = np.einsum("nk,nk->n", camera_xy, u)  # each object's camera, projected on its own line
    normal_at = np.einsum("nk,nk->n", camera_xy, normal)
    for lo in range(0, n, block):
        i = np.arange(lo, min(lo + block, n))
        # [i, j]: how much farther object j lies than object i along i's line from i's camera, and how far across it;
        # j must lie ahead of the camera on that line (along + rng[i] > 0), not behind it
        along = u[i] @ xy.T - (u_at[i] + rng[i])[:, None]
        across = np.abs(normal[i] @ xy.T - normal_at[i][:, None])
        front = (frame[None, :] == frame[i, None]) & (along <= -ahead_m[0]) & (along >= -ahead_m[1]) & (
            across <= across_m) & (along + rng[i][:, None] > 0)
        front[np.arange(len(i)), i] = False
        out[i] = front.any(axis=1)
    return out


class Fusion:
    """Fuses the objects of one tick from several cameras; see the module docstring."""

    def __init__(self, regions: Sequence[CameraRegion] = (), config: FusionConfig | None = None) -> None:
        self.config = config or FusionConfig()
        self.regions = list(regions)
        names = [r.name for r in self.regions]
        if len(set(names)) != len(names):
            raise ValueError(f"regions must name each camera once, got {names}")
        self._index = {name: i for i, name in enumerate(names)}
        self._pos = np.array([r.position_xy for r in self.regions], np.float64).reshape(-1, 2)
        self._voronoi = np.array([r.polygon_xy is None for r in self.regions], bool)
        self._range = np.array([np.inf if r.max_range_m is None else r.max_range_m for r in self.regions])
        sigma = self.config.position_sigma
        self._sigma = None if sigma is None else np.asarray(sigma, np.float64)
        self._delivered_ns = np.zeros(len(self.regions), np.int64)  # each camera's last tick with a frame
        self._heard = np.zeros(len(self.regions), bool)  # and whether it has delivered at all
        self._first_ns: int | None = None  # the first tick any camera delivered to
        self._last_ns = 0  # the last tick watched
        self.down: frozenset[str] = frozenset()  # the cameras whose regions the last tick handed over

    @property
    def cameras(self) -> list[str]:
        return list(self._index)

    def contains(self, xy: np.ndarray, down: np.ndarray | None = None) -> np.ndarray:
        """xy (N, 2) m site frame -> (N, C) bool: point n lies in the region of camera c (`cameras` order). With
        `down` ((C,) bool, cameras that are down) a point whose regions are all down cameras' lies in the region of
        the nearest camera that is up (and whose `max_range_m` reaches it)."""
        return self._regions(xy, down)[0]

    def _regions(self, xy: np.ndarray, down: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`contains`, and (N, C) bool: the (point, camera) pairs a down camera handed over."""
        xy = np.asarray(xy, np.float64).reshape(-1, 2)
        d = np.linalg.norm(xy[:, None, :] - self._pos[None], axis=2)  # (N, C)
        inside = d <= self._range
        if self._voronoi.any():
            vor = np.flatnonzero(self._voronoi)
            nearest = vor[np.argmin(d[:, vor], axis=1)]
            inside[:, vor] &= nearest[:, None] == vor[None]
        for c in np.flatnonzero(~self._voronoi):
            inside[:, c] &= points_in_polygon(xy, self.regions[c].polygon_xy)
        inherited = np.zeros_like(inside)
        if down is not None and down.any() and not down.all():
            orphan = np.flatnonzero(inside[:, down].any(axis=1) & ~inside[:, ~down].any(axis=1))
            inside[:, down] = False
            reach = np.where(down[None, :] | (d[orphan] > self._range), np.inf, d[orphan])
            heir = np.argmin(reach, axis=1)
            ok = np.isfinite(reach[np.arange(len(orphan)), heir])
            inherited[orphan[ok], heir[ok]] = True
            inside |= inherited
        return inside, inherited

    def _watch(self, delivered: Iterable[str] | None, t_ref_ns: int) -> np.ndarray | None:
        """(C,) bool, the cameras down at t_ref_ns (module doc, 5), after noting those that `delivered` a frame to
        this tick; None without `delivered` or with handover off."""
        if delivered is None or self.config.handover_s <= 0:
            return None
        if self._first_ns is not None and int(t_ref_ns) < self._last_ns:  # the clocks went back: start again
            self._heard[:], self._first_ns = False, None
        self._last_ns = int(t_ref_ns)
        for name in delivered:
            if name in self._index:
                self._delivered_ns[self._index[name]] = int(t_ref_ns)
                self._heard[self._index[name]] = True
                if self._first_ns is None:
                    self._first_ns = int(t_ref_ns)
        if self._first_ns is None:
            return None
        # a camera never heard from is given handover_s from the first tick, as if it had delivered to it
        since = np.where(self._heard, self._delivered_ns, self._first_ns)
        down = (int(t_ref_ns) - since) > round(self.config.handover_s * NS_PER_S)
        now = frozenset(self.regions[c].name for c in np.flatnonzero(down))
        if now - self.down:
            log.warning("cameras down (no frame for %g s of capture time): %s; their regions go to the nearest "
                        "cameras up", self.config.handover_s, ", ".join(sorted(now - self.down)))
        if self.down - now:
            log.warning("cameras up again: %s", ", ".join(sorted(self.down - now)))
        self.down = now
        return down

    def fuse(self, objects: ObjectBatch, t_ref_ns: int, velocity: np.ndarray | None = None,
             delivered: Iterable[str] | None = None) -> ObjectBatch:
        """One tick's objects (any cameras, any capture times) -> fused objects, one per vehicle.

        velocity: optional (N, 2) float m/s (east, north) per object, used to bring each object to
        `t_ref_ns` before gating and averaging; zeros (no shift) where unknown.
        delivered: the cameras that delivered a frame to this tick, with or without objects (module doc, 5); the
        fusion remembers them from tick to tick (call it with ticks in order). None: every camera counts as up.
        Returns an ObjectBatch whose `sources` lists the cameras merged into each row and whose
        `t_ns` is the members' weighted mean capture time (xy is the position at that time).
        """
        n = len(objects)
        vel = np.zeros((n, 2)) if velocity is None else as_column("fuse", "velocity", velocity, np.float64)
        if vel.shape != (n, 2):
            raise ValueError(f"fuse.velocity must have shape (N, 2) = ({n}, 2) like the objects, got {vel.shape}")
        check_columns("fuse", {"velocity": (vel, (2,))})
        down = self._watch(delivered, t_ref_ns)
        keep = np.flatnonzero(objects.score >= self.config.min_score)
        if len(keep) < n:
            objects, vel = objects.select(keep), vel[keep]
            n = len(objects)
        if n == 0:
            return ObjectBatch.empty()
        # two pools (split_score): fused in one pass, never with each other, as if each were fused alone, the
        # high-scoring pool's objects first
        pool = (objects.score < self.config.split_score).astype(np.int64)
        return self._under_long_vehicles(self._fuse(objects, t_ref_ns, vel, pool, down))

    def _under_long_vehicles(self, fused: ObjectBatch) -> ObjectBatch:
        """The fused objects less those inside the footprint of a longer fused object at least long_vehicle_m long
        (its length and width times long_footprint, along its heading; module doc, 6): the longest first, an object
        already dropped dropping nothing. Whatever its score, and extend-only too: limited to objects it outscores,
        or to long objects that are not extend-only, the rule gained less (docs/pipeline.md, "Long vehicles across
        cameras")."""
        lmin = self.config.long_vehicle_m
        if lmin <= 0 or len(fused) < 2:
            return fused
        length = fused.size_lwh[:, 0].astype(np.float64)
        long_ = np.flatnonzero(length >= lmin)
        if not long_.size:
            return fused
        drop = np.zeros(len(fused), bool)
        order = long_[np.lexsort((-fused.score[long_], -length[long_]))]  # the longest first, then the surest
        for start in range(0, len(order), FOOTPRINT_ROWS):  # a block of footprints at a time: memory grows with N
            block = order[start:start + FOOTPRINT_ROWS]
            block = block[~drop[block]]
            inside = in_footprints(fused.xy, fused.yaw, fused.size_lwh, self.config.long_footprint, rows=block)
            for i, row in zip(block.tolist(), inside, strict=True):
                if not drop[i]:
                    drop |= row & (length < length[i])
        return fused.select(np.flatnonzero(~drop)) if drop.any() else fused

    def _fuse(self, objects: ObjectBatch, t_ref_ns: int, vel: np.ndarray, pool: np.ndarray,
              down: np.ndarray | None = None) -> ObjectBatch:
        n = len(objects)
        dt_s = (int(t_ref_ns) - objects.t_ns) / NS_PER_S
        p_ref = objects.xy + vel * dt_s[:, None]  # positions at the reference time
        cam_idx = np.array([self._index.get(c, -1) for c in objects.camera.tolist()])
        owners, inherited = self._regions(p_ref, down)  # (N, C) each
        # on ground handed over (module doc, 5) only the heir's objects scoring handover_min_score count as its own; an
        # object of a camera without a region lies in none (with no regions at all `owners` has no column to look up)
        in_region = np.zeros(n, bool)
        known = np.flatnonzero(cam_idx >= 0)
        own = cam_idx[known]
        in_region[known] = owners[known, own] & (
            ~inherited[known, own] | (objects.score[known] >= self.config.handover_min_score))
        region_weight = np.where(in_region, 1.0, self.config.out_of_region_weight)
        weight = np.maximum(objects.score, 1e-6) * region_weight
        source = frame_labels(objects.camera, objects.t_ns)  # the frame each object comes from
        labels, extend = self._group(objects, p_ref, in_region, weight, cam_idx, owners, source, pool)
        if pool.any() and (labels >= 0).any():  # the high-scoring pool's groups first, each pool's in its own order
            groups = np.zeros(int(labels.max()) + 1, np.int64)
            groups[labels[labels >= 0]] = pool[labels >= 0]
            rank = np.empty_like(groups)
            rank[np.argsort(groups, kind="stable")] = np.arange(len(groups))
            labels = np.where(labels >= 0, rank[np.maximum(labels, 0)], -1)
        return self._merge(objects, vel, weight, labels, extend | objects.extend_mask(), cam_idx, source, pool)

    def _group(self, objects: ObjectBatch, p_ref: np.ndarray, in_region: np.ndarray, weight: np.ndarray,
               cam_idx: np.ndarray, owners: np.ndarray, source: np.ndarray,
               pool: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N,) group label per object, -1 for dropped objects, and (N,) bool: kept as extend-only. Objects of
        different pools (N,) never meet: as far as grouping goes, they lie beyond every gate of each other."""
        gate = self.config.merge_gate_m
        dx, dy = p_ref[:, None, 0] - p_ref[None, :, 0], p_ref[:, None, 1] - p_ref[None, :, 1]
        # (N, N): within the gate of each other; one frame never sees a vehicle twice; the other pool's objects are
        # not there
        near = (dx * dx + dy * dy <= gate * gate) & (source[:, None] != source[None]) & (pool[:, None] == pool[None])
        labels = np.full(len(objects), -1)
        # 1. Objects in their own camera's region seed the groups.
        seeds = np.flatnonzero(in_region)
        labels[seeds] = self._cluster(seeds, near, source, weight, p_ref, pool)
        g = int(labels.max()) + 1
        # 2. The others join a group within the gate (one object per frame and group).
        out = np.flatnonzero(~in_region)
        if g and len(out):
            w = weight[seeds]
            centre = np.stack([np.bincount(labels[seeds], w * p_ref[seeds, k], g) for k in range(2)], 1)
            centre /= np.bincount(labels[seeds], w, g)[:, None]
            has = np.zeros((g, source.max() + 1), bool)
            has[labels[seeds], source[seeds]] = True
            group_pool = np.zeros(g, np.int64)
            group_pool[labels[seeds]] = pool[seeds]
            dg = np.hypot(p_ref[out, None, 0] - centre[None, :, 0], p_ref[out, None, 1] - centre[None, :, 1])
            dg[has[:, source[out]].T | (pool[out, None] != group_pool[None])] = np.inf
            cost = np.where(dg <= gate, dg, 1e9)
            for s in np.unique(source[out]):
                r = np.flatnonzero(source[out] == s)
                i, j = linear_sum_assignment(cost[r])
                ok = cost[r[i], j] <= gate
                labels[out[r[i[ok]]]] = j[ok]
        # 3. Occlusion fallback (objects of cameras without a region always; the others with
        #    `occlusion_fallback`, or as extend-only within `extend_range_m` of their own camera): an object
        #    left over is kept when no camera whose region contains it saw anything within the gate, and merged
        #    with the other objects kept so.
        extend = np.zeros(len(objects), bool)
        rest = out[labels[out] < 0]
        full = (cam_idx[rest] < 0) | self.config.occlusion_fallback
        if self.config.extend_range_m > 0 and not full.all():
            own = self._pos[np.maximum(cam_idx[rest], 0)]
            extend[rest] = ~full & (np.hypot(*(p_ref[rest] - own).T) <= self.config.extend_range_m)
        rest = rest[full | extend[rest]]
        if len(rest):
            known = np.flatnonzero(cam_idx >= 0)
            seen = near[np.ix_(rest, known)] & owners[np.ix_(rest, cam_idx[known])]
            rest = rest[~seen.any(axis=1)]
            labels[rest] = g + self._cluster(rest, near, source, weight, p_ref, pool)
        return labels, extend & (labels >= 0)

    def _cluster(self, rows: np.ndarray, near: np.ndarray, source: np.ndarray, weight: np.ndarray,
                 p_ref: np.ndarray, pool: np.ndarray) -> np.ndarray:
        """Labels 0.. for `rows`: objects of different frames (and the same pool) within the gate of a group's
        weighted centre form one group (frame by frame, Hungarian assignment); objects with no such neighbour
        (`near`, (N, N) bool, `_group`) stand alone."""
        gate = self.config.merge_gate_m
        out = np.full(len(rows), -1)
        linked = near[np.ix_(rows, rows)].any(axis=1)
        lone = np.flatnonzero(~linked)
        out[lone] = np.arange(len(lone))
        first = len(lone)
        members = np.flatnonzero(linked)
        centre, wsum, has = np.zeros((0, 2)), np.zeros(0), np.zeros((0, source.max() + 1), bool)
        centre_pool = np.zeros(0, np.int64)
        for s in np.unique(source[rows[members]]):
            mine = members[source[rows[members]] == s]
            p, w, mine_pool = p_ref[rows[mine]], weight[rows[mine]], pool[rows[mine]]
            taken = np.zeros(len(mine), bool)
            if len(centre):
                dg = np.hypot(p[:, None, 0] - centre[None, :, 0], p[:, None, 1] - centre[None, :, 1])
                cost = np.where((dg <= gate) & ~has[:, s] & (mine_pool[:, None] == centre_pool[None]), dg, 1e9)
                i, j = linear_sum_assignment(cost)
                ok = cost[i, j] <= gate
                i, j = i[ok], j[ok]
                centre[j] = (centre[j] * wsum[j, None] + p[i] * w[i, None]) / (wsum[j] + w[i])[:, None]
                wsum[j] += w[i]
                has[j, s] = True
                out[mine[i]] = first + j
                taken[i] = True
            new = np.flatnonzero(~taken)
            out[mine[new]] = first + len(centre) + np.arange(len(new))
            centre = np.concatenate([centre, p[new]])
            centre_pool = np.concatenate([centre_pool, mine_pool[new]])
            wsum = np.concatenate([wsum, w[new]])
            fresh = np.zeros((len(new), has.shape[1]), bool)
            fresh[:, s] = True
            has = np.concatenate([has, fresh])
        return out

    def _merge(self, objects: ObjectBatch, vel: np.ndarray, weight: np.ndarray, labels: np.ndarray,
               extend: np.ndarray, cam_idx: np.ndarray, source: np.ndarray,
               pool: np.ndarray) -> ObjectBatch:
        """One object per group; a group is extend-only when all its members are. weight: each object's weight,
        its score times its region weight (1 in its camera's region, out_of_region_weight outside it); cam_idx: each
        object's camera as an index into the regions, -1 for a camera without one; source: the frame each object
        comes from; pool: each object's pool (a group's members share one; each pool's times count from its own
        earliest)."""
        kept = np.flatnonzero(labels >= 0)
        lab, w = labels[kept], weight[kept]
        g = int(lab.max()) + 1 if len(lab) else 0
        if g == 0:
            return ObjectBatch.empty()
        wsum = np.bincount(lab, w, g)
        kept_pool = pool[kept]
        t0_pool = np.array([objects.t_ns[kept][kept_pool == k].min() if (kept_pool == k).any() else 0 for k in
                            range(int(kept_pool.max()) + 1)], np.int64)
        t0 = np.zeros(g, np.int64)
        t0[lab] = t0_pool[kept_pool]  # each group's pool's earliest capture time
        t_rel_s = (objects.t_ns[kept] - t0[lab]) / NS_PER_S
        cov = None
        if self._sigma is None:
            t_out_s = np.bincount(lab, w * t_rel_s, g) / wsum
            xy_at = objects.xy[kept] + vel[kept] * (t_out_s[lab] - t_rel_s)[:, None]
            xy = np.stack([np.bincount(lab, w * xy_at[:, k], g) for k in range(2)], 1) / wsum[:, None]
        else:  # information-weighted: each member's weight times the inverse of its position covariance
            cam = cam_idx[kept]
            info = np.tile(np.eye(2), (len(kept), 1, 1))  # a camera without a region: 1 m either way
            own = cam >= 0
            if own.any():
                info[own] = position_information(objects.xy[kept][own], self._pos[cam[own]], self._sigma)
                if self.config.crowded_sigma_factor > 1:
                    mine = kept[own]  # in front only within its own pool, as if the pool were fused alone
                    hidden = crowded(objects.xy[mine], self._pos[cam[own]], 2 * source[mine] + pool[mine],
                                     self.config.crowd_ahead_m, self.config.crowd_across_m)
                    info[np.flatnonzero(own)[hidden]] /= self.config.crowded_sigma_factor**2
            info *= w[:, None, None]
            a = np.zeros((g, 2, 2))
            np.add.at(a, lab, info)
            a_inv = inverse_2x2(a)
            share = a_inv[lab] @ info  # each member's part of its group's position: A^-1 I_i
            # The group's time: each member's capture time weighted by its part along its motion, so that an
            # error in the velocity hints cancels along the motion, as scalar weights make it cancel altogether.
            speed = np.hypot(vel[kept, 0], vel[kept, 1])
            heading = np.where((speed > 0)[:, None], vel[kept] / np.maximum(speed, 1e-12)[:, None], 0.0)
            t_weight = np.maximum(np.where(speed > 0, np.einsum("ni,nij,nj->n", heading, share, heading),
                                           np.trace(share, axis1=1, axis2=2) / 2), 0.0)
            t_sum = np.bincount(lab, t_weight, g)
            flat = t_sum[lab] < 1e-6  # no member's share lies along its motion (degenerate): plain weights
            t_weight[flat] = w[flat]
            t_out_s = np.bincount(lab, t_weight * t_rel_s, g) / np.bincount(lab, t_weight, g)
            xy_at = objects.xy[kept] + vel[kept] * (t_out_s[lab] - t_rel_s)[:, None]
            b = np.zeros((g, 2))
            np.add.at(b, lab, np.einsum("nij,nj->ni", info, xy_at))
            xy = np.einsum("gij,gj->gi", a_inv, b)
            # its error: A^-1 (sum of W_i C_i W_i) A^-1 with W_i = w_i I_i and C_i = (r_i I_i)^-1 the members' own, r_i
            # the region weight: out_of_region_weight stands for the variance ratio of in- and out-of-region
            # localization (FusionConfig), so an out-of-region member's error is 1 / r_i times its range model's, as
            # the mean weighs it
            c = np.zeros((g, 2, 2))
            np.add.at(c, lab, np.maximum(objects.score[kept], 1e-6)[:, None, None] * info)  # w_i / r_i: its score
            cov = symmetric(a_inv @ c @ a_inv)
        # The heaviest member of each group gives its camera and which way its heading points (front or back); the
        # member heaviest in heading weight (w_view, below) the axis its members' headings are aligned to, reversed
        # ones flipped: aligned to a far member's axis instead, which is the worse, near members about 90 degrees
        # from it fell on either side of the flip and cancelled, leaving the far member's heading. Which way it points
        # from the member heaviest in heading weight too, or from a doubled-angle mean and a vote weighted by w_view,
        # gave a larger heading error on the validation recordings (validation 77's mean 56.6 -> 69.2 and 70.0 deg).
        order = np.lexsort((-w, lab))
        first = order[np.r_[True, lab[order][1:] != lab[order][:-1]]]
        w_view = w
        if self.config.yaw_size_range_m > 0:  # the farther from its camera, the less a member's heading and size count
            cam = cam_idx[kept]
            r2 = np.zeros(len(kept))
            located = cam >= 0
            r2[located] = np.sum((objects.xy[kept][located] - self._pos[cam[located]]) ** 2, axis=1)
            w_view = w / (1.0 + r2 / self.config.yaw_size_range_m**2)
        order = np.lexsort((-w_view, lab))
        anchor_yaw = objects.yaw[kept][order[np.r_[True, lab[order][1:] != lab[order][:-1]]]]
        d = wrap_angle(objects.yaw[kept] - anchor_yaw[lab])
        d = wrap_angle(np.where(np.abs(d) > np.pi / 2, d + np.pi, d))  # a reversed heading counts as the same
        mean_d = np.arctan2(np.bincount(lab, w_view * np.sin(d), g), np.bincount(lab, w_view * np.cos(d), g))
        yaw = wrap_angle(anchor_yaw + mean_d)
        back = np.abs(wrap_angle(yaw - objects.yaw[kept][first])) > np.pi / 2  # against the heaviest member's
        yaw = wrap_angle(np.where(back, yaw + np.pi, yaw))
        size = np.stack([np.bincount(lab, w_view * objects.size_lwh[kept, k], g) for k in range(3)], 1)
        size /= np.bincount(lab, w_view, g)[:, None]
        votes = np.zeros((g, int(objects.vtype[kept].max()) + 1))
        np.add.at(votes, (lab, objects.vtype[kept]), w)
        score = np.zeros(g)
        np.maximum.at(score, lab, objects.score[kept])
        if objects.sources is None:
            members = [[c] for c in objects.camera[kept].tolist()]
        else:
            members = [objects.sources[i] for i in kept.tolist()]
        sources: list[set[str]] = [set() for _ in range(g)]
        for gi, cameras in zip(lab.tolist(), members, strict=True):
            sources[gi].update(cameras)
        ext = None
        if extend[kept].any():
            ext = np.bincount(lab, ~extend[kept], g) == 0
        if not (np.isfinite(xy).all() and np.isfinite(t_out_s).all()):  # finite members, positive weights: only a
            # degenerate information matrix
            raise ValueError("fusion gave a non-finite position or time (a group's information matrix is singular)")
        # means, maxima and votes of validated rows: the constructor's checks are not run again on this per-tick path
        return ObjectBatch._validated(
            camera=objects.camera[kept][first], t_ns=t0 + np.round(t_out_s * NS_PER_S).astype(np.int64), xy=xy,
            yaw=yaw, size_lwh=size, vtype=np.argmax(votes, axis=1), score=score, sources=[sorted(s) for s in sources],
            extend_only=ext, xy_cov=cov)
