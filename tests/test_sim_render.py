"""Renderer details on a small hand-made site: a vehicle partly behind a pinhole camera, and ground mip levels."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from shared.cameras import Camera, Pose
from sim.geometry import rect
from sim.groundtruth import frame_ground_truth
from sim.raycast import ray_boxes
from sim.render import CameraRenderer, ShadowCaster, World, sample_environment
from sim.site import load_site
from sim.texture import ASPHALT, GroundRaster
from sim.traffic import VEHICLE_TYPES, SceneState
from sim.vehicles import vehicle_parts

EXTENT_M = 24.0
BUS_LWH = (12.76, 2.58, 3.16)


@pytest.fixture(scope="module")
def world() -> World:
    """A flat 48 m site with a plain asphalt ground and no scenery (the real sites take seconds to build)."""
    site = load_site("intersection").model_copy(update={"extent_m": EXTENT_M, "terrain": {}})
    res_m = 0.04
    size = int(round(2 * EXTENT_M / res_m))
    ground = GroundRaster(
        res_m,
        EXTENT_M,
        np.full((size, size), ASPHALT, np.uint8),
        np.full((size, size, 3), 90, np.uint8),
        np.full((size, size), 120, np.uint8),
    )
    shapes = {"box_center": (0, 3), "box_half": (0, 3), "box_yaw": (0,), "box_rgb": (0, 3), "box_thermal": (0,)}
    shapes |= {"sph_center": (0, 3), "sph_radius": (0,), "sph_rgb": (0, 3), "sph_thermal": (0,)}
    return World(site, None, ground, {k: np.zeros(s) for k, s in shapes.items()})


def _camera(modality: str = "visible") -> Camera:
    """A small pinhole camera on a 7.5 m pole at the origin, looking north and 22 degrees down (as C_NW)."""
    return Camera(
        name="P",
        kind="pinhole",
        width=320,
        height=180,
        fx=160.0,
        fy=160.0,
        cx=159.5,
        cy=89.5,
        dist=(-0.12, 0.03, 0.0, 0.0, 0.0),
        pose=Pose.from_angles([0.0, 0.0, 7.5], 0.0, 22.0),
        modality=modality,
    )


def _renderer(world: World, cam: Camera) -> CameraRenderer:
    env = sample_environment(np.random.default_rng(0), "overcast")
    return CameraRenderer(cam, world, env, ShadowCaster(world, env), seed=1)


def _scene(xy, yaw: float, vtype: str = "bus", lwh=BUS_LWH) -> SceneState:
    return SceneState(
        t_s=0.0,
        ids=np.array([7]),
        xy=np.array([xy], float),
        yaw=np.array([yaw]),
        lwh=np.array([lwh], float),
        speed=np.zeros(1),
        velocity=np.zeros((1, 2)),
        type_idx=np.array([VEHICLE_TYPES.index(vtype)]),
        colors=np.array([[200, 40, 40]], np.uint8),
        parked=np.zeros(1, bool),
        ped_xy=np.zeros((0, 2)),
        ped_yaw=np.zeros(0),
        ped_color=np.zeros((0, 3), np.uint8),
    )


def _silhouette(r: CameraRenderer, centres: np.ndarray, halves: np.ndarray, yaw: float) -> np.ndarray:
    """The boxes' unoccluded mask over the whole image, ray-cast at every pixel (no crop)."""
    t, _, _ = ray_boxes(r.cam.pose.position_m, r.dirs.reshape(-1, 3), centres, halves, np.full(len(centres), yaw))
    return (np.isfinite(t) & r.valid.reshape(-1)).reshape(r.cam.height, r.cam.width)


