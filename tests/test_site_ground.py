"""One ground surface for a site's cameras (calibration/site_ground.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.fit import SURFACE_MAX_RANGE_M, CalibConfig, _onto_surface, calibrate
from calibration.landmarks import Landmarks
from calibration.site_ground import GRID_M, MAX_BUMPS, GroundSurface, calibrate_site, fit_ground_surface
from shared.cameras import Camera, Pose
from shared.ground import Bump, Terrain, ground_lookup
from tests.test_calibration import GEO, _fisheye, _pinhole, _synthetic_landmarks

# a crown and a dip the planes of one camera cannot follow
BUMPY = Terrain(0.004, -0.006, (Bump(8.0, 6.0, 10.0, 0.6), Bump(40.0, 30.0, 9.0, -0.4)))


def test_fit_recovers_a_smooth_surface_and_the_grid_matches_the_exact_surface():
    rng = np.random.default_rng(0)
    xy = rng.uniform(-30, 60, (200, 2))
    z = BUMPY.height(xy[:, 0], xy[:, 1]) + 0.3
    surface = fit_ground_surface(xy, z, np.ones(len(xy)), grid_m=10.0)  # a grid as fine as the bumps
    probe = rng.uniform(-20, 50, (500, 2))
    err = surface.height(probe) - (BUMPY.height(probe[:, 0], probe[:, 1]) + 0.3)
    assert np.mean(np.abs(err)) < 0.03 and np.max(np.abs(err)) < 0.15
    many = rng.uniform(-40, 70, (30000, 2))  # read off the 0.5 m grid
    assert np.max(np.abs(surface.height(many) - surface._exact(many))) < 1e-3
    assert json.loads(json.dumps(surface.to_dict()))["model"] == "plane + Gaussian bumps"


def test_fit_needs_heights_and_ignores_non_finite_ones():
    with pytest.raises(ValueError, match="at least 3 landmark heights"):
        fit_ground_surface(np.zeros((2, 2)), np.zeros(2), np.ones(2))
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0], [5.0, 5.0]])
    z = np.array([0.0, 0.1, 0.2, 0.3, np.nan])
    surface = fit_ground_surface(xy, z, np.ones(5))
    assert np.isfinite(surface.height(xy)).all()


def _second_pinhole() -> Camera:
    return Camera("Q", "pinhole", 640, 512, 600.0, 600.0, 319.5, 255.5, (-0.08, 0.01, 0.0, 0.0, 0.0),
                  Pose.from_angles([-15.0, -10.0, 8.0], 40.0, 14.0))


def _error(cal, cam: Camera, terrain: Terrain, radius_m: float) -> float:
    truth, valid = ground_lookup(cam, terrain)
    grid = cam.pixel_grid().reshape(-1, 2)[::7]
    t = truth.reshape(-1, 3)[::7]
    near = valid.reshape(-1)[::7] & (np.linalg.norm(t[:, :2] - cam.pose.position_m[:2], axis=1) < radius_m)
    xy, ok = cal.pixel_to_xy(grid[near])
    assert ok.mean() > 0.95
    return float(np.mean(np.linalg.norm(xy[ok] - t[near][ok, :2], axis=1)))


def test_pinhole_cameras_on_the_site_surface_follow_a_ground_their_planes_cannot():
    """Three cameras over a crown and a dip, exact landmarks: the pinhole cameras refitted on one surface fitted
    to all the landmarks lift their pixels closer to the truth than their own planes do; the fisheye keeps its
    planes; the surface's heights sit on the terrain."""
    rng = np.random.default_rng(3)
    fish, p1, p2 = _fisheye(), _pinhole(), _second_pinhole()
    jobs = [
        ("F", _synthetic_landmarks(fish, 20, rng, 40.0, terrain=BUMPY),
         CalibConfig("fisheye", 1280, 960, image_circle=(639.5, 479.5, fish.image_circle_radius_px()), fov_deg=188.0)),
        ("P", _synthetic_landmarks(p1, 20, rng, 60.0, terrain=BUMPY), CalibConfig("pinhole", 640, 512)),
        ("Q", _synthetic_landmarks(p2, 20, rng, 60.0, terrain=BUMPY), CalibConfig("pinhole", 640, 512)),
    ]
    site = calibrate_site(jobs, GEO)
    assert site["F"].ground is None and site["P"].ground is not None and site["Q"].ground is site["P"].ground
    assert isinstance(site["P"].ground, GroundSurface) and site["P"].ground.cameras == ("F", "P", "Q")
    for name, cam in (("P", p1), ("Q", p2)):
        alone = calibrate(jobs[[j[0] for j in jobs].index(name)][1], CalibConfig("pinhole", 640, 512), GEO)
        # measured P 0.373 against 0.458 m, Q 0.285 against 0.421 m
        assert _error(site[name], cam, BUMPY, 40.0) < 0.85 * _error(alone, cam, BUMPY, 40.0)
    # the lifted points lie on the surface and on their rays
    uv = np.array([[320.0, 300.0], [100.0, 450.0], [600.0, 400.0]])
    xy, ok = site["P"].pixel_to_xy(uv)
    assert ok.all()
    dirs, _ = site["P"].camera.unproject(uv)
    o = site["P"].camera.pose.position_m
    t = (xy[:, 0] - o[0]) / dirs[:, 0]
    assert np.allclose(o[2] + t * dirs[:, 2], site["P"].ground.height(xy), atol=0.01)


