"""A georeferenced top-down image (orthophoto or simulator render) placed in the site ENU frame.

A `Basemap` is an image plus the site-frame positions (metres) of its four outer corners. It is built
from one of:

- `Basemap.from_array(image, extent_m)`: an in-memory (H, W) grey or (H, W, 3) RGB uint8 array whose
  row 0 is the north edge, covering `extent_m = (x_min, x_max, y_min, y_max)` in site metres.
- `Basemap.from_corners(image, top_left, bottom_right, origin)`: a north-up image (array or PNG/JPG
  path) whose top-left and bottom-right outer pixel corners are at the given (lat, lon) degrees
  (WGS84); `origin` is the site's GeoFrame. All four corners are converted exactly, so the small
  rotation of true north against the site's ENU axes away from the origin is kept.
- `Basemap.from_world_file(path, origin=None)`: a small YAML or JSON file (JSON is valid YAML)::

      image: ortho.jpg                 # PNG/JPG, relative to this file
      # either the geodetic outer corners of a north-up image ...
      top_left: {lat: 42.2815, lon: -83.7420}      # or [lat, lon]
      bottom_right: {lat: 42.2797, lon: -83.7396}
      # ... or its extent in site metres (row 0 = north edge):
      # extent_m: [x_min, x_max, y_min, y_max]
      origin: {lat_deg: 42.2806, lon_deg: -83.7408, alt_m: 0.0}   # optional: used when no `origin` is passed

  or the four outer corners `{"tl": [lat, lon], "tr": ..., "bl": ..., "br": ...}` (as the State/Ellsworth
  orthophoto's `roundabout.json`), the image then being the PNG/JPG of the same name beside the file
  unless `image` names it. `path` may also be a folder holding exactly one such JSON file.

  The site frame is the tracks': the `origin` argument (the site's, `--site`) places lat/lon corners, and the
  file's own `origin` only when none is passed. One that is more than `ORIGIN_TOLERANCE_M` from the passed
  origin is a ValueError naming both (with it the map would sit that far off under the tracks).

The image is kept as uint8, (H, W) or (H, W, 3) RGB, reduced to at most `max_side_px` pixels on its
long side (a GPU texture limit, and it keeps the .rrd small).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from shared.files import visible_files
from shared.geo import GeoFrame

MAX_SIDE_PX = 4096
CORNER_KEYS = ("tl", "tr", "bl", "br")
FAR_FROM_SITE_M = 10_000.0  # a map with a corner further than this from the site's origin is another place's
ORIGIN_TOLERANCE_M = 0.5  # a world file's origin this far (horizontally) from the site's contradicts it


@dataclass(frozen=True)
class Basemap:
    """image: (H, W) or (H, W, 3) uint8 RGB, row 0 the top (north) edge.
    corners_m: (4, 2) float64 metres, site ENU frame: the outer corners top-left, top-right,
    bottom-right, bottom-left of the image."""

    image: np.ndarray
    corners_m: np.ndarray

    def __post_init__(self) -> None:
        img = self.image
        if not isinstance(img, np.ndarray) or img.dtype != np.uint8:
            raise ValueError(f"basemap image must be a uint8 numpy array, got {getattr(img, 'dtype', type(img))}")
        if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) or min(img.shape[:2]) < 1:
            raise ValueError(f"basemap image must have shape (H, W) or (H, W, 3), got {img.shape}")
        c = np.asarray(self.corners_m, dtype=np.float64)
        if c.shape != (4, 2) or not np.all(np.isfinite(c)):
            raise ValueError(f"basemap corners_m must be (4, 2) finite metres, got {self.corners_m!r}")
        object.__setattr__(self, "corners_m", c)

    @property
    def extent_m(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) metres, site frame: the bounding box of the corners."""
        c = self.corners_m
        return float(c[:, 0].min()), float(c[:, 0].max()), float(c[:, 1].min()), float(c[:, 1].max())

    @classmethod
    def from_array(cls, image: np.ndarray, extent_m: Sequence[float], *, max_side_px: int = MAX_SIDE_PX) -> Basemap:
        """`image` (H, W) grey or (H, W, 3) RGB (uint8, or float in [0, 1]), row 0 = north edge;
        `extent_m` (x_min, x_max, y_min, y_max) metres, site frame, of its outer edges."""
        ext = np.asarray(extent_m, dtype=np.float64).reshape(-1)
        if ext.shape != (4,) or not np.all(np.isfinite(ext)) or ext[0] >= ext[1] or ext[2] >= ext[3]:
            raise ValueError(f"extent_m must be finite (x_min, x_max, y_min, y_max) with min < max, got {extent_m!r}")
        x0, x1, y0, y1 = ext
        corners = np.array([[x0, y1], [x1, y1], [x1, y0], [x0, y0]])
        return cls(_as_uint8(image, max_side_px), corners)

    @classmethod
    def from_corners(
        cls,
        image: np.ndarray | str | Path,
        top_left: Sequence[float],
        bottom_right: Sequence[float],
        origin: GeoFrame,
        *,
        max_side_px: int = MAX_SIDE_PX,
    ) -> Basemap:
        """A north-up image (array, or a PNG/JPG path) whose outer corners are at `top_left` and
        `bottom_right` = (lat_deg, lon_deg); placed in the site frame of `origin`."""
        if not isinstance(origin, GeoFrame):
            raise ValueError(f"a basemap georeferenced by lat/lon needs the site origin (a GeoFrame), got {origin!r}")
        lat_t, lon_l = _latlon(top_left, "top_left")
        lat_b, lon_r = _latlon(bottom_right, "bottom_right")
        if not (lat_t > lat_b and lon_r > lon_l):
            raise ValueError(f"top_left {tuple(top_left)} must be north-west of bottom_right {tuple(bottom_right)}")
        lat = np.array([lat_t, lat_t, lat_b, lat_b])
        lon = np.array([lon_l, lon_r, lon_r, lon_l])
        corners = origin.to_enu(lat, lon, origin.alt0_m)[:, :2]
        _near_site(corners, "top_left and bottom_right")
        img = load_image(image) if isinstance(image, str | Path) else image
        return cls(_as_uint8(img, max_side_px), corners)

    @classmethod
    def from_world_file(
        cls, path: str | Path, origin: GeoFrame | None = None, *, max_side_px: int = MAX_SIDE_PX
    ) -> Basemap:
        """Read the YAML/JSON world file described in the module docstring."""
        import yaml

        path = Path(path)
        if path.is_dir():
            found = visible_files(path, "*.json") + visible_files(path, "*.yaml")
            if len(found) != 1:
                raise ValueError(f"basemap folder {path} must hold exactly one .json/.yaml world file, "
                                 f"found {len(found)}")
            path = found[0]
        if not path.is_file():
            raise FileNotFoundError(f"basemap world file not found: {path}")
        try:
            spec = yaml.safe_load(path.read_text())
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise ValueError(f"basemap world file {path} is not valid YAML or JSON: "
                             f"{str(exc).strip().splitlines()[0]}") from None
        corners4 = isinstance(spec, Mapping) and all(k in spec for k in CORNER_KEYS)
        if not isinstance(spec, Mapping) or ("image" not in spec and not corners4):
            raise ValueError(f"basemap world file {path} must be a mapping with an 'image' key, or the corners "
                             f"{', '.join(CORNER_KEYS)} of an image beside it")
        if "image" in spec:
            image = load_image(path.parent / str(spec["image"]))
        else:
            beside = [path.with_suffix(ext) for ext in (".jpg", ".jpeg", ".png")]
            image_path = next((q for q in beside if q.is_file()), None)
            if image_path is None:
                raise FileNotFoundError(f"basemap image not found beside {path} (looked for {path.stem}.jpg/.png)")
            image = load_image(image_path)
        if corners4:
            if "origin" in spec:
                origin = _site_origin(origin, _origin(spec["origin"], path), path)
            if not isinstance(origin, GeoFrame):
                raise ValueError(f"basemap world file {path} gives lat/lon corners but no site origin")
            ll = np.array([_latlon(spec[k], k) for k in ("tl", "tr", "br", "bl")])
            corners = origin.to_enu(ll[:, 0], ll[:, 1], origin.alt0_m)[:, :2]
            _near_site(corners, f"{path}: the corners")
            _upright(corners, path)
            return cls(_as_uint8(image, max_side_px), corners)
        if "extent_m" in spec:
            if "origin" in spec:  # site metres about another origin than the site's: the map would sit off
                _site_origin(origin, _origin(spec["origin"], path), path)
            return cls.from_array(image, spec["extent_m"], max_side_px=max_side_px)
        if "top_left" not in spec or "bottom_right" not in spec:
            raise ValueError(f"basemap world file {path} needs either 'extent_m' or 'top_left' and 'bottom_right'")
        if "origin" in spec:
            origin = _site_origin(origin, _origin(spec["origin"], path), path)
        if origin is None:
            raise ValueError(
                f"basemap world file {path} gives lat/lon corners but no site origin "
                "(add 'origin' to the file or pass the site origin)"
            )
        return cls.from_corners(image, spec["top_left"], spec["bottom_right"], origin, max_side_px=max_side_px)


