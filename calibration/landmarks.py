"""Landmark files: ground points a person marked both in a camera image and on a map.

Two formats are read:
- JSON: `{"camera": ..., "width": W, "height": H, "landmarks": [{"id", "u", "v", "lat", "lon",
  "segment"?}, ...]}` (the simulator's landmark files are this format; extra keys are ignored);
- CSV with a header row `id,u,v,lat,lon[,segment]`.
Pixels (u, v) are in the original image, (0, 0) the centre of the top-left pixel. A segment is a whole number >= 0
naming the piece of planar ground the landmark lies on (a ramp, a bridge deck); left out, the calibration splits
the ground itself. Segment polygons (`--segment-polygons`) are a JSON object from segment number to the
polygon's [lat, lon] vertices: `{"1": [[42.2301, -83.7391], ...], "2": [...]}`.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.geo import GeoFrame

FAR_FROM_OTHERS_M = 2000.0
# A landmark further than this from the others' median, and than FAR_SPREADS times the others' own spread (the
# median distance of the others from it), is a typo: a roadside camera's landmarks lie within ~140 m of each other
# (the simulator's pinhole cameras: at most 0.65 of this limit; the real site's: 0.2)
FAR_FLOOR_M = 200.0
FAR_SPREADS = 5.0
MIN_SPREAD_M = 2.0  # landmarks narrower than this (the standard deviation across their spread) fix no camera
MIN_SPREAD_PX = 10.0
MAX_SEGMENTS = 8
MAX_SEGMENT_NUMBER = 2**31 - 1


@dataclass(frozen=True)
class Landmarks:
    """N landmarks: ids (N,), uv (N, 2) pixels, latlon (N, 2) degrees, segment (N,) int (-1 = auto)."""

    ids: tuple[str, ...]
    uv: np.ndarray
    latlon: np.ndarray
    segment: np.ndarray

    def __len__(self) -> int:
        return len(self.ids)

    def subset(self, idx) -> Landmarks:
        idx = np.asarray(idx)
        return Landmarks(tuple(self.ids[i] for i in idx), self.uv[idx], self.latlon[idx], self.segment[idx])

    def without_segments(self) -> Landmarks:
        """The same landmarks with no segment named (the calibration splits the ground itself)."""
        return Landmarks(self.ids, self.uv, self.latlon, np.full(len(self.ids), -1, int))

    def digest(self) -> str:
        """A hash of the landmark values (ids, pixels, lat/lon), recorded with the masks made from them."""
        h = hashlib.sha256()
        for i, (u, v), (la, lo), s in zip(self.ids, self.uv, self.latlon, self.segment, strict=True):
            h.update(f"{i},{u:.4f},{v:.4f},{la:.10f},{lo:.10f},{s};".encode())
        return h.hexdigest()[:16]

    def to_local(self, geo: GeoFrame) -> np.ndarray:
        """(N, 2) site-frame metres."""
        return geo.to_enu(self.latlon[:, 0], self.latlon[:, 1], geo.alt0_m)[:, :2]


def load_landmarks(path: str | Path) -> tuple[Landmarks, dict]:
    """Read a landmark file -> (Landmarks, header dict with optional camera/width/height)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"landmark file not found: {path}")
    header: dict = {}
    try:
        if path.suffix.lower() == ".csv":
            with path.open(newline="", encoding="utf-8-sig") as f:  # -sig: a spreadsheet's byte-order mark
                reader = csv.DictReader(f)
                if reader.fieldnames:  # " segment" or "Segment" in a spreadsheet's header is the segment column
                    reader.fieldnames = [name.strip().lower() for name in reader.fieldnames]
                rows, row_names = [], []
                for row in reader:
                    if not _blank(row):  # a spreadsheet saves the empty rows under a table as ",,,,"
                        rows.append(row)
                        row_names.append(f"row {reader.line_num}")  # the header is row 1, as in the spreadsheet
                columns = set(reader.fieldnames or ())
            if len(columns) == 1 and any(sep in next(iter(columns)) for sep in ";\t"):
                raise ValueError(f"{path}: the header {next(iter(columns))!r} is one column: the columns must be "
                                 "separated by commas (id,u,v,lat,lon), not semicolons or tabs")
            missing = {"id", "u", "v", "lat", "lon"} - columns
            if missing:
                raise ValueError(f"{path}: CSV header lacks column(s) {', '.join(sorted(missing))}")
        else:
            try:
                data = json.loads(path.read_text(encoding="utf-8"))
            except json.JSONDecodeError as exc:
                raise ValueError(f"{path}: not valid JSON: {exc}") from None
            if not isinstance(data, dict) or not isinstance(data.get("landmarks"), list):
                raise ValueError(f"{path}: expected an object with a 'landmarks' list")
            rows, row_names = data["landmarks"], None
            header = {k: data[k] for k in ("camera", "kind", "width", "height") if k in data}
    except UnicodeDecodeError as exc:
        raise ValueError(f"{path}: not a UTF-8 text file ({exc.reason} at byte {exc.start})") from None
    for k in ("width", "height"):
        if k in header and (isinstance(header[k], bool) or not isinstance(header[k], int) or header[k] <= 0):
            raise ValueError(f"{path}: {k} must be a whole number of pixels > 0, got {header[k]!r}")
    if "kind" in header and header["kind"] not in ("pinhole", "fisheye"):
        raise ValueError(f"{path}: kind must be pinhole or fisheye, got {header['kind']!r}")
    return landmarks_from_rows(rows, str(path), row_names), header