def test_site_calibration_refuses_one_camera_and_twice_the_same_name():
    rng = np.random.default_rng(4)
    p1 = _pinhole()
    job = ("P", _synthetic_landmarks(p1, 12, rng, 60.0), CalibConfig("pinhole", 640, 512))
    with pytest.raises(ValueError, match="at least two cameras"):
        calibrate_site([job], GEO)
    with pytest.raises(ValueError, match="unique"):
        calibrate_site([job, job], GEO)
    with pytest.raises(ValueError, match="iterations"):
        calibrate_site([job, ("Q", *job[1:])], GEO, iterations=0)


def test_cli_calibrate_with_shared_ground(tmp_path, capsys):
    from roadside.cli import main

    rng = np.random.default_rng(5)
    files = {}
    for name, cam in (("P", _pinhole()), ("Q", _second_pinhole())):
        lm = _synthetic_landmarks(cam, 14, rng, 60.0, pixel_sigma=0.5, map_sigma=0.05, terrain=BUMPY)
        rows = [{"id": i, "u": float(u), "v": float(v), "lat": float(la), "lon": float(lo)}
                for i, (u, v), (la, lo) in zip(lm.ids, lm.uv, lm.latlon, strict=True)]
        files[name] = tmp_path / f"{name}.json"
        files[name].write_text(json.dumps({"width": 640, "height": 512, "landmarks": rows}))
    out = tmp_path / "P.npz"
    assert main(["calibrate", "--landmarks", str(files["P"]), "--kind", "pinhole", "--out", str(out),
                 "--origin", f"{GEO.lat0_deg},{GEO.lon0_deg},{GEO.alt0_m}",
                 "--shared-ground", f"{files['Q']}:pinhole"]) == 0
    assert "the site's ground surface (fitted to the landmarks of 2 cameras" in capsys.readouterr().out
    report = json.loads(out.with_suffix(".report.json").read_text())
    loo = [lm["leave_one_out_m"] for lm in report["landmarks"] if lm["inlier"]]
    assert all(v is not None for v in loo) and 0 < np.mean(loo) < 2.0  # refitted on the surface without each one
    assert report["ground"]["model"] == "plane + Gaussian bumps" and len(report["ground"]["cameras"]) == 2
    from calibration.masks import load_masks

    assert load_masks(out).meta["ground"]["cameras"] == report["ground"]["cameras"]
    with pytest.raises(SystemExit):
        main(["calibrate", "--landmarks", str(files["P"]), "--kind", "pinhole", "--out", str(out),
              "--shared-ground", f"{files['Q']}:wide"])
    from calibration.run import CalibrateJob, run_calibration

    with pytest.raises(ValueError, match="fisheye camera keeps its own planes"):
        run_calibration(CalibrateJob(files["P"], "fisheye", out, image_circle=(320.0, 256.0, 420.0),
                                     shared_ground=((files["Q"], "pinhole", None),)))
    files["Q"].write_text(json.dumps({"kind": "fisheye", **json.loads(files["Q"].read_text())}))
    with pytest.raises(ValueError, match=r"Q.json is for a fisheye camera, not --shared-ground \.\.\.:pinhole"):
        run_calibration(CalibrateJob(files["P"], "pinhole", out, shared_ground=((files["Q"], "pinhole", None),)))


