"""Camera models: pinhole (OpenCV radial-tangential) and fisheye (OpenCV Kannala-Brandt)."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest

from shared.cameras import Camera, Pose

PINHOLE_DIST = (-0.12, 0.03, 0.0012, -0.0008, 0.004)
FISHEYE_DIST = (0.012, -0.004, 0.001, -0.0005)


def _pinhole(dist=PINHOLE_DIST, pose: Pose | None = None) -> Camera:
    pose = pose or Pose.from_angles([3.0, -2.0, 8.0], 30.0, 25.0, 4.0)
    return Camera("cam_p", "pinhole", 640, 480, 500.0, 505.0, 319.5, 241.0, dist, pose)


def _fisheye(dist=FISHEYE_DIST, pose: Pose | None = None, max_angle_deg: float = 95.0) -> Camera:
    pose = pose or Pose.from_angles([27.0, 26.0, 11.0], 225.0, 80.0, 2.0)
    return Camera(
        "cam_f",
        "fisheye",
        1280,
        960,
        300.0,
        302.0,
        639.5,
        479.5,
        dist,
        pose,
        max_angle_deg=max_angle_deg,
    )


def _cam_dirs(rng: np.random.Generator, n: int, th_lo_deg: float, th_hi_deg: float) -> np.ndarray:
    """Unit camera-frame directions at off-axis angles in [th_lo, th_hi] degrees."""
    th = np.radians(rng.uniform(th_lo_deg, th_hi_deg, n))
    ph = rng.uniform(0, 2 * math.pi, n)
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)


def _world_points(cam: Camera, dirs_cam: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    ranges = rng.uniform(1.5, 90.0, len(dirs_cam))
    return cam.pose.position_m + cam.pose.to_world_dirs(dirs_cam) * ranges[:, None]


def _rvec_tvec(pose: Pose) -> tuple[np.ndarray, np.ndarray]:
    r = pose.r_cam_from_world
    rvec = cv2.Rodrigues(r)[0]
    tvec = (-r @ pose.position_m).reshape(3, 1)
    return rvec, tvec


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


# ---- agreement with OpenCV ------------------------------------------------------------------


@pytest.mark.parametrize("dist", [PINHOLE_DIST, (0.0,) * 5, (0.08, -0.05, -0.002, 0.001, 0.01)])
def test_pinhole_project_matches_opencv(dist) -> None:
    cam = _pinhole(dist)
    rng = np.random.default_rng(0)
    pts = _world_points(cam, _cam_dirs(rng, 3000, 0.0, 38.0), rng)
    uv, valid = cam.project(pts)
    assert valid.all()
    rvec, tvec = _rvec_tvec(cam.pose)
    ref, _ = cv2.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, cam.k_matrix, np.array(dist))
    assert np.max(np.abs(ref.reshape(-1, 2) - uv)) < 1e-6


@pytest.mark.parametrize("dist", [FISHEYE_DIST, (0.0,) * 4, (-0.02, 0.003, -0.0004, 0.0001)])
def test_fisheye_project_matches_opencv(dist) -> None:
    cam = _fisheye(dist)
    rng = np.random.default_rng(1)
    pts = _world_points(cam, _cam_dirs(rng, 3000, 0.0, 80.0), rng)
    uv, valid = cam.project(pts)
    assert valid.all()
    rvec, tvec = _rvec_tvec(cam.pose)
    ref, _ = cv2.fisheye.projectPoints(pts.reshape(-1, 1, 3), rvec, tvec, cam.k_matrix, np.array(dist).reshape(4, 1))
    assert np.max(np.abs(ref.reshape(-1, 2) - uv)) < 1e-6


def test_fisheye_principal_point_on_axis() -> None:
    cam = _fisheye()
    axis = cam.pose.to_world_dirs(np.array([[0.0, 0.0, 1.0]]))
    uv, valid = cam.project(cam.pose.position_m + 10.0 * axis)
    assert valid[0]
    np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)


# ---- project / unproject round trips --------------------------------------------------------


def test_pinhole_round_trip_recovers_ray() -> None:
    cam = _pinhole()
    rng = np.random.default_rng(2)
    pts = _world_points(cam, _cam_dirs(rng, 3000, 0.0, 38.0), rng)
    uv, valid = cam.project(pts)
    assert valid.all()
    rays, ok = cam.unproject(uv)
    assert ok.all()
    np.testing.assert_allclose(np.linalg.norm(rays, axis=1), 1.0, atol=1e-12)
    assert np.max(np.abs(rays - _unit(pts - cam.pose.position_m))) < 1e-9


@pytest.mark.parametrize(("th_lo", "th_hi"), [(0.0, 89.0), (91.0, 94.0)])
def test_fisheye_round_trip_recovers_ray(th_lo: float, th_hi: float) -> None:
    cam = _fisheye()
    rng = np.random.default_rng(3)
    dirs = _cam_dirs(rng, 3000, th_lo, th_hi)
    pts = _world_points(cam, dirs, rng)
    if th_lo > 90:
        # Behind the image plane: negative depth in the camera frame.
        assert np.all(cam.pose.to_camera(pts)[:, 2] < 0)
    uv, valid = cam.project(pts)
    assert valid.all()
    assert np.all(np.isfinite(uv))
    rays, ok = cam.unproject(uv)
    assert ok.all()
    assert np.max(np.abs(rays - _unit(pts - cam.pose.position_m))) < 1e-9


def test_fisheye_beyond_90_degrees_is_outside_the_90_degree_circle() -> None:
    """The radius of the image point keeps growing past 90 degrees off-axis (no fold-back)."""
    cam = _fisheye(pose=Pose.from_angles([0.0, 0.0, 10.0], 0.0, 90.0))
    th = np.radians(np.linspace(0.5, 94.5, 200))
    dirs = np.stack([np.sin(th), np.zeros_like(th), np.cos(th)], 1)
    uv, valid = cam.project_cam(dirs * 20.0)
    assert valid.all()
    r = uv[:, 0] - cam.cx
    assert np.all(np.diff(r) > 0)


def test_fisheye_beyond_fov_invalid() -> None:
    cam = _fisheye(max_angle_deg=95.0)
    dirs = _cam_dirs(np.random.default_rng(4), 100, 96.0, 179.0)
    _, valid = cam.project_cam(dirs * 5.0)
    assert not valid.any()


@pytest.mark.parametrize("dist", [(-0.2, 0.0, 0.0, 0.0), FISHEYE_DIST])
def test_a_fisheye_pixel_is_valid_only_where_its_ray_projects_back_onto_it(dist) -> None:
    """Where the lens map folds back (a strong negative k1) Newton's method stops on a ray whose image is
    elsewhere; and the corners outside the image circle have no ray at all: such pixels are invalid, every valid
    one round-trips."""
    cam = _fisheye(dist=dist)
    v, u = np.mgrid[0:cam.height:7, 0:cam.width:7]
    uv = np.stack([u.ravel(), v.ravel()], 1).astype(float)
    rays, valid = cam.unproject_cam(uv)
    back, ok = cam.project_cam(rays[valid] * 5.0)
    assert valid.any() and not valid.all() and ok.all()
    assert np.abs(back - uv[valid]).max() < 1e-3


def test_pinhole_behind_camera_invalid() -> None:
    cam = _pinhole()
    dirs = _cam_dirs(np.random.default_rng(5), 100, 91.0, 179.0)
    _, valid = cam.project_cam(dirs * 5.0)
    assert not valid.any()


def test_unproject_cam_principal_point_is_optical_axis() -> None:
    for cam in (_pinhole(), _fisheye()):
        rays, ok = cam.unproject_cam(np.array([[cam.cx, cam.cy]]))
        assert ok[0]
        np.testing.assert_allclose(rays[0], [0.0, 0.0, 1.0], atol=1e-12)


# ---- pose conventions -----------------------------------------------------------------------


def _axes(pose: Pose) -> np.ndarray:
    """Rows: the camera x (right), y (down), z (optical axis) in world coordinates."""
    return pose.to_world_dirs(np.eye(3))


def test_pose_pitch_90_looks_straight_down() -> None:
    for yaw in (0.0, 45.0, 225.0):
        pose = Pose.from_angles([1.0, 2.0, 10.0], yaw, 90.0)
        np.testing.assert_allclose(_axes(pose)[2], [0.0, 0.0, -1.0], atol=1e-12)


def test_pose_yaw_0_looks_north_with_x_east_y_down() -> None:
    axes = _axes(Pose.from_angles([0.0, 0.0, 5.0], 0.0, 0.0))
    np.testing.assert_allclose(axes[2], [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(axes[0], [1.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(axes[1], [0.0, 0.0, -1.0], atol=1e-12)


def test_pose_yaw_90_looks_east() -> None:
    axes = _axes(Pose.from_angles([0.0, 0.0, 5.0], 90.0, 0.0))
    np.testing.assert_allclose(axes[2], [1.0, 0.0, 0.0], atol=1e-12)
    # Image x points to the right of the view direction: south.
    np.testing.assert_allclose(axes[0], [0.0, -1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(axes[1], [0.0, 0.0, -1.0], atol=1e-12)


def test_pose_pitch_tilts_below_horizon() -> None:
    axes = _axes(Pose.from_angles([0.0, 0.0, 5.0], 0.0, 30.0))
    np.testing.assert_allclose(axes[2], [0.0, math.cos(math.radians(30)), -0.5], atol=1e-12)


def test_pose_roll_keeps_optical_axis() -> None:
    a = _axes(Pose.from_angles([0.0, 0.0, 5.0], 60.0, 20.0, 0.0))
    b = _axes(Pose.from_angles([0.0, 0.0, 5.0], 60.0, 20.0, 15.0))
    np.testing.assert_allclose(a[2], b[2], atol=1e-12)
    assert abs(float(a[0] @ b[0]) - math.cos(math.radians(15))) < 1e-12


def test_pose_is_proper_rotation_and_maps_position_to_origin() -> None:
    pose = Pose.from_angles([4.0, -7.0, 9.0], 123.0, 47.0, -11.0)
    r = pose.r_cam_from_world
    np.testing.assert_allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert abs(np.linalg.det(r) - 1.0) < 1e-12
    np.testing.assert_allclose(pose.to_camera(pose.position_m[None]), 0.0, atol=1e-12)


def test_pose_rejects_non_rotation() -> None:
    with pytest.raises(ValueError):
        Pose(np.zeros(3), np.diag([1.0, 1.0, 2.0]))
    with pytest.raises(ValueError):
        Pose(np.zeros(3), np.diag([1.0, 1.0, -1.0]))


def test_world_point_below_downward_camera_projects_to_centre() -> None:
    cam = _fisheye(pose=Pose.from_angles([5.0, 6.0, 10.0], 37.0, 90.0))
    uv, valid = cam.project(np.array([[5.0, 6.0, 0.0]]))
    assert valid[0]
    np.testing.assert_allclose(uv[0], [cam.cx, cam.cy], atol=1e-9)


# ---- image helpers ------------------------------------------------------------------------


def test_fisheye_in_image_circle() -> None:
    cam = _fisheye()
    r_circle = cam.image_circle_radius_px()
    # Image circle radius = f * theta_d(max angle).
    th = math.radians(95.0)
    k1, k2, k3, k4 = FISHEYE_DIST
    expected = cam.fx * th * (1 + k1 * th**2 + k2 * th**4 + k3 * th**6 + k4 * th**8)
    assert abs(r_circle - expected) < 0.2
    assert r_circle < cam.height / 2 + 60  # the circle is smaller than the image diagonal
    corners = np.array([[0.0, 0.0], [cam.width - 1, 0.0], [0.0, cam.height - 1], [cam.width - 1.0, cam.height - 1.0]])
    # Corners are inside the image rectangle but outside the circle.
    assert not cam.in_image(corners).any()
    ang = np.linspace(0, 2 * math.pi, 16, endpoint=False)
    unit = np.stack([np.cos(ang), np.sin(ang) * cam.fy / cam.fx], 1)
    centre = np.array([cam.cx, cam.cy])
    inside = centre + unit * (r_circle - 2.0)
    outside = centre + unit * (r_circle + 2.0)
    in_rect = (np.abs(outside[:, 1] - cam.cy) < cam.height / 2 - 1) & (
        np.abs(outside[:, 0] - cam.cx) < cam.width / 2 - 1
    )
    assert in_rect.sum() >= 4  # the test exercises points within the rectangle
    ok_in = cam.in_image(inside)
    rect_in = (np.abs(inside[:, 1] - cam.cy) < cam.height / 2) & (np.abs(inside[:, 0] - cam.cx) < cam.width / 2)
    assert np.all(ok_in == rect_in)
    assert not cam.in_image(outside).any()
    assert cam.in_image(centre[None])[0]


def test_fisheye_in_image_margin_shrinks_circle() -> None:
    cam = _fisheye()
    r_circle = cam.image_circle_radius_px()
    pt = np.array([[cam.cx + r_circle - 5.0, cam.cy]])
    assert cam.in_image(pt)[0]
    assert not cam.in_image(pt, margin_px=10.0)[0]


def test_pinhole_in_image_bounds() -> None:
    cam = _pinhole()
    uv = np.array(
        [[-0.5, -0.5], [cam.width - 0.5, cam.height - 0.5], [-0.6, 10.0], [10.0, cam.height - 0.4], [5.0, 5.0]]
    )
    np.testing.assert_array_equal(cam.in_image(uv), [True, True, False, False, True])
    np.testing.assert_array_equal(cam.in_image(uv, margin_px=6.0), [False, False, False, False, False])


def test_pixel_grid() -> None:
    cam = Camera("g", "pinhole", 5, 3, 10.0, 10.0, 2.0, 1.0, (), Pose.from_angles([0, 0, 1], 0, 0))
    g = cam.pixel_grid()
    assert g.shape == (3, 5, 2)
    np.testing.assert_array_equal(g[2, 4], [4.0, 2.0])
    np.testing.assert_array_equal(g[0, 0], [0.0, 0.0])


# ---- serialisation --------------------------------------------------------------------------


@pytest.mark.parametrize("make", [_pinhole, _fisheye])
def test_dict_round_trip_identical_projections(make) -> None:
    cam = make()
    d = json.loads(json.dumps(cam.to_dict()))
    cam2 = Camera.from_dict(d)
    assert (cam2.name, cam2.kind, cam2.width, cam2.height) == (cam.name, cam.kind, cam.width, cam.height)
    assert cam2.dist == cam.dist
    rng = np.random.default_rng(6)
    th_hi = 38.0 if cam.kind == "pinhole" else 94.0
    pts = _world_points(cam, _cam_dirs(rng, 500, 0.0, th_hi), rng)
    uv1, v1 = cam.project(pts)
    uv2, v2 = cam2.project(pts)
    np.testing.assert_array_equal(v1, v2)
    np.testing.assert_array_equal(uv1, uv2)
    r1, _ = cam.unproject(uv1)
    r2, _ = cam2.unproject(uv1)
    np.testing.assert_array_equal(r1, r2)


def test_pose_from_dict_angles() -> None:
    d = {"position_m": [1.0, 2.0, 3.0], "yaw_deg": 90.0, "pitch_deg": 10.0}
    pose = Pose.from_dict(d)
    ref = Pose.from_angles([1.0, 2.0, 3.0], 90.0, 10.0)
    np.testing.assert_array_equal(pose.r_cam_from_world, ref.r_cam_from_world)


def test_from_dict_missing_field_names_camera() -> None:
    d = _pinhole().to_dict()
    del d["fx"]
    with pytest.raises(ValueError, match="cam_p"):
        Camera.from_dict(d)


# ---- validation -----------------------------------------------------------------------------


def _kwargs(**over) -> dict:
    kw = {
        "name": "bad_cam",
        "kind": "pinhole",
        "width": 640,
        "height": 480,
        "fx": 500.0,
        "fy": 500.0,
        "cx": 320.0,
        "cy": 240.0,
        "dist": (0.0,) * 5,
        "pose": Pose.from_angles([0, 0, 5], 0, 10),
    }
    kw.update(over)
    return kw


@pytest.mark.parametrize(
    "over",
    [
        {"fx": 0.0},
        {"fx": -100.0},
        {"fy": 0.0},
        {"fx": float("nan")},
        {"dist": (0.1,) * 6},
        {"kind": "fisheye", "dist": (0.1,) * 5},
        {"dist": (0.1, float("nan"))},
        {"kind": "omni"},
        {"width": 0},
        {"max_angle_deg": 90.0},
        {"kind": "fisheye", "dist": (0.0,) * 4, "max_angle_deg": 180.0},
    ],
)
def test_invalid_camera_raises_naming_camera(over: dict) -> None:
    with pytest.raises(ValueError, match="bad_cam"):
        Camera(**_kwargs(**over))


def test_short_dist_is_zero_padded() -> None:
    cam = Camera(**_kwargs(dist=(0.1, 0.01)))
    assert cam.dist == (0.1, 0.01, 0.0, 0.0, 0.0)
