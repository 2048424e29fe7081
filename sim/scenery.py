"""Static 3D objects of a site: camera and light poles, signs, signal masts, trees, bushes,
buildings. Each is a set of primitives (oriented boxes and spheres) with a colour and a
thermal level, so the renderer can ray-cast them and they occlude vehicles like real ones.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from shared.ground import Terrain
from sim.roads import RoadNetwork
from sim.site import SiteSpec
from sim.texture import GRASS, GroundRaster


@dataclass
class Primitives:
    """Struct of arrays. Boxes: centre (B, 3) of the box, half sizes (B, 3) in its own frame,
    yaw (B,), rgb (B, 3) float, thermal (B,) 0..1. Spheres: centre (S, 3), radius (S,), rgb, thermal."""

    box_center: list = field(default_factory=list)
    box_half: list = field(default_factory=list)
    box_yaw: list = field(default_factory=list)
    box_rgb: list = field(default_factory=list)
    box_thermal: list = field(default_factory=list)
    sph_center: list = field(default_factory=list)
    sph_radius: list = field(default_factory=list)
    sph_rgb: list = field(default_factory=list)
    sph_thermal: list = field(default_factory=list)

    def box(self, center, half, yaw: float, rgb, thermal: float) -> None:
        self.box_center.append(np.asarray(center, float))
        self.box_half.append(np.asarray(half, float))
        self.box_yaw.append(float(yaw))
        self.box_rgb.append(np.asarray(rgb, float))
        self.box_thermal.append(float(thermal))

    def sphere(self, center, radius: float, rgb, thermal: float) -> None:
        self.sph_center.append(np.asarray(center, float))
        self.sph_radius.append(float(radius))
        self.sph_rgb.append(np.asarray(rgb, float))
        self.sph_thermal.append(float(thermal))

    def arrays(self) -> dict[str, np.ndarray]:
        def arr(x, shape):
            return np.asarray(x, float).reshape(shape)

        return {
            "box_center": arr(self.box_center, (-1, 3)),
            "box_half": arr(self.box_half, (-1, 3)),
            "box_yaw": arr(self.box_yaw, (-1,)),
            "box_rgb": arr(self.box_rgb, (-1, 3)),
            "box_thermal": arr(self.box_thermal, (-1,)),
            "sph_center": arr(self.sph_center, (-1, 3)),
            "sph_radius": arr(self.sph_radius, (-1,)),
            "sph_rgb": arr(self.sph_rgb, (-1, 3)),
            "sph_thermal": arr(self.sph_thermal, (-1,)),
        }


def _vertical(
    prims: Primitives, terrain: Terrain, xy, size_xy, height: float, yaw: float, rgb, thermal: float, z0: float = 0.0
) -> None:
    g = float(terrain.height(xy[0], xy[1]))
    prims.box([xy[0], xy[1], g + z0 + height / 2], [size_xy[0] / 2, size_xy[1] / 2, height / 2], yaw, rgb, thermal)


def build_scenery(site: SiteSpec, net: RoadNetwork, ground: GroundRaster, seed: int) -> Primitives:
    rng = np.random.default_rng([seed, 13])
    terrain = site.ground
    prims = Primitives()
    grey = (118, 120, 122)
    cams = [(c.position_m, c.pole_offset_m) for c in site.cameras]
    # Camera poles: a mast beside the camera with an arm reaching out to it, and the housing.
    done = set()
    for pos, off in cams:
        off = off if off is not None else (1.8 * math.copysign(1, pos[0] or 1), 1.2 * math.copysign(1, pos[1] or 1))
        base = (round(pos[0] + off[0], 1), round(pos[1] + off[1], 1))
        if base not in done:
            done.add(base)
            _vertical(prims, terrain, base, (0.32, 0.32), pos[2] + 0.8, 0.0, grey, 0.42)
        arm_c = np.array([(pos[0] + base[0]) / 2, (pos[1] + base[1]) / 2, pos[2] + 0.35])
        arm_len = math.hypot(off[0], off[1])
        prims.box(arm_c, [arm_len / 2, 0.06, 0.06], math.atan2(-off[1], -off[0]), grey, 0.42)
        prims.box([pos[0], pos[1], pos[2] + 0.2], [0.12, 0.12, 0.12], 0.0, (40, 40, 42), 0.55)
    # Light poles along the legs, at the sidewalk's outer edge.
    for leg in site.approaches:
        u, r = leg.unit_out, leg.unit_right
        d = net.junction_radius_m + 12.0
        side = 1.0
        while d < site.extent_m * 0.95:
            xy = u * d + r * side * (leg.half_width_m + 4.6)
            _vertical(prims, terrain, xy, (0.25, 0.25), 9.0, 0.0, grey, 0.4)
            arm = xy - r * side * 1.5
            prims.box(
                [arm[0], arm[1], float(terrain.height(*xy)) + 8.9], [1.5, 0.08, 0.08], math.atan2(r[1], r[0]), grey, 0.4
            )
            d += 32.0
            side = -side
        # A sign on the right of the inbound lanes before the junction.
        sxy = u * (net.junction_radius_m + 6.0) - r * (leg.half_width_m + 0.9)
        _vertical(prims, terrain, sxy, (0.08, 0.08), 2.2, 0.0, grey, 0.45)
        gz = float(terrain.height(*sxy))
        plate = (220, 30, 30) if site.layout == "roundabout" else (30, 110, 60)
        prims.box([sxy[0], sxy[1], gz + 2.55], [0.45, 0.04, 0.45], math.atan2(u[1], u[0]) + math.pi / 2, plate, 0.5)
        if site.layout == "intersection":
            # Signal mast over the inbound lanes with three signal heads.
            mxy = u * (net.junction_radius_m + 1.0) - r * (leg.half_width_m + 1.2)
            _vertical(prims, terrain, mxy, (0.35, 0.35), 6.5, 0.0, (70, 72, 70), 0.45)
            reach = leg.lanes_in * leg.lane_width_m + 1.0
            mid = mxy + r * reach / 2
            mz = float(terrain.height(*mxy)) + 6.2
            prims.box([mid[0], mid[1], mz], [reach / 2, 0.1, 0.1], math.atan2(r[1], r[0]), (70, 72, 70), 0.45)
            for k in range(leg.lanes_in):
                hxy = mxy + r * (1.0 + (k + 0.5) * leg.lane_width_m)
                prims.box([hxy[0], hxy[1], mz - 0.6], [0.2, 0.18, 0.5], math.atan2(r[1], r[0]), (30, 30, 30), 0.5)
    # Buildings.
    for b in site.buildings:
        gz = float(terrain.height(*b.center_m))
        wall = tuple(int(c) for c in rng.choice([(170, 160, 150), (140, 110, 90), (190, 185, 175), (120, 120, 130)]))
        prims.box(
            [b.center_m[0], b.center_m[1], gz + b.height_m / 2 - 0.5],
            [b.size_m[0] / 2, b.size_m[1] / 2, b.height_m / 2 + 0.5],
            math.radians(90 - b.yaw_deg),
            wall,
            0.5,
        )
    # Trees and bushes on grass, away from roads, cameras and buildings.
    dist_ok = _far_from_road(ground, site.trees.min_road_gap_m)
    placed: list[np.ndarray] = []
    cam_xy = np.array([[c[0][0], c[0][1]] for c in cams])
    tries = 0
    while len(placed) < site.trees.count and tries < 20000:
        tries += 1
        xy = rng.uniform(-site.extent_m * 0.97, site.extent_m * 0.97, 2)
        if not dist_ok(xy):
            continue
        if np.min(np.linalg.norm(cam_xy - xy, axis=1)) < 9.0:
            continue
        if placed and np.min(np.linalg.norm(np.array(placed) - xy, axis=1)) < 5.0:
            continue
        if any(
            abs(xy[0] - b.center_m[0]) < b.size_m[0] / 2 + 4 and abs(xy[1] - b.center_m[1]) < b.size_m[1] / 2 + 4
            for b in site.buildings
        ):
            continue
        placed.append(xy)
        gz = float(terrain.height(*xy))
        if rng.random() < 0.25:
            r = rng.uniform(0.7, 1.3)
            prims.sphere([xy[0], xy[1], gz + 0.6 * r], r, (60 + rng.normal(0, 8), 80 + rng.normal(0, 8), 45), 0.33)
            continue
        trunk_h = rng.uniform(2.0, 3.5)
        _vertical(prims, terrain, xy, (0.35, 0.35), trunk_h + 1.0, 0.0, (80, 62, 45), 0.36)
        leafless = rng.random() < 0.5  # December: many trees are bare
        canopy_r = rng.uniform(1.8, 3.6)
        rgb = (110 + rng.normal(0, 10), 95, 80) if leafless else (50 + rng.normal(0, 8), 75 + rng.normal(0, 10), 40)
        prims.sphere([xy[0], xy[1], gz + trunk_h + canopy_r * 0.8], canopy_r, rgb, 0.34)
    return prims


def _far_from_road(ground: GroundRaster, gap_m: float):
    import cv2

    grass = (ground.material == GRASS).astype(np.uint8)
    dist = cv2.distanceTransform(grass, cv2.DIST_L2, 3) * ground.res_m

    def ok(xy: np.ndarray) -> bool:
        c, r = np.round(ground.to_px(xy)).astype(int)
        if not (0 <= r < dist.shape[0] and 0 <= c < dist.shape[1]):
            return False
        return bool(dist[r, c] >= gap_m)

    return ok