def _blank(row: dict) -> bool:
    """Whether every cell of a CSV row is empty (csv.DictReader: None for a missing cell, a list for extra ones)."""
    cells = [c for v in row.values() for c in (v if isinstance(v, list) else [v])]
    return all(c is None or not str(c).strip() for c in cells)


def landmarks_from_rows(rows: list[dict], where: str, row_names: list[str] | None = None) -> Landmarks:
    """Landmarks from dicts with id, u, v, lat, lon and an optional segment (extra keys are ignored);
    `where` (a file name) starts every error message, `row_names` (a CSV file's "row 7") name a row without an id
    (default: "landmark entry N")."""
    ids, uv, latlon, seg = [], [], [], []
    for n, row in enumerate(rows, 1):
        if not isinstance(row, dict):
            raise ValueError(f"{where}: landmark entry {n} must be an object with id, u, v, lat, lon, got {row!r}")
        lid = str(row.get("id", f"#{n}")).strip()
        if not lid:
            place = row_names[n - 1] if row_names else f"landmark entry {n}"
            raise ValueError(f"{where}: {place} has no id: give every landmark one (the report names them by it)")
        try:
            vals = [float(row[k]) for k in ("u", "v", "lat", "lon")]
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{where}: landmark {lid!r}: u, v, lat and lon must all be numbers") from None
        if not all(math.isfinite(x) for x in vals):
            raise ValueError(f"{where}: landmark {lid!r}: u, v, lat, lon must be finite, got {vals}")
        ids.append(lid)
        uv.append(vals[:2])
        latlon.append(vals[2:])
        s = row.get("segment")
        try:
            seg.append(-1 if s in (None, "") else _whole(s))
        except (TypeError, ValueError):
            raise ValueError(f"{where}: landmark {lid!r}: segment must be a whole number, got {s!r}") from None
        if not -1 <= seg[-1] <= MAX_SEGMENT_NUMBER:  # -1: none named, as an empty cell
            raise ValueError(f"{where}: landmark {lid!r}: segment must be a whole number from 0 to "
                             f"{MAX_SEGMENT_NUMBER} (or left empty, or -1), "
                             f"got {s!r}")
    return Landmarks(
        tuple(ids), np.array(uv, float).reshape(-1, 2), np.array(latlon, float).reshape(-1, 2), np.array(seg, int)
    )


def median_latlon(latlon: np.ndarray) -> np.ndarray:
    """(2,) the median latitude and longitude of (N, 2) points, the longitudes taken around the first one's (a
    site on the antimeridian has landmarks at 179.9996 and -179.9998 degrees, whose plain median is 0)."""
    latlon = np.asarray(latlon, float).reshape(-1, 2)
    lon0 = latlon[0, 1]
    lon = np.median((latlon[:, 1] - lon0 + 180.0) % 360.0 - 180.0) + lon0
    return np.array([np.median(latlon[:, 0]), (lon + 180.0) % 360.0 - 180.0])


def median_frame(latlon: np.ndarray) -> GeoFrame:
    """The site frame at the points' median latitude and longitude (`median_latlon`)."""
    med = median_latlon(latlon)
    return GeoFrame(float(med[0]), float(med[1]))


def _whole(x) -> int:
    """An int from an int or a string of one ("2", " 3 "); TypeError or ValueError otherwise (2.5, [1], True)."""
    if isinstance(x, bool) or not isinstance(x, int | str):
        raise TypeError(x)
    return int(x)


