"""Terrain height field, ray/ground intersection and the exact pixel -> ground lookup."""

from __future__ import annotations

import math

import numpy as np
import pytest

from shared.cameras import Camera, Pose
from shared.ground import Bump, Terrain, ground_lookup

BUMPY = Terrain(
    slope_x=0.12,
    slope_y=-0.1,
    bumps=(Bump(5.0, 5.0, 3.0, 1.0), Bump(-10.0, 8.0, 6.0, -0.8), Bump(20.0, -15.0, 4.0, 1.5)),
)
GENTLE = Terrain(
    slope_x=0.006,
    slope_y=0.009,
    bumps=(Bump(0.0, 0.0, 14.0, 0.45), Bump(45.0, -40.0, 20.0, -0.6), Bump(-50.0, 45.0, 25.0, 0.5)),
)
TERRAINS = {"flat": Terrain(), "slope": Terrain(0.15, -0.15), "gentle": GENTLE, "bumpy": BUMPY}


def _down_dirs(rng: np.random.Generator, n: int, el_lo_deg: float, el_hi_deg: float) -> np.ndarray:
    """Unit directions with elevation in [el_lo, el_hi] degrees (negative: below the horizon)."""
    el = np.radians(rng.uniform(el_lo_deg, el_hi_deg, n))
    az = rng.uniform(0, 2 * math.pi, n)
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=1)


def test_height_values() -> None:
    t = Terrain(0.1, -0.05, (Bump(2.0, 3.0, 4.0, 0.5),))
    assert t.height(0.0, 0.0) == pytest.approx(0.5 * math.exp(-13 / 32))
    assert t.height(2.0, 3.0) == pytest.approx(0.2 - 0.15 + 0.5)
    assert t.height(1000.0, 0.0) == pytest.approx(100.0)
    assert t.height(np.zeros((3, 4)), np.zeros((3, 4))).shape == (3, 4)


def test_gradient_matches_finite_differences() -> None:
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-30, 30, (2, 500))
    gx, gy = BUMPY.gradient(x, y)
    h = 1e-5
    fx = (BUMPY.height(x + h, y) - BUMPY.height(x - h, y)) / (2 * h)
    fy = (BUMPY.height(x, y + h) - BUMPY.height(x, y - h)) / (2 * h)
    np.testing.assert_allclose(gx, fx, atol=1e-7)
    np.testing.assert_allclose(gy, fy, atol=1e-7)


@pytest.mark.parametrize("name", list(TERRAINS))
def test_intersect_lands_on_surface(name: str) -> None:
    terrain = TERRAINS[name]
    rng = np.random.default_rng(1)
    origin = np.array([1.0, 2.0, 11.0])
    dirs = _down_dirs(rng, 20000, -89.9, -3.0)
    pts, t, valid = terrain.intersect(origin, dirs, max_range_m=1e3)
    assert valid.mean() > 0.9
    p, tv, d = pts[valid], t[valid], dirs[valid]
    assert np.max(np.abs(p[:, 2] - terrain.height(p[:, 0], p[:, 1]))) < 1e-6
    # The point lies on the ray, t along it.
    np.testing.assert_allclose(p, origin + tv[:, None] * d, atol=1e-9)
    assert np.all(tv > 0)


@pytest.mark.parametrize("name", ["gentle", "bumpy"])
def test_intersect_is_first_hit(name: str) -> None:
    """No point of the ray before the returned one lies below the ground."""
    terrain = TERRAINS[name]
    rng = np.random.default_rng(2)
    origin = np.array([-3.0, 4.0, 9.0])
    dirs = _down_dirs(rng, 3000, -60.0, -4.0)
    _, t, valid = terrain.intersect(origin, dirs, max_range_m=1e3)
    frac = np.linspace(0.0, 0.999, 300)
    samples = origin + (frac[None, :, None] * t[valid][:, None, None]) * dirs[valid][:, None, :]
    below = samples[..., 2] < terrain.height(samples[..., 0], samples[..., 1]) - 1e-6
    assert not below.any()


def test_intersect_flat_ground_closed_form() -> None:
    origin = np.array([0.0, 0.0, 10.0])
    dirs = np.array([[0.0, 0.0, -1.0], [math.sqrt(0.5), 0.0, -math.sqrt(0.5)]])
    pts, t, valid = Terrain().intersect(origin, dirs)
    assert valid.all()
    np.testing.assert_allclose(t, [10.0, 10.0 * math.sqrt(2)], atol=1e-9)
    np.testing.assert_allclose(pts, [[0.0, 0.0, 0.0], [10.0, 0.0, 0.0]], atol=1e-9)


@pytest.mark.parametrize("name", list(TERRAINS))
def test_rays_pointing_up_or_level_are_invalid(name: str) -> None:
    terrain = TERRAINS[name]
    rng = np.random.default_rng(3)
    dirs = _down_dirs(rng, 500, 0.5, 89.0)
    dirs = np.vstack([dirs, [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]])
    _, _, valid = terrain.intersect(np.array([0.0, 0.0, 10.0]), dirs)
    assert not valid.any()


def test_rays_beyond_max_range_are_invalid() -> None:
    origin = np.array([0.0, 0.0, 10.0])
    # Elevation -1 deg hits flat ground at ~573 m.
    el = math.radians(-1.0)
    d = np.array([[math.cos(el), 0.0, math.sin(el)]])
    _, t, valid = Terrain().intersect(origin, d, max_range_m=1e3)
    assert valid[0]
    assert t[0] == pytest.approx(10.0 / math.sin(-el), rel=1e-9)
    _, _, valid = Terrain().intersect(origin, d, max_range_m=300.0)
    assert not valid[0]


