"""Landmarks -> camera model -> piecewise-planar ground -> pixel-to-ground map.

The paper lifts detections to the ground with per-segment homographies fitted on landmarks
(fisheye images first undistorted with a Kannala-Brandt model). Free 8-parameter homographies
overfit 5-20 noisy landmarks badly, so the homographies here are plane-induced: the lens and
the pose are fitted once from all landmarks (robust least squares, gross mistakes rejected by
their reprojection residual), then each segment gets a ground plane z = a x + b y + c (3
parameters, pulled toward one global plane when the segment has few landmarks). The pixel ->
ground map of a segment is then exactly a homography of the undistorted view (`homography`).
Segments split the image around the camera's nadir and are blended smoothly at their borders.
Everything is fitted in the local metric site frame, never in raw degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from scipy.optimize import least_squares

from calibration.landmarks import Landmarks
from shared.cameras import Camera, Pose
from shared.geo import GeoFrame

MIN_PER_SEGMENT = 4
MAX_VIEW_ANGLE_DEG = 86.0  # fisheye pixels further off axis than this look at the horizon
PLANE_PRIOR_WEIGHT = 2.0  # pull of the global plane on a segment's plane (in landmark units)


@dataclass(frozen=True)
class CalibConfig:
    kind: str  # "pinhole" | "fisheye"
    width: int
    height: int
    segments: int | None = None  # default: 1 pinhole, 4 fisheye
    outlier_px: float = 8.0  # smallest reprojection residual (px) that can mark a gross mistake
    image_circle: tuple[float, float, float] | None = None  # fisheye: cx, cy, radius (px)
    fov_deg: float = 188.0  # fisheye: full field of view at the image circle's edge (datasheet)

    def __post_init__(self) -> None:
        if self.kind not in ("pinhole", "fisheye"):
            raise ValueError(f"kind must be pinhole or fisheye, got {self.kind!r}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if self.segments is not None and not 1 <= self.segments <= 8:
            raise ValueError(f"segments must be in [1, 8], got {self.segments}")
        if not self.outlier_px > 0:
            raise ValueError(f"outlier_px must be > 0, got {self.outlier_px}")

    @property
    def wanted_segments(self) -> int:
        return self.segments if self.segments is not None else (4 if self.kind == "fisheye" else 1)

    @property
    def circle(self) -> tuple[float, float, float]:
        if self.image_circle is not None:
            return self.image_circle
        return ((self.width - 1) / 2, (self.height - 1) / 2, min(self.width, self.height) / 2)


@dataclass
class Calibration:
    """A fitted pixel -> site-metres model: `camera` (lens + pose), `planes` (P, 3) as
    z = a x + b y + c per segment, `sector_centres` (P,) angles around `nadir_px`."""

    config: CalibConfig
    geo: GeoFrame
    camera: Camera
    planes: np.ndarray
    sector_centres: np.ndarray
    nadir_px: np.ndarray
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rejected: list[tuple[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)

    def weights(self, uv: np.ndarray) -> np.ndarray:
        """(N, P) blending weights of the segments at pixels uv (rows sum to 1)."""
        p = len(self.planes)
        if p == 1:
            return np.ones((len(uv), 1))
        ang = np.arctan2(uv[:, 1] - self.nadir_px[1], uv[:, 0] - self.nadir_px[0])
        d = np.abs(np.angle(np.exp(1j * (ang[:, None] - self.sector_centres[None, :]))))
        half = math.pi / p
        w = np.clip(1.0 - (d - half * 0.6) / (half * 0.8), 0.0, 1.0)
        return w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)

    def pixel_to_xy(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> ((N, 2) site metres, (N,) valid)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        dirs, ok = self.camera.unproject(uv)
        if self.camera.kind == "fisheye":
            cam_rays, _ = self.camera.unproject_cam(uv)
            ok &= cam_rays[:, 2] > math.cos(math.radians(MAX_VIEW_ANGLE_DEG))
        o = self.camera.pose.position_m
        w = self.weights(uv)
        out = np.zeros((len(uv), 2))
        for k, (a, b, c) in enumerate(self.planes):
            m = w[:, k] > 0
            if not m.any():
                continue
            d = dirs[m]
            den = d[:, 2] - a * d[:, 0] - b * d[:, 1]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (a * o[0] + b * o[1] + c - o[2]) / den
            good = (t > 0) & np.isfinite(t)
            pts = np.where(good[:, None], o[:2] + t[:, None] * d[:, :2], np.nan)
            out[m] += w[m, k, None] * pts
        ok &= np.all(np.isfinite(out), axis=1)
        return np.where(ok[:, None], out, np.nan), ok

    def homography(self, k: int) -> np.ndarray:
        """Segment k's plane-induced homography: undistorted view (x/z, y/z) -> site metres."""
        a, b, c = self.planes[k]
        r = self.camera.pose.r_cam_from_world
        o = self.camera.pose.position_m
        # A point on the plane: X = o + t R^T q~, with q~ = (x, y, 1). Solve linearly for 4+ points.
        q = np.array([[x, y] for x in (-0.5, 0.0, 0.5) for y in (-0.5, 0.0, 0.5)])
        d = np.column_stack([q, np.ones(len(q))]) @ r
        t = (a * o[0] + b * o[1] + c - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
        xy = o[:2] + t[:, None] * d[:, :2]
        h, _ = cv2.findHomography(q, xy, 0)
        return h


# ---- camera model -------------------------------------------------------------------------------
def _camera(p: np.ndarray, cfg: CalibConfig) -> Camera:
    f, cx, cy, k1, k2 = p[:5]
    r = cv2.Rodrigues(np.asarray(p[5:8], float))[0]
    pos = -r.T @ np.asarray(p[8:11], float)
    if cfg.kind == "fisheye":
        dist, max_angle = (float(k1), float(k2), 0.0, 0.0), 100.0
    else:
        dist, max_angle = (float(k1), float(k2), 0.0, 0.0, 0.0), 89.0
    return Camera(
        "fit",
        cfg.kind,
        cfg.width,
        cfg.height,
        float(f),
        float(f),
        float(cx),
        float(cy),
        dist,
        Pose(pos, r),
        max_angle_deg=max_angle,
    )


def _initial_fisheye(uv: np.ndarray, obj: np.ndarray, cfg: CalibConfig) -> tuple[np.ndarray, float]:
    cx0, cy0, rad = cfg.circle
    f0 = rad / (math.pi / 2)
    d = (uv - [cx0, cy0]) / f0
    theta = np.linalg.norm(d, axis=1)
    keep = theta < math.radians(80)
    if keep.sum() < 4:
        keep = np.ones(len(theta), bool)
    norm = d * (np.tan(np.minimum(theta, 1.45)) / np.maximum(theta, 1e-9))[:, None]
    ok, rvec, tvec = cv2.solvePnP(obj[keep], norm[keep], np.eye(3), None, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise ValueError("could not find an initial camera pose from the landmarks")
    return np.array([f0, cx0, cy0, 0.0, 0.0, *rvec.ravel(), *tvec.ravel()]), f0


def _initial_pinhole(uv: np.ndarray, obj: np.ndarray, cfg: CalibConfig) -> tuple[np.ndarray, float]:
    cx0, cy0 = (cfg.width - 1) / 2, (cfg.height - 1) / 2
    best = None
    for hfov in (15, 25, 35, 45, 55, 65, 80, 95, 110):
        f = 0.5 * cfg.width / math.tan(math.radians(hfov) / 2)
        k = np.array([[f, 0, cx0], [0, f, cy0], [0, 0, 1]])
        ok, rvec, tvec = cv2.solvePnP(obj, uv, k, None, flags=cv2.SOLVEPNP_SQPNP)
        if not ok:
            continue
        proj, _ = cv2.projectPoints(obj, rvec, tvec, k, None)
        err = float(np.median(np.linalg.norm(proj.reshape(-1, 2) - uv, axis=1)))
        if best is None or err < best[0]:
            best = (err, f, rvec, tvec)
    if best is None:
        raise ValueError("could not find an initial camera pose from the landmarks")
    _, f, rvec, tvec = best
    return np.array([f, cx0, cy0, 0.0, 0.0, *rvec.ravel(), *tvec.ravel()]), f


def _fit_camera(uv: np.ndarray, obj: np.ndarray, cfg: CalibConfig, p0: np.ndarray | None = None) -> np.ndarray:
    """Robust least squares of the reprojection error; frees parameters as landmarks allow."""
    if p0 is None:
        p0, _ = (_initial_fisheye if cfg.kind == "fisheye" else _initial_pinhole)(uv, obj, cfg)
    n = len(uv)
    free = [True] * 11
    idx = np.nonzero(free)[0]
    f0 = p0[0]
    span = 0.15 * (cfg.circle[2] if cfg.kind == "fisheye" else max(cfg.width, cfg.height) / 2)
    lo_all = np.array([0.4 * f0, p0[1] - span, p0[2] - span, -0.5, -0.3, *[-np.inf] * 6])
    hi_all = np.array([2.5 * f0, p0[1] + span, p0[2] + span, 0.5, 0.3, *[np.inf] * 6])
    x0 = np.clip(p0[idx], lo_all[idx] + 1e-9, hi_all[idx] - 1e-9)

    def full(x):
        p = p0.copy()
        p[idx] = x
        return p

    # Priors that a user knows: the fisheye image circle's radius at half the field of view,
    # the principal point near the circle (or image) centre, small higher-order distortion.
    ccx, ccy, crad = cfg.circle
    theta_edge = math.radians(cfg.fov_deg / 2)
    centre_sigma = 3.0 if cfg.kind == "fisheye" else 12.0
    k2_sigma = 0.01 if cfg.kind == "fisheye" else 0.05
    weight = math.sqrt(max(n, 4))

    def resid(x):
        p = full(x)
        cam = _camera(p, cfg)
        proj, ok = cam.project(obj)
        r = np.where(ok[:, None], proj - uv, 1e3).ravel()
        prior = [(p[1] - ccx) / centre_sigma, (p[2] - ccy) / centre_sigma, p[4] / k2_sigma]
        if cfg.kind == "fisheye":
            t2 = theta_edge**2
            r_edge = p[0] * theta_edge * (1 + p[3] * t2 + p[4] * t2 * t2)
            prior.append((r_edge - crad) / 2.0)
        return np.concatenate([r, weight * np.array(prior)])

    sol = least_squares(
        resid, x0, bounds=(lo_all[idx], hi_all[idx]), loss="soft_l1", f_scale=3.0, x_scale="jac", max_nfev=600
    )
    return full(sol.x)


# ---- ground planes --------------------------------------------------------------------------
def _implied_heights(cam: Camera, uv: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ground height at each landmark implied by its pixel ray, and a weight (steep rays say
    little about height)."""
    dirs, _ = cam.unproject(uv)
    o = cam.pose.position_m
    dxy = dirs[:, :2]
    t = np.sum((xy - o[:2]) * dxy, axis=1) / np.maximum(np.sum(dxy * dxy, axis=1), 1e-12)
    z = o[2] + t * dirs[:, 2]
    horiz = np.linalg.norm(dxy, axis=1)
    slope = np.abs(dirs[:, 2]) / np.maximum(horiz, 1e-6)  # tan(depression)
    weight = 1.0 / (0.15**2 * slope**2 + 0.02**2)
    return z, weight


def _fit_plane(
    xy: np.ndarray, z: np.ndarray, w: np.ndarray, prior: np.ndarray | None, centre: np.ndarray
) -> np.ndarray:
    a_mat = np.column_stack([xy - centre, np.ones(len(xy))]) * np.sqrt(w)[:, None]
    rhs = z * np.sqrt(w)
    if prior is not None:
        # prior plane expressed about `centre`: z = a (x - cx) + b (y - cy) + c'
        pa, pb, pc = prior
        c_local = pa * centre[0] + pb * centre[1] + pc
        lam = PLANE_PRIOR_WEIGHT * float(np.median(w))
        a_mat = np.vstack([a_mat, np.diag([20.0, 20.0, 1.0]) * math.sqrt(lam)])
        rhs = np.concatenate([rhs, np.array([pa * 20.0, pb * 20.0, c_local]) * math.sqrt(lam)])
    sol, *_ = np.linalg.lstsq(a_mat, rhs, rcond=None)
    a, b, c_local = sol
    return np.array([a, b, c_local - a * centre[0] - b * centre[1]])


def _sectors(uv: np.ndarray, nadir: np.ndarray, p: int) -> tuple[np.ndarray, np.ndarray]:
    """Sector centres (P,) balancing landmarks across sectors, and each landmark's sector (N,)."""
    ang = np.arctan2(uv[:, 1] - nadir[1], uv[:, 0] - nadir[0])
    best = None
    for start in np.linspace(0, 2 * math.pi / p, 16, endpoint=False):
        lab = (((ang - start) % (2 * math.pi)) // (2 * math.pi / p)).astype(int)
        cnt = np.bincount(lab, minlength=p).min()
        if best is None or cnt > best[0]:
            best = (cnt, start, lab)
    _, start, lab = best
    return start + (np.arange(p) + 0.5) * 2 * math.pi / p, lab


def calibrate(lm: Landmarks, cfg: CalibConfig, geo: GeoFrame) -> Calibration:
    """Fit one camera's pixel -> ground model. Gross mistakes are rejected and reported."""
    xy = lm.to_local(geo)
    n = len(lm)
    obj = np.column_stack([xy, np.zeros(n)])
    p = _fit_camera(lm.uv, obj, cfg)
    use = np.ones(n, bool)
    for _ in range(2):
        cam = _camera(p, cfg)
        proj, ok = cam.project(obj)
        res_px = np.where(ok, np.linalg.norm(proj - lm.uv, axis=1), np.inf)
        mad = 1.4826 * np.median(np.abs(res_px[use] - np.median(res_px[use])))
        thr = max(cfg.outlier_px, np.median(res_px[use]) + 4.0 * mad)
        new_use = res_px < thr
        if new_use.sum() < 4 or (new_use == use).all():
            break
        use = new_use
        p = _fit_camera(lm.uv[use], obj[use], cfg, p)
    cam = _camera(p, cfg)
    # Ground planes: a global one, then one per segment around the nadir.
    z, w = _implied_heights(cam, lm.uv[use], xy[use])
    centre = xy[use].mean(axis=0)
    global_plane = _fit_plane(xy[use], z, w, None, centre) if use.sum() >= 6 else np.zeros(3)
    # Refit the camera on the plane's heights (the ground is not at z = 0).
    obj[:, 2] = global_plane[0] * xy[:, 0] + global_plane[1] * xy[:, 1] + global_plane[2]
    p = _fit_camera(lm.uv[use], obj[use], cfg, p)
    cam = _camera(p, cfg)
    z, w = _implied_heights(cam, lm.uv[use], xy[use])
    if use.sum() >= 6:
        global_plane = _fit_plane(xy[use], z, w, global_plane, centre)
    nadir_px = cam.project(cam.pose.position_m[None] - [0.0, 0.0, 10.0])[0][0]
    warnings: list[str] = []
    n_seg = cfg.wanted_segments
    while n_seg > 1 and np.bincount(_sectors(lm.uv[use], nadir_px, n_seg)[1], minlength=n_seg).min() < MIN_PER_SEGMENT:
        n_seg -= 1
    if n_seg < cfg.wanted_segments:
        warnings.append(
            f"{int(use.sum())} usable landmarks: fitted {n_seg} ground segment(s) instead of "
            f"{cfg.wanted_segments} (each needs at least {MIN_PER_SEGMENT} landmarks)"
        )
    if n_seg > 1:
        centres, lab = _sectors(lm.uv[use], nadir_px, n_seg)
        planes = []
        for s in range(n_seg):
            m = lab == s
            planes.append(_fit_plane(xy[use][m], z[m], w[m], global_plane, xy[use][m].mean(axis=0)))
        planes = np.array(planes)
    else:
        centres, planes = np.zeros(1), global_plane[None]
    cal = Calibration(cfg, geo, cam, planes, centres, nadir_px, use)
    proj, _ = cam.project(obj)
    res_px = np.linalg.norm(proj - lm.uv, axis=1)
    cal.rejected = [
        (
            lm.ids[i],
            f"reprojection residual {res_px[i]:.1f} px is inconsistent with the other "
            f"landmarks (threshold {thr:.1f} px): a wrong pixel or map point",
        )
        for i in np.nonzero(~use)[0]
    ]
    cal.warnings = warnings
    return cal