@pytest.mark.parametrize(
    "xy, yaw, null_corners",
    [
        ((3.0, 2.0), math.pi / 2, [False, False, True, True]),  # beside the pole, its rear behind the camera
        ((-2.5, 1.0), -math.pi / 2 + 0.3, [True, True, False, False]),  # the other way, its front behind it
        ((2.0, 3.0), -3 * math.pi / 4, [False] * 4),  # diagonally below the camera, a roof corner behind it
    ],
)
def test_a_vehicle_partly_behind_a_pinhole_camera_is_drawn_with_its_ground_truth(world, xy, yaw, null_corners):
    cam = _camera()
    r = _renderer(world, cam)
    scene = _scene(xy, yaw)
    l, w, h = BUS_LWH
    centre = np.array([xy[0], xy[1], h / 2])
    corners = np.array([[sx * l / 2, sy * w / 2, sz * h / 2] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    c, s = math.cos(yaw), math.sin(yaw)
    corners = centre + corners @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T
    assert (cam.pose.to_camera(corners)[:, 2] < 0).any(), "the case needs part of the bus behind the camera"

    res = r.render(scene, np.random.default_rng(0))
    parts, halves, _ = vehicle_parts("bus", *BUS_LWH)
    want = _silhouette(r, centre - [0, 0, h / 2] + parts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T, halves, yaw)
    assert want.sum() > 1000
    # Every pixel of the bus is drawn (nothing else is in front of it) and counted.
    assert res.hit_px[0] == want.sum()
    assert ((res.ids == 0) == want).all()

    gt = frame_ground_truth(cam, scene, res, world.site.ground, world.site.geo)
    assert len(gt) == 1
    v = gt[0]
    assert v["visible_px"] == want.sum() and v["visible_fraction"] == 1.0
    ys, xs = np.nonzero(want)
    assert v["box_visible"] == [xs.min(), ys.min(), xs.max(), ys.max()]
    # The 2D box is the bounds of the whole 3D box's image clipped to the image: it holds the pixel centres the
    # box covers and reaches past them by less than the pixel grid (a thin tip may miss a centre, hence 2 px).
    box = _silhouette(r, centre[None], np.array([[l / 2, w / 2, h / 2]]), yaw)
    ys, xs = np.nonzero(box)
    x1, y1, x2, y2 = v["box"]
    assert x1 <= xs.min() + 0.01 and y1 <= ys.min() + 0.01 and x2 >= xs.max() - 0.01 and y2 >= ys.max() - 0.01
    np.testing.assert_allclose(v["box"], [xs.min(), ys.min(), xs.max(), ys.max()], atol=2.0)
    # A footprint corner behind the camera has no pixel position: null, not NaN (which is not JSON).
    foot = np.column_stack([rect(xy, l, w, yaw), np.zeros(4)])
    assert list(cam.pose.to_camera(foot)[:, 2] <= 0) == null_corners
    assert [p is None for p in v["corners_uv"]] == null_corners
    json.dumps(gt, allow_nan=False)


def test_a_vehicle_in_front_of_a_pinhole_camera_is_unchanged(world):
    """The ordinary case keeps its crop from the sampled hull: a car ahead is drawn whole."""
    cam = _camera()
    r = _renderer(world, cam)
    scene = _scene((1.0, 16.0), 0.4, "car", (4.5, 1.8, 1.5))
    res = r.render(scene, np.random.default_rng(0))
    parts, halves, _ = vehicle_parts("car", 4.5, 1.8, 1.5)
    c, s = math.cos(0.4), math.sin(0.4)
    want = _silhouette(
        r, np.array([1.0, 16.0, 0.0]) + parts @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T, halves, 0.4
    )
    assert want.sum() > 100 and res.hit_px[0] == want.sum()
    v = frame_ground_truth(cam, scene, res, world.site.ground, world.site.geo)[0]
    assert None not in v["corners_uv"] and v["visible_fraction"] == 1.0


def test_ground_mip_levels_sample_the_texel_the_ray_hits(world):
    # cv2.pyrDown keeps fine texel 2 i at the centre of coarse texel i (x -> x / 2), not at (x + 0.5) / 2 - 0.5.
    impulse = np.zeros((8, 64), np.float32)
    impulse[:, 20] = 1.0
    assert int(np.argmax(cv2.pyrDown(impulse)[2])) == 10
    # A linear ramp (value = raster column or row) survives pyrDown, so the fetched value is the texel fetched.
    cam = _camera("thermal")
    r = _renderer(world, cam)
    pts, _, _ = world.site.ground.intersect(cam.pose.position_m, r.dirs.reshape(-1, 3), 3 * EXTENT_M)
    pts = pts.reshape(cam.height, cam.width, 3)
    gv = r.ground_visible.reshape(cam.height, cam.width)
    g = world.ground
    px = g.to_px(pts[..., :2])
    foot = np.maximum(
        np.linalg.norm(np.gradient(px, axis=1), axis=-1), np.linalg.norm(np.gradient(px, axis=0), axis=-1)
    )
    level = np.clip(np.floor(np.log2(np.maximum(foot, 1e-6))), 0, 6).astype(int)
    inner = gv & (px > 100).all(-1) & (px < g.size - 100).all(-1)
    saved = g.thermal
    try:
        for axis in (0, 1):
            ramp = np.arange(g.size, dtype=np.float32)
            g.thermal = np.ascontiguousarray(
                np.broadcast_to(ramp[None, :] if axis == 0 else ramp[:, None], saved.shape)
            )
            err = r._sample_ground(pts, gv)[..., 0] - px[..., axis]
            for lv in range(4):
                m = inner & (level == lv)
                assert m.sum() > 200, f"level {lv} has too few pixels for the check"
                # cv2.remap places a sample to 1/32 of a texel of its level: 2**lv / 32 texels of the full raster.
                assert np.abs(err[m]).max() <= 2**lv / 32 + 0.01, (axis, lv, float(np.median(err[m])))
    finally:
        g.thermal = saved
