"""Render a site through a camera model: visible colour or thermal grey levels.

Per camera, a static layer is made once: the ground texture seen through the lens (with a
mip level per pixel), scenery ray-cast with a depth buffer, static shadows, fog and sky.
Per frame, vehicles and pedestrians are ray-cast in image crops against that depth buffer,
their shadows are cast on the ground, then optics and sensor effects (blur, vignetting, noise,
fixed-pattern noise for thermal) are applied. An id buffer gives ground-truth visibility.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import cv2
import numpy as np

from shared.cameras import Camera
from sim.raycast import ray_boxes, ray_spheres
from sim.roads import RoadNetwork, build_network
from sim.scenery import Primitives, build_scenery
from sim.site import SiteSpec
from sim.texture import ASPHALT, GroundRaster, paint_ground
from sim.traffic import VEHICLE_TYPES, SceneState
from sim.vehicles import PART_KINDS, pedestrian_parts, vehicle_parts

WEATHERS = ("clear", "overcast", "dusk", "fog", "rain")
SHADOW_RES_M = 0.1
BACKGROUND_ID = -1
PEDESTRIAN_ID = -2


@dataclass(frozen=True)
class Environment:
    """Lighting and weather of a clip."""

    name: str
    sun_azimuth_deg: float
    sun_elevation_deg: float
    ambient: float
    diffuse: float
    fog_visibility_m: float
    tint: tuple[float, float, float]
    noise_sigma: float
    wet: bool

    @property
    def sun_dir(self) -> np.ndarray:
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])

    def to_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def sample_environment(rng: np.random.Generator, weather: str = "auto") -> Environment:
    if weather == "auto":
        weather = WEATHERS[int(rng.choice(len(WEATHERS), p=[0.4, 0.2, 0.15, 0.1, 0.15]))]
    if weather not in WEATHERS:
        raise ValueError(f"unknown weather {weather!r} (known: auto, {', '.join(WEATHERS)})")
    az = float(rng.uniform(100, 260))
    if weather == "clear":
        return Environment("clear", az, float(rng.uniform(22, 60)), 0.42, 0.75, 1e9, (1.0, 1.0, 1.0), 2.0, False)
    if weather == "overcast":
        return Environment("overcast", az, float(rng.uniform(20, 50)), 0.9, 0.12, 1e9, (0.97, 0.99, 1.03), 2.5, False)
    if weather == "dusk":
        return Environment(
            "dusk",
            float(rng.uniform(230, 290)),
            float(rng.uniform(6, 14)),
            0.32,
            0.55,
            1500.0,
            (1.08, 0.93, 0.78),
            4.5,
            False,
        )
    if weather == "fog":
        return Environment(
            "fog", az, float(rng.uniform(15, 40)), 0.85, 0.1, float(rng.uniform(90, 220)), (0.98, 0.99, 1.0), 3.0, False
        )
    return Environment(
        "rain", az, float(rng.uniform(20, 45)), 0.72, 0.08, float(rng.uniform(350, 700)), (0.93, 0.96, 1.0), 3.5, True
    )


def site_seed(site: SiteSpec) -> int:
    """A fixed seed per site, so the static world (texture, trees) is the same in every clip."""
    return int.from_bytes(hashlib.sha256(site.name.encode()).digest()[:4], "little")


@dataclass
class World:
    site: SiteSpec
    net: RoadNetwork
    ground: GroundRaster
    scenery: dict[str, np.ndarray]


def build_world(site: SiteSpec) -> World:
    seed = site_seed(site)
    net = build_network(site)
    ground = paint_ground(net, site.extent_m, seed)
    prims: Primitives = build_scenery(site, net, ground, seed)
    return World(site, net, ground, prims.arrays())


def _hull_fill(raster: np.ndarray, pts_px: np.ndarray, value: int) -> None:
    hull = cv2.convexHull(np.round(pts_px * 4).astype(np.int32))
    cv2.fillConvexPoly(raster, hull, value, cv2.LINE_AA, 2)


def _shadow_points(points: np.ndarray, ground_z: float | np.ndarray, sun: np.ndarray) -> np.ndarray:
    """Project 3D points (N, 3) along the sun direction onto the horizontal plane at ground_z."""
    k = (points[:, 2] - ground_z) / max(sun[2], 0.05)
    return points[:, :2] - sun[None, :2] * k[:, None]


def _box_corners(center: np.ndarray, half: np.ndarray, yaw: float) -> np.ndarray:
    s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    loc = s * half
    c, sn = math.cos(yaw), math.sin(yaw)
    rot = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]])
    return center + loc @ rot.T


# The 12 edges of a box as pairs of _box_corners indices (corners that differ in one sign).
_BOX_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if (a ^ b) in (1, 2, 4)]
NEAR_PLANE_M = 1e-3
EDGE_STEP_M = 0.05


def image_border(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    """The pixel centres (K, 2) of the image's outermost rows and columns that have a ray, and their world
    ray directions (K, 3)."""
    w, h = camera.width, camera.height
    u, v = np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64)
    uv = np.concatenate(
        [
            np.column_stack([u, np.zeros(w)]),
            np.column_stack([u, np.full(w, h - 1.0)]),
            np.column_stack([np.zeros(h), v]),
            np.column_stack([np.full(h, w - 1.0), v]),
        ]
    )
    dirs, ok = camera.unproject(uv)
    return uv[ok], dirs[ok]


def clipped_box_image_points(
    camera: Camera, center: np.ndarray, half: np.ndarray, yaw: float, border_uv: np.ndarray, border_dirs: np.ndarray
) -> np.ndarray:
    """Image points (K, 2), K may be 0, whose bounds are the bounds of an oriented box's image clipped to the
    image, also when part of the box is behind the camera or outside the lens model's field of view.

    The points are samples of the box's edges clipped at the camera plane (z = NEAR_PLANE_M in the camera
    frame) that project into the image, and the border pixels (from `image_border`) whose rays hit the box.
    Where the box's image leaves the image it crosses the border, so together they hold the bounds.
    """
    corners = _box_corners(center, half, yaw)
    zc = camera.pose.to_camera(corners)[:, 2]
    if (zc <= NEAR_PLANE_M).all():  # wholly behind the camera: no ray reaches it
        return np.zeros((0, 2))
    segments = []
    for a, b in _BOX_EDGES:
        za, zb = zc[a], zc[b]
        if za <= NEAR_PLANE_M and zb <= NEAR_PLANE_M:
            continue
        pa, pb = corners[a], corners[b]
        if za < NEAR_PLANE_M:
            pa = pa + (pb - pa) * ((NEAR_PLANE_M - za) / (zb - za))
        elif zb < NEAR_PLANE_M:
            pb = pb + (pa - pb) * ((NEAR_PLANE_M - zb) / (za - zb))
        n = int(min(512, max(8, math.ceil(float(np.linalg.norm(pb - pa)) / EDGE_STEP_M)))) + 1
        segments.append(pa + np.linspace(0.0, 1.0, n)[:, None] * (pb - pa))
    points = [np.zeros((0, 2))]
    if segments:
        uv, ok = camera.project(np.concatenate(segments))
        points.append(uv[ok & camera.in_image(uv)])
    if len(border_dirs):
        t, _, _ = ray_boxes(camera.pose.position_m, border_dirs, center[None], half[None], np.array([yaw]))
        points.append(border_uv[np.isfinite(t)])
    return np.concatenate(points)


class ShadowCaster:
    """Shadow rasters (SHADOW_RES_M per pixel) over the site, uint8 0..255 (255 = full shadow)."""

    def __init__(self, world: World, env: Environment) -> None:
        self.extent = world.site.extent_m
        self.size = int(round(2 * self.extent / SHADOW_RES_M))
        self.env = env
        self.sun = env.sun_dir
        self.terrain = world.site.ground
        self.static = np.zeros((self.size, self.size), np.uint8)
        sc = world.scenery
        for c, h, y in zip(sc["box_center"], sc["box_half"], sc["box_yaw"], strict=True):
            corners = _box_corners(c, h, y)
            gz = float(self.terrain.height(c[0], c[1]))
            _hull_fill(self.static, self.to_px(_shadow_points(corners, gz, self.sun)), 255)
        sphere_pts = _fibonacci_sphere(48)
        for c, r in zip(sc["sph_center"], sc["sph_radius"], strict=True):
            gz = float(self.terrain.height(c[0], c[1]))
            _hull_fill(self.static, self.to_px(_shadow_points(c + r * sphere_pts, gz, self.sun)), 200)
        self.static = cv2.GaussianBlur(self.static, (0, 0), 1.0)

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        return np.stack(
            [(xy[..., 0] + self.extent) / SHADOW_RES_M - 0.5, (self.extent - xy[..., 1]) / SHADOW_RES_M - 0.5], -1
        )

    def dynamic(self, scene: SceneState) -> np.ndarray:
        """Cast shadows of vehicles and pedestrians (plus a soft contact shadow under each)."""
        r = np.zeros((self.size, self.size), np.uint8)
        for i in range(len(scene)):
            l, w, h = scene.lwh[i]
            gz = float(self.terrain.height(*scene.xy[i]))
            c = np.array([scene.xy[i][0], scene.xy[i][1], gz + h / 2])
            if self.env.diffuse > 0.2:
                corners = _box_corners(c, np.array([l / 2, w / 2, h / 2 * 0.92]), scene.yaw[i])
                _hull_fill(r, self.to_px(_shadow_points(corners, gz, self.sun)), 255)
            foot = _box_corners(np.array([c[0], c[1], gz]), np.array([l / 2 + 0.25, w / 2 + 0.25, 0.0]), scene.yaw[i])
            _hull_fill(r, self.to_px(foot[:, :2]), 255)
        for j in range(len(scene.ped_xy)):
            gz = float(self.terrain.height(*scene.ped_xy[j]))
            c = np.array([scene.ped_xy[j][0], scene.ped_xy[j][1], gz + 0.87])
            corners = _box_corners(c, np.array([0.15, 0.22, 0.87]), scene.ped_yaw[j])
            if self.env.diffuse > 0.2:
                _hull_fill(r, self.to_px(_shadow_points(corners, gz, self.sun)), 255)
        return r


def _fibonacci_sphere(n: int) -> np.ndarray:
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = math.pi * (1 + 5**0.5) * k
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], 1)


@dataclass
class RenderResult:
    """image: (H, W, 3) uint8 BGR for visible cameras, (H, W) uint8 for thermal.
    ids: (H, W) int32, index into the scene's vehicles, BACKGROUND_ID or PEDESTRIAN_ID.
    hit_px: (N,) int64 pixels each vehicle would cover with nothing in front of it.
    border: the camera's `image_border` (pixel centres and ray directions), computed once per renderer."""

    image: np.ndarray
    ids: np.ndarray
    hit_px: np.ndarray
    border: tuple[np.ndarray, np.ndarray]