def _near_site(corners: np.ndarray, what: str) -> None:
    """ValueError when a corner (site metres) is further than `FAR_FROM_SITE_M` from the site's origin."""
    far = float(np.max(np.linalg.norm(corners, axis=1)))
    if far > FAR_FROM_SITE_M:
        raise ValueError(f"{what} put the basemap {far / 1000:.0f} km from the site's origin: another place's map, "
                         "or latitude and longitude swapped ([lat, lon] each)")


def _upright(corners: np.ndarray, path: Path) -> None:
    """ValueError unless the corners tl, tr, br, bl (site metres, x east, y north) are an image's, the right way
    round: top above bottom, left west of right (turned by less than 45 degrees), not mirrored, with an area."""
    tl, tr, br, bl = corners
    e = corners - corners.mean(axis=0)
    area = 0.5 * float(np.sum(e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1)))
    if not (tl[1] > bl[1] and tr[1] > br[1] and tr[0] > tl[0] and br[0] > bl[0]) or area > -1.0:
        raise ValueError(f"basemap world file {path}: the corners tl, tr, br, bl are not those of an image with its "
                         "top to the north and its left to the west (swapped or mirrored corners?)")


def _site_origin(site: GeoFrame | None, own: GeoFrame, path: Path) -> GeoFrame:
    """The origin that places a world file's lat/lon corners: the site's (`site`, the tracks' frame) when given,
    else the file's own; ValueError naming both when they are more than `ORIGIN_TOLERANCE_M` apart."""
    if site is None:
        return own
    if not isinstance(site, GeoFrame):
        raise ValueError(f"the site origin must be a GeoFrame, got {site!r}")
    apart = float(np.hypot(*site.to_enu(np.array([own.lat0_deg]), np.array([own.lon0_deg]), site.alt0_m)[0, :2]))
    if apart > ORIGIN_TOLERANCE_M:
        raise ValueError(
            f"basemap world file {path}: its origin (lat {own.lat0_deg}, lon {own.lon0_deg}) is {apart:.1f} m from "
            f"the site origin (lat {site.lat0_deg}, lon {site.lon0_deg}), the tracks' frame: remove the file's "
            "origin or make it the site's"
        )
    return site


