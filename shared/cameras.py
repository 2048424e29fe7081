"""Camera models with a pose: pinhole (radial-tangential) and fisheye (Kannala-Brandt).

Conventions, used everywhere in the project:
- World points are metres in the site ENU frame (x east, y north, z up).
- The camera frame is OpenCV's: x right, y down, z forward (the optical axis).
- Pixel coordinates (u, v) are in the original image, u to the right, v down; the centre of the
  top-left pixel is (0, 0), so pixel (col, row) covers [col - 0.5, col + 0.5).
- The pinhole distortion is OpenCV's (k1, k2, p1, p2, k3). The fisheye distortion is
  OpenCV's `cv2.fisheye` one: theta_d = theta * (1 + k1 theta^2 + k2 theta^4 + k3 theta^6 +
  k4 theta^8), i.e. the Kannala-Brandt r(theta) = f (theta + k1 theta^3 + ...). Unlike
  `cv2.fisheye`, rays more than 90 degrees off the axis are handled (360-degree cameras).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

CameraKind = Literal["pinhole", "fisheye"]

# Base orientation: a camera with yaw = pitch = roll = 0 looks north along the horizon,
# image x to the east and image y down. Columns are the camera axes in world coordinates.
_BASE_CAM_TO_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])


def _rot_x(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def _rot_z(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Pose:
    """Camera pose: centre `position_m` (3,) in the site frame and `r_cam_from_world` (3, 3).

    A world point X maps to camera coordinates r_cam_from_world @ (X - position_m).
    """

    position_m: np.ndarray
    r_cam_from_world: np.ndarray

    def __post_init__(self) -> None:
        p = np.asarray(self.position_m, dtype=np.float64).reshape(-1)
        r = np.asarray(self.r_cam_from_world, dtype=np.float64)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"position_m must be 3 finite numbers, got {self.position_m!r}")
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6):
            raise ValueError(f"r_cam_from_world must be a 3x3 rotation, got {r.tolist()!r}")
        if np.linalg.det(r) < 0:
            raise ValueError("r_cam_from_world must be a proper rotation (det = +1)")
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "r_cam_from_world", r)

    @classmethod
    def from_angles(cls, position_m, yaw_deg: float, pitch_deg: float, roll_deg: float = 0.0) -> Pose:
        """Pose from a compass bearing of the optical axis (`yaw_deg`, 0 = north, 90 = east),
        its depression below the horizon (`pitch_deg`, 90 = straight down) and a roll about it."""
        r_world_from_cam = (
            _rot_z(-math.radians(yaw_deg))
            @ _BASE_CAM_TO_WORLD
            @ _rot_x(-math.radians(pitch_deg))
            @ _rot_z(math.radians(roll_deg))
        )
        return cls(np.asarray(position_m, dtype=np.float64), r_world_from_cam.T)

    def to_camera(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world metres -> (N, 3) camera-frame metres."""
        return (np.asarray(points_world, dtype=np.float64) - self.position_m) @ self.r_cam_from_world.T

    def to_world_dirs(self, dirs_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame directions -> (N, 3) world directions."""
        return np.asarray(dirs_cam, dtype=np.float64) @ self.r_cam_from_world

    def to_dict(self) -> dict:
        return {
            "position_m": [float(x) for x in self.position_m],
            "r_cam_from_world": [[float(x) for x in row] for row in self.r_cam_from_world],
        }

    @classmethod
    def from_dict(cls, d: dict) -> Pose:
        if "r_cam_from_world" in d:
            return cls(np.asarray(d["position_m"]), np.asarray(d["r_cam_from_world"]))
        return cls.from_angles(d["position_m"], d["yaw_deg"], d["pitch_deg"], d.get("roll_deg", 0.0))


@dataclass(frozen=True)
class Camera:
    """Intrinsics + distortion + pose, for both lens kinds.

    `dist` holds (k1, k2, p1, p2, k3) for pinhole and (k1, k2, k3, k4) for fisheye.
    `max_angle_deg` bounds the field of view: rays further off the optical axis are invalid.
    """

    name: str
    kind: CameraKind
    width: int
    height: int
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...]
    pose: Pose
    max_angle_deg: float = 89.0
    modality: Literal["visible", "thermal"] = "visible"
    _theta_limit: float = field(init=False, repr=False, default=0.0)

    def __post_init__(self) -> None:
        if self.kind not in ("pinhole", "fisheye"):
            raise ValueError(f"camera {self.name!r}: kind must be pinhole or fisheye, got {self.kind!r}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera {self.name!r}: image size must be positive, got {self.width}x{self.height}")
        for key in ("fx", "fy"):
            if not getattr(self, key) > 0:
                raise ValueError(f"camera {self.name!r}: {key} must be > 0, got {getattr(self, key)}")
        want = 5 if self.kind == "pinhole" else 4
        dist = tuple(float(x) for x in self.dist) + (0.0,) * max(0, want - len(self.dist))
        if len(dist) != want or not all(math.isfinite(x) for x in dist):
            raise ValueError(f"camera {self.name!r}: dist must have {want} finite numbers, got {self.dist!r}")
        object.__setattr__(self, "dist", dist)
        if self.kind == "pinhole" and not 0 < self.max_angle_deg < 90:
            raise ValueError(
                f"camera {self.name!r}: pinhole max_angle_deg must be in (0, 90), got {self.max_angle_deg}"
            )
        if self.kind == "fisheye" and not 0 < self.max_angle_deg < 180:
            raise ValueError(
                f"camera {self.name!r}: fisheye max_angle_deg must be in (0, 180), got {self.max_angle_deg}"
            )
        object.__setattr__(self, "_theta_limit", self._monotonic_limit())

    # ---- intrinsics helpers -------------------------------------------------------------
    @property
    def k_matrix(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def _radial_map(self, theta: np.ndarray) -> np.ndarray:
        """Distorted normalized radius as a function of the off-axis angle theta (radians)."""
        if self.kind == "fisheye":
            k1, k2, k3, k4 = self.dist
            t2 = theta * theta
            return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))
        k1, k2, _, _, k3 = self.dist
        r = np.tan(theta)
        r2 = r * r
        return r * (1 + r2 * (k1 + r2 * (k2 + r2 * k3)))

    def _monotonic_limit(self) -> float:
        """The largest angle (rad) up to which the lens mapping is monotonic and in the FOV."""
        limit = math.radians(self.max_angle_deg)
        thetas = np.linspace(0.0, limit, 4001)
        rd = self._radial_map(thetas)
        bad = np.nonzero(np.diff(rd) <= 0)[0]
        return float(thetas[bad[0]]) if bad.size else limit

    # ---- projection -----------------------------------------------------------------------
    def project_cam(self, points_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) camera-frame points -> ((N, 2) pixels, (N,) bool valid: inside the lens FOV)."""
        p = np.asarray(points_cam, dtype=np.float64)
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        rxy = np.hypot(x, y)
        theta = np.arctan2(rxy, z)
        valid = (theta <= self._theta_limit) & np.isfinite(theta)
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.kind == "fisheye":
                rd = self._radial_map(theta)
                scale = np.where(rxy > 1e-12, rd / np.maximum(rxy, 1e-300), 1.0 / np.maximum(z, 1e-300))
                xd, yd = x * scale, y * scale
            else:
                k1, k2, p1, p2, k3 = self.dist
                zs = np.where(z > 1e-12, z, np.nan)
                xn, yn = x / zs, y / zs
                r2 = xn * xn + yn * yn
                radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn)
                yd = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn
        uv = np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], axis=-1)
        valid &= np.all(np.isfinite(uv), axis=-1)
        return uv, valid

    def project(self, points_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) world metres -> ((N, 2) pixels, (N,) bool valid). Valid means in the lens FOV,
        not necessarily inside the image (see `in_image`)."""
        return self.project_cam(self.pose.to_camera(points_world))

    def unproject_cam(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> ((N, 3) unit camera-frame rays, (N,) bool valid)."""
        uv = np.asarray(uv, dtype=np.float64)
        xd = (uv[..., 0] - self.cx) / self.fx
        yd = (uv[..., 1] - self.cy) / self.fy
        if self.kind == "fisheye":
            rd = np.hypot(xd, yd)
            theta = self._solve_theta(rd)
            # where the lens map folds back (a strong negative k1), Newton's steps stop on a theta whose image is
            # elsewhere: such a pixel has no ray of this model
            valid = (theta <= self._theta_limit + 1e-9) & (np.abs(self._distort_theta(theta) - rd) < 1e-6)
            with np.errstate(divide="ignore", invalid="ignore"):
                s = np.where(rd > 1e-12, np.sin(theta) / np.maximum(rd, 1e-300), 1.0)
            rays = np.stack([xd * s, yd * s, np.cos(theta)], axis=-1)
        else:
            xn, yn = self._undistort_pinhole(xd, yd)
            rays = np.stack([xn, yn, np.ones_like(xn)], axis=-1)
            rays /= np.linalg.norm(rays, axis=-1, keepdims=True)
            theta = np.arccos(np.clip(rays[..., 2], -1, 1))
            valid = theta <= self._theta_limit + 1e-9
        valid &= np.all(np.isfinite(rays), axis=-1)
        return rays, valid

    def unproject(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> ((N, 3) unit world-frame ray directions from `pose.position_m`, valid)."""
        rays, valid = self.unproject_cam(uv)
        return self.pose.to_world_dirs(rays), valid

    def _distort_theta(self, theta: np.ndarray) -> np.ndarray:
        """The fisheye radial map: theta (rad) -> distorted radius on the normalised image plane."""
        k1, k2, k3, k4 = self.dist
        t2 = theta * theta
        return theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4))))

    def _solve_theta(self, rd: np.ndarray) -> np.ndarray:
        """Invert the fisheye radial map by Newton's method (vectorised)."""
        if not any(self.dist):
            return np.minimum(rd, self._theta_limit + 0.01)
        theta = np.minimum(rd, self._theta_limit)
        k1, k2, k3, k4 = self.dist
        for _ in range(12):
            t2 = theta * theta
            f = theta * (1 + t2 * (k1 + t2 * (k2 + t2 * (k3 + t2 * k4)))) - rd
            df = 1 + t2 * (3 * k1 + t2 * (5 * k2 + t2 * (7 * k3 + t2 * 9 * k4)))
            theta = np.clip(theta - f / np.where(np.abs(df) > 1e-9, df, 1e-9), 0.0, math.pi)
        return theta

    def _undistort_pinhole(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k1, k2, p1, p2, k3 = self.dist
        if not any(self.dist):
            return xd, yd
        x, y = xd.copy(), yd.copy()
        for _ in range(20):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x = (xd - dx) / radial
            y = (yd - dy) / radial
        return x, y

    # ---- image helpers ----------------------------------------------------------------------
    def in_image(self, uv: np.ndarray, margin_px: float = 0.0) -> np.ndarray:
        """(N, 2) pixels -> (N,) bool: inside the image (and inside the image circle for fisheye)."""
        uv = np.asarray(uv, dtype=np.float64)
        u, v = uv[..., 0], uv[..., 1]
        inside = (
            (u >= -0.5 + margin_px)
            & (u <= self.width - 0.5 - margin_px)
            & (v >= -0.5 + margin_px)
            & (v <= self.height - 0.5 - margin_px)
        )
        if self.kind == "fisheye":
            r = np.hypot((u - self.cx) / self.fx, (v - self.cy) / self.fy)
            r_max = float(self._radial_map(np.array(self._theta_limit)))
            inside &= r * self.fx <= r_max * self.fx - margin_px
        return inside

    def image_circle_radius_px(self) -> float:
        """Radius (px) of the fisheye image circle (the FOV edge); for pinhole, the half-diagonal."""
        if self.kind == "fisheye":
            return float(self._radial_map(np.array(self._theta_limit))) * self.fx
        return 0.5 * math.hypot(self.width, self.height)

    def image_area_px(self, max_angle_deg: float | None = None) -> tuple[int, int, int, int]:
        """The smallest whole-pixel rectangle (x0, y0, x1, y1), x1 and y1 exclusive, holding every pixel that sees
        anything (or, with `max_angle_deg`, up to that angle off the optical axis: 90 for a fisheye looking down
        sees no ground beyond it): a fisheye's image circle clipped to the image, else the whole image (a camera's
        `detect_area_px`)."""
        if self.kind != "fisheye":
            return 0, 0, self.width, self.height
        if max_angle_deg is None:
            r = self.image_circle_radius_px()
        else:
            theta = min(math.radians(max_angle_deg), self._theta_limit)
            r = float(self._radial_map(np.array(theta))) * self.fx
        return (max(0, math.floor(self.cx - r)), max(0, math.floor(self.cy - r)),
                min(self.width, math.ceil(self.cx + r) + 1), min(self.height, math.ceil(self.cy + r) + 1))

    def pixel_grid(self) -> np.ndarray:
        """(H, W, 2) float64 pixel centres (u, v)."""
        v, u = np.mgrid[0 : self.height, 0 : self.width].astype(np.float64)
        return np.stack([u, v], axis=-1)

    # ---- serialisation ----------------------------------------------------------------------
    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "kind": self.kind,
            "modality": self.modality,
            "width": self.width,
            "height": self.height,
            "fx": self.fx,
            "fy": self.fy,
            "cx": self.cx,
            "cy": self.cy,
            "dist": list(self.dist),
            "max_angle_deg": self.max_angle_deg,
            "pose": self.pose.to_dict(),
        }

    @classmethod
    def from_dict(cls, d: dict) -> Camera:
        try:
            return cls(
                name=str(d["name"]),
                kind=d["kind"],
                width=int(d["width"]),
                height=int(d["height"]),
                fx=float(d["fx"]),
                fy=float(d["fy"]),
                cx=float(d["cx"]),
                cy=float(d["cy"]),
                dist=tuple(d.get("dist", ())),
                pose=Pose.from_dict(d["pose"]),
                max_angle_deg=float(d.get("max_angle_deg", 89.0)),
                modality=d.get("modality", "visible"),
            )
        except KeyError as exc:
            raise ValueError(f"camera {d.get('name', '?')!r}: missing field {exc.args[0]!r}") from None


def select_cameras(cameras: list[Camera], which: str, owner: str) -> list[Camera]:
    """The cameras that `which` names: 'all', a kind ('fisheye', 'pinhole'), a modality ('thermal',
    'visible') or a comma list of names (in that order). `owner` (a site or recording) heads the errors."""
    if which == "all":
        chosen = list(cameras)
    elif which in ("fisheye", "pinhole"):
        chosen = [c for c in cameras if c.kind == which]
    elif which in ("thermal", "visible"):
        chosen = [c for c in cameras if c.modality == which]
    else:
        names = [n.strip() for n in which.split(",") if n.strip()]
        if twice := sorted({n for n in names if names.count(n) > 1}):
            raise ValueError(f"{owner}: camera {twice[0]} is named twice in {which!r}")
        by_name = {c.name: c for c in cameras}
        unknown = [n for n in names if n not in by_name]
        if unknown:
            raise ValueError(f"{owner}: unknown camera(s) {', '.join(unknown)} (has: {', '.join(by_name)})")
        chosen = [by_name[n] for n in names]
    if not chosen:
        raise ValueError(f"{owner}: no camera matches {which!r} (has: {', '.join(c.name for c in cameras)})")
    return chosen