def test_a_site_too_large_for_the_bumps_gets_a_coarser_grid():
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 900, (300, 2))
    surface = fit_ground_surface(xy, 0.01 * xy[:, 0], np.ones(len(xy)))
    assert len(surface.centres) <= MAX_BUMPS and surface.sigma_m > GRID_M
    assert np.allclose(surface.height(xy[:5]), 0.01 * xy[:5, 0], atol=0.05)


def _first_crossing(surface, o: np.ndarray, dirs: np.ndarray, step_m: float = 0.02) -> np.ndarray:
    """x, y where each ray first dips under the surface: a fine march from the camera (the reference)."""
    out = np.full((len(dirs), 2), np.nan)
    for i, d in enumerate(dirs):
        t = np.arange(0.0, 600.0, step_m) / np.hypot(d[0], d[1])
        under = np.flatnonzero(o[2] + t * d[2] <= surface.height(o[:2] + t[:, None] * d[:2]))
        if len(under):
            out[i] = o[:2] + t[under[0]] * d[:2]
    return out


def _rays(depression_deg) -> np.ndarray:
    a = np.radians(np.asarray(depression_deg, float))
    return np.column_stack([np.cos(a), np.zeros_like(a), -np.sin(a)])


def test_pixels_are_lifted_onto_the_first_crossing_of_a_ground_steeper_than_their_ray():
    """A camera 8 m up looking along a ground that rises faster than its far rays fall (3 %, and a 0.6 m bump at
    120 m), and over a 2.5 m rise: each ray's point is where it first meets the ground, not
    an unconverged point (metres off the ground) or the ground behind the rise (measured before the fix: 50.3 m and
    43.1 m off, marked valid)."""
    o = np.array([0.0, 0.0, 8.0])
    rising = GroundSurface(0.0, (0.03, 0.0), np.array([[120.0, 0.0]]), np.array([0.6]), 20.0)
    rise = GroundSurface(0.0, (0.0, 0.0), np.array([[110.0, 0.0]]), np.array([2.5]), 25.0)
    for surface, depression in ((rising, [0.5, 1.0, 2.0, 3.0, 4.0, 10.0]), (rise, np.arange(2.0, 5.01, 0.25))):
        dirs = _rays(depression)
        want = _first_crossing(surface, o, dirs)
        got = _onto_surface(surface, o, dirs, np.zeros(3))  # a surface's own bounds, whatever the start plane
        assert np.isfinite(got).all()
        np.testing.assert_allclose(got, want, atol=0.05)
        t = got[:, 0] / dirs[:, 0]
        assert np.abs(o[2] + t * dirs[:, 2] - surface.height(got)).max() < 0.01
    assert abs(_onto_surface(rise, o, _rays([2.75]), np.zeros(3))[0, 0] - 115.96) < 0.05  # the rise's front