def validate_landmarks(
    lm: Landmarks, width: int, height: int, image_circle: tuple[float, float, float] | None = None
) -> None:
    """Raise ValueError naming the landmark for: duplicate ids, lat/lon out of range, a landmark far
    from the others (a swapped lat/lon, a typo: 2 km, or for a fisheye, whose `image_circle` is given, 5 times the
    others' spread), pixels outside the image or the fisheye image circle (cx, cy, radius), fewer than 4 landmarks,
    all landmarks (nearly) collinear."""
    seen: dict[str, int] = {}
    for i, lid in enumerate(lm.ids):
        if lid in seen:
            raise ValueError(f"landmark {lid!r} is listed twice (entries {seen[lid] + 1} and {i + 1})")
        seen[lid] = i
    for lid, (la, lo) in zip(lm.ids, lm.latlon, strict=True):
        if not -90 <= la <= 90:
            raise ValueError(f"landmark {lid!r}: latitude {la} is out of range [-90, 90] (swapped with longitude?)")
        if not -180 <= lo <= 180:
            raise ValueError(f"landmark {lid!r}: longitude {lo} is out of range [-180, 180]")
    for lid, (u, v) in zip(lm.ids, lm.uv, strict=True):
        if not (-0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
            raise ValueError(f"landmark {lid!r}: pixel ({u:.1f}, {v:.1f}) is outside the {width}x{height} image")
        if image_circle is not None:
            cx, cy, r = image_circle
            if math.hypot(u - cx, v - cy) > r:
                raise ValueError(f"landmark {lid!r}: pixel ({u:.1f}, {v:.1f}) is outside the fisheye image circle")
    if len(lm) < 4:
        raise ValueError(f"need at least 4 landmarks, got {len(lm)}")
    geo = median_frame(lm.latlon)
    xy = lm.to_local(geo)
    for lid, p in zip(lm.ids, xy, strict=True):
        d = float(np.hypot(*p))
        if d > FAR_FROM_OTHERS_M:
            raise ValueError(f"landmark {lid!r} is {d / 1000:.1f} km from the others (a typo or swapped lat/lon?)")
    # Nearer, but still far for the others: one mistyped digit drags the fit so far that it rejects good landmarks
    # with it, and fails without naming the culprit. Measured against the others alone (the median and the median
    # distance from it), which the one far point cannot move. A fisheye only: it sees the ground around its pole, so a
    # point far beyond the others is a typo; a pinhole camera may look far down a road, where one landmark hundreds of
    # metres beyond the others is right (a typo there is named when it fails the fit: calibration/run.py)
    for i, lid in enumerate(lm.ids if image_circle is not None else ()):
        others = np.delete(xy, i, axis=0)
        centre = np.median(others, axis=0)
        spread = float(np.median(np.linalg.norm(others - centre, axis=1)))
        d = float(np.linalg.norm(xy[i] - centre))
        if d > max(FAR_FLOOR_M, FAR_SPREADS * spread):
            raise ValueError(f"landmark {lid!r} is {d:.0f} m from the other landmarks' median position, half of them "
                             f"lying within {spread:.0f} m of it: a typo in its latitude or longitude?")
    _check_spread(lm.ids, xy, "map", MIN_SPREAD_M, "m")
    _check_spread(lm.ids, lm.uv, "image", MIN_SPREAD_PX, "px")


def _check_spread(ids: tuple[str, ...], pts: np.ndarray, where: str, least: float, unit: str) -> None:
    centred = pts - pts.mean(axis=0)
    sv = np.linalg.svd(centred, compute_uv=False)
    if sv[0] == 0 or sv[1] / sv[0] < 0.02:
        raise ValueError(
            f"landmarks {', '.join(ids)} are (nearly) collinear in the {where}: they cannot fix a homography"
        )
    spread = float(np.sqrt(sv[1] ** 2 / len(pts)))  # the narrower way's standard deviation
    if spread < least:
        raise ValueError(f"landmarks {', '.join(ids)} lie within {spread:.2g} {unit} of each other across their "
                         f"narrower spread in the {where} (at least {least:g} {unit}): bunched at one spot, they "
                         "cannot fix the camera; spread them over the ground it sees"
                         + (" (or latitude and longitude swapped: they squeeze the map one way)" if unit == "m"
                            else ""))


def load_segment_polygons(path: str | Path) -> dict[int, np.ndarray]:
    """Read a segment polygon file (the module's docstring) -> {segment: (M, 2) [lat, lon] vertices}."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"segment polygon file not found: {path}")
    try:
        doc = json.loads(path.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: not a JSON file ({e})") from None
    if not isinstance(doc, dict) or not doc:
        raise ValueError(f'{path}: expected a JSON object from segment number to [lat, lon] vertices, e.g. '
                         '{"1": [[42.23, -83.74], [42.24, -83.74], [42.24, -83.73]]}')
    out: dict[int, np.ndarray] = {}
    for key, verts in doc.items():
        try:
            label = _whole(key)
            if not 0 <= label <= MAX_SEGMENT_NUMBER:
                raise ValueError(label)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: segment {key!r}: segment numbers are whole numbers from 0 to "
                             f"{MAX_SEGMENT_NUMBER}") from None
        try:
            poly = np.array(verts, float)
        except (TypeError, ValueError):
            raise ValueError(f"{path}: segment {label}: vertices must be [lat, lon] pairs of numbers") from None
        if poly.ndim != 2 or poly.shape[1] != 2 or len(poly) < 3:
            raise ValueError(f"{path}: segment {label}: a polygon needs at least 3 [lat, lon] vertices")
        if not np.isfinite(poly).all() or (np.abs(poly[:, 0]) > 90).any() or (np.abs(poly[:, 1]) > 180).any():
            raise ValueError(f"{path}: segment {label}: a vertex is not a latitude and longitude")
        if label in out:
            raise ValueError(f"{path}: segment {label} is given twice")
        out[label] = poly
    if len(out) > MAX_SEGMENTS:
        raise ValueError(f"{path}: {len(out)} segments; at most {MAX_SEGMENTS}")
    return out
