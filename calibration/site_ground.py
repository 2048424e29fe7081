"""One ground surface for a whole site, fitted to the landmarks of all its cameras at once.

Per camera, `calibration.fit` follows the ground with a few planes fitted to that camera's own 5-20
landmarks, and what is left of a forward-looking camera's error is the ground those planes cannot follow:
on the simulated State/Ellsworth site, thermal cameras refitted on the TRUE terrain fall from 0.31 to
0.20 m in-ROI (docs/calibration.md). The cameras of a site look at one ground, so their landmarks
together sample it far more densely than any camera's alone. `calibrate_site`:

1. calibrates every camera on its own (`calibrate`: lens, pose, outlier rejection); a camera whose fit shows its
   landmark file is wrong (the caller's `check`: the CLI's camera under its ground, a third of the landmarks
   rejected) is refused, naming it, before its landmarks can bend the surface, and so after each refit;
2. fits one surface to the height each inlier landmark implies through its camera (the landmark's ray
   met with the vertical through its map point; weighted by how steep the ray is, `implied_heights`):
   z = c + sx x + sy y + sum_k h_k exp(-|p - p_k|^2 / (2 s^2)), Gaussian bumps on a `grid_m` grid where
   there are landmarks, ridge-regularised towards the plane;
3. refits the pose and lens of each forward-looking (pinhole) camera on the surface's heights at its
   landmarks, and lifts its pixels onto the surface instead of its planes (`Calibration.ground`: where each ray
   first meets it, `calibration.fit._onto_surface`; invalid where it meets none within range);
4. repeats 2-3 (`iterations`) with the refitted cameras.

Fisheye cameras keep their own planes: their steep rays say little about height, and refitted on the
shared surface they did worse (0.250 -> 0.285 m in-ROI, against 0.325 -> 0.239 m for thermal; docs/calibration.md).
Their landmarks still feed the surface, with the low weight of a steep ray.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from calibration.fit import (
    CalibConfig,
    Calibration,
    calibrate,
    camera_from_params,
    camera_params,
    fit_camera,
    implied_heights,
)
from calibration.landmarks import Landmarks
from shared.geo import GeoFrame

# spacing (and Gaussian sigma) of the surface's bumps: chosen on bench seeds 2 and 3 (thermal in-ROI at 10 and 20
# landmarks, State/Ellsworth: 0.286 m at 12 m, 0.233 m at 20 m; the intersection's pinhole 0.230 / 0.225 m)
GRID_M = 20.0
RIDGE = 1.0  # pull of each bump towards 0, in units of a median landmark's weight
MAX_BUMPS = 400  # beyond this the grid is made coarser (about 400 x 400 m of landmarks at 20 m)
# (name, calibration, landmarks, config) -> why the camera's fit shows its landmark file is wrong, or None
SiteCheck = Callable[[str, Calibration, Landmarks, CalibConfig], "str | None"]


@dataclass(frozen=True)
class GroundSurface:
    """z = offset_m + slope . (x, y) + sum_k heights[k] exp(-|(x, y) - centres[k]|^2 / (2 sigma_m^2)), site
    metres; `cameras` names the cameras whose landmarks it was fitted to."""

    offset_m: float
    slope: tuple[float, float]
    centres: np.ndarray  # (K, 2)
    heights: np.ndarray  # (K,)
    sigma_m: float
    cameras: tuple[str, ...] = ()

    def height(self, xy: np.ndarray) -> np.ndarray:
        """(N, 2) site metres -> (N,) ground height (m). Many points at once (a whole image's rays) are read off
        a 0.5 m grid of the surface by bilinear interpolation (well under a millimetre off for bumps this wide), and
        so is every later call, however few its points, once the grid is built (a search along rays asks for fewer
        and fewer)."""
        xy = np.asarray(xy, float).reshape(-1, 2)
        if len(xy) < 20000 and "_grid" not in self.__dict__:
            return self._exact(xy)
        x0, y0, cell, grid = self._grid
        gx, gy = (xy[:, 0] - x0) / cell, (xy[:, 1] - y0) / cell
        inside = (gx >= 0) & (gy >= 0) & (gx < grid.shape[1] - 1) & (gy < grid.shape[0] - 1)
        z = np.empty(len(xy))
        i, j = np.floor(gy[inside]).astype(int), np.floor(gx[inside]).astype(int)
        fy, fx = gy[inside] - i, gx[inside] - j
        z[inside] = ((grid[i, j] * (1 - fx) + grid[i, j + 1] * fx) * (1 - fy)
                     + (grid[i + 1, j] * (1 - fx) + grid[i + 1, j + 1] * fx) * fy)
        z[~inside] = self._exact(xy[~inside])
        return z

    def _exact(self, xy: np.ndarray) -> np.ndarray:
        z = self.offset_m + xy @ np.asarray(self.slope, float)
        if not len(self.heights):
            return z
        # points over 8 sigma from the box around the bumps' centres: the bumps add under e^-32 sum |h_k| there
        lo, hi = self.centres.min(axis=0), self.centres.max(axis=0)
        near = np.flatnonzero(np.hypot(*np.maximum(np.maximum(lo - xy, xy - hi), 0.0).T) <= 8 * self.sigma_m)
        for start in range(0, len(near), 16384):  # (chunk, K) at a time
            rows = near[start:start + 16384]
            d2 = ((xy[rows, None, :] - self.centres[None]) ** 2).sum(axis=2)
            z[rows] += np.exp(-d2 / (2 * self.sigma_m**2)) @ self.heights
        return z

    @cached_property
    def _grid(self) -> tuple[float, float, float, np.ndarray]:
        """(x0, y0, cell, (H, W) heights) over the bumps' reach (4 sigma beyond the outermost centres)."""
        cell = 0.5
        lo = self.centres.min(axis=0) - 4 * self.sigma_m
        hi = self.centres.max(axis=0) + 4 * self.sigma_m
        xs, ys = np.arange(lo[0], hi[0] + cell, cell), np.arange(lo[1], hi[1] + cell, cell)
        gx, gy = np.meshgrid(xs, ys)
        heights = self._exact(np.column_stack([gx.ravel(), gy.ravel()])).reshape(gx.shape)
        return float(lo[0]), float(lo[1]), cell, heights

    @cached_property
    def relief(self) -> tuple[np.ndarray, float, float, float]:
        """(plane (a, b, c): z = a x + b y + c, lowest and highest the bumps reach from it (m), their steepest slope),
        with margins: what bounds the search along a ray for its first crossing (`calibration.fit._onto_surface`).
        Read off the 0.5 m grid; beyond it every bump is over 4 sigma away, so all together reach at most
        e^-8 sum |h_k|."""
        plane = np.array([self.slope[0], self.slope[1], self.offset_m])
        if not len(self.heights):  # the plane alone: margins still, so a ray's search starts short of its crossing
            return plane, -1e-3, 1e-3, 1e-4
        x0, y0, cell, grid = self._grid
        xs, ys = x0 + cell * np.arange(grid.shape[1]), y0 + cell * np.arange(grid.shape[0])
        bumps = grid - (self.offset_m + self.slope[0] * xs[None, :] + self.slope[1] * ys[:, None])
        gy, gx = np.gradient(bumps, cell)
        margin = 1e-3 + 0.01 * float(np.ptp(bumps)) + np.exp(-8.0) * float(np.abs(self.heights).sum())
        return (plane, min(float(bumps.min()), 0.0) - margin, max(float(bumps.max()), 0.0) + margin,
                1.25 * float(np.hypot(gx, gy).max()) + 1e-4)

    def to_dict(self) -> dict:
        return {"model": "plane + Gaussian bumps", "offset_m": round(self.offset_m, 4),
                "slope": [round(float(s), 6) for s in self.slope], "sigma_m": self.sigma_m,
                "centres_m": np.round(self.centres, 3).tolist(), "heights_m": np.round(self.heights, 4).tolist(),
                "cameras": list(self.cameras)}


def fit_ground_surface(xy: np.ndarray, z: np.ndarray, weight: np.ndarray, grid_m: float = GRID_M,
                       ridge: float = RIDGE, cameras: tuple[str, ...] = ()) -> GroundSurface:
    """Weighted ridge least squares of a `GroundSurface` to height samples z at xy (the plane unpenalised)."""
    xy, z, weight = np.asarray(xy, float).reshape(-1, 2), np.asarray(z, float), np.asarray(weight, float)
    ok = np.isfinite(xy).all(axis=1) & np.isfinite(z) & np.isfinite(weight) & (weight > 0)
    xy, z, weight = xy[ok], z[ok], weight[ok]
    if len(xy) < 3:
        raise ValueError(f"a site ground surface needs at least 3 landmark heights, got {len(xy)}")
    while True:  # bumps where there are landmarks; a site too large for MAX_BUMPS gets a coarser grid
        lo, hi = xy.min(axis=0) - grid_m, xy.max(axis=0) + grid_m
        gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1e-9, grid_m), np.arange(lo[1], hi[1] + 1e-9, grid_m))
        centres = np.column_stack([gx.ravel(), gy.ravel()])
        centres = centres[np.min(np.linalg.norm(centres[:, None] - xy[None], axis=2), axis=1) <= 2 * grid_m]
        if len(centres) <= MAX_BUMPS:
            break
        grid_m *= 1.25
    phi = np.exp(-((xy[:, None, :] - centres[None]) ** 2).sum(axis=2) / (2 * grid_m**2))
    a = np.column_stack([np.ones(len(xy)), xy, phi])
    reg = np.zeros((a.shape[1], a.shape[1]))
    reg[3:, 3:] = np.eye(len(centres)) * ridge * float(np.median(weight))
    sol = np.linalg.solve((a * weight[:, None]).T @ a + reg, (a * weight[:, None]).T @ z)
    return GroundSurface(float(sol[0]), (float(sol[1]), float(sol[2])), centres, sol[3:], grid_m, tuple(cameras))