def test_a_pixel_is_invalid_where_no_ground_is_met_within_range_or_its_point_is_off_the_ground():
    o = np.array([0.0, 0.0, 8.0])
    flat = GroundSurface(0.0, (0.0, 0.0), np.array([[0.0, 0.0]]), np.array([0.0]), 20.0)
    got = _onto_surface(flat, o, _rays([10.0, -1.0, 0.0, 0.1]), np.zeros(3))
    assert np.allclose(got[0], [8.0 / np.tan(np.radians(10.0)), 0.0])
    assert np.isnan(got[1:]).all()  # above the horizon; level; 4.6 km away, beyond SURFACE_MAX_RANGE_M
    assert 8.0 / np.tan(np.radians(0.1)) > SURFACE_MAX_RANGE_M
    under = _onto_surface(flat, np.array([0.0, 0.0, -1.0]), _rays([10.0]), np.zeros(3))
    assert np.isnan(under).all()  # the camera under the ground

    class Cliff:  # a ground with no `relief` (searched in steps from the camera), 1 m higher from x = 50 m on
        @staticmethod
        def height(xy):
            return np.where(np.asarray(xy)[:, 0] < 50.0, 0.0, 1.0)

    # 10 deg meets the level ground at 45.4 m; 8.5 deg would pass over it to 53.5 m but meets the cliff's face
    # at x = 50 m, 0.53 m up: no point of the height field there is within SURFACE_TOL_M of the ray's
    got = _onto_surface(Cliff(), o, _rays([10.0, 8.5, 6.0]), np.zeros(3))
    assert np.allclose(got[0], [8.0 / np.tan(np.radians(10.0)), 0.0], atol=1e-3)
    assert np.isnan(got[1]).all()
    assert np.allclose(got[2], [7.0 / np.tan(np.radians(6.0)), 0.0], atol=1e-3)  # onto the top


def _landmark_file(path, lm: Landmarks, mirrored: bool = False):
    u = 639.0 - lm.uv[:, 0] if mirrored else lm.uv[:, 0]
    rows = [{"id": i, "u": float(uu), "v": float(v), "lat": float(la), "lon": float(lo)}
            for i, uu, v, (la, lo) in zip(lm.ids, u, lm.uv[:, 1], lm.latlon, strict=True)]
    path.write_text(json.dumps({"width": 640, "height": 512, "landmarks": rows}))
    return path


def test_cli_refuses_a_shared_ground_file_whose_own_fit_fails(tmp_path):
    """Another camera's file with mirrored pixels (u counted from the right) puts that camera under the ground: it
    would bend the surface this camera is lifted onto (measured: P's error within 60 m 0.348 -> 0.414 m), so the
    run stops and names the file instead of using it."""
    from calibration.run import CalibrateJob, run_calibration

    rng = np.random.default_rng(5)
    p = _landmark_file(tmp_path / "P.json", _synthetic_landmarks(_pinhole(), 14, rng, 60.0, 0.5, 0.05, BUMPY))
    q = _landmark_file(tmp_path / "Q.json", _synthetic_landmarks(_second_pinhole(), 14, rng, 60.0, 0.5, 0.05, BUMPY),
                       mirrored=True)
    origin = (GEO.lat0_deg, GEO.lon0_deg, GEO.alt0_m)
    with pytest.raises(ValueError, match=r"Q\.json \(on its own\): the fit puts the camera -?\d+\.\d m above the "
                                         r"ground it sees.*pixels mirrored.*leave it out of --shared-ground"):
        run_calibration(CalibrateJob(p, "pinhole", tmp_path / "P.npz", origin=origin,
                                     shared_ground=((q, "pinhole", None),)))
    assert not (tmp_path / "P.npz").exists()
    # this camera's own file mirrored: refused before its landmarks shape the surface, without the advice for others
    with pytest.raises(ValueError, match=r"Q\.json \(on its own\): the fit puts the camera.*A roadside camera looks "
                                         r"down from a pole$"):
        run_calibration(CalibrateJob(q, "pinhole", tmp_path / "Q.npz", origin=origin,
                                     shared_ground=((p, "pinhole", None),)))


def test_site_calibration_checks_every_camera_on_its_own_and_after_each_refit():
    rng = np.random.default_rng(4)
    cfg = CalibConfig("pinhole", 640, 512)
    jobs = [("P", _synthetic_landmarks(_pinhole(), 12, rng, 60.0, terrain=BUMPY), cfg),
            ("Q", _synthetic_landmarks(_second_pinhole(), 12, rng, 60.0, terrain=BUMPY), cfg)]
    seen = []

    def check(name, cal, lm, config):
        seen.append((name, cal.ground is not None))
        assert lm is dict((n, j) for n, j, _ in jobs)[name] and config is cfg
        return None

    calibrate_site(jobs, GEO, iterations=2, check=check)
    assert seen == [("P", False), ("Q", False), ("P", True), ("Q", True), ("P", True), ("Q", True)]
    with pytest.raises(ValueError, match=r"^Q \(refitted on the site's ground surface\): under it$"):
        calibrate_site(jobs, GEO, check=lambda name, cal, lm, config: "under it"
                       if name == "Q" and cal.ground is not None else None)



