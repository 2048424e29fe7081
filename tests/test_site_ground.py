"""One ground surface for a site's cameras (calibration/site_ground.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.fit import CalibConfig, calibrate
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
