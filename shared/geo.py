"""WGS84 latitude/longitude/altitude <-> the local site frame.

The site frame is East-North-Up (ENU) in metres around a site origin (a WGS84 point).
Conversions are exact (pymap3d's ellipsoidal ENU), not a flat-earth approximation.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pymap3d


@dataclass(frozen=True)
class GeoFrame:
    """A local ENU frame anchored at (lat0_deg, lon0_deg, alt0_m) on the WGS84 ellipsoid."""

    lat0_deg: float
    lon0_deg: float
    alt0_m: float = 0.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.lat0_deg) or not -90.0 <= self.lat0_deg <= 90.0:
            raise ValueError(f"lat0_deg must be in [-90, 90], got {self.lat0_deg}")
        if not np.isfinite(self.lon0_deg) or not -180.0 <= self.lon0_deg <= 180.0:
            raise ValueError(f"lon0_deg must be in [-180, 180], got {self.lon0_deg}")
        if not np.isfinite(self.alt0_m):
            raise ValueError(f"alt0_m must be finite, got {self.alt0_m}")

    def to_enu(self, lat_deg: np.ndarray, lon_deg: np.ndarray, alt_m: np.ndarray | float = 0.0) -> np.ndarray:
        """(N,) latitudes/longitudes in degrees -> (N, 3) float64 metres, site ENU frame.

        `alt_m` is the ellipsoidal height; pass the site's ground altitude to get z near 0.
        """
        lat = np.asarray(lat_deg, dtype=np.float64)
        lon = np.asarray(lon_deg, dtype=np.float64)
        alt = np.broadcast_to(np.asarray(alt_m, dtype=np.float64), lat.shape)
        e, n, u = pymap3d.geodetic2enu(lat, lon, alt, self.lat0_deg, self.lon0_deg, self.alt0_m)
        return np.stack([np.asarray(e), np.asarray(n), np.asarray(u)], axis=-1)

    def to_geodetic(self, enu_m: np.ndarray) -> np.ndarray:
        """(N, 3) or (N, 2) metres in the site ENU frame -> (N, 3) float64 [lat_deg, lon_deg, alt_m].

        (N, 2) input is taken at z = 0 (the origin's height).
        """
        p = np.asarray(enu_m, dtype=np.float64)
        if p.shape[-1] == 2:
            p = np.concatenate([p, np.zeros((*p.shape[:-1], 1))], axis=-1)
        if p.shape[-1] != 3:
            raise ValueError(f"enu_m must have 2 or 3 columns, got shape {p.shape}")
        lat, lon, alt = pymap3d.enu2geodetic(p[..., 0], p[..., 1], p[..., 2], self.lat0_deg, self.lon0_deg, self.alt0_m)
        return np.stack([np.asarray(lat), np.asarray(lon), np.asarray(alt)], axis=-1)

    def to_dict(self) -> dict:
        return {"lat_deg": self.lat0_deg, "lon_deg": self.lon0_deg, "alt_m": self.alt0_m}

    @classmethod
    def from_dict(cls, d: dict) -> GeoFrame:
        return cls(float(d["lat_deg"]), float(d["lon_deg"]), float(d.get("alt_m", 0.0)))
