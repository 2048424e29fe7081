"""Per-camera lookup masks: pixel -> latitude/longitude and site metres, and their file.

File (`.npz`, numpy's zip of arrays, loaded without pickle):
- `lat`, `lon`: (H, W) float64 degrees at each pixel centre (NaN where invalid);
- `xy`: (H, W, 2) float32 site-frame metres (east, north) around `meta.geo_origin`;
- `valid`: (H, W) bool, ground pixels inside the calibrated area;
- `meta`: a JSON string: format, version, camera (fitted model), geo origin, segments with
  their ground planes and homographies, `ground` ("planes", or the site surface the pixels were lifted
  onto: `calibration.site_ground`), landmark hash, calibrated area, warnings.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from shared.geo import GeoFrame
from shared.raster import bilinear, bilinear_cells

if TYPE_CHECKING:  # the fit (scipy) is not needed to load and look up masks: localize stays small
    from calibration.fit import Calibration

FORMAT = "roadside-lookup-masks"
VERSION = 1


@dataclass
class LookupMasks:
    lat: np.ndarray
    lon: np.ndarray
    xy: np.ndarray
    valid: np.ndarray
    meta: dict

    @property
    def shape(self) -> tuple[int, int]:
        return self.valid.shape

    def _near_antimeridian(self) -> bool:
        """Whether the longitudes span more than 180 deg (a site astride the antimeridian), once per `lon` array."""
        known = self.__dict__.get("_antimeridian")
        if known is None or known[0] is not self.lon:
            lon = self.lon[np.isfinite(self.lon)]
            known = self.__dict__["_antimeridian"] = (self.lon, bool(lon.size) and float(lon.max() - lon.min()) > 180)
        return known[1]

    @property
    def geo(self) -> GeoFrame:
        return GeoFrame.from_dict(self.meta["geo_origin"])

    def camera_position_m(self) -> np.ndarray:
        """(3,) the fitted camera centre in the masks' site frame (x, y of its foot on the ground, height);
        ValueError when the file carries no camera pose."""
        try:
            return np.asarray(self.meta["camera"]["pose"]["position_m"], np.float64).reshape(3)
        except (KeyError, TypeError, ValueError):
            raise ValueError("the masks carry no camera pose (meta.camera.pose.position_m): "
                             "build them with roadside calibrate") from None

    def lookup(self, uv: np.ndarray, geodetic: bool = True,
               latlon_rows: int | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Bilinear lookup at sub-pixel positions.

        uv (N, 2) pixels -> (latlon (N, 2) float64 degrees, xy (N, 2) float64 metres, valid (N,)).
        A position is valid when its four neighbouring pixel centres are all valid. `geodetic=False`
        leaves latlon NaN (metres only); `latlon_rows` limits latlon to the first that many positions (the rest NaN).
        """
        if self.lat.size == 0 and self.valid.size:
            raise ValueError("these masks were loaded without latitude/longitude (load_masks(with_latlon=False)): "
                             "use services.localize.lift.GroundLookup, which computes them from metres")
        cells = bilinear_cells(uv, *self.valid.shape)
        v0, u0, _, _, inside = cells
        ok = inside & self.valid[v0, u0] & self.valid[v0, u0 + 1] & self.valid[v0 + 1, u0] & self.valid[v0 + 1, u0 + 1]
        xy = bilinear(self.xy, cells)
        xy[~ok] = np.nan
        if not geodetic:
            return np.full_like(xy, np.nan), xy, ok
        m = len(xy) if latlon_rows is None else max(0, min(int(latlon_rows), len(xy)))
        first = tuple(c[:m] for c in cells)
        latlon = np.full_like(xy, np.nan)
        lon = bilinear(self.lon, first)[:, 0]
        # four pixel centres astride the antimeridian (179.99999 and -179.99999) would average to about 0: there the
        # longitude comes from the metres, as GroundLookup computes every one
        if self._near_antimeridian():
            v0, u0 = first[0], first[1]
            corners = [self.lon[v0 + dv, u0 + du] for dv, du in ((0, 0), (0, 1), (1, 0), (1, 1))]
            astride = np.flatnonzero(np.ptp(corners, axis=0) > 180.0)
            lon[astride] = self.geo.to_geodetic(xy[:m][astride])[:, 1]
        latlon[:m] = np.column_stack([bilinear(self.lat, first)[:, 0], lon])
        latlon[~ok] = np.nan
        return latlon, xy, ok

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.is_dir():
            raise ValueError(f"masks file {path} is a folder")
        tmp = path.with_name(path.name + ".partial")
        try:
            with tmp.open("wb") as f:
                np.savez(f, lat=self.lat, lon=self.lon, xy=self.xy, valid=self.valid,
                         meta=np.array(json.dumps(self.meta)))
            tmp.replace(path)
        finally:
            tmp.unlink(missing_ok=True)  # nothing half-written is left behind
        return path


