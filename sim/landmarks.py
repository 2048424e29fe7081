"""Ground landmarks per camera, picked the way a person would, with a documented noise model.

Candidates are painted features a person can click both in the image and on an orthophoto:
crosswalk stripe corners, dash ends of lane lines, yield-line tooth tips, stop-line ends,
island noses, parking stall line ends. A candidate counts for a camera when it is inside the
image (away from the edge, and for fisheye not at the extreme rim), within range, and not
hidden by scenery. Landmarks are ordered by farthest-point sampling in the image, so the
first N of them are well spread for any N.

Noise model (`LandmarkNoise`): the clicked pixel has isotropic Gaussian error
(`pixel_sigma_px`), the map position isotropic Gaussian error (`map_sigma_m`, as when reading
an orthophoto), and with probability `gross_rate` the landmark is a gross mistake: either the
pixel (half the cases) is off by a uniform 25-60 px in a random direction, or the map point is
off by a uniform 4-10 m (e.g. the neighbouring stripe). Truth is kept beside the noisy values.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from shared.cameras import Camera
from shared.geo import GeoFrame
from shared.ground import Terrain


@dataclass(frozen=True)
class LandmarkNoise:
    pixel_sigma_px: float = 2.0
    map_sigma_m: float = 0.15
    gross_rate: float = 0.05
    gross_pixel_px: tuple[float, float] = (25.0, 60.0)
    gross_map_m: tuple[float, float] = (4.0, 10.0)

    def to_dict(self) -> dict:
        return asdict(self)


def apply_noise(
    uv: np.ndarray, xy: np.ndarray, rng: np.random.Generator, noise: LandmarkNoise
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy (uv (N, 2), xy (N, 2)) and (N,) gross-mistake flags for true pixels / map metres."""
    n = len(uv)
    uv_n = uv + rng.normal(0, noise.pixel_sigma_px, (n, 2))
    xy_n = xy + rng.normal(0, noise.map_sigma_m, (n, 2))
    gross = rng.random(n) < noise.gross_rate
    in_pixel = rng.random(n) < 0.5
    ang = rng.uniform(0, 2 * math.pi, n)
    unit = np.stack([np.cos(ang), np.sin(ang)], 1)
    mag_px = rng.uniform(*noise.gross_pixel_px, n)
    mag_m = rng.uniform(*noise.gross_map_m, n)
    uv_n = np.where((gross & in_pixel)[:, None], uv_n + unit * mag_px[:, None], uv_n)
    xy_n = np.where((gross & ~in_pixel)[:, None], xy_n + unit * mag_m[:, None], xy_n)
    return uv_n, xy_n, gross


def _farthest_point_order(uv: np.ndarray, start: int) -> np.ndarray:
    order = [start]
    d = np.linalg.norm(uv - uv[start], axis=1)
    for _ in range(len(uv) - 1):
        k = int(np.argmax(d))
        order.append(k)
        d = np.minimum(d, np.linalg.norm(uv - uv[k], axis=1))
    return np.array(order)


def pick_landmarks(
    camera: Camera,
    features: list[tuple[float, float, str]],
    terrain: Terrain,
    geo: GeoFrame,
    static_depth: np.ndarray,
    rng: np.random.Generator,
    count: int = 30,
    noise: LandmarkNoise = LandmarkNoise(),
) -> list[dict]:
    """Up to `count` landmarks for one camera (see the module doc for how they are chosen)."""
    if not features:
        return []
    xy = np.array([[f[0], f[1]] for f in features])
    kinds = [f[2] for f in features]
    z = terrain.height(xy[:, 0], xy[:, 1])
    pts = np.column_stack([xy, z])
    uv, ok = camera.project(pts)
    ok &= camera.in_image(uv, margin_px=15)
    dist = np.linalg.norm(pts - camera.pose.position_m, axis=1)
    max_range = 55.0 if camera.kind == "fisheye" else 140.0
    ok &= dist < max_range
    if camera.kind == "fisheye":
        rays = camera.pose.to_camera(pts)
        theta = np.degrees(np.arctan2(np.hypot(rays[:, 0], rays[:, 1]), rays[:, 2]))
        ok &= theta < 80
    idx = np.nonzero(ok)[0]
    if idx.size == 0:
        return []
    px = np.clip(np.round(uv[idx]).astype(int), 0, [camera.width - 1, camera.height - 1])
    visible = static_depth[px[:, 1], px[:, 0]] >= dist[idx] - 0.3
    idx = idx[visible]
    if idx.size == 0:
        return []
    # Drop near-duplicates (two corners of one stripe 0.6 m apart are one click apart).
    keep: list[int] = []
    for i in idx:
        if all(np.linalg.norm(uv[i] - uv[j]) > 12 for j in keep):
            keep.append(int(i))
    keep_a = np.array(keep)
    centre = np.array([camera.cx, camera.cy])
    start = int(np.argmin(np.linalg.norm(uv[keep_a] - centre, axis=1)))
    chosen = keep_a[_farthest_point_order(uv[keep_a], start)][:count]
    uv_n, xy_n, gross = apply_noise(uv[chosen], xy[chosen], rng, noise)
    ll_true = geo.to_geodetic(pts[chosen])
    ll_noisy = geo.to_geodetic(np.column_stack([xy_n, z[chosen]]))
    out = []
    for k, i in enumerate(chosen):
        out.append(
            {
                "id": f"L{k + 1:02d}",
                "u": round(float(uv_n[k, 0]), 2),
                "v": round(float(uv_n[k, 1]), 2),
                "lat": round(float(ll_noisy[k, 0]), 9),
                "lon": round(float(ll_noisy[k, 1]), 9),
                "kind": kinds[i],
                "truth": {
                    "u": round(float(uv[i, 0]), 3),
                    "v": round(float(uv[i, 1]), 3),
                    "lat": round(float(ll_true[k, 0]), 10),
                    "lon": round(float(ll_true[k, 1]), 10),
                    "xyz": np.round(pts[i], 4).tolist(),
                },
                "gross": bool(gross[k]),
            }
        )
    return out