def _origin(value: object, path: Path) -> GeoFrame:
    try:
        return GeoFrame.from_dict(value)
    except (KeyError, TypeError, AttributeError) as exc:
        raise ValueError(f"basemap world file {path}: origin must be {{lat_deg, lon_deg[, alt_m]}}, got {value!r} "
                         f"({type(exc).__name__}: {exc})") from None


def load_image(path: str | Path) -> np.ndarray:
    """A PNG/JPG file -> (H, W) or (H, W, 3) uint8 RGB."""
    import cv2

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"basemap image not found: {path}")
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ValueError(f"cannot decode basemap image {path}")
    if img.dtype != np.uint8:
        img = (img / 257).astype(np.uint8) if img.dtype == np.uint16 else img.astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 4:
        img = img[:, :, :3]
    if img.ndim == 3:
        img = np.ascontiguousarray(img[:, :, ::-1])  # OpenCV's BGR -> RGB
    return img


def _latlon(value: Sequence[float] | Mapping, name: str) -> tuple[float, float]:
    if isinstance(value, Mapping):
        value = (value.get("lat"), value.get("lon"))
    try:
        lat, lon = (float(v) for v in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be (lat, lon) degrees, got {value!r}") from None
    if not (np.isfinite(lat) and np.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
        raise ValueError(f"{name} must be (lat, lon) degrees, got {value!r}")
    return lat, lon


def _as_uint8(image: np.ndarray, max_side_px: int) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)) or min(img.shape[:2]) < 1:
        raise ValueError(f"basemap image must have shape (H, W) or (H, W, 3), got {img.shape}")
    if img.dtype != np.uint8:
        if img.dtype.kind != "f":
            raise ValueError(f"basemap image must be uint8, or float in [0, 1], got dtype {img.dtype}")
        img = (np.clip(np.nan_to_num(img), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    scale = max_side_px / max(img.shape[:2])
    if scale < 1.0:
        import cv2

        size = (max(1, round(img.shape[1] * scale)), max(1, round(img.shape[0] * scale)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    return np.ascontiguousarray(img)