def test_a_shared_ground_camera_whose_segments_hold_a_ramp_is_not_refused(tmp_path):
    """Another camera's file that calibrates cleanly on its own run (its named segments: a road and a deck 2.5 m
    up) had a third of its landmarks rejected on a fit without its segments, and the whole run was refused as if the
    file were wrong."""
    from calibration.run import CalibrateJob, run_calibration

    def make(cam, n, rng, level_only=False):
        pts = []
        while len(pts) < n:
            xy = cam.pose.position_m[:2] + rng.uniform(-60.0, 60.0, 2)
            seg = int((xy[0] + xy[1]) / np.sqrt(2) > 20.0)
            if np.linalg.norm(xy - cam.pose.position_m[:2]) > 60.0 or (level_only and seg):
                continue
            uv, ok = cam.project(np.array([[*xy, 2.5 * seg]]))
            if ok[0] and cam.in_image(uv, margin_px=20)[0]:
                pts.append((uv[0], xy, seg))
        ll = GEO.to_geodetic(np.column_stack([[p[1] for p in pts], np.zeros(n)]))
        return Landmarks(tuple(f"L{i}" for i in range(n)), np.array([p[0] for p in pts]), ll[:, :2],
                         np.array([p[2] for p in pts]))

    def write(path, lm, segments):
        rows = [{"id": i, "u": float(u), "v": float(v), "lat": float(a), "lon": float(o),
                 **({"segment": int(s)} if segments else {})}
                for i, (u, v), (a, o), s in zip(lm.ids, lm.uv, lm.latlon, lm.segment, strict=True)]
        path.write_text(json.dumps({"width": 640, "height": 512, "kind": "pinhole", "landmarks": rows}))
        return path

    q_cam = Camera("Q", "pinhole", 640, 512, 600.0, 600.0, 319.5, 255.5, (-0.08, 0.01, 0.0, 0.0, 0.0),
                   Pose.from_angles([-15.0, -10.0, 8.0], 40.0, 14.0))
    q_lm = make(q_cam, 16, np.random.default_rng(1))
    cfg = CalibConfig("pinhole", 640, 512)
    assert len(calibrate(q_lm, cfg, GEO).rejected) == 0 and len(calibrate(q_lm.without_segments(), cfg, GEO).rejected)
    p = write(tmp_path / "P.json", make(_pinhole(), 16, np.random.default_rng(7), level_only=True), False)
    q = write(tmp_path / "Q.json", q_lm, True)
    origin = (GEO.lat0_deg, GEO.lon0_deg, GEO.alt0_m)
    run_calibration(CalibrateJob(p, "pinhole", tmp_path / "P.npz", origin=origin,
                                 shared_ground=((q, "pinhole", None),)))
    assert (tmp_path / "P.npz").is_file()


def test_a_level_or_rising_ray_meets_ground_that_rises_faster():
    """A camera 6 m up over a 10 % grade (a plane alone, no bumps): rays level or 1-3 deg up still meet the ground
    (they were invalid: only falling rays were searched, and a plane's search started exactly at the crossing)."""
    o = np.array([0.0, 0.0, 6.0])
    uphill = GroundSurface(0.0, (0.1, 0.0), np.zeros((0, 2)), np.zeros(0), 20.0)
    up = np.array([-0.5, 0.0, 1.0, 3.0])  # degrees above the horizon
    got = _onto_surface(uphill, o, _rays(-up), np.zeros(3))
    np.testing.assert_allclose(got[:, 0], 6.0 / (0.1 - np.tan(np.radians(up))), atol=0.01)  # 55.2, 60.0, 72.7, 126.1