def _read_arrays(path: Path, keys: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The arrays `keys` of a masks file; ValueError naming the file when it is a folder, missing, empty, not an
    .npz archive, or lacks one of them."""
    if path.is_dir():
        raise ValueError(f"lookup masks {path} is a folder, not a masks file")
    if not path.is_file():
        raise ValueError(f"lookup masks not found: {path} (roadside calibrate makes them: deploy/sites/README.md)")
    empty = path.stat().st_size == 0
    if empty or not zipfile.is_zipfile(path):  # numpy's own errors: EOFError (empty), TypeError (a .npy array)
        why = "an empty file" if empty else "not an .npz archive"
        raise ValueError(f"{path}: not a lookup masks file ({why}; make one with roadside calibrate)")
    try:
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in keys}
    except (OSError, ValueError, KeyError, EOFError, TypeError, zipfile.BadZipFile) as exc:  # a member cut short
        why = "not an .npz archive" if "allow_pickle" in str(exc) else f"{type(exc).__name__}: {exc}"  # numpy's hint
        raise ValueError(f"{path}: not a lookup masks file ({why}; make one with roadside calibrate)") from None


def read_masks_meta(path: str | Path) -> dict:
    """A masks file's metadata alone (the small array; fuse_track reads the camera positions from it), checked as
    `load_masks` checks it: format, version and origin; ValueError naming the file and what is wrong."""
    path = Path(path)
    return _checked_meta(path, _read_arrays(path, ("meta",))["meta"])


def load_masks(path: str | Path, with_latlon: bool = True) -> LookupMasks:
    """Load a masks file; ValueError naming the file and what is wrong. `with_latlon=False` leaves the
    float64 latitude/longitude arrays on disk (two thirds of the file) and stores zero-size placeholders:
    for a reader that needs only metres and validity (localize computes lat/lon from metres)."""
    path = Path(path)
    keys = ("lat", "lon", "xy", "valid", "meta") if with_latlon else ("xy", "valid", "meta")
    arrays = _read_arrays(path, keys)
    meta = _checked_meta(path, arrays["meta"])
    h, w = arrays["valid"].shape
    if (with_latlon and arrays["lat"].shape != (h, w)) or arrays["xy"].shape != (h, w, 2):
        raise ValueError(f"{path}: array shapes disagree")
    if not with_latlon:
        arrays["lat"] = arrays["lon"] = np.zeros((0, 0))
    return LookupMasks(arrays["lat"], arrays["lon"], arrays["xy"], arrays["valid"].astype(bool), meta)


def _checked_meta(path: Path, array: np.ndarray) -> dict:
    """A masks file's metadata array as a dict; ValueError naming the file unless it is JSON of this format and
    version with a valid origin."""
    try:
        meta = json.loads(str(array))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not a lookup masks file (its metadata is not JSON: {exc})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{path}: not a lookup masks file (its metadata is a {type(meta).__name__}, not an object)")
    if meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise ValueError(
            f"{path}: format {meta.get('format')!r} v{meta.get('version')!r}, expected {FORMAT!r} v{VERSION}"
        )
    try:  # every reader places the masks by their origin
        GeoFrame.from_dict(meta["geo_origin"])
    except (KeyError, TypeError, AttributeError, ValueError) as exc:
        raise ValueError(f"{path}: not a lookup masks file ({type(exc).__name__}: {exc}; its metadata has no valid "
                         "geo_origin)") from None
    return meta


def calibrated_area(cal: Calibration, xy_landmarks: np.ndarray, margin: float = 1.25) -> dict:
    """The area the masks answer for: ground within `margin` x the farthest inlier landmark's
    distance from the camera (plus 5 m). Beyond it the planes are extrapolated, so it is invalid."""
    o = cal.camera.pose.position_m[:2]
    far = float(np.max(np.linalg.norm(xy_landmarks[cal.inliers] - o, axis=1)))
    return {"center_m": [float(o[0]), float(o[1])], "radius_m": round(far * margin + 5.0, 2)}


def build_masks(cal: Calibration, landmarks_hash: str, area: dict, extra_meta: dict | None = None) -> LookupMasks:
    """Evaluate the calibration at every pixel centre of the image."""
    cfg = cal.config
    h, w = cfg.height, cfg.width
    v, u = np.mgrid[0:h, 0:w]
    uv = np.column_stack([u.ravel(), v.ravel()]).astype(np.float64)
    xy, ok = cal.pixel_to_xy(uv)
    centre = np.asarray(area["center_m"])
    ok &= np.linalg.norm(np.where(ok[:, None], xy, 0.0) - centre, axis=1) <= area["radius_m"]
    if cfg.kind == "fisheye":
        cx, cy, r = cfg.circle
        ok &= np.hypot(uv[:, 0] - cx, uv[:, 1] - cy) <= r
    xy = np.where(ok[:, None], xy, np.nan)
    lat = np.full(h * w, np.nan)
    lon = np.full(h * w, np.nan)
    if ok.any():
        ll = cal.geo.to_geodetic(np.column_stack([xy[ok], np.zeros(int(ok.sum()))]))
        lat[ok], lon[ok] = ll[:, 0], ll[:, 1]
    segments = []
    sectors = len(cal.planes) > 1 and not len(cal.band_edges_m) and cal.labelled is None
    edges = [0.0, *map(float, cal.band_edges_m), None]
    bands = [[edges[k], edges[k + 1]] for k in range(len(edges) - 1)]
    for k, plane in enumerate(cal.planes):
        hmat = cal.homography(k)
        segments.append(
            {
                "plane_abc": [float(x) for x in plane],
                "sector_center_rad": float(cal.sector_centres[k]) if sectors else None,
                "band_m": bands[k] if len(cal.band_edges_m) else None,  # [from, to) ground distance, m
                # a segment the user named: its label, and its polygon (site metres) when one was given
                "label": cal.labelled.labels[k] if cal.labelled is not None else None,
                "polygon_m": (cal.labelled.polygons_xy[k].tolist()
                              if cal.labelled is not None and cal.labelled.polygons_xy[k] is not None else None),
                "homography_undistorted_to_xy": [[float(x) for x in row] for row in hmat],
            }
        )
    meta = {
        "format": FORMAT,
        "version": VERSION,
        "kind": cfg.kind,
        "width": w,
        "height": h,
        "camera": cal.camera.to_dict(),
        "geo_origin": cal.geo.to_dict(),
        "nadir_px": [float(x) for x in cal.nadir_px],
        "segments": segments,  # the camera's own planes; with a site surface (`ground`) pixels are lifted onto that
        "ground": cal.ground.to_dict() if cal.ground is not None else "planes",
        "landmarks_hash": landmarks_hash,
        "calibrated_area": area,
        "warnings": list(cal.warnings),
        **(extra_meta or {}),
    }
    return LookupMasks(
        lat.reshape(h, w), lon.reshape(h, w), xy.reshape(h, w, 2).astype(np.float32), ok.reshape(h, w), meta
    )


def roi_mask(xy: np.ndarray, roi: dict | None) -> np.ndarray:
    """(N,) bool: points (N, 2) site metres inside an ROI {center_m, radius_m} or {polygon_m}."""
    if roi is None:
        return np.ones(len(xy), bool)
    if "polygon_m" in roi:
        import cv2

        poly = np.asarray(roi["polygon_m"], np.float32)
        return np.array([cv2.pointPolygonTest(poly, (float(x), float(y)), False) >= 0 for x, y in xy])
    c = np.asarray(roi["center_m"], float)
    return np.linalg.norm(xy - c, axis=1) <= float(roi["radius_m"])


def default_roi(cal: Calibration) -> dict:
    """The paper's ROI: 25 m around a fisheye camera; 200 m around a pinhole/thermal one (the report's coverage
    check counts only the part of it the camera sees, in front of it)."""
    o = cal.camera.pose.position_m[:2]
    return {"center_m": [float(o[0]), float(o[1])], "radius_m": 25.0 if cal.config.kind == "fisheye" else 200.0}


def angular_coverage_deg(xy: np.ndarray, centre: np.ndarray) -> float:
    """Largest angle around `centre` NOT covered by the points (0 = surrounded, 360 = none)."""
    if len(xy) == 0:
        return 360.0
    ang = np.sort(np.degrees(np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0])))
    gaps = np.diff(np.concatenate([ang, [ang[0] + 360.0]]))
    return float(gaps.max()) if len(ang) > 1 else 360.0


def excluded(valid: np.ndarray, polygons: list) -> np.ndarray:
    """A copy of a validity mask (H, W) with the pixels inside the polygons (pixel coordinates, pixel centres on
    integers) set invalid, so that a detection there is dropped like one outside the calibrated area. A pixel is
    inside when its centre is (even-odd rule; a centre on the outline counts as inside): exactly the pixels
    cv2.pointPolygonTest puts inside or on the polygon, not the outline pixels around it that cv2.fillPoly adds."""
    out = valid.copy()
    h, w = valid.shape
    for poly in polygons:
        p = np.asarray(poly, np.float64).reshape(-1, 2)
        lo, hi = np.ceil(p.min(axis=0)), np.floor(p.max(axis=0))  # the pixel centres within its bounding box
        u0, v0 = int(max(lo[0], 0)), int(max(lo[1], 0))
        u1, v1 = int(min(hi[0], w - 1)), int(min(hi[1], h - 1))
        if u1 < u0 or v1 < v0:
            continue
        out[v0:v1 + 1, u0:u1 + 1] &= ~_inside_polygon(p, np.arange(u0, u1 + 1.0), np.arange(v0, v1 + 1.0))
    return out


def _inside_polygon(p: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(len(v), len(u)) bool: the points (u, v) of a grid inside polygon p ((K, 2) vertices) or on its outline.
    Even-odd: a point is inside when a ray from it towards +u crosses the outline an odd number of times (an edge
    counts where it spans the point's v half-open, so a vertex on the ray is crossed once); then every point on an
    edge is added. One row of crossings per edge and grid row: the cost grows with edges x pixels of the box."""
    uu = u[None, :]
    inside = np.zeros((len(v), len(u)), bool)
    edge = np.zeros_like(inside)
    for (x1, y1), (x2, y2) in zip(p, np.roll(p, -1, axis=0), strict=True):
        spans = (y1 > v) != (y2 > v)  # (len(v),) the rows this edge crosses
        if spans.any():
            x = x1 + (v[spans] - y1) * (x2 - x1) / (y2 - y1)  # where it crosses them
            inside[spans] ^= uu < x[:, None]
        # on the edge: within its extent and collinear with it
        rows = np.flatnonzero((v >= min(y1, y2)) & (v <= max(y1, y2)))
        cols = np.flatnonzero((u >= min(x1, x2)) & (u <= max(x1, x2)))
        if len(rows) and len(cols):
            box = np.ix_(rows, cols)
            edge[box] |= (x2 - x1) * (v[rows, None] - y1) == (y2 - y1) * (u[None, cols] - x1)
    return inside | edge
