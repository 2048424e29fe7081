"""Landmark noise model and per-camera landmark picking."""

from __future__ import annotations

import numpy as np
import pytest

from sim.landmarks import LandmarkNoise, apply_noise, pick_landmarks
from sim.render import CameraRenderer, ShadowCaster, build_world, sample_environment
from sim.site import load_site

N = 20000


@pytest.fixture(scope="module")
def noisy():
    rng = np.random.default_rng(0)
    uv = rng.uniform(0, 1000, (N, 2))
    xy = rng.uniform(-50, 50, (N, 2))
    uv0, xy0 = uv.copy(), xy.copy()
    uv_n, xy_n, gross = apply_noise(uv, xy, np.random.default_rng(1), LandmarkNoise())
    np.testing.assert_array_equal(uv, uv0)  # inputs untouched
    np.testing.assert_array_equal(xy, xy0)
    return uv, xy, uv_n, xy_n, gross


def test_apply_noise_shapes(noisy) -> None:
    _, _, uv_n, xy_n, gross = noisy
    assert uv_n.shape == (N, 2)
    assert xy_n.shape == (N, 2)
    assert gross.shape == (N,)
    assert gross.dtype == bool


def test_gross_fraction(noisy) -> None:
    gross = noisy[4]
    assert 0.04 <= gross.mean() <= 0.06


def test_non_gross_error_statistics(noisy) -> None:
    uv, xy, uv_n, xy_n, gross = noisy
    e_px = (uv_n - uv)[~gross]
    e_m = (xy_n - xy)[~gross]
    for axis in (0, 1):
        assert abs(e_px[:, axis].std() - 2.0) < 0.05 * 2.0
        assert abs(e_m[:, axis].std() - 0.15) < 0.05 * 0.15
        assert abs(e_px[:, axis].mean()) < 0.1
        assert abs(e_m[:, axis].mean()) < 0.01
    # Gaussian, not heavy tailed: nothing beyond 6 sigma.
    assert np.abs(e_px).max() < 12.0
    assert np.abs(e_m).max() < 0.9


def test_gross_errors_are_pixel_or_map_mistakes(noisy) -> None:
    uv, xy, uv_n, xy_n, gross = noisy
    d_px = np.linalg.norm(uv_n - uv, axis=1)[gross]
    d_m = np.linalg.norm(xy_n - xy, axis=1)[gross]
    pixel_kind = d_px > 15.0
    map_kind = d_m > 2.0
    # Each gross mistake is exactly one of the two kinds.
    assert np.all(pixel_kind ^ map_kind)
    assert 0.4 < pixel_kind.mean() < 0.6
    # Pixel mistakes: 25-60 px plus the ordinary ~2 px noise.
    assert d_px[pixel_kind].min() >= 25.0 - 8.0
    assert d_px[pixel_kind].max() <= 60.0 + 8.0
    assert d_px[pixel_kind].mean() == pytest.approx(42.5, abs=2.0)
    assert d_m[pixel_kind].max() < 0.9
    # Map mistakes: 4-10 m plus the ordinary 0.15 m noise.
    assert d_m[map_kind].min() >= 4.0 - 0.8
    assert d_m[map_kind].max() <= 10.0 + 0.8
    assert d_px[map_kind].max() < 12.0


def test_apply_noise_deterministic_and_configurable() -> None:
    uv = np.zeros((500, 2))
    xy = np.zeros((500, 2))
    a = apply_noise(uv, xy, np.random.default_rng(5), LandmarkNoise())
    b = apply_noise(uv, xy, np.random.default_rng(5), LandmarkNoise())
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    quiet = LandmarkNoise(pixel_sigma_px=0.0, map_sigma_m=0.0, gross_rate=0.0)
    uv_n, xy_n, gross = apply_noise(uv, xy, np.random.default_rng(5), quiet)
    assert not gross.any()
    np.testing.assert_array_equal(uv_n, uv)
    np.testing.assert_array_equal(xy_n, xy)
    all_gross = LandmarkNoise(gross_rate=1.0)
    _, _, gross = apply_noise(uv, xy, np.random.default_rng(5), all_gross)
    assert gross.all()


# ---- pick_landmarks on a real site camera ---------------------------------------------------


@pytest.fixture(scope="module")
def ellsworth():
    site = load_site("state_ellsworth")
    world = build_world(site)
    env = sample_environment(np.random.default_rng(0), "clear")
    shadows = ShadowCaster(world, env)
    cam = next(c for c in site.build_cameras() if c.name == "NE")
    assert cam.kind == "fisheye"
    renderer = CameraRenderer(cam, world, env, shadows, seed=0)
    lms = pick_landmarks(cam, world.net.paint.features, site.ground, site.geo, renderer.depth, np.random.default_rng(0))
    return site, world, cam, renderer, lms


