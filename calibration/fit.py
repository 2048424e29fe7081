"""Landmarks -> camera model -> piecewise-planar ground -> pixel-to-ground map.

The paper lifts detections to the ground with per-segment homographies fitted on landmarks
(fisheye images first undistorted with a Kannala-Brandt model). Free 8-parameter homographies
overfit 5-20 noisy landmarks badly, so the homographies here are plane-induced: the lens and
the pose are fitted once from all landmarks (errors-in-variables least squares, gross mistakes
rejected one at a time), then each segment gets a ground plane z = a x + b y + c (3
parameters, pulled toward one global plane when the segment has few landmarks). Gross mistakes are
found by a group outlier test (`_landmark_tests`): a landmark's two pixel and two map residuals,
corrected for what the fit itself explains (the hat matrix), against a chi-square with two degrees
of freedom; the smallest mistake each landmark's test would catch is kept, so the report can say
where a mistake could hide. The pixel ->
ground map of a segment is then exactly a homography of the undistorted view (`homography`).
Segments split the image around the camera's nadir and are blended smoothly at their borders.
Everything is fitted in the local metric site frame, never in raw degrees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from scipy.optimize import OptimizeResult, least_squares

from calibration.landmarks import MAX_SEGMENTS, Landmarks
from shared.cameras import Camera, Pose
from shared.geo import GeoFrame

MIN_PER_SEGMENT = 4
MIN_LANDMARKS = 5  # below this a gross mistake cannot be told from the rest
MAX_VIEW_ANGLE_DEG = 86.0  # fisheye pixels further off axis than this look at the horizon
PLANE_PRIOR_WEIGHT = 2.0  # pull of the global plane on a segment's plane (in landmark units)
HIDDEN_MISTAKE_M = 3.0  # warn when a map mistake this large at a landmark would pass the outlier test
SEGMENT_BLEND_M = 2.0  # segments a user labelled blend over this much ground across their borders
POLYGON_SLACK_M = 2.0  # a landmark labelled with a segment may lie this far outside its polygon (map error)
SEGMENT_SLOPE_SIGMA = 0.1  # how far a named segment's plane may tilt from the global plane (grade)...
SEGMENT_HEIGHT_SIGMA_M = 1.0  # ... and rise or fall from it at the landmarks' centre
POLYGON_TOLERANCE_M = 0.1  # segment polygons are simplified to this...
MAX_POLYGON_VERTICES = 64  # ... and may keep this many vertices
FAR_POLYGON_M = 200.0  # a segment polygon further than this from every landmark is another site's
# lifting pixels onto a site's ground surface (`_onto_surface`): the search along each ray steps at least this much
# ground, looks this far (m of ground) and this many steps, refines the crossing in this many steps, and leaves a
# point this far off the surface invalid
SURFACE_STEP_M = 0.5
SURFACE_MAX_RANGE_M = 2000.0
MAX_SURFACE_STEPS = 4000
SURFACE_REFINE_STEPS = 60
SURFACE_TOL_M = 0.01


@dataclass(frozen=True)
class CalibConfig:
    kind: str  # "pinhole" | "fisheye"
    width: int
    height: int
    segments: int | None = None  # default: 2 pinhole (near and far range bands), 4 fisheye
    pixel_sigma_px: float = 2.0  # how precisely a person clicks a landmark in the image
    map_sigma_m: float = 0.15  # how precisely it is read off the map (an orthophoto pixel is ~0.1-0.3 m)
    outlier_sigma: float = 4.0  # combined residual (in the noise units above) that marks a gross mistake
    image_circle: tuple[float, float, float] | None = None  # fisheye: cx, cy, radius (px)
    fov_deg: float = 188.0  # fisheye: full field of view at the image circle's edge (datasheet)

    def __post_init__(self) -> None:
        if self.kind not in ("pinhole", "fisheye"):
            raise ValueError(f"kind must be pinhole or fisheye, got {self.kind!r}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"image size must be positive, got {self.width}x{self.height}")
        if self.segments is not None and not 1 <= self.segments <= 8:
            raise ValueError(f"segments must be in [1, 8], got {self.segments}")
        for name in ("pixel_sigma_px", "map_sigma_m", "outlier_sigma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not (math.isfinite(self.fov_deg) and 0 < self.fov_deg < 360):
            raise ValueError(f"fov_deg must be a field of view between 0 and 360 degrees, got {self.fov_deg}")
        if self.image_circle is not None:
            if not (all(math.isfinite(x) for x in self.image_circle) and self.image_circle[2] > 0):
                raise ValueError(f"image circle must be a finite centre and a radius > 0 (px), got {self.image_circle}")

    @property
    def wanted_segments(self) -> int:
        # Pinhole: two range bands, not the paper's one plane. A forward-looking camera's near ground is seen
        # steeply and its far ground at a grazing angle, and one plane fitted over both follows neither:
        # `roadside bench calibration`, 10-20 landmarks, in-ROI thermal 0.39 -> 0.30 m, pinhole 0.14 -> 0.13 m.
        return self.segments if self.segments is not None else (4 if self.kind == "fisheye" else 2)

    @property
    def circle(self) -> tuple[float, float, float]:
        if self.image_circle is not None:
            return self.image_circle
        return ((self.width - 1) / 2, (self.height - 1) / 2, min(self.width, self.height) / 2)


@dataclass
class Calibration:
    """A fitted pixel -> site-metres model: `camera` (lens + pose), `planes` (P, 3) as
    z = a x + b y + c per segment. Fisheye segments are sectors around `nadir_px` (centre angles
    in `sector_centres`); pinhole segments are range bands (`band_edges_m`, P - 1 ground
    distances from the camera's foot), since a forward-looking camera's nadir is off the image."""

    config: CalibConfig
    geo: GeoFrame
    camera: Camera
    planes: np.ndarray
    sector_centres: np.ndarray
    nadir_px: np.ndarray
    band_edges_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    rejected: list[tuple[str, str]] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    # per landmark (N,), NaN for rejected ones: the outlier test's statistic in sigma units and the
    # smallest map mistake (m) / pixel mistake (px) that would push it over `outlier_sigma`
    test_sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))
    detectable_map_m: np.ndarray = field(default_factory=lambda: np.zeros(0))
    detectable_pixel_px: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # a site-wide ground surface (`calibration.site_ground`, anything with `height((N, 2) xy) -> (N,)`): pixels are
    # lifted onto it instead of the planes
    ground: Any = None
    # segments the user labelled (the landmark file's segment column, or polygons): where each lies on the ground
    labelled: LabelledSegments | None = None

    def weights(self, uv: np.ndarray, dirs: np.ndarray | None = None) -> np.ndarray:
        """(N, P) blending weights of the segments at pixels uv (rows sum to 1)."""
        p = len(self.planes)
        if p == 1:
            return np.ones((len(uv), 1))
        if self.labelled is not None:
            dirs = dirs if dirs is not None else self.camera.unproject(uv)[0]
            return self.labelled.ray_weights(self.camera.pose.position_m, dirs, self.planes)
        if len(self.band_edges_m):
            return _band_weights(self._range_m(dirs if dirs is not None else self.camera.unproject(uv)[0]),
                                 self.band_edges_m)
        ang = np.arctan2(uv[:, 1] - self.nadir_px[1], uv[:, 0] - self.nadir_px[0])
        d = np.abs(np.angle(np.exp(1j * (ang[:, None] - self.sector_centres[None, :]))))
        half = math.pi / p
        w = np.clip(1.0 - (d - half * 0.6) / (half * 0.8), 0.0, 1.0)
        return w / np.maximum(w.sum(axis=1, keepdims=True), 1e-12)

    def ground_z(self, xy: np.ndarray, uv: np.ndarray) -> np.ndarray:
        """(N,) the fitted ground's height at ground points xy (N, 2) seen at pixels uv: the site's surface, or the
        segments' planes blended as at those pixels."""
        if self.ground is not None:
            return self.ground.height(xy)
        z = self.planes[:, 0] * xy[:, :1] + self.planes[:, 1] * xy[:, 1:2] + self.planes[:, 2]
        return np.sum(self.weights(uv) * z, axis=1)

    @property
    def segment_polygons(self) -> dict[int, np.ndarray] | None:
        """The polygons (site metres) the user gave for named segments, by label (`calibrate`'s argument)."""
        if self.labelled is None:
            return None
        return {k: p for k, p in zip(self.labelled.labels, self.labelled.polygons_xy, strict=True) if p is not None}

    def _range_m(self, dirs: np.ndarray) -> np.ndarray:
        """Ground distance from the camera's foot along each ray, on the mean of the planes."""
        _, t = _ray_plane(self.camera.pose.position_m, dirs, self.planes.mean(axis=0))
        return np.where(np.isfinite(t), t * np.linalg.norm(dirs[:, :2], axis=1), np.inf)

    def pixel_to_xy(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> ((N, 2) site metres, (N,) valid)."""
        uv = np.asarray(uv, float).reshape(-1, 2)
        dirs, ok = self.camera.unproject(uv)
        if self.camera.kind == "fisheye":
            cam_rays, _ = self.camera.unproject_cam(uv)
            ok &= cam_rays[:, 2] > math.cos(math.radians(MAX_VIEW_ANGLE_DEG))
        o = self.camera.pose.position_m
        if self.ground is not None:
            out = _onto_surface(self.ground, o, dirs, self.planes.mean(axis=0))
            ok &= np.all(np.isfinite(out), axis=1)
            return np.where(ok[:, None], out, np.nan), ok
        w = self.weights(uv, dirs)
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


def _ray_plane(o: np.ndarray, dirs: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) points, (N,) distances along the rays) where rays from o along dirs meet z = a x + b y + c (NaN
    where they do not)."""
    a, b, c = plane
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (a * o[0] + b * o[1] + c - o[2]) / (dirs[:, 2] - a * dirs[:, 0] - b * dirs[:, 1])
    t = np.where((t > 0) & np.isfinite(t), t, np.nan)
    return o[:2] + t[:, None] * dirs[:, :2], t


@dataclass(frozen=True)
class LabelledSegments:
    """Ground segments a user named: `labels` (P,) as in the landmark file, and where each lies: its polygon
    (site metres) where one was given, otherwise its landmarks' ground positions (a point belongs to the segment
    of the landmark nearest to it). Segments blend linearly over `SEGMENT_BLEND_M` across their borders."""

    labels: tuple[int, ...]
    landmarks_xy: tuple[np.ndarray, ...]
    polygons_xy: tuple[np.ndarray | None, ...]
    of_landmark: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # (N,) each landmark's segment label

    def _nearest_landmark(self, xy: np.ndarray, segments) -> np.ndarray:
        """(N,) ground distance from each point to the nearest landmark of `segments` (indices)."""
        d = np.full(len(xy), np.inf)
        for k in segments:
            for p in self.landmarks_xy[k]:
                d = np.minimum(d, np.hypot(xy[:, 0] - p[0], xy[:, 1] - p[1]))
        return d

    def distance(self, k: int, xy: np.ndarray) -> np.ndarray:
        """(N,) how far (m) ground points lie outside segment k: from its polygon; without one, how much nearer
        another segment's landmark is than k's nearest (0 in k's cell of all the landmarks), and never 0 inside
        another segment's polygon (that ground is the polygon's)."""
        if self.polygons_xy[k] is not None:
            return polygon_distance(xy, self.polygons_xy[k])
        d = self._nearest_landmark(xy, [k]) - self._nearest_landmark(xy, range(len(self.labels)))
        for poly in self.polygons_xy:
            if poly is not None:
                d = np.where(polygon_distance(xy, poly) == 0.0, np.maximum(d, SEGMENT_BLEND_M), d)
        return d

    def segment_of(self, xy: np.ndarray) -> np.ndarray:
        """(N,) index (into `labels`) of the segment each ground point lies in, or is nearest to."""
        return np.argmin(np.column_stack([self.distance(k, xy) for k in range(len(self.labels))]), axis=1)

    def ray_weights(self, o: np.ndarray, dirs: np.ndarray, planes: np.ndarray) -> np.ndarray:
        """(N, P) blending weights of the segments for rays from o along dirs, over the segments' planes (P, 3).

        Each ray is met with every segment's own plane, and a segment whose own point lies in it is a surface the
        ray can see; of those the ray sees the nearest (a deck hides the ground behind it), else the segment its
        point lies nearest to. Segments blend linearly over `SEGMENT_BLEND_M` of how far outside each its point
        lies, but only where its point is within `SEGMENT_BLEND_M` of the seen one's (where planes meet, not
        across an edge that hides one from the other). Equal where no plane is met."""
        n, p = len(dirs), len(self.labels)
        xy, t = np.full((n, p, 2), np.nan), np.full((n, p), np.inf)
        d = np.full((n, p), np.inf)
        for k in range(p):
            xy[:, k], tk = _ray_plane(o, dirs, planes[k])
            hit = np.isfinite(tk)
            t[hit, k] = tk[hit]
            d[hit, k] = np.maximum(self.distance(k, xy[hit, k]), 0.0)
        inside = d <= 1e-9
        seen = np.where(inside.any(axis=1), np.argmin(np.where(inside, t, np.inf), axis=1), np.argmin(d, axis=1))
        rows = np.arange(n)
        with np.errstate(invalid="ignore"):  # rays that meet no plane: NaN here, equal weights below
            near = np.linalg.norm(xy - xy[rows, seen][:, None, :], axis=2) <= SEGMENT_BLEND_M
            w = np.clip(1.0 - (d - d[rows, seen][:, None]) / SEGMENT_BLEND_M, 0.0, 1.0) * near
        w[rows, seen] = 1.0
        w[~np.isfinite(d).any(axis=1)] = 1.0
        return w / w.sum(axis=1, keepdims=True)


def simplified_polygon(poly: np.ndarray, label: int) -> np.ndarray:
    """A segment polygon (site metres) with the vertices that move its outline less than `POLYGON_TOLERANCE_M`
    dropped (a GIS outline has hundreds; every pixel of a mask is tested against each edge); ValueError naming the
    segment when more than `MAX_POLYGON_VERTICES` are left."""
    approx = cv2.approxPolyDP(np.asarray(poly, np.float64).reshape(-1, 1, 2).astype(np.float32),
                              POLYGON_TOLERANCE_M, True).reshape(-1, 2).astype(np.float64)
    if len(approx) < 3:  # too small to simplify: its area is checked on its own vertices
        return np.asarray(poly, np.float64)
    if len(approx) > MAX_POLYGON_VERTICES:
        raise ValueError(f"segment {label}'s polygon has {len(approx)} vertices {POLYGON_TOLERANCE_M:g} m apart or "
                         f"more; at most {MAX_POLYGON_VERTICES}: draw it coarser (a plane's outline needs few)")
    return approx


def polygon_distance(xy: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """(N,) distance from points to a polygon's area (0 inside; even-odd rule)."""
    x, y = xy[:, 0], xy[:, 1]
    d = np.full(len(xy), np.inf)
    inside = np.zeros(len(xy), bool)
    for (ax, ay), (bx, by) in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        ex, ey = bx - ax, by - ay
        t = np.clip(((x - ax) * ex + (y - ay) * ey) / max(ex * ex + ey * ey, 1e-12), 0.0, 1.0)
        d = np.minimum(d, np.hypot(x - ax - t * ex, y - ay - t * ey))
        crosses = (ay > y) != (by > y)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_cross = ax + (y - ay) * ex / ey
        inside ^= crosses & (x < x_cross)
    return np.where(inside, 0.0, d)


def _onto_surface(ground: Any, o: np.ndarray, dirs: np.ndarray, start_plane: np.ndarray,
                  step_m: float = SURFACE_STEP_M, max_range_m: float = SURFACE_MAX_RANGE_M,
                  tol_m: float = SURFACE_TOL_M) -> np.ndarray:
    """(N, 2) points where rays from o along dirs FIRST meet z = ground.height(x, y); NaN where a ray does not
    descend, meets no ground within `max_range_m` of ground distance, or its point ends more than `tol_m` off the
    surface (the camera under the ground, a search that did not converge).

    With the ground split into a plane and a relief above it that stays within [low, high] and is nowhere steeper
    than `steep` (`ground.relief`, as `GroundSurface` gives it; a ground without one: `start_plane` and a relief
    without bounds), the ray's height above the ground is f(t) = A + B t - relief: positive while A + B t > high,
    not positive once A + B t <= low, so the first crossing lies between. From the near end each step goes as far
    as f cannot reach 0 on the way (f / (steep |d_xy| - B)), and at least `step_m` of ground (a crossing and a
    recrossing closer together than that are missed, a bump's grazed top), until f <= 0 brackets the crossing;
    then regula falsi (Illinois) in the bracket."""
    relief = getattr(ground, "relief", None)
    if relief is None:
        plane, low, high, steep = np.asarray(start_plane, float), -np.inf, np.inf, np.inf
    else:
        plane, low, high, steep = relief
    a, b, c = plane
    o = np.asarray(o, float)
    n = len(dirs)
    hor = np.hypot(dirs[:, 0], dirs[:, 1])
    rise = o[2] - (a * o[0] + b * o[1] + c)  # A: the camera's height above the plane
    climb = dirs[:, 2] - a * dirs[:, 0] - b * dirs[:, 1]  # B: the ray's climb above the plane per unit of t

    def above(t: np.ndarray, rows: np.ndarray) -> np.ndarray:  # f(t) of the rays `rows`
        return o[2] + t * dirs[rows, 2] - ground.height(o[:2] + t[:, None] * dirs[rows, :2])

    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        falls = climb < 0
        t_far = np.where(hor > 0, max_range_m / np.where(hor > 0, hor, 1.0), 0.0)
        t_near = np.where(falls, np.maximum((rise - high) / -climb, 0.0), 0.0)
        t_far = np.minimum(np.where(falls, (rise - low) / -climb, np.inf), t_far)
        # a level or rising ray may still meet ground that rises faster (the bounds decide, not the ray's sign)
        live = (hor > 0) & (falls | (rise <= high)) & np.isfinite(t_near) & (t_near <= t_far)
    t_lo, t_hi = np.full(n, np.nan), np.full(n, np.nan)  # each ray's bracket: f(t_lo) > 0 >= f(t_hi)
    f_lo, f_hi = np.full(n, np.nan), np.full(n, np.nan)
    rows = np.flatnonzero(live)
    t = t_near[rows]
    f = above(t, rows)
    rows, t, f = rows[f > 0], t[f > 0], f[f > 0]  # f <= 0 at the near end: the camera is under the ground
    for _ in range(MAX_SURFACE_STEPS):
        if not len(rows):
            break
        gain = steep * hor[rows] - climb[rows]  # how fast f can fall per unit of t
        with np.errstate(divide="ignore", invalid="ignore"):
            safe = np.where(gain > 0, f / np.where(gain > 0, gain, 1.0), np.inf)
        t_next = np.minimum(t + np.maximum(np.nan_to_num(safe, nan=0.0), step_m / hor[rows]), t_far[rows])
        f_next = above(t_next, rows)
        cross = f_next <= 0
        k = rows[cross]
        t_lo[k], t_hi[k], f_lo[k], f_hi[k] = t[cross], t_next[cross], f[cross], f_next[cross]
        on = ~cross & (t_next < t_far[rows]) & np.isfinite(f_next)  # at the far end without a crossing: none
        rows, t, f = rows[on], t_next[on], f_next[on]
    best, off = t_hi.copy(), np.abs(f_hi)  # the crossing, and how far its point is off the ground (m)
    rows = np.flatnonzero(np.isfinite(t_hi))
    kept = np.zeros(len(rows), int)  # Illinois: +1 / -1 when the low / high end was kept last time
    for _ in range(SURFACE_REFINE_STEPS):
        if not len(rows):
            break
        lo, hi, fl, fh = t_lo[rows], t_hi[rows], f_lo[rows], f_hi[rows]
        with np.errstate(divide="ignore", invalid="ignore"):
            m = hi - fh * (hi - lo) / (fh - fl)
        m = np.where(np.isfinite(m) & (m > lo) & (m < hi), m, 0.5 * (lo + hi))
        fm = above(m, rows)
        up = fm > 0
        best[rows], off[rows] = m, np.abs(fm)
        t_lo[rows], t_hi[rows] = np.where(up, m, lo), np.where(up, hi, m)
        f_lo[rows] = np.where(up, fm, np.where(kept == 1, 0.5 * fl, fl))
        f_hi[rows] = np.where(up, np.where(kept == -1, 0.5 * fh, fh), fm)
        kept = np.where(up, -1, 1)
        done = (np.abs(fm) < 1e-4) | ((t_hi[rows] - t_lo[rows]) * hor[rows] < 1e-4)  # 0.1 mm: a grid read's error
        rows, kept = rows[~done], kept[~done]
    best[~(off <= tol_m)] = np.nan
    return o[:2] + best[:, None] * dirs[:, :2]


def _band_weights(r: np.ndarray, edges: np.ndarray, blend: float = 0.15) -> np.ndarray:
    """(N, P) weights of P range bands split at `edges`, blended linearly over +-blend x edge."""
    w = np.zeros((len(r), len(edges) + 1))
    w[:, 0] = 1.0
    for k, e in enumerate(edges):
        s = np.clip((r - e * (1 - blend)) / (2 * blend * e), 0.0, 1.0)  # 0 before the edge, 1 after
        w[:, k + 1] = w[:, k] * s
        w[:, k] *= 1 - s
    return w


# ---- camera model -------------------------------------------------------------------------------
def camera_from_params(p: np.ndarray, cfg: CalibConfig) -> Camera:
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


def camera_params(cam: Camera) -> np.ndarray:
    """A fitted camera's parameter vector, as `camera_from_params` takes it (f, cx, cy, k1, k2, Rodrigues rotation,
    translation)."""
    r = cam.pose.r_cam_from_world
    return np.array([cam.fx, cam.cx, cam.cy, cam.dist[0], cam.dist[1], *cv2.Rodrigues(r)[0].ravel(),
                     *(-r @ cam.pose.position_m)])


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


def fit_camera(
    uv: np.ndarray, obj: np.ndarray, cfg: CalibConfig, p0: np.ndarray | None = None, robust: bool = True
) -> tuple[np.ndarray, np.ndarray, OptimizeResult]:
    """Errors-in-variables least squares: the lens, the pose and each landmark's true ground
    position (within `map_sigma_m` of the map point) are fitted together, pixel residuals in
    units of `pixel_sigma_px`, so a landmark's map error counts as much as it moves its pixel
    (a lot under the camera, little far away). Returns (parameters, (N, 2) ground corrections,
    the solver's result: normalised residuals `fun` and their Jacobian `jac`, rows 2i, 2i+1 landmark
    i's pixel, rows 2N + 2i, 2N + 2i + 1 its map correction, then the priors)."""
    if p0 is None:
        p0, _ = (_initial_fisheye if cfg.kind == "fisheye" else _initial_pinhole)(uv, obj, cfg)
    n = len(uv)
    lo_cam, hi_cam = _camera_bounds(p0, cfg)
    lo = np.concatenate([lo_cam, np.full(2 * n, -np.inf)])
    hi = np.concatenate([hi_cam, np.full(2 * n, np.inf)])
    x0 = np.clip(np.concatenate([p0, np.zeros(2 * n)]), lo + 1e-9, hi - 1e-9)

    def resid(x):
        p, dxy = x[:11], x[11:].reshape(n, 2)
        pts = obj.copy()
        pts[:, :2] += dxy
        return np.concatenate([_pixel_residuals(p, pts, uv, cfg), dxy.ravel() / cfg.map_sigma_m,
                               _camera_priors(p, cfg)])

    loss = "soft_l1" if robust else "linear"
    sol = least_squares(resid, x0, bounds=(lo, hi), loss=loss, f_scale=2.5, x_scale="jac", max_nfev=800)
    return sol.x[:11], sol.x[11:].reshape(n, 2), sol


def _camera_bounds(p0: np.ndarray, cfg: CalibConfig) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the 11 camera parameters around a start: focal length, principal point, distortion."""
    f0 = p0[0]
    span = 0.15 * (cfg.circle[2] if cfg.kind == "fisheye" else max(cfg.width, cfg.height) / 2)
    return (np.array([0.4 * f0, p0[1] - span, p0[2] - span, -0.5, -0.3, *[-np.inf] * 6]),
            np.array([2.5 * f0, p0[1] + span, p0[2] + span, 0.5, 0.3, *[np.inf] * 6]))


def _pixel_residuals(p: np.ndarray, pts: np.ndarray, uv: np.ndarray, cfg: CalibConfig) -> np.ndarray:
    """(2N,) where the camera p projects ground points pts, against the clicks uv, in units of the click's sigma."""
    proj, ok = camera_from_params(p, cfg).project(pts)
    return np.where(ok[:, None], proj - uv, 1e3).ravel() / cfg.pixel_sigma_px


def _camera_priors(p: np.ndarray, cfg: CalibConfig) -> np.ndarray:
    """Priors that a user knows, normalised: the fisheye image circle's radius at half the field of view, the
    principal point near the circle (or image) centre, small higher-order distortion."""
    ccx, ccy, crad = cfg.circle
    centre_sigma = 3.0 if cfg.kind == "fisheye" else 12.0
    k2_sigma = 0.01 if cfg.kind == "fisheye" else 0.05
    prior = [(p[1] - ccx) / centre_sigma, (p[2] - ccy) / centre_sigma, p[4] / k2_sigma]
    if cfg.kind == "pinhole":
        prior.append(p[3] / 0.25)  # keeps k1 from wandering when few landmarks reach the image corners
    else:
        t2 = math.radians(cfg.fov_deg / 2) ** 2
        r_edge = p[0] * math.sqrt(t2) * (1 + p[3] * t2 + p[4] * t2 * t2)
        prior.append((r_edge - crad) / 2.0)
    return np.array(prior)


def fit_camera_on_segments(uv: np.ndarray, xy: np.ndarray, lab: np.ndarray, planes: np.ndarray,
                           global_plane: np.ndarray, cfg: CalibConfig, p0: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, OptimizeResult]:
    """The camera and the planes of segments the user named, fitted together: each landmark (lab: its segment)
    lies on its segment's plane (z = a x + b y + c), so where the ground bends the camera is not bent to fit one
    plane. The planes' mean is held to the global plane (the site's height and tilt trade with the camera's);
    each plane is free within `SEGMENT_SLOPE_SIGMA` of it. Returns (camera parameters, (N, 2) ground
    corrections, (P, 3) planes, the solver's result with `fit_camera`'s row layout: pixels, map corrections, then
    the priors)."""
    n, k = len(uv), len(planes)
    lo_cam, hi_cam = _camera_bounds(p0, cfg)
    lo = np.concatenate([lo_cam, np.full(3 * k + 2 * n, -np.inf)])
    hi = np.concatenate([hi_cam, np.full(3 * k + 2 * n, np.inf)])
    x0 = np.clip(np.concatenate([p0, planes.ravel(), np.zeros(2 * n)]), lo + 1e-9, hi - 1e-9)
    centre = xy.mean(axis=0)

    def about_centre(pl: np.ndarray) -> np.ndarray:
        """(..., 3) planes as slope x, slope y and height at the landmarks' centre."""
        return np.stack([pl[..., 0], pl[..., 1], pl[..., 0] * centre[0] + pl[..., 1] * centre[1] + pl[..., 2]], -1)

    g = about_centre(global_plane)
    scale = np.array([SEGMENT_SLOPE_SIGMA, SEGMENT_SLOPE_SIGMA, SEGMENT_HEIGHT_SIGMA_M])

    def resid(x):
        p, pl, dxy = x[:11], x[11:11 + 3 * k].reshape(k, 3), x[11 + 3 * k:].reshape(n, 2)
        g_xy = xy + dxy
        z = pl[lab, 0] * g_xy[:, 0] + pl[lab, 1] * g_xy[:, 1] + pl[lab, 2]
        local = about_centre(pl)
        return np.concatenate([_pixel_residuals(p, np.column_stack([g_xy, z]), uv, cfg),
                               dxy.ravel() / cfg.map_sigma_m, _camera_priors(p, cfg),
                               ((local - g) / scale).ravel(), (local.mean(axis=0) - g) / (0.01 * scale)])

    sol = least_squares(resid, x0, bounds=(lo, hi), x_scale="jac", max_nfev=800)
    return sol.x[:11], sol.x[11 + 3 * k:].reshape(n, 2), sol.x[11:11 + 3 * k].reshape(k, 3), sol


def _landmark_tests(sol: OptimizeResult, n: int, cfg: CalibConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per landmark of a plain least-squares fit (`fit_camera`'s result): the group outlier test
    statistic (sigma units) and the smallest map mistake (m) and pixel mistake (px) it would detect.

    A landmark contributes four normalised residuals (two pixel, two map). Deleting it is tested
    by w = r_b' (I - H_bb)^+ r_b, H the fit's hat matrix; without a mistake w is chi-square with 2
    degrees of freedom, so sqrt(w) > `outlier_sigma` is a mistake. A mistake b moves r_b by
    (I - H_bb) b (normalised), so the mistake that reaches the threshold is
    outlier_sigma / sqrt(smallest eigenvalue of that block) in noise units."""
    q, _ = np.linalg.qr(np.asarray(sol.jac, float))
    stat, mdb_map, mdb_px = np.zeros(n), np.zeros(n), np.zeros(n)
    for i in range(n):
        rows = [2 * i, 2 * i + 1, 2 * n + 2 * i, 2 * n + 2 * i + 1]
        m = np.eye(4) - q[rows] @ q[rows].T
        r = sol.fun[rows]
        stat[i] = math.sqrt(max(float(r @ np.linalg.pinv(m, rcond=1e-6) @ r), 0.0))
        # a pixel mistake enters the pixel rows, a map mistake the map rows
        # (no redundancy left there: no mistake of any size would show, inf)
        lam_px = float(np.linalg.eigvalsh(m[:2, :2])[0])
        lam_map = float(np.linalg.eigvalsh(m[2:, 2:])[0])
        mdb_px[i] = cfg.outlier_sigma * cfg.pixel_sigma_px / math.sqrt(lam_px) if lam_px > 1e-9 else math.inf
        mdb_map[i] = cfg.outlier_sigma * cfg.map_sigma_m / math.sqrt(lam_map) if lam_map > 1e-9 else math.inf
    return stat, mdb_map, mdb_px


# ---- ground planes --------------------------------------------------------------------------
def implied_heights(cam: Camera, uv: np.ndarray, xy: np.ndarray, pixel_sigma_px: float,
                    map_sigma_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Ground height at each landmark implied by its pixel ray, and a weight: 1 / its variance from the map
    error (a steep ray says little about height) and from the click (a grazing ray's height moves with its
    pixel: at range d and depression a, one radian of ray is d / cos^2 a of height, so a far landmark under a
    fisheye, 2 px off, is 0.3-0.4 m off in height)."""
    dirs, _ = cam.unproject(uv)
    o = cam.pose.position_m
    dxy = dirs[:, :2]
    t = np.sum((xy - o[:2]) * dxy, axis=1) / np.maximum(np.sum(dxy * dxy, axis=1), 1e-12)
    z = o[2] + t * dirs[:, 2]
    horiz = np.linalg.norm(dxy, axis=1)
    slope = np.abs(dirs[:, 2]) / np.maximum(horiz, 1e-6)  # tan(depression)
    # radians of ray per pixel here: the mean over a one-pixel step in u and in v
    rad_px = np.zeros(len(uv))
    for step in ((1.0, 0.0), (0.0, 1.0)):
        d2, _ = cam.unproject(np.asarray(uv, float) + step)
        rad_px += 0.5 * np.arccos(np.clip(np.sum(dirs * d2, axis=1), -1.0, 1.0))
    d = np.linalg.norm(xy - o[:2], axis=1)
    var = (map_sigma_m * slope) ** 2 + (pixel_sigma_px * rad_px * d * (1.0 + slope**2)) ** 2 + 0.02**2
    return z, 1.0 / var


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


def labelled_segments(lm: Landmarks, xy: np.ndarray, use: np.ndarray, polygons: dict[int, np.ndarray] | None
                      ) -> LabelledSegments | None:
    """The segments a user named (`calibrate`), or None when the landmarks name none and no polygons are given.
    A landmark without a segment takes the one it lies in or is nearest to; a segment's landmarks are its usable
    ones (all of them when none is usable)."""
    labels = tuple(sorted({int(s) for s in lm.segment if s >= 0} | set(polygons or {})))
    if not labels:
        return None
    polys = tuple(None if not polygons or k not in polygons else np.asarray(polygons[k], float) for k in labels)
    seg = lm.segment.copy()
    named = seg >= 0
    if not named.all():
        by_label = LabelledSegments(labels, tuple(xy[seg == k] for k in labels), polys)
        seg[~named] = np.asarray(labels)[by_label.segment_of(xy[~named])]
    pts = tuple(xy[(seg == k) & use] if ((seg == k) & use).any() else xy[seg == k] for k in labels)
    return LabelledSegments(labels, pts, polys, seg)


def check_segments(lm: Landmarks, xy: np.ndarray, polygons_xy: dict[int, np.ndarray] | None,
                   min_per_segment: int = MIN_PER_SEGMENT) -> None:
    """ValueError naming the segment and its landmarks for segments the user named that cannot be fitted: more
    than `MAX_SEGMENTS`, fewer than `min_per_segment` landmarks, a polygon without area or far from the landmarks,
    a landmark lying well outside its own segment's polygon. xy: the landmarks in site metres, polygons too."""
    named = labelled_segments(lm, xy, np.ones(len(lm), bool), polygons_xy)
    if named is None:
        return
    if len(named.labels) > MAX_SEGMENTS:
        raise ValueError(f"the landmarks name {len(named.labels)} segments; at most {MAX_SEGMENTS}")
    for label, poly in (polygons_xy or {}).items():
        e = poly - poly.mean(axis=0)
        area = 0.5 * abs(float(np.sum(e[:, 0] * np.roll(e[:, 1], -1) - e[:, 1] * np.roll(e[:, 0], -1))))
        if area < 1.0:
            raise ValueError(f"segment {label}'s polygon encloses {area:.2g} m2: no ground")
        far = float(np.min(polygon_distance(xy, poly)))
        if far > FAR_POLYGON_M:
            raise ValueError(f"segment {label}'s polygon is {far:.0f} m from the nearest landmark (latitude and "
                             "longitude swapped, or another site's?)")
    for k, label in enumerate(named.labels):
        mine = np.nonzero(named.of_landmark == label)[0]
        ids = ", ".join(lm.ids[i] for i in mine) or "none"
        if len(mine) < min_per_segment:
            raise ValueError(f"segment {label} has {len(mine)} landmark(s) ({ids}); a segment's plane needs at "
                             f"least {min_per_segment}: add landmarks on it, or merge it with its neighbour")
        poly = named.polygons_xy[k]
        if poly is None:
            continue
        for i in mine:
            d = float(polygon_distance(xy[i : i + 1], poly)[0])
            if lm.segment[i] >= 0 and d > POLYGON_SLACK_M:
                raise ValueError(f"landmark {lm.ids[i]!r} is labelled segment {label} but lies {d:.1f} m outside "
                                 f"that segment's polygon: a wrong segment, or a wrong map point")


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


def calibrate(lm: Landmarks, cfg: CalibConfig, geo: GeoFrame,
              segment_polygons: dict[int, np.ndarray] | None = None, exclude: int | None = None) -> Calibration:
    """Fit one camera's pixel -> ground model. Gross mistakes are rejected and reported.

    The ground segments are automatic (fisheye sectors around the nadir, pinhole range bands) unless the user
    names them: by the landmarks' segment column, or by `segment_polygons` (label -> (M, 2) polygon in site
    metres; landmarks without a segment then take the polygon they lie in or nearest). Either way each segment's
    plane is fitted to its own landmarks (`labelled_segments`). `exclude`: the index of a landmark rejected before
    the fit starts (`single_gross_mistake`'s), reported as rejected like the others."""
    xy = lm.to_local(geo)
    n = len(lm)
    obj = np.column_stack([xy, np.zeros(n)])
    use = np.ones(n, bool)
    if exclude is None:
        p, dxy, _ = fit_camera(lm.uv, obj, cfg)  # robust: a start that gross mistakes do not drag far
    else:
        use[exclude] = False
        p, dxy, _ = fit_camera(lm.uv[use], obj[use], cfg)
    # Segments the user named: the camera and their planes are fitted together from the start, so that a landmark
    # where the ground bends is not taken for a mistake against one plane.
    named = labelled_segments(lm, xy, use, segment_polygons)
    seg = np.searchsorted(named.labels, named.of_landmark) if named is not None and len(named.labels) > 1 else None
    named_planes = np.zeros((len(named.labels), 3)) if seg is not None else None
    # Reject the landmark with the worst outlier test while it fails, refitting each time.
    warnings: list[str] = []
    while True:
        if seg is None:
            p_ls, dxy_ls, sol = fit_camera(lm.uv[use], obj[use], cfg, p, robust=False)
        else:
            p_ls, dxy_ls, planes_ls, sol = fit_camera_on_segments(lm.uv[use], xy[use], seg[use], named_planes,
                                                                  np.zeros(3), cfg, p)
        stat, mdb_map, mdb_px = _landmark_tests(sol, int(use.sum()), cfg)
        worst = int(np.argmax(stat))
        if use.sum() <= MIN_LANDMARKS:  # too few to tell a mistake from the rest: keep the robust fit
            if stat[worst] > cfg.outlier_sigma:
                warnings.append(
                    f"{lm.ids[np.nonzero(use)[0][worst]]} fails the outlier test ({stat[worst]:.1f} sigma), but with "
                    f"{int(use.sum())} landmarks a mistake cannot be told from the rest: check it, add landmarks"
                )
            break
        p, dxy = p_ls, dxy_ls
        if seg is not None:
            named_planes = planes_ls
        if stat[worst] <= cfg.outlier_sigma:
            break
        use[np.nonzero(use)[0][worst]] = False
    test_sigma, detectable_map, detectable_px = (np.full(n, np.nan) for _ in range(3))
    test_sigma[use], detectable_map[use], detectable_px[use] = stat, mdb_map, mdb_px
    cam = camera_from_params(p, cfg)
    if seg is not None:
        labelled = labelled_segments(lm, xy, use, segment_polygons)  # where each segment lies: its usable landmarks
        for k, label in enumerate(labelled.labels):
            if (seg[use] == k).sum() < MIN_PER_SEGMENT:
                warnings.append(f"segment {label} keeps {int((seg[use] == k).sum())} usable landmark(s), fewer "
                                f"than {MIN_PER_SEGMENT}: its plane leans on the others; add landmarks there")
        nadir_px = cam.project(cam.pose.position_m[None] - [0.0, 0.0, 10.0])[0][0]
        obj[:, 2] = np.sum(named_planes[seg] * np.column_stack([xy, np.ones(n)]), axis=1)  # on its own plane
        return _finish(Calibration(cfg, geo, cam, named_planes, np.zeros(len(named_planes)), nadir_px,
                                   inliers=use, test_sigma=test_sigma, detectable_map_m=detectable_map,
                                   detectable_pixel_px=detectable_px, labelled=labelled), lm, obj, xy, warnings)
    # Ground planes: a global one, then one per segment around the nadir.
    z, w = implied_heights(cam, lm.uv[use], xy[use], cfg.pixel_sigma_px, cfg.map_sigma_m)
    centre = xy[use].mean(axis=0)
    global_plane = _fit_plane(xy[use], z, w, None, centre) if use.sum() >= 6 else np.zeros(3)
    # Refit the camera on the plane's heights (the ground is not at z = 0).
    obj[:, 2] = global_plane[0] * xy[:, 0] + global_plane[1] * xy[:, 1] + global_plane[2]
    p, dxy, _ = fit_camera(lm.uv[use], obj[use], cfg, p, robust=False)
    cam = camera_from_params(p, cfg)
    xy_use = xy[use] + dxy  # the fitted ground positions of the landmarks
    z, w = implied_heights(cam, lm.uv[use], xy_use, cfg.pixel_sigma_px, cfg.map_sigma_m)
    if use.sum() >= 6:
        global_plane = _fit_plane(xy_use, z, w, global_plane, centre)
    nadir_px = cam.project(cam.pose.position_m[None] - [0.0, 0.0, 10.0])[0][0]
    ranges = np.linalg.norm(xy_use - cam.pose.position_m[:2], axis=1)

    def split(p: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Segment centres, band edges and each landmark's segment for P segments."""
        if cfg.kind == "fisheye":
            centres, lab = _sectors(lm.uv[use], nadir_px, p)
            return centres, np.zeros(0), lab
        edges = np.quantile(ranges, np.arange(1, p) / p)
        return np.zeros(p), edges, np.searchsorted(edges, ranges)

    n_seg = 1 if named is not None else cfg.wanted_segments  # one segment named: the one plane, so labelled
    while n_seg > 1 and np.bincount(split(n_seg)[2], minlength=n_seg).min() < MIN_PER_SEGMENT:
        n_seg -= 1
    if named is None and n_seg < cfg.wanted_segments:
        warnings.append(
            f"{int(use.sum())} usable landmarks: fitted {n_seg} ground segment(s) instead of "
            f"{cfg.wanted_segments} (each needs at least {MIN_PER_SEGMENT} landmarks)"
        )
    centres, edges, lab = split(n_seg)
    if n_seg > 1:
        planes = np.array([
            _fit_plane(xy_use[lab == s], z[lab == s], w[lab == s], global_plane, xy_use[lab == s].mean(axis=0))
            for s in range(n_seg)
        ])
    else:
        edges, planes = np.zeros(0), global_plane[None]
    cal = Calibration(cfg, geo, cam, planes, centres, nadir_px, edges, use, test_sigma=test_sigma,
                      detectable_map_m=detectable_map, detectable_pixel_px=detectable_px, labelled=named)
    return _finish(cal, lm, obj, xy, warnings)


def single_gross_mistake(lm: Landmarks, cfg: CalibConfig, geo: GeoFrame) -> tuple[int, float] | None:
    """The one landmark that a failed fit of all of them (most rejected, the camera under the ground) trips on:
    (its index, how far (m) its map point lies from where the others place its pixel on level ground), or None.

    One mistyped digit of a latitude or longitude (tens of metres) drags `calibrate`'s robust start so far that
    the one-at-a-time rejection then drops good landmarks instead. So each landmark is left out in turn and the
    same robust start fitted to the rest: the mistake is the landmark whose leaving out leaves every other one
    within `outlier_sigma` while it itself lies off the fit by more than that. None when no landmark, or more than
    one, is such (several mistakes, swapped columns, another camera's pixels), and with `MIN_LANDMARKS` or fewer."""
    xy = lm.to_local(geo)
    n = len(lm)
    if n <= MIN_LANDMARKS:  # too few to tell a mistake from the rest (`calibrate`)
        return None
    obj = np.column_stack([xy, np.zeros(n)])
    found = []
    for i in range(n):
        keep = np.arange(n) != i
        try:
            p, _, sol = fit_camera(lm.uv[keep], obj[keep], cfg)
        except ValueError:  # no initial pose from the rest
            continue
        r = np.asarray(sol.fun[: 4 * (n - 1)]).reshape(2, n - 1, 2)  # pixel rows, then map rows (normalised)
        if np.sqrt(np.sum(r**2, axis=(0, 2))).max() > cfg.outlier_sigma:
            continue  # the rest still disagree
        cam = camera_from_params(p, cfg)
        proj, ok = cam.project(obj[i : i + 1])
        if ok[0] and np.linalg.norm(proj[0] - lm.uv[i]) <= cfg.outlier_sigma * cfg.pixel_sigma_px:
            continue  # it agrees with them too: not the mistake
        dirs, _ = cam.unproject(lm.uv[i : i + 1])
        at, _ = _ray_plane(cam.pose.position_m, dirs, np.zeros(3))  # its pixel's ray onto the level ground (z = 0)
        off = float(np.linalg.norm(at[0] - xy[i]))
        found.append((i, off if math.isfinite(off) else math.inf))
    return found[0] if len(found) == 1 else None


def _finish(cal: Calibration, lm: Landmarks, obj: np.ndarray, xy: np.ndarray, warnings: list[str]) -> Calibration:
    """`calibrate`'s report on a fitted camera: the rejected landmarks and why, and where a mistake could hide."""
    cfg, cam, use, detectable_map = cal.config, cal.camera, cal.inliers, cal.detectable_map_m
    proj, _ = cam.project(obj)
    res_px = np.linalg.norm(proj - lm.uv, axis=1)
    ground, _ = cal.pixel_to_xy(lm.uv)
    res_m = np.linalg.norm(ground - xy, axis=1)
    cal.rejected = [
        (
            lm.ids[i],
            f"{res_px[i]:.1f} px from where its map point projects ({res_m[i]:.2f} m on the ground), "
            f"inconsistent with the other landmarks beyond {cfg.outlier_sigma:g} sigma of the expected "
            f"{cfg.pixel_sigma_px:g} px / {cfg.map_sigma_m:g} m: a wrong pixel or map point",
        )
        for i in np.nonzero(~use)[0]
    ]
    hidden = [i for i in np.nonzero(use)[0] if detectable_map[i] > HIDDEN_MISTAKE_M]
    if hidden:
        least = max(hidden, key=lambda i: detectable_map[i])  # the least checked landmark
        size = f"up to {detectable_map[least]:.1f} m" if np.isfinite(detectable_map[least]) else "of any size"
        warnings.append(
            f"a map mistake could go unnoticed at {', '.join(lm.ids[i] for i in hidden)} ({size} at "
            f"{lm.ids[least]}): the other landmarks cannot check them; add landmarks near them or check them by hand"
        )
    cal.warnings = warnings
    return cal
