"""The ground surface of a site: a smooth height field z = h(x, y), and ray/ground intersection.

Real roads are not one plane (cross-fall, crowns, a raised central island), which is why the
paper fits piecewise-planar homographies. The simulator and the exact pixel -> ground lookup
share this model, so calibration is scored against the same surface the images were made of.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields

import numpy as np

from shared.cameras import Camera


@dataclass(frozen=True)
class Bump:
    """A Gaussian rise (or dip, negative height) of the ground."""

    x_m: float
    y_m: float
    sigma_m: float
    height_m: float


@dataclass(frozen=True)
class Terrain:
    """z = slope_x * x + slope_y * y + sum of Gaussian bumps (metres, site frame)."""

    slope_x: float = 0.0
    slope_y: float = 0.0
    bumps: tuple[Bump, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        for name in ("slope_x", "slope_y"):
            v = getattr(self, name)
            if not np.isfinite(v) or abs(v) > 0.15:
                raise ValueError(f"terrain.{name} must be a finite grade within +-0.15, got {v}")
        for i, b in enumerate(self.bumps):
            if not b.sigma_m > 0:
                raise ValueError(f"terrain.bumps[{i}].sigma_m must be > 0, got {b.sigma_m}")

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Ground height (m) at site coordinates x, y (any matching shapes)."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        z = self.slope_x * x + self.slope_y * y
        for b in self.bumps:
            z = z + b.height_m * np.exp(-((x - b.x_m) ** 2 + (y - b.y_m) ** 2) / (2 * b.sigma_m**2))
        return z

    def gradient(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        gx = np.full_like(x, self.slope_x)
        gy = np.full_like(y, self.slope_y)
        for b in self.bumps:
            e = b.height_m * np.exp(-((x - b.x_m) ** 2 + (y - b.y_m) ** 2) / (2 * b.sigma_m**2))
            gx = gx - e * (x - b.x_m) / b.sigma_m**2
            gy = gy - e * (y - b.y_m) / b.sigma_m**2
        return gx, gy

    def intersect(
        self, origin_m: np.ndarray, dirs: np.ndarray, max_range_m: float = 1e4
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Rays from `origin_m` (3,) along `dirs` (N, 3) -> (points (N, 3), t (N,), valid (N,)).

        `t` is the distance along each unit ray. Newton's method on the height field, started
        from the z = 0 plane; rays that do not descend, or meet the ground beyond
        `max_range_m`, are invalid.
        """
        o = np.asarray(origin_m, dtype=np.float64)
        d = np.asarray(dirs, dtype=np.float64)
        dz = d[..., 2]
        descending = dz < -1e-6
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(descending, (self.height(o[0], o[1]) - o[2]) / np.where(descending, dz, -1), 0.0)
        t = np.clip(t, 0.0, max_range_m * 2)
        for _ in range(8):
            px = o[0] + t * d[..., 0]
            py = o[1] + t * d[..., 1]
            f = o[2] + t * dz - self.height(px, py)
            gx, gy = self.gradient(px, py)
            df = dz - gx * d[..., 0] - gy * d[..., 1]
            step = np.where(np.abs(df) > 1e-9, f / np.where(np.abs(df) > 1e-9, df, 1.0), 0.0)
            t = np.clip(t - step, 0.0, max_range_m * 2)
        pts = o + t[..., None] * d
        residual = np.abs(pts[..., 2] - self.height(pts[..., 0], pts[..., 1]))
        valid = descending & (t > 0) & (t <= max_range_m) & (residual < 1e-4)
        return pts, t, valid

    def to_dict(self) -> dict:
        return {
            "slope_x": self.slope_x,
            "slope_y": self.slope_y,
            "bumps": [{"x_m": b.x_m, "y_m": b.y_m, "sigma_m": b.sigma_m, "height_m": b.height_m} for b in self.bumps],
        }

    @classmethod
    def from_dict(cls, d: dict | None) -> Terrain:
        """The terrain of `to_dict`, or of a site file's `terrain:` section (every key optional, None: flat).
        Raises ValueError naming the entry (`terrain.bumps[1].sigma_m`) that is unknown, missing or not a finite
        number."""
        if d is None:
            d = {}
        if not isinstance(d, dict):
            raise ValueError(f"terrain must be a mapping of slope_x, slope_y and bumps, got {d!r}")
        _check_keys("terrain", d, ("slope_x", "slope_y", "bumps"), ())
        raw_bumps = d.get("bumps")
        if raw_bumps is None:  # `bumps:` with nothing after it
            raw_bumps = []
        if not isinstance(raw_bumps, list | tuple):
            raise ValueError(f"terrain.bumps must be a list of bumps (each x_m, y_m, sigma_m, height_m), "
                             f"got {raw_bumps!r}")
        names = tuple(f.name for f in fields(Bump))
        bumps = []
        for i, b in enumerate(raw_bumps):
            where = f"terrain.bumps[{i}]"
            if not isinstance(b, dict):
                raise ValueError(f"{where} must be a mapping of {', '.join(names)}, got {b!r}")
            _check_keys(where, b, names, names)
            bumps.append(Bump(*(_number(f"{where}.{k}", b[k]) for k in names)))
        return cls(
            _number("terrain.slope_x", d.get("slope_x", 0.0)),
            _number("terrain.slope_y", d.get("slope_y", 0.0)),
            tuple(bumps),
        )


def _check_keys(where: str, d: dict, known: tuple[str, ...], required: tuple[str, ...]) -> None:
    """ValueError naming the first key of `d` not in `known`, or the first of `required` missing."""
    for k in d:
        if k not in known:
            raise ValueError(f"{where}: unknown key {k!r} (known: {', '.join(known)})")
    for k in required:
        if k not in d:
            raise ValueError(f"{where}: {k} is missing")


def _number(where: str, v: object) -> float:
    """`v` as a float; ValueError naming `where` unless it is a finite real number, or a string of one (YAML reads
    `6e-3` as a string), and not a bool."""
    try:
        x = float(v) if isinstance(v, str) else v
    except ValueError:
        x = None
    if isinstance(x, bool) or not isinstance(x, numbers.Real) or not math.isfinite(x):
        raise ValueError(f"{where} must be a finite number, got {v!r}")
    return float(x)


def ground_lookup(camera: Camera, terrain: Terrain, max_range_m: float = 1e3) -> tuple[np.ndarray, np.ndarray]:
    """The exact pixel -> ground lookup of a camera: the ray through each pixel centre met with
    the ground.

    Returns ((H, W, 3) float64 site-frame metres, (H, W) bool valid). Invalid pixels: outside
    the lens FOV / image circle, looking above the horizon, or meeting the ground beyond
    `max_range_m`. Occlusion by objects standing on the ground is not considered here.
    """
    grid = camera.pixel_grid().reshape(-1, 2)
    dirs, ok = camera.unproject(grid)
    pts, _, hit = terrain.intersect(camera.pose.position_m, dirs, max_range_m)
    valid = ok & hit & camera.in_image(grid)
    h, w = camera.height, camera.width
    return pts.reshape(h, w, 3), valid.reshape(h, w)
