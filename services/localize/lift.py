"""Lift image detections to the ground through a camera's lookup masks (no transport here).

The bottom centre goes through the masks' bilinear lookup to latitude/longitude and site metres.
The image-space heading becomes a world yaw through the local Jacobian of the lookup: the bottom
centre and a point `step_px` along the heading are both lifted, and the yaw is the direction between
them (where the forward point falls outside the calibrated area, the backward point is used).
The detector regresses the 3D size in metres, so size needs no conversion.

Two vehicles cannot stand on the same ground: `footprint_groups` finds the objects of one frame whose ground point
lies inside the footprint of a higher-scoring one (its length and width, scaled), the second peaks the detector
puts on a long vehicle (a truck read as two cars, one on each half). With `merge` (`localize.footprint_merge`) the
peaks that line up with the kept object (within MERGE_ACROSS_M of its axis, their axes within MERGE_AXIS_DEG) are
not just dropped: the kept object spans them all along its axis (the union of their lengths, at most
MERGE_MAX_LENGTH_M), so its ground point moves to the middle of what the peaks cover and its length grows to it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import partial

import numpy as np

from calibration.masks import LookupMasks
from shared.geo import FOOTPRINT_ROWS, GeoFrame, in_footprints
from shared.raster import bilinear, bilinear_cells

# the peaks a kept object takes in (`merge_along`): within this distance of its axis, their own axes within this
# angle of its, and the union no longer than a long bus (longer ones are left out: two vehicles, not one)
MERGE_ACROSS_M = 1.0
MERGE_AXIS_DEG = 20.0
MERGE_MAX_LENGTH_M = 18.0


class GroundLookup:
    """The part of a camera's lookup masks that localize keeps in memory: site metres (float32) and
    validity (about 11 MB for 1280x960, a third of the whole file); latitude/longitude are computed
    exactly from metres for the few points looked up. When `site` differs from the masks' own origin
    the metres are re-expressed in the site frame."""

    def __init__(self, masks: LookupMasks, site: GeoFrame | None = None) -> None:
        self.xy = masks.xy
        self.valid = masks.valid
        self.masks_geo = masks.geo
        self.site_geo = site or masks.geo

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def lookup(self, uv: np.ndarray, geodetic: bool = True,
               latlon_rows: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """uv (N, 2) px -> (latlon (N, 2) deg, xy (N, 2) m site frame, valid (N,)); NaN where invalid.
        `geodetic=False` leaves latlon NaN (the ellipsoid conversion is most of a lookup's time); `latlon_rows`
        limits latlon to the first that many points (the rest NaN, their metres as usual)."""
        cells = bilinear_cells(uv, *self.valid.shape)
        v0, u0, _, _, inside = cells
        va = self.valid
        ok = inside & va[v0, u0] & va[v0, u0 + 1] & va[v0 + 1, u0] & va[v0 + 1, u0 + 1]
        xy = bilinear(self.xy, cells)
        xy[~ok] = np.nan
        latlon = np.full_like(xy, np.nan)
        other_site = self.site_geo != self.masks_geo
        want = ok.copy()
        if latlon_rows is not None:
            want[latlon_rows:] = False
        if other_site and ok.any():  # every point through latitude/longitude into the site frame
            ll = self.masks_geo.to_geodetic(xy[ok])[:, :2]
            xy[ok] = self.site_geo.to_enu(ll[:, 0], ll[:, 1], self.site_geo.alt0_m)[:, :2]
            if geodetic:
                latlon[want] = ll[want[ok]]
        elif geodetic and want.any():
            latlon[want] = self.masks_geo.to_geodetic(xy[want])[:, :2]
        return latlon, xy, ok


@dataclass
class Lifted:
    """valid (N,) bool: inside the calibrated area; xy (N, 2) float64 m site ENU; latlon (N, 2) float64 deg;
    yaw (N,) float64 rad counter-clockwise from east. Rows of invalid detections hold NaN."""

    valid: np.ndarray
    xy: np.ndarray
    latlon: np.ndarray
    yaw: np.ndarray


def lift(masks: GroundLookup | LookupMasks, uv: np.ndarray, heading_uv: np.ndarray, step_px: float = 6.0) -> Lifted:
    """uv (N, 2) px and heading_uv (N, 2) directions in the masks' image (any length but zero) -> Lifted."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    heading = np.asarray(heading_uv, np.float64).reshape(-1, 2)
    if len(heading) != len(uv):
        raise ValueError(f"uv has {len(uv)} rows, heading_uv {len(heading)}")
    n = len(uv)
    if n == 0:
        return Lifted(np.zeros(0, bool), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    # the contract asks a heading of any length but zero: the step is step_px whatever its length (a raw pixel
    # vector would step off the calibrated ground, a tiny one onto the bottom centre itself)
    norm = np.hypot(heading[:, 0], heading[:, 1])
    heading = heading / np.where(norm > 0, norm, 1.0)[:, None]
    # one lookup for the bottom centres and both ends (its cost is mostly per call); latitude/longitude of the
    # bottom centres only
    latlon, pts, ok_all = masks.lookup(np.concatenate([uv, uv + step_px * heading, uv - step_px * heading]),
                                       latlon_rows=n)
    latlon, xy, ok = latlon[:n], pts[:n], ok_all[:n]
    fwd, back, ok_f, ok_b = pts[n:2 * n], pts[2 * n:], ok_all[n:2 * n], ok_all[2 * n:]
    d = np.where(ok_f[:, None], fwd - xy, xy - back)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    valid = ok & (ok_f | ok_b) & (np.hypot(d[:, 0], d[:, 1]) > 1e-6)
    yaw[~valid] = np.nan
    return Lifted(valid, xy, latlon, yaw)


def footprint_inputs(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, score: np.ndarray) -> tuple:
    """`footprint_groups`' objects as float64 arrays (xy (N, 2), yaw (N,), size (N, 3), score (N,)), the order it
    keeps them in (best score first) and which of them take part (finite position, yaw and size)."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    score = np.asarray(score, np.float64).reshape(n)
    yaw = np.asarray(yaw, np.float64).reshape(n)
    size = np.asarray(size_lwh, np.float64).reshape(n, 3)
    ok = np.isfinite(xy).all(axis=1) & np.isfinite(yaw) & np.isfinite(size[:, :2]).all(axis=1)
    return xy, yaw, size, score, np.argsort(-score, kind="stable"), ok


def footprint_groups(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, score: np.ndarray, scale: float,
                     take: Callable[[int, np.ndarray], np.ndarray] | None = None) -> dict[int, np.ndarray]:
    """The footprint rule: greedy by score, as non-maximum suppression, an object (site metres, world yaw, size in
    metres, score) is suppressed when its ground point lies inside the footprint (length and width times `scale`,
    along the yaw) of a higher-scoring object that is kept, or the kept one's point inside its own. Returns the
    objects kept, each with the indices of those it suppresses, in the order kept (highest score first): {kept
    index: (M,) int indices}. `scale` 0 suppresses none; objects with a non-finite position, yaw or size neither
    suppress nor are suppressed. `take(kept, candidates)`, when given, says which of the candidates (those the
    footprints overlap, not suppressed yet, ascending) the kept object suppresses; the others stay candidates for
    the objects after it (`footprint_rule`'s later rounds: only the peaks a merged object takes in).
    The footprints are compared FOOTPRINT_ROWS objects at a time (best first), so memory grows with N, not N^2."""
    xy, yaw, size, score, order, ok = footprint_inputs(xy, yaw, size_lwh, score)
    n = len(xy)
    if n < 2 or scale <= 0:
        return {int(a): np.zeros(0, np.int64) for a in order}
    drop = np.zeros(n, bool)
    groups = {}
    for start in range(0, n, FOOTPRINT_ROWS):
        block = order[start:start + FOOTPRINT_ROWS]
        block = block[~drop[block]]  # those suppressed already are never kept: their rows are not needed
        if not len(block):
            continue
        # overlap[i, b]: b's point in block[i]'s footprint, or block[i]'s point in b's
        overlap = in_footprints(xy, yaw, size, scale, rows=block, either=True)
        overlap &= ok[None, :]
        overlap[~ok[block]] = False
        overlap[np.arange(len(block)), block] = False
        for a, row in zip(block.tolist(), overlap, strict=True):
            if not drop[a]:  # kept: no kept higher-scoring object overlaps it
                members = np.flatnonzero(row & ~drop)
                if take is not None:
                    members = take(a, members)
                groups[a] = members
                drop[members] = True
    return groups


def merge_along(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, score: np.ndarray,
                groups: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(xy, size_lwh) copies in which each kept object of `groups` (`footprint_groups`) spans, along its own axis,
    itself and the suppressed peaks that line up with it (module docstring; best score first, a peak that would
    make it longer than MERGE_MAX_LENGTH_M left out: `span_along`): its point moves to the middle of that span and its
    length becomes the span's. Width and height stay the kept object's."""
    xy = np.array(xy, np.float64).reshape(-1, 2)
    size = np.array(size_lwh, np.float64).reshape(-1, 3)
    yaw = np.asarray(yaw, np.float64).reshape(-1)
    score = np.asarray(score, np.float64).reshape(-1)
    for a, members in groups.items():
        if not len(members):
            continue
        lo, hi, _ = span_along(a, members, xy, yaw, size, score)
        xy[a] = xy[a] + np.array([np.cos(yaw[a]), np.sin(yaw[a])]) * (lo + hi) / 2
        size[a, 0] = hi - lo
    return xy, size


def span_along(a: int, members: np.ndarray, xy: np.ndarray, yaw: np.ndarray, size: np.ndarray,
               score: np.ndarray) -> tuple[float, float, np.ndarray]:
    """What object a (float64 arrays as `merge_along` takes them) spans along its axis with the peaks among
    `members` that line up with it (within MERGE_ACROSS_M of its axis, their axes within MERGE_AXIS_DEG of its),
    taken best score first while the span stays within MERGE_MAX_LENGTH_M: (lo, hi) metres along the axis from a's
    point, and the members taken (ascending)."""
    axis = np.array([np.cos(yaw[a]), np.sin(yaw[a])])
    normal = np.array([-axis[1], axis[0]])
    max_axis = np.radians(MERGE_AXIS_DEG)
    lo, hi = -size[a, 0] / 2, size[a, 0] / 2
    taken = []
    for b in members[np.argsort(-score[members], kind="stable")]:
        e = xy[b] - xy[a]
        turn = abs((yaw[b] - yaw[a] + np.pi / 2) % np.pi - np.pi / 2)  # between the axes, 0 to 90 deg
        if abs(e @ normal) > MERGE_ACROSS_M or turn > max_axis:
            continue
        p = e @ axis
        lo2, hi2 = min(lo, p - size[b, 0] / 2), max(hi, p + size[b, 0] / 2)
        if hi2 - lo2 <= MERGE_MAX_LENGTH_M:
            lo, hi = lo2, hi2
            taken.append(b)
    return lo, hi, np.sort(np.asarray(taken, np.int64))


def _taken_in(xy: np.ndarray, yaw: np.ndarray, size: np.ndarray, score: np.ndarray, a: int,
              members: np.ndarray) -> np.ndarray:
    """`footprint_groups`' `take` in merging rounds after the first: the members object a takes in (`span_along`)."""
    return span_along(a, members, xy, yaw, size, score)[2]


def footprint_rule(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, score: np.ndarray, scale: float,
                   merge: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """localize's rule on one frame's objects: (kept indices ascending, xy, size_lwh), the objects a higher-scoring
    one's footprint holds left out (`footprint_groups`) and, with `merge`, the kept ones spanning the peaks they
    suppress (`merge_along`; otherwise xy and size_lwh are returned as given). Merging repeats on the kept objects
    while a grown footprint holds a peak that the grown object takes in (`span_along`: lined up with it, the span
    within MERGE_MAX_LENGTH_M; a bus read as peaks at 0, 3 and 6 m, best at 0: the one at 6 m lies in the first
    round's 7.5 m span, and joins it in the second). After the first round nothing else is suppressed: a car that
    a grown footprint holds but that does not line up with it (crossing in front of a bus) is kept."""
    groups = footprint_groups(xy, yaw, size_lwh, score, scale)
    kept = np.sort(np.fromiter(groups, np.int64, len(groups)))
    if not merge:
        return kept, xy, size_lwh
    yaw, score = np.asarray(yaw, np.float64).reshape(-1), np.asarray(score, np.float64).reshape(-1)
    while any(len(m) for m in groups.values()):  # each round keeps fewer objects: it ends
        xy, size_lwh = merge_along(xy, yaw, size_lwh, score, groups)
        objs = (xy[kept], yaw[kept], size_lwh[kept], score[kept])
        sub = footprint_groups(*objs, scale, partial(_taken_in, *objs))
        groups = {int(kept[a]): kept[m] for a, m in sub.items()}
        kept = np.sort(np.fromiter(groups, np.int64, len(groups)))
    return kept, xy, size_lwh


def lift_kept(masks: GroundLookup | LookupMasks, det, step_px: float, footprint_overlap: float,
              merge: bool) -> tuple[Lifted, np.ndarray, np.ndarray]:
    """A frame's detections (uv, heading_uv, size_lwh, score) lifted, the indices of those localize publishes
    (inside the calibrated area, then `footprint_rule`), and the sizes (N, 3). With `merge` the kept objects'
    site metres, latitude/longitude and length in the returned Lifted and sizes are the merged ones."""
    lifted = lift(masks, det.uv, det.heading_uv, step_px)
    size = np.asarray(det.size_lwh, np.float64).reshape(-1, 3)
    k = np.flatnonzero(lifted.valid)
    kept, xy, size_k = footprint_rule(lifted.xy[k], lifted.yaw[k], size[k], np.asarray(det.score)[k],
                                      footprint_overlap, merge)
    moved = k[np.any(xy != lifted.xy[k], axis=1)] if merge else k[:0]
    if len(moved):
        geo = masks.site_geo if isinstance(masks, GroundLookup) else masks.geo
        lifted.xy[k] = xy
        lifted.latlon[moved] = geo.to_geodetic(lifted.xy[moved])[:, :2]
    if merge:  # a span grown on both sides keeps its point but not its length
        size = size.copy()
        size[k] = size_k
    return lifted, k[kept], size