def calibrate_site(cameras: list[tuple[str, Landmarks, CalibConfig]], geo: GeoFrame, iterations: int = 2,
                   grid_m: float = GRID_M, ridge: float = RIDGE, check: SiteCheck | None = None
                   ) -> dict[str, Calibration]:
    """Calibrate every camera of a site (name, landmarks, config), then fit one ground surface to all their
    landmarks and move the pinhole cameras onto it (module doc). Returns {name: Calibration}; the pinhole
    cameras' have `ground` set. Needs at least two cameras.

    `check(name, calibration, landmarks, config)` says why a camera's fit shows its landmark file is wrong (the
    camera under its ground, many landmarks rejected: `calibration.run`'s checks), or None. Every camera is checked
    on its own fit, before its landmarks go into the surface, and again after each refit on the surface (before
    the next surface); one that fails raises ValueError naming it: its landmarks would bend the ground every other
    camera is refitted on and lifted onto."""
    names = [name for name, _, _ in cameras]
    if len(cameras) < 2:
        raise ValueError("a site ground surface needs the landmarks of at least two cameras")
    if len(set(names)) != len(names):
        raise ValueError(f"camera names must be unique, got {names}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    cals = {}
    for name, lm, cfg in cameras:
        cals[name] = calibrate(lm, cfg, geo)
        _refuse_failed(check, name, cals[name], lm, cfg)
    for _ in range(iterations):
        xy_all, z_all, w_all = [], [], []
        for name, lm, _ in cameras:
            cal = cals[name]
            use = cal.inliers
            xy = lm.to_local(geo)[use]
            # weighted by the map error alone: with the click's share in the weights as well (as each camera's own
            # planes are) the surface did worse on the seeds its grid was chosen on (2, 3: thermal in-ROI 0.238
            # against 0.233 m) and no better on seeds 0, 1 (0.261 against 0.243 m). Measured again 2026-11-30 (bench
            # seed 0, stride 3): beyond the ROI better at 10-20 landmarks (pinhole out-ROI 1.373 -> 1.225 m, thermal
            # 1.315 -> 1.281 m; in-ROI 0.107 -> 0.107, 0.236 -> 0.230 m) but at 5 landmarks far worse (pinhole in-ROI
            # 0.627 -> 1.677 m, one camera's refit 7 -> 12 m up; thermal 0.467 -> 0.545 m): not kept
            z, w = implied_heights(cal.camera, lm.uv[use], xy, 0.0, cal.config.map_sigma_m)
            xy_all.append(xy), z_all.append(z), w_all.append(w)
        surface = fit_ground_surface(np.concatenate(xy_all), np.concatenate(z_all), np.concatenate(w_all),
                                     grid_m, ridge, tuple(names))
        for name, lm, cfg in cameras:
            if cfg.kind != "fisheye":
                cals[name] = refit_on_surface(cals[name], lm, cfg, surface, cals[name].inliers)
                _refuse_failed(check, name, cals[name], lm, cfg)
    return cals


def _refuse_failed(check: SiteCheck | None, name: str, cal: Calibration, lm: Landmarks, cfg: CalibConfig) -> None:
    """ValueError naming the camera when `check` fails its fit (`calibrate_site`)."""
    reason = check(name, cal, lm, cfg) if check is not None else None
    if reason is not None:
        stage = "refitted on the site's ground surface" if cal.ground is not None else "on its own"
        raise ValueError(f"{name} ({stage}): {reason}")


def refit_on_surface(cal: Calibration, lm: Landmarks, cfg: CalibConfig, surface: GroundSurface,
                     use: np.ndarray) -> Calibration:
    """`cal` with its lens and pose refitted on the landmarks `use` (bool mask) at the surface's heights, from
    its current camera, and its pixels lifted onto the surface (`Calibration.ground`)."""
    xy = lm.to_local(cal.geo)
    obj = np.column_stack([xy, surface.height(xy)])
    p, _, _ = fit_camera(lm.uv[use], obj[use], cfg, camera_params(cal.camera), robust=False)
    return replace(cal, camera=camera_from_params(p, cfg), ground=surface)