class CameraRenderer:
    def __init__(self, camera: Camera, world: World, env: Environment, shadows: ShadowCaster, seed: int) -> None:
        self.cam, self.world, self.env, self.shadows = camera, world, env, shadows
        self.thermal = camera.modality == "thermal"
        h, w = camera.height, camera.width
        grid = camera.pixel_grid().reshape(-1, 2)
        dirs, ok = camera.unproject(grid)
        ok &= camera.in_image(grid)
        self.dirs = dirs.astype(np.float32).reshape(h, w, 3)
        self.valid = ok.reshape(h, w)
        self.border = image_border(camera)
        origin = camera.pose.position_m
        terrain = world.site.ground
        pts, t_ground, hit = terrain.intersect(origin, dirs, max_range_m=world.site.extent_m * 3)
        inside = (np.abs(pts[:, 0]) < world.site.extent_m) & (np.abs(pts[:, 1]) < world.site.extent_m)
        ground_ok = hit & ok & inside
        far_ground = hit & ok & ~inside
        t_ground = np.where(hit & ok, t_ground, np.inf).astype(np.float32)
        # Scenery.
        sc = world.scenery
        flat_dirs = self.dirs.reshape(-1, 3)
        sel = np.nonzero(ok)[0]
        tb, ib, nb = ray_boxes(origin, flat_dirs[sel], sc["box_center"], sc["box_half"], sc["box_yaw"], t_ground[sel])
        ts, is_, ns = ray_spheres(
            origin, flat_dirs[sel], sc["sph_center"], sc["sph_radius"], np.minimum(tb, t_ground[sel])
        )
        sphere_hit = is_ >= 0
        box_hit = (ib >= 0) & ~sphere_hit
        t_static = t_ground.copy()
        t_static[sel[box_hit]] = tb[box_hit]
        t_static[sel[sphere_hit]] = ts[sphere_hit]
        self.ground_visible = np.zeros(h * w, bool)
        self.ground_visible[ground_ok] = True
        self.ground_visible[sel[box_hit | sphere_hit]] = False
        sun = env.sun_dir
        chans = 1 if self.thermal else 3
        bg = np.zeros((h * w, chans), np.float32)
        lit = env.ambient + env.diffuse * max(sun[2], 0.0)
        # Ground: texture through the lens with a mip level from each pixel's ground footprint.
        gv = self.ground_visible
        texel = self._sample_ground(pts.reshape(h, w, 3), gv.reshape(h, w)).reshape(h * w, chans)
        shadow_s = self._sample_raster(shadows.static, pts.reshape(h, w, 3)).reshape(-1) / 255.0
        level = lit - (lit - env.ambient) * shadow_s
        if env.wet and not self.thermal:
            mat = world.ground.material_at(pts[:, :2])
            texel = np.where((mat == ASPHALT)[:, None], texel * 0.72, texel * 0.9)
        if self.thermal:
            bg[gv] = texel[gv] / 255.0 - 0.06 * shadow_s[gv, None] * (env.diffuse > 0.2)
        else:
            bg[gv] = texel[gv] * level[gv, None]
        self.shadow_gain = np.zeros(h * w, np.float32)
        k = (lit - env.ambient) / lit
        self.shadow_gain[gv] = (k * (1 - shadow_s[gv])) if not self.thermal else 0.06 * (env.diffuse > 0.2)
        # Scenery colours.
        if box_hit.any():
            rows = sel[box_hit]
            base = sc["box_thermal"][ib[box_hit], None] if self.thermal else sc["box_rgb"][ib[box_hit]]
            bg[rows] = self._shade(base, nb[box_hit])
        if sphere_hit.any():
            rows = sel[sphere_hit]
            base = sc["sph_thermal"][is_[sphere_hit], None] if self.thermal else sc["sph_rgb"][is_[sphere_hit]]
            rng = np.random.default_rng([seed, 3])
            leaf = 1 + 0.25 * rng.standard_normal((len(rows), 1)).astype(np.float32)
            bg[rows] = self._shade(base, ns[sphere_hit]) * (leaf if not self.thermal else 1.0)
        # Far ground (outside the modelled site) and sky.
        sky = ok & ~np.isfinite(t_static)
        far = far_ground & ~np.isin(np.arange(h * w), sel[box_hit | sphere_hit])
        up = np.clip(flat_dirs[:, 2], 0, 1)
        if self.thermal:
            bg[sky] = (0.05 + 0.1 * (1 - up[sky]))[:, None]
            bg[far] = 0.4
        else:
            horizon = np.array([205, 212, 220], np.float32) * (0.6 + 0.5 * lit)
            zenith = np.array([120, 150, 200], np.float32) * (0.6 + 0.5 * lit)
            bg[sky] = horizon + (zenith - horizon) * up[sky, None]
            bg[far] = np.array([95, 100, 80], np.float32) * lit
        self.depth = np.where(ok, t_static, 0.0).astype(np.float32).reshape(h, w)
        bg = self._apply_fog(bg, self._fog_factor(self.depth.reshape(-1)))
        self.background = bg.reshape(h, w, chans)
        self.shadow_gain = self.shadow_gain.reshape(h, w)
        shadow_map = shadows.to_px(pts[:, :2]).astype(np.float32).reshape(h, w, 2)
        shadow_map[~gv.reshape(h, w)] = -10.0
        self.shadow_map = shadow_map
        # Sensor: vignetting, noise bank, fixed-pattern noise.
        rng = np.random.default_rng([seed, 5])
        r_norm = np.hypot(*(grid - [camera.cx, camera.cy]).T) / camera.image_circle_radius_px()
        vignette = (1 - 0.3 * np.clip(r_norm, 0, 1) ** 3).astype(np.float32).reshape(h, w, 1)
        tint = 1.0 if self.thermal else np.asarray(env.tint[::-1], np.float32)
        valid3 = self.valid[..., None]
        self.gain = np.where(valid3, vignette * tint, 0.0).astype(np.float32)  # (H, W, C)
        self.offset = np.where(valid3, 0.0, 0.0 if self.thermal else np.array([8, 8, 10], np.float32)).astype(
            np.float32
        )
        self.pad = 48
        self.noise = (rng.standard_normal((h + self.pad, w + self.pad, chans)) * 40).clip(-127, 127).astype(np.int8)
        self.fixed = (rng.standard_normal((1, w, 1)) * 1.6).astype(np.float32) if self.thermal else None

    # ---- static helpers ----------------------------------------------------------------------
    def _sample_raster(self, raster: np.ndarray, pts: np.ndarray) -> np.ndarray:
        m = self.shadows.to_px(pts[..., :2]).astype(np.float32)
        return cv2.remap(
            raster, m[..., 0], m[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0
        ).astype(np.float32)

    def _sample_ground(self, pts: np.ndarray, valid: np.ndarray) -> np.ndarray:
        g = self.world.ground
        src = g.thermal if self.thermal else g.albedo
        px = g.to_px(pts[..., :2])
        du = np.gradient(px, axis=1)
        dv = np.gradient(px, axis=0)
        foot = np.maximum(np.linalg.norm(du, axis=-1), np.linalg.norm(dv, axis=-1))
        level = np.clip(np.floor(np.log2(np.maximum(foot, 1e-6))), 0, 6).astype(np.int64)
        level[~valid] = 0
        chans = 1 if self.thermal else 3
        out = np.zeros((*pts.shape[:2], chans), np.float32)
        img = src
        for lv in range(int(level.max()) + 1):
            scale = 2.0**lv
            # cv2.pyrDown centres coarse texel i on fine texel 2 i, so level lv holds texel x at x / 2**lv.
            mx = (px[..., 0] / scale).astype(np.float32)
            my = (px[..., 1] / scale).astype(np.float32)
            sampled = cv2.remap(img, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(np.float32)
            if sampled.ndim == 2:
                sampled = sampled[..., None]
            m = level == lv
            out[m] = sampled[m]
            img = cv2.pyrDown(img)
        if not self.thermal:
            out = out[..., ::-1]  # raster is RGB, images are BGR
        return out

    def _shade(self, base: np.ndarray, normals: np.ndarray) -> np.ndarray:
        """Lambert shading of base colours (K, 3) BGR-ordered RGB input, or thermal (K, 1)."""
        sun = self.env.sun_dir.astype(np.float32)
        ndl = np.clip(normals @ sun, 0, 1)
        if self.thermal:
            return (base + 0.06 * ndl[:, None] * (self.env.diffuse > 0.2)).astype(np.float32)
        rgb = base[:, ::-1].astype(np.float32)  # RGB -> BGR
        sky = 0.12 * np.clip(normals[:, 2], 0, 1)
        return rgb * (self.env.ambient * (0.8 + sky) + self.env.diffuse * ndl)[:, None]

    def _fog_factor(self, t: np.ndarray) -> np.ndarray:
        vis = self.env.fog_visibility_m * (4.0 if self.thermal else 1.0)
        return np.exp(-3.0 * np.minimum(t, 1e6) / vis).astype(np.float32)

    def _apply_fog(self, col: np.ndarray, f: np.ndarray) -> np.ndarray:
        if self.env.fog_visibility_m > 1e8:
            return col
        fog = (
            np.array([0.35], np.float32)
            if self.thermal
            else np.array([200, 200, 198], np.float32) * (0.55 + 0.5 * self.env.ambient)
        )
        return col * f[:, None] + fog * (1 - f[:, None])

    # ---- per frame --------------------------------------------------------------------------
    def render(self, scene: SceneState, rng: np.random.Generator) -> RenderResult:
        cam = self.cam
        h, w = cam.height, cam.width
        img = self.background.copy()
        depth = self.depth.copy()
        ids = np.full((h, w), BACKGROUND_ID, np.int32)
        # Moving shadows on the ground.
        dyn = self.shadows.dynamic(scene)
        s = cv2.remap(
            dyn,
            self.shadow_map[..., 0],
            self.shadow_map[..., 1],
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=0,
        )
        gain = 1 - self.shadow_gain * (s.astype(np.float32) / 255.0)
        if self.thermal:
            img -= (self.shadow_gain * (s.astype(np.float32) / 255.0))[..., None]
        else:
            img *= gain[..., None]
        hit_px = np.zeros(len(scene), np.int64)
        origin = cam.pose.position_m
        terrain = self.world.site.ground
        gz = terrain.height(scene.xy[:, 0], scene.xy[:, 1]) if len(scene) else np.zeros(0)
        for i in range(len(scene)):
            vtype = VEHICLE_TYPES[scene.type_idx[i]]
            centres, halves, kinds = vehicle_parts(vtype, *scene.lwh[i])
            n = self._draw_object(
                img,
                depth,
                ids,
                i,
                origin,
                scene.xy[i],
                gz[i],
                scene.yaw[i],
                centres,
                halves,
                kinds,
                scene.lwh[i],
                scene.colors[i],
                vtype,
                bool(scene.parked[i]),
            )
            hit_px[i] = n
        pc, ph, pk = pedestrian_parts()
        for j in range(len(scene.ped_xy)):
            pz = float(terrain.height(*scene.ped_xy[j]))
            self._draw_object(
                img,
                depth,
                ids,
                PEDESTRIAN_ID,
                origin,
                scene.ped_xy[j],
                pz,
                scene.ped_yaw[j],
                pc,
                ph,
                pk,
                np.array([0.3, 0.46, 1.75]),
                scene.ped_color[j],
                "pedestrian",
                False,
            )
        return RenderResult(self._sensor(img, rng), ids, hit_px, self.border)

    def _draw_object(
        self, img, depth, ids, obj_id, origin, xy, gz, yaw, centres, halves, kinds, lwh, color, vtype, parked
    ) -> int:
        cam = self.cam
        l, w, h = lwh
        c, s = math.cos(yaw), math.sin(yaw)
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        base = np.array([xy[0], xy[1], gz])
        # Image crop from the projected hull of the object's box (sampled edges for fisheye).
        lin = np.linspace(-1, 1, 5)
        g = np.array([[a, b, cc] for a in lin for b in lin for cc in (0, 0.5, 1)], float)
        local = g * [l / 2 + 0.05, w / 2 + 0.05, 1.0]
        local[:, 2] = g[:, 2] * (h + 0.05)
        world = base + local @ rot.T
        uv, ok = cam.project(world)
        if cam.kind == "pinhole" and not ok.all():
            # Part of the box is behind the camera (or beyond the lens model's field of view), where the
            # samples tell nothing about its image: the crop comes from the box clipped at the camera plane.
            half = np.array([l / 2 + 0.05, w / 2 + 0.05, (h + 0.05) / 2])
            center = np.array([base[0], base[1], base[2] + half[2]])
            uv = clipped_box_image_points(cam, center, half, yaw, *self.border)
            if len(uv) == 0:
                return 0
        else:
            if not ok.any():
                return 0
            uv = uv[ok]
        pad = 3 + 0.04 * (uv.max(0) - uv.min(0))
        u0, v0 = np.floor(uv.min(0) - pad).astype(int)
        u1, v1 = np.ceil(uv.max(0) + pad).astype(int) + 1
        u0, v0 = max(u0, 0), max(v0, 0)
        u1, v1 = min(u1, cam.width), min(v1, cam.height)
        if u1 <= u0 or v1 <= v0:
            return 0
        dirs = self.dirs[v0:v1, u0:u1].reshape(-1, 3)
        world_c = base + centres @ rot.T
        yaws = np.full(len(centres), yaw)
        t, part, normal = ray_boxes(origin, dirs, world_c, halves, yaws)
        valid = self.valid[v0:v1, u0:u1].reshape(-1)
        hit = np.isfinite(t) & valid
        n_hit = int(hit.sum())
        if n_hit == 0:
            return 0
        dcrop = depth[v0:v1, u0:u1].reshape(-1)
        vis = hit & (t < dcrop)
        if vis.any():
            rows = np.nonzero(vis)[0]
            p_world = origin + dirs[rows] * t[rows, None]
            p_local = (p_world - base) @ rot
            col = self._material(kinds[part[rows]], normal[rows], p_local, rot, lwh, color, vtype, parked)
            col = self._apply_fog(col, self._fog_factor(t[rows]))
            icrop = img[v0:v1, u0:u1].reshape(-1, img.shape[2])
            icrop[rows] = col
            img[v0:v1, u0:u1] = icrop.reshape(v1 - v0, u1 - u0, img.shape[2])
            dcrop[rows] = t[rows]
            depth[v0:v1, u0:u1] = dcrop.reshape(v1 - v0, u1 - u0)
            idc = ids[v0:v1, u0:u1].reshape(-1)
            idc[rows] = obj_id
            ids[v0:v1, u0:u1] = idc.reshape(v1 - v0, u1 - u0)
        return n_hit

    def _material(self, kinds, normals, p_local, rot, lwh, color, vtype, parked) -> np.ndarray:
        """Colour (K, 3) BGR or thermal level (K, 1) of hit points on an object."""
        l, w, h = lwh
        n_local = normals @ rot  # world -> object frame
        top = n_local[:, 2] > 0.5
        front = n_local[:, 0] > 0.5
        rear = n_local[:, 0] < -0.5
        z, x, y = p_local[:, 2], p_local[:, 0], p_local[:, 1]
        name = np.array(PART_KINDS)[kinds]
        glass_from_m = (h * 0.55 if vtype in ("car", "suv_van") else 1.3) + 0.08
        glass = (name == "cabin") & ~top & (z > glass_from_m)
        glass |= (name == "busbody") & ~top & (z > 1.25) & (z < h - 0.45) & ((np.abs(x) % 1.7) > 0.2)
        if self.thermal:
            hot = 0.5 if parked else 0.74
            t = np.full(len(kinds), 0.45, np.float32)
            t[top & (name != "cabin")] = 0.5
            engine = ((name == "body") | (name == "cabin")) & (x > l * 0.22) & (front | top) & (z < h * 0.65)
            t[engine] = hot
            t[name == "wheel"] = 0.42 + (0.0 if parked else 0.26)
            t[name == "chassis"] = 0.55 + (0.0 if parked else 0.1)
            t[glass] = 0.27
            exhaust = rear & (z < 0.55) & (y < -w / 2 + 0.65) & (y > -w / 2 + 0.15)
            t[exhaust] = 0.5 if parked else 0.97
            if vtype == "bus":
                t[rear & (z < 1.5)] = hot
            t[np.isin(name, ["rider", "head", "legs", "torso"])] = 0.8
            if vtype == "pedestrian":
                t[:] = np.where(name == "head", 0.86, 0.78)
            return self._shade(t[:, None], normals)
        body = np.asarray(color, np.float32)[None, :].repeat(len(kinds), 0)
        body[name == "wheel"] = (24, 24, 26)
        body[name == "chassis"] = (38, 38, 40)
        body[(name == "body") & (front | rear)] *= 0.75
        body[glass] = (40, 46, 55)
        if vtype == "pedestrian":
            body[name == "legs"] = (45, 50, 70)
            body[name == "head"] = (170, 130, 110)
        elif vtype == "motorcycle":
            body[name == "rider"] = (40, 40, 48)
        col = self._shade(body, normals)
        refl = glass & (n_local[:, 2] > -0.2)
        col[refl] += 25 * (0.5 + self.env.ambient)
        return col

    def _sensor(self, img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        h, w = self.cam.height, self.cam.width
        if self.thermal:
            lo, hi = 0.18, 0.9
            out = cv2.GaussianBlur((img[..., 0] - lo) * (255.0 / (hi - lo)), (0, 0), 1.1)[..., None]
            out += self.fixed
            sigma = self.env.noise_sigma * 1.3
        else:
            out = cv2.GaussianBlur(img, (0, 0), 0.7)
            sigma = self.env.noise_sigma
        dy, dx = rng.integers(0, self.pad, 2)
        out *= self.gain
        out += self.offset
        out += self.noise[dy : dy + h, dx : dx + w] * np.float32(sigma / 40.0)
        out = np.clip(out, 0, 255).astype(np.uint8)
        return out[..., 0] if self.thermal else out