def test_landmark_count_and_ids(ellsworth) -> None:
    lms = ellsworth[4]
    assert 5 <= len(lms) <= 30
    ids = [lm["id"] for lm in lms]
    assert len(set(ids)) == len(ids)
    kinds = {lm["kind"] for lm in lms}
    assert kinds <= {"crosswalk_corner", "dash_end", "yield_tooth", "stop_line_end", "island_nose", "stall_line_end"}


def test_landmark_truth_inside_image_and_visible(ellsworth) -> None:
    site, _, cam, renderer, lms = ellsworth
    uv = np.array([[lm["truth"]["u"], lm["truth"]["v"]] for lm in lms])
    assert cam.in_image(uv).all()
    assert cam.in_image(uv, margin_px=14.9).all()
    xyz = np.array([lm["truth"]["xyz"] for lm in lms])
    # On the ground.
    np.testing.assert_allclose(xyz[:, 2], site.ground.height(xyz[:, 0], xyz[:, 1]), atol=1e-4)
    # Not hidden by scenery: the static depth reaches the landmark.
    dist = np.linalg.norm(xyz - cam.pose.position_m, axis=1)
    px = np.round(uv).astype(int)
    assert np.all(renderer.depth[px[:, 1], px[:, 0]] >= dist - 0.3)
    assert dist.max() < 55.0
    # Distinct clicks: no two landmarks within 12 px of each other.
    d = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    d[np.arange(len(uv)), np.arange(len(uv))] = np.inf
    assert d.min() > 12.0


def test_landmark_truth_consistent_with_camera_and_geo(ellsworth) -> None:
    site, _, cam, _, lms = ellsworth
    xyz = np.array([lm["truth"]["xyz"] for lm in lms])
    uv_truth = np.array([[lm["truth"]["u"], lm["truth"]["v"]] for lm in lms])
    uv, valid = cam.project(xyz)
    assert valid.all()
    assert np.max(np.abs(uv - uv_truth)) < 0.01
    ll = site.geo.to_geodetic(xyz)
    ll_truth = np.array([[lm["truth"]["lat"], lm["truth"]["lon"]] for lm in lms])
    # 1e-9 deg ~ 0.1 mm.
    assert np.max(np.abs(ll[:, :2] - ll_truth)) < 1e-9


def test_landmark_noise_consistent_with_gross_flag(ellsworth) -> None:
    site, _, _, _, lms = ellsworth
    geo = site.geo
    for lm in lms:
        t = lm["truth"]
        d_px = float(np.hypot(lm["u"] - t["u"], lm["v"] - t["v"]))
        z = t["xyz"][2]
        xy_noisy = geo.to_enu(np.array([lm["lat"]]), np.array([lm["lon"]]), geo.alt0_m + z)[0, :2]
        d_m = float(np.linalg.norm(xy_noisy - np.array(t["xyz"][:2])))
        if lm["gross"]:
            pixel_kind = 25.0 - 8.0 <= d_px <= 60.0 + 8.0 and d_m < 0.9
            map_kind = 4.0 - 0.8 <= d_m <= 10.0 + 0.8 and d_px < 12.0
            assert pixel_kind or map_kind, lm
        else:
            assert d_px < 12.0, lm
            assert d_m < 0.9, lm


def test_first_landmarks_are_spread(ellsworth) -> None:
    _, _, cam, _, lms = ellsworth
    uv = np.array([[lm["truth"]["u"], lm["truth"]["v"]] for lm in lms[:5]])
    assert np.ptp(uv[:, 0]) >= 0.3 * cam.width
    # The first one is the candidate nearest the image centre.
    all_uv = np.array([[lm["truth"]["u"], lm["truth"]["v"]] for lm in lms])
    r = np.linalg.norm(all_uv - [cam.cx, cam.cy], axis=1)
    assert r[0] == pytest.approx(r.min())


def test_pick_landmarks_deterministic_and_count(ellsworth) -> None:
    site, world, cam, renderer, lms = ellsworth
    feats = world.net.paint.features
    again = pick_landmarks(cam, feats, site.ground, site.geo, renderer.depth, np.random.default_rng(0))
    assert again == lms
    few = pick_landmarks(cam, feats, site.ground, site.geo, renderer.depth, np.random.default_rng(0), count=7)
    assert len(few) == 7
    # Same order of picks (farthest-point order does not depend on count).
    assert [lm["truth"] for lm in few] == [lm["truth"] for lm in lms[:7]]
    assert pick_landmarks(cam, [], site.ground, site.geo, renderer.depth, np.random.default_rng(0)) == []