@pytest.mark.parametrize(("slope_x", "slope_y"), [(0.16, 0.0), (0.0, -0.2), (float("nan"), 0.0), (0.0, float("inf"))])
def test_rejects_steep_or_bad_slopes(slope_x: float, slope_y: float) -> None:
    with pytest.raises(ValueError, match="slope"):
        Terrain(slope_x, slope_y)


def test_accepts_max_slope_and_rejects_bad_bump() -> None:
    Terrain(0.15, -0.15)
    with pytest.raises(ValueError, match="sigma"):
        Terrain(bumps=(Bump(0.0, 0.0, 0.0, 1.0),))


def test_dict_round_trip() -> None:
    t2 = Terrain.from_dict(BUMPY.to_dict())
    assert t2 == BUMPY
    assert Terrain.from_dict(None) == Terrain()


# ---- ground_lookup ------------------------------------------------------------------------


def _check_lookup(cam: Camera, terrain: Terrain) -> tuple[np.ndarray, np.ndarray]:
    pts, valid = ground_lookup(cam, terrain)
    assert pts.shape == (cam.height, cam.width, 3)
    assert valid.shape == (cam.height, cam.width)
    p = pts[valid]
    assert np.max(np.abs(p[:, 2] - terrain.height(p[:, 0], p[:, 1]))) < 1e-6
    uv, ok = cam.project(p)
    assert ok.all()
    grid = cam.pixel_grid()[valid]
    assert np.max(np.abs(uv - grid)) < 1e-6
    return pts, valid


def test_ground_lookup_pinhole_looking_down_projects_back() -> None:
    cam = Camera(
        "down",
        "pinhole",
        64,
        48,
        40.0,
        40.0,
        31.5,
        23.5,
        (-0.1, 0.02, 0.001, -0.001, 0.0),
        Pose.from_angles([3.0, -2.0, 12.0], 30.0, 90.0),
    )
    _, valid = _check_lookup(cam, BUMPY)
    assert valid.all()


def test_ground_lookup_tilted_pinhole_excludes_sky() -> None:
    # Pitch 10 deg and a 60 deg vertical FOV: the top of the image sees the sky.
    cam = Camera(
        "tilt",
        "pinhole",
        64,
        48,
        41.6,
        41.6,
        31.5,
        23.5,
        (),
        Pose.from_angles([0.0, 0.0, 8.0], 45.0, 10.0),
    )
    pts, valid = _check_lookup(cam, GENTLE)
    assert not valid[0].any()  # top row: above the horizon
    assert valid[-1].all()  # bottom row: on the ground
    assert 0.2 < valid.mean() < 0.9
    # Range limit: every valid ground point is within the default 1 km.
    d = np.linalg.norm(pts[valid] - cam.pose.position_m, axis=1)
    assert d.max() <= 1e3


def test_ground_lookup_fisheye_outside_circle_invalid() -> None:
    cam = Camera(
        "fish",
        "fisheye",
        64,
        48,
        14.0,
        14.0,
        31.5,
        23.5,
        (0.01, -0.003, 0.0, 0.0),
        Pose.from_angles([1.0, 1.0, 10.0], 200.0, 90.0),
        max_angle_deg=95.0,
    )
    _, valid = _check_lookup(cam, GENTLE)
    grid = cam.pixel_grid()
    r = np.hypot(grid[..., 0] - cam.cx, grid[..., 1] - cam.cy)
    circle = cam.image_circle_radius_px()
    assert not valid[r > circle].any()
    assert valid[r < 0.9 * circle].all()


@pytest.mark.parametrize(("section", "message"), [
    ({"slopex": 0.01}, r"terrain: unknown key 'slopex'"),
    ({"bumps": 3}, r"terrain\.bumps must be a list of bumps"),
    ({"bumps": [{"x_m": 0, "y_m": 0, "sigma_m": 3, "heigth_m": 1}]}, r"terrain\.bumps\[0\]: unknown key 'heigth_m'"),
    ({"bumps": [{"x_m": 0, "y_m": 0, "height_m": 1}]}, r"terrain\.bumps\[0\]: sigma_m is missing"),
    ({"bumps": [{"x_m": 0, "y_m": 0, "sigma_m": 2, "height_m": 1}, [1, 2]]}, r"terrain\.bumps\[1\] must be a mapping"),
    ({"bumps": [{"x_m": 0, "y_m": "north", "sigma_m": 2, "height_m": 1}]},
     r"terrain\.bumps\[0\]\.y_m must be a finite number, got 'north'"),
    ({"bumps": [{"x_m": 0, "y_m": 0, "sigma_m": float("nan"), "height_m": 1}]}, r"terrain\.bumps\[0\]\.sigma_m"),
    ({"bumps": [{"x_m": 0, "y_m": 0, "sigma_m": 0, "height_m": 1}]}, r"terrain\.bumps\[0\]\.sigma_m must be > 0"),
    ({"slope_y": True}, r"terrain\.slope_y must be a finite number, got True"),
    ([0.01, 0.02], r"terrain must be a mapping"),
])
def test_from_dict_names_the_bad_entry(section: object, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        Terrain.from_dict(section)


def test_from_dict_takes_an_empty_bump_list_and_whole_numbers() -> None:
    assert Terrain.from_dict({"bumps": None}) == Terrain()
    t = Terrain.from_dict({"slope_x": 0, "bumps": [{"x_m": 1, "y_m": 2, "sigma_m": 3, "height_m": 1}]})
    assert t == Terrain(0.0, 0.0, (Bump(1.0, 2.0, 3.0, 1.0),))
    assert Terrain.from_dict({"slope_x": "6e-3"}).slope_x == 0.006  # YAML reads 6e-3 (no dot) as a string
