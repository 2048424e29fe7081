"""Lift image detections to the ground through a camera's lookup masks (no transport here).

The bottom centre goes through the masks' bilinear lookup to latitude/longitude and site metres.
The image-space heading becomes a world yaw through the local Jacobian of the lookup: the bottom
centre and a point `step_px` along the heading are both lifted, and the yaw is the direction between
them (where the forward point falls outside the calibrated area, the backward point is used).
The detector regresses the 3D size in metres, so size needs no conversion.

Two vehicles cannot stand on the same ground: `overlapping` finds the objects of one frame whose ground point
lies inside the footprint of a higher-scoring one (its length and width, scaled), the second peaks the detector
puts on a long vehicle (a truck read as two cars, one on each half).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calibration.masks import LookupMasks
from shared.geo import GeoFrame
from shared.raster import bilinear, bilinear_cells


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

    def lookup(self, uv: np.ndarray, geodetic: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """uv (N, 2) px -> (latlon (N, 2) deg, xy (N, 2) m site frame, valid (N,)); NaN where invalid.
        `geodetic=False` leaves latlon NaN (the ellipsoid conversion is most of a lookup's time)."""
        cells = bilinear_cells(uv, *self.valid.shape)
        v0, u0, _, _, inside = cells
        va = self.valid
        ok = inside & va[v0, u0] & va[v0, u0 + 1] & va[v0 + 1, u0] & va[v0 + 1, u0 + 1]
        xy = bilinear(self.xy, cells)
        xy[~ok] = np.nan
        latlon = np.full_like(xy, np.nan)
        other_site = self.site_geo != self.masks_geo
        if ok.any() and (geodetic or other_site):
            ll = self.masks_geo.to_geodetic(xy[ok])[:, :2]
            if other_site:
                xy[ok] = self.site_geo.to_enu(ll[:, 0], ll[:, 1], self.site_geo.alt0_m)[:, :2]
            if geodetic:
                latlon[ok] = ll
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
    """uv (N, 2) px and heading_uv (N, 2) unit vectors in the masks' image -> Lifted."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    heading = np.asarray(heading_uv, np.float64).reshape(-1, 2)
    if len(heading) != len(uv):
        raise ValueError(f"uv has {len(uv)} rows, heading_uv {len(heading)}")
    n = len(uv)
    if n == 0:
        return Lifted(np.zeros(0, bool), np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
    latlon, xy, ok = masks.lookup(uv)
    _, ends, ok_ends = masks.lookup(np.concatenate([uv + step_px * heading, uv - step_px * heading]), geodetic=False)
    fwd, back, ok_f, ok_b = ends[:n], ends[n:], ok_ends[:n], ok_ends[n:]
    d = np.where(ok_f[:, None], fwd - xy, xy - back)
    yaw = np.arctan2(d[:, 1], d[:, 0])
    valid = ok & (ok_f | ok_b) & (np.hypot(d[:, 0], d[:, 1]) > 1e-6)
    yaw[~valid] = np.nan
    return Lifted(valid, xy, latlon, yaw)


def overlapping(xy: np.ndarray, yaw: np.ndarray, size_lwh: np.ndarray, score: np.ndarray,
                scale: float) -> np.ndarray:
    """(N,) bool: the objects (site metres, world yaw, size in metres, score) to drop because their ground point
    lies inside the footprint (length and width times `scale`, along the yaw) of a higher-scoring object that is
    kept, or the kept one's point inside theirs. Greedy by score, as non-maximum suppression; `scale` 0 drops
    none. Objects with a non-finite position, yaw or size neither drop nor are dropped."""
    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    n = len(xy)
    drop = np.zeros(n, bool)
    if n < 2 or scale <= 0:
        return drop
    yaw = np.asarray(yaw, np.float64).reshape(n)
    half = 0.5 * scale * np.asarray(size_lwh, np.float64).reshape(n, 3)[:, :2]
    ok = np.isfinite(xy).all(axis=1) & np.isfinite(yaw) & np.isfinite(half).all(axis=1)
    d = xy[None, :, :] - xy[:, None, :]  # d[a, b]: from a to b
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    along = np.abs(d[..., 0] * c + d[..., 1] * s)
    across = np.abs(d[..., 1] * c - d[..., 0] * s)
    inside = (along <= half[:, :1]) & (across <= half[:, 1:])  # inside[a, b]: b's point in a's footprint
    inside = (inside | inside.T) & ok[:, None] & ok[None, :]
    np.fill_diagonal(inside, False)
    for a in np.argsort(-np.asarray(score, np.float64).reshape(n), kind="stable"):
        if not drop[a]:  # kept: no kept higher-scoring object overlaps it
            drop |= inside[a]
    return drop


def lift_kept(masks: GroundLookup | LookupMasks, det, step_px: float,
              footprint_overlap: float) -> tuple[Lifted, np.ndarray]:
    """A frame's detections (uv, heading_uv, size_lwh, score) lifted, and the indices of those localize publishes:
    inside the calibrated area and not inside a higher-scoring one's footprint (`overlapping`)."""
    lifted = lift(masks, det.uv, det.heading_uv, step_px)
    k = np.flatnonzero(lifted.valid)
    return lifted, k[~overlapping(lifted.xy[k], lifted.yaw[k], det.size_lwh[k], det.score[k], footprint_overlap)]
