"""Training labels for a real camera without a person labelling: moving vehicles found against a
background model of the static scene, kept when their ground footprint has a vehicle's size, linked over
time for a heading from motion, written as a COCO-style file that `roadside train --coco` reads.

Per camera (one folder of frames, capture time in the file names, and the camera's lookup masks):

1. Background: the per-pixel median of the frames (a vehicle that stops for less than half the window
   stays out of it). Frames are worked at `scale` (0.5: 1280x960 -> 640x480, the detector's input size).
2. Foreground: the largest colour difference to the background above `diff_thr`, opened and closed,
   inside the calibrated area and within `roi_m` of the camera; connected components.
3. Footprint: the component's pixels are lifted to the ground through the masks. A point at height z above
   the ground is seen where the ray from the camera (height H) meets the ground, its distance from the
   camera's foot scaled by H / (H - z); a vehicle of height h therefore spans ground distances from its
   near edge r_near to its roof's far edge r_far, with the footprint's far edge at r_far * (H - h) / H.
   The footprint centre is the centre of the points' smallest enclosing rectangle (whole even where a post
   hides the vehicle's middle), scaled towards the camera's foot by the middle of the two scales (sides and
   roof lie between them); its extent along the bearing (from r_near to the footprint's far edge) and
   across it (deflated by that middle scale) must fit a vehicle (`length_m`, `width_m`). A bigger component
   (vehicles merged, a vehicle and its shadow) is written as an ignore region (COCO `iscrowd`), a smaller one
   is dropped.
4. Linking: footprints of consecutive frames are matched (Hungarian, gate `max_speed_mps` * dt); the
   heading comes from a straight-line fit of a track's positions over `heading_window` frames, kept where
   the vehicle moves at least `min_speed_mps`. A track shorter than `min_track_frames` is an ignore region.
5. What the labels may miss (both optional): every vehicle left unlabelled on a training image teaches the
   detector to miss it. With `ignore_small`, a foreground component too small for a vehicle (a part of
   one, a pedestrian) is an ignore region instead of being dropped. A parked or waiting vehicle is part of
   the background, so steps 1-4 never see it: with a `teacher` (a detector, e.g. the simulator-trained
   model), its detections (score >= `teacher_thr`, low: this is about what might be a vehicle) further
   than `teacher_clear_m` from every label and ignore region of the frame become ignore regions too.
   (Labelling them instead was tried: the persistent teacher detections at this site were mostly lamp
   heads, painted words and grass patches.) With `tracks` (training/track_labels.py: the pipeline's own tracks
   of the same footage), vehicles the cameras followed together while they moved become labels where the
   frame has none near them.
6. Output: each frame as a grey image at `scale` with everything outside the region of interest set to
   the frame's mean grey (parked vehicles there are never labelled, so they must not be shown as
   background), and the labels: bottom centre (the footprint centre, mapped back to the image through the
   masks' local Jacobian), 2D box (the component's), image-space heading, type unknown ("vehicle").

The camera's height and foot come from the masks' camera pose (`meta.camera.pose.position_m`).
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from datetime import UTC, time, tzinfo
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from calibration.masks import LookupMasks, load_masks
from services.ingest.sources import capture_time_from_name, image_files
from shared.raster import bilinear, bilinear_cells
from training.track_labels import TrackTeacher, label_from_track

COCO_PIXEL_OFFSET = 0.5  # COCO coordinate = our pixel-centre coordinate + 0.5 (as training.data)
CAR_MAX_M = (6.5, 2.8)  # a union of two vehicle-sized parts no bigger than this is one car
MERGE_GAP_PX = 12  # components this close may be one vehicle behind an occluder (see find_blobs)
NS_PER_DAY = 86_400 * 10**9


@dataclass(frozen=True)
class AutolabelConfig:
    scale: float = 0.5  # working and output resolution relative to the frames
    diff_thr: float = 28.0  # grey levels: largest colour-channel difference to the background
    min_area_px: int = 40  # smallest component kept (at `scale`)
    roi_m: float = 30.0  # labels and shown pixels within this ground distance of the camera's foot
    vehicle_height_m: float = 1.5  # assumed height of a vehicle's roof for the footprint deflation
    length_m: tuple[float, float] = (2.5, 20.0)  # longer footprint side of a vehicle
    width_m: tuple[float, float] = (1.0, 4.5)  # shorter footprint side
    max_speed_mps: float = 25.0  # linking gate
    min_track_frames: int = 3
    heading_window: int = 5  # frames in the straight-line fit for the heading
    min_speed_mps: float = 1.5  # slower vehicles get no heading
    min_valid_share: float = 0.8  # a component with fewer of its pixels on calibrated ground is ignored
    ignore_small: bool = False  # components too small for a vehicle become ignore regions (else dropped)
    teacher_thr: float = 0.1  # teacher detections at least this confident become ignore regions
    teacher_clear_m: float = 2.5  # ... when at least this far from the frame's labels and ignore regions

    def __post_init__(self) -> None:
        if not 0 < self.scale <= 1:
            raise ValueError(f"scale must be in (0, 1], got {self.scale}")
        for name in ("diff_thr", "roi_m", "vehicle_height_m", "max_speed_mps", "min_speed_mps"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        for name in ("length_m", "width_m"):
            lo, hi = getattr(self, name)
            if not 0 < lo < hi:
                raise ValueError(f"{name} must be (low, high) with 0 < low < high, got {(lo, hi)}")
        if not 0 < self.teacher_thr <= 1:
            raise ValueError(f"teacher_thr must be in (0, 1], got {self.teacher_thr}")
        if self.min_track_frames < 1 or self.heading_window < 2 or self.min_area_px < 1:
            raise ValueError("min_track_frames must be >= 1, heading_window >= 2, min_area_px >= 1")


@dataclass
class Blob:
    """One foreground component of one frame, at the working resolution."""

    frame: int
    box: np.ndarray  # (4,) x1, y1, x2, y2 pixel edges
    centre_xy: np.ndarray  # (2,) footprint centre, site metres
    extent_m: tuple[float, float]  # (along the bearing, across it)
    status: str  # "vehicle" | "too_big" | "too_small" | "off_ground"
    track: int = -1
    heading_xy: np.ndarray | None = None  # unit vector, site frame


def name_clock_ns(name: str) -> int | None:
    """The time of day a file name gives, ns after midnight, the clock `--until` reads whatever the names' time zone:
    a date-time name's own fields as written, an epoch name's (a simulator recording's) UTC time of day. None when
    the name carries no time."""
    t = capture_time_from_name(name, UTC)  # read as UTC, a date and time keeps exactly the fields it is written with
    return None if t is None else t % NS_PER_DAY


def time_of_day_ns(until: time) -> int:
    """A time of day (`--until`) in ns after midnight."""
    return ((until.hour * 60 + until.minute) * 60 + until.second) * 10**9 + until.microsecond * 1000


def list_frames(folder: str | Path, until: time | None = None, tz: tzinfo = UTC) -> list[tuple[int, Path]]:
    """(capture time ns, path) of the images in `folder`, in time order, the names read in time zone `tz` (as ingest
    reads them with `ingest.timezone`); frames at or after the time of day `until` are left out, `until` being the
    clock written in the names (`name_clock_ns`: not moved by `tz`; the UTC time of day for names of epoch time).
    Raises ValueError when a name has no time."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ValueError(f"frames folder not found: {folder}")
    until_ns = None if until is None else time_of_day_ns(until)
    out = []
    for path in sorted(image_files(folder)):  # as ingest lists them: not hidden files (macOS's `._<name>` beside each)
        t = capture_time_from_name(path.name, tz)
        if t is None:
            raise ValueError(f"{path}: no capture time in the file name (expected e.g. 2023-12-19 11-00-00-034395)")
        if until_ns is not None and name_clock_ns(path.name) >= until_ns:
            continue
        out.append((t, path))
    if not out:
        raise ValueError(f"{folder}: no frames" + (f" before {until}" if until else ""))
    return sorted(out)


def read_frame(path: Path, size: tuple[int, int]) -> np.ndarray:
    """A frame (BGR) of the expected (width, height); ValueError naming the file otherwise."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    if (img.shape[1], img.shape[0]) != size:
        raise ValueError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, the masks are for {size[0]}x{size[1]}")
    return img


class GroundView:
    """The masks at the working resolution, with the camera's foot and height."""

    def __init__(self, masks: LookupMasks, scale: float, roi_m: float) -> None:
        h, w = masks.shape
        self.size = (w, h)
        self.scale = scale
        ws, hs = round(w * scale), round(h * scale)
        # working pixel centre p <-> full-resolution position q: q + 0.5 = (p + 0.5) / scale. At scale 0.5 that is
        # 2p + 0.5, between two full-resolution pixel centres: sampled bilinearly there (the nearest pixel, by
        # numpy's rounding half to even always 2p, was a quarter working pixel off), valid where the lookup is
        uq = (np.arange(ws) + 0.5) / scale - 0.5
        vq = (np.arange(hs) + 0.5) / scale - 0.5
        grid = np.stack(np.meshgrid(uq, vq), axis=2).reshape(-1, 2)
        _, xy, ok = masks.lookup(grid, geodetic=False)
        self.xy = xy.reshape(hs, ws, 2)
        self.valid = ok.reshape(hs, ws)
        pos = masks.camera_position_m()
        self.foot = pos[:2]
        self.height_m = float(pos[2])
        if not self.height_m > 2.0:
            raise ValueError(f"camera height {self.height_m:.2f} m from the masks is too low for autolabel")
        dist = np.hypot(*(self.xy - self.foot).transpose(2, 0, 1))
        self.roi = self.valid & (dist <= roi_m)
        nad = masks.meta.get("nadir_px")
        pp = nad if nad else [masks.meta["camera"]["cx"], masks.meta["camera"]["cy"]]
        self.principal_point = ((pp[0] + 0.5) * scale - 0.5, (pp[1] + 0.5) * scale - 0.5)

    def to_pixel(self, xy: np.ndarray, near: tuple[int, int, int, int]) -> np.ndarray | None:
        """Working pixel (u, v) whose ground point is `xy`, searched in the box `near` (x1, y1, x2, y2)
        grown by 8 px and refined by two Newton steps on the local Jacobian; None if off the ground (also where a
        step lands within a pixel of the calibrated ground's edge, on cells holding no ground point)."""
        hs, ws = self.valid.shape
        x1, y1 = max(0, near[0] - 8), max(0, near[1] - 8)
        x2, y2 = min(ws - 1, near[2] + 8), min(hs - 1, near[3] + 8)
        win = self.xy[y1:y2, x1:x2]
        d2 = ((win - xy) ** 2).sum(axis=2)
        d2[~self.valid[y1:y2, x1:x2]] = np.inf
        if not np.isfinite(d2).any():
            return None
        v, u = np.unravel_index(np.argmin(d2), d2.shape)
        p = np.array([u + x1, v + y1], np.float64)
        for _ in range(2):
            jac = self.jacobian(p)
            if jac is None:
                return None
            p = p + np.linalg.solve(jac, xy - self.lookup(p))
        return p if np.isfinite(p).all() else None

    def lookup(self, p: np.ndarray) -> np.ndarray:
        """Ground point (2,) at working pixel p, bilinear (clamped to the outermost pixel centres)."""
        hs, ws = self.valid.shape
        q = np.clip(np.asarray(p, np.float64), 0, [ws - 1, hs - 1])
        return bilinear(self.xy, bilinear_cells(q[None], hs, ws))[0]

    def jacobian(self, p: np.ndarray) -> np.ndarray | None:
        """d(xy)/d(uv) at p (2x2), None where it is singular or off the ground."""
        hs, ws = self.valid.shape
        u, v = int(round(p[0])), int(round(p[1]))
        if not (0 <= u < ws - 1 and 0 <= v < hs - 1) or not self.valid[v:v + 2, u:u + 2].all():
            return None
        jac = np.stack([self.xy[v, u + 1] - self.xy[v, u], self.xy[v + 1, u] - self.xy[v, u]], axis=1)
        return jac if abs(np.linalg.det(jac)) > 1e-9 else None


def background(frames: list[np.ndarray]) -> np.ndarray:
    """Per-pixel median of the frames (uint8, same shape as one frame)."""
    return np.median(np.stack(frames), axis=0).astype(np.uint8)


def foreground(frame: np.ndarray, bg: np.ndarray, roi: np.ndarray, cfg: AutolabelConfig) -> np.ndarray:
    """uint8 0/1 mask of moving things: colour difference, opened and closed, inside the ROI."""
    diff = cv2.absdiff(frame, bg).max(axis=2)
    fg = ((diff > cfg.diff_thr) & roi).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    return cv2.morphologyEx(fg, cv2.MORPH_CLOSE, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7)))


def footprint(points: np.ndarray, view: GroundView, cfg: AutolabelConfig) -> tuple[np.ndarray, float, float]:
    """(centre (2,), extent along the bearing, extent across it) in metres of the ground points of one
    component (see the module docstring)."""
    d = points - view.foot
    r = np.hypot(d[:, 0], d[:, 1])
    bearing = math.atan2(np.sin(np.arctan2(d[:, 1], d[:, 0])).mean(), np.cos(np.arctan2(d[:, 1], d[:, 0])).mean())
    ang = np.angle(np.exp(1j * (np.arctan2(d[:, 1], d[:, 0]) - bearing)))
    deflate = (view.height_m - cfg.vehicle_height_m) / view.height_m
    r_near, r_far = np.quantile(r, 0.02), np.quantile(r, 0.98)
    a_lo, a_hi = np.quantile(ang, 0.02), np.quantile(ang, 0.98)
    r_far_ground = max(r_far * deflate, r_near + 0.5)
    r_mid = (r_near + r_far_ground) / 2
    # points between the ground (scale 1) and the roof (scale 1 / deflate) average a scale of about the middle
    (cx, cy), _, _ = cv2.minAreaRect(d.astype(np.float32))
    centre = view.foot + np.array([cx, cy]) * 2 / (1 + 1 / deflate)
    across = (a_hi - a_lo) * r_mid * 2 / (1 + 1 / deflate)
    return centre, float(r_far_ground - r_near), float(across)


def _components(fg: np.ndarray, cfg: AutolabelConfig, counts: dict[str, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """(ys, xs) pixels of each connected component of at least min_area_px."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(fg, connectivity=8)
    comps = []
    for k in range(1, n):
        x, y, w, h, area = stats[k]
        if area < cfg.min_area_px:
            counts["too_small"] += 1
            continue
        ys, xs = np.nonzero(lab[y:y + h, x:x + w] == k)
        comps.append((ys + y, xs + x))
    return comps


def _measure(ys: np.ndarray, xs: np.ndarray, view: GroundView, cfg: AutolabelConfig) -> tuple:
    """(status, centre, (along, across)) of one component: "vehicle", "too_big", "too_small", "off_ground"."""
    ok = view.valid[ys, xs]
    if ok.mean() < cfg.min_valid_share:
        return "off_ground", np.full(2, np.nan), (np.nan, np.nan)
    centre, along, across = footprint(view.xy[ys[ok], xs[ok]], view, cfg)
    long_side, short_side = max(along, across), min(along, across)
    if long_side > cfg.length_m[1] or short_side > cfg.width_m[1]:
        return "too_big", centre, (along, across)
    if long_side < cfg.length_m[0] or short_side < cfg.width_m[0]:
        return "too_small", centre, (along, across)
    return "vehicle", centre, (along, across)


def _box(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    return np.array([xs.min(), ys.min(), xs.max() + 1, ys.max() + 1], np.float64)


def find_blobs(index: int, frame: np.ndarray, bg: np.ndarray, view: GroundView, cfg: AutolabelConfig,
               counts: dict[str, int]) -> list[Blob]:
    """The frame's foreground components, measured on the ground. Two components whose boxes come within
    MERGE_GAP_PX of each other are joined when the union still has a vehicle's footprint and either part
    alone does not, or when both do but the union is no bigger than one car (CAR_MAX_M): a vehicle cut in two
    by a lamp post or a sign in front of it."""
    comps = _components(foreground(frame, bg, view.roi, cfg), cfg, counts)
    measured = [_measure(ys, xs, view, cfg) for ys, xs in comps]
    merged = True
    while merged:
        merged = False
        boxes = [_box(ys, xs) for ys, xs in comps]
        for i in range(len(comps)):
            for j in range(i + 1, len(comps)):
                gap = max(boxes[i][0] - boxes[j][2], boxes[j][0] - boxes[i][2],
                          boxes[i][1] - boxes[j][3], boxes[j][1] - boxes[i][3])
                if gap > MERGE_GAP_PX:
                    continue
                ys, xs = np.concatenate([comps[i][0], comps[j][0]]), np.concatenate([comps[i][1], comps[j][1]])
                m = _measure(ys, xs, view, cfg)
                both = measured[i][0] == "vehicle" and measured[j][0] == "vehicle"
                if m[0] == "vehicle" and (not both or (max(m[2]) <= CAR_MAX_M[0] and min(m[2]) <= CAR_MAX_M[1])):
                    comps[i], measured[i] = (ys, xs), m
                    del comps[j], measured[j]
                    counts["merged"] += 1
                    merged = True
                    break
            if merged:
                break
    blobs = []
    for (ys, xs), (status, centre, extent) in zip(comps, measured, strict=True):
        if status == "too_small" and not cfg.ignore_small:
            counts["not_vehicle_size"] += 1
            continue
        blobs.append(Blob(index, _box(ys, xs), centre, extent, status))
    return blobs


def link(per_frame: list[list[Blob]], times_s: np.ndarray, cfg: AutolabelConfig) -> int:
    """Give the vehicle blobs track ids (Hungarian on footprint distance between consecutive frames);
    returns the number of tracks."""
    next_id = 0
    prev: list[Blob] = []
    for i, blobs in enumerate(per_frame):
        cur = [b for b in blobs if b.status == "vehicle"]
        if prev and cur and i > 0:
            gate = max(2.0, cfg.max_speed_mps * (times_s[i] - times_s[i - 1]))
            cost = np.linalg.norm(np.array([b.centre_xy for b in prev])[:, None]
                                  - np.array([b.centre_xy for b in cur])[None], axis=2)
            rows, cols = linear_sum_assignment(np.where(cost <= gate, cost, 1e6))
            for r, c in zip(rows, cols, strict=True):
                if cost[r, c] <= gate:
                    cur[c].track = prev[r].track
        for b in cur:
            if b.track < 0:
                b.track, next_id = next_id, next_id + 1
        prev = cur
    return next_id


def headings(per_frame: list[list[Blob]], times_s: np.ndarray, cfg: AutolabelConfig) -> dict[int, int]:
    """Heading from motion on each vehicle blob of a moving track; returns track lengths by id."""
    tracks: dict[int, list[Blob]] = {}
    for blobs in per_frame:
        for b in blobs:
            if b.track >= 0:
                tracks.setdefault(b.track, []).append(b)
    half = cfg.heading_window // 2
    for members in tracks.values():
        t = np.array([times_s[b.frame] for b in members])
        xy = np.array([b.centre_xy for b in members])
        for j, b in enumerate(members):
            lo, hi = max(0, j - half), min(len(members), j + half + 1)
            if hi - lo < 2 or t[hi - 1] - t[lo] <= 0:
                continue
            vx = np.polyfit(t[lo:hi], xy[lo:hi, 0], 1)[0]
            vy = np.polyfit(t[lo:hi], xy[lo:hi, 1], 1)[0]
            speed = math.hypot(vx, vy)
            if speed >= cfg.min_speed_mps:
                b.heading_xy = np.array([vx, vy]) / speed
    return {k: len(v) for k, v in tracks.items()}


def teacher_regions(frames: list[np.ndarray], view: GroundView, detect, cfg: AutolabelConfig) -> list[list]:
    """Per frame (BGR), the teacher's detections in the ROI (score >= `cfg.teacher_thr`) as (ground point, box).
    Also used by training.composite on its background (its config has the same `teacher_thr`)."""
    out = []
    hs, ws = view.valid.shape
    for frame in frames:
        d = detect(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
        found = []
        for k in np.nonzero(np.asarray(d.score) >= cfg.teacher_thr)[0]:
            u, v = (int(round(c)) for c in d.uv[k])
            if 0 <= u < ws and 0 <= v < hs and view.roi[v, u]:
                found.append((view.lookup(np.asarray(d.uv[k], np.float64)), np.asarray(d.box[k], np.float64)))
        out.append(found)
    return out


def autolabel_camera(frames_dir: str | Path, masks_path: str | Path, out_dir: str | Path, camera: str,
                     until: time | None = None, cfg: AutolabelConfig | None = None, log=print,
                     teacher=None, tracks: str | Path | None = None, tz: tzinfo = UTC) -> dict:
    """Label one camera's frames; writes `out_dir`/images/*.png and `out_dir`/labels.json (COCO-style);
    returns the report (also in `out_dir`/report.json). `teacher`: a detector (grey image -> detections
    with score, uv, box) whose detections become ignore regions (module doc, step 5); None: no teacher.
    `tracks`: a tracks file (the pipeline's tracks of the same footage, read by `training.track_labels.TrackTeacher`):
    its moving vehicles away from the frame's labels and ignore regions become labels too (`from_tracks` in the file).
    Only its lines before the end of the labelled slice are read (the `until` instant, or just after the last frame
    without one), so that nothing after the slice decides which tracks moved; the report counts the lines left out
    (`track_lines_after_slice`). `tz`: the time zone of the frames' names (the site's `ingest.timezone`), so that they
    meet the tracks' times."""
    cfg = cfg or AutolabelConfig()
    masks = load_masks(masks_path)
    view = GroundView(masks, cfg.scale, cfg.roi_m)
    listed = list_frames(frames_dir, until, tz)
    if tracks is not None:
        t_last, last = listed[-1]
        # the until instant: the last frame's capture time plus what its name's clock lacks to `until`
        t_end = t_last + 1 if until is None else t_last + time_of_day_ns(until) - name_clock_ns(last.name)
        tracks = TrackTeacher(tracks, t_end_ns=t_end)
    if tracks is not None and not (tracks.times[0] - 10**9 <= listed[-1][0] and listed[0][0] <= tracks.times[-1]
                                   + 10**9):
        raise ValueError(f"the tracks ({tracks.times[0]} to {tracks.times[-1]} ns) do not span the frames' capture "
                         f"times ({listed[0][0]} to {listed[-1][0]} ns): the names in another time zone than "
                         "--timezone, or another footage's tracks?")
    ws, hs = view.valid.shape[1], view.valid.shape[0]
    frames = []
    for _, path in listed:
        frames.append(cv2.resize(read_frame(path, view.size), (ws, hs), interpolation=cv2.INTER_AREA))
    times_s = np.array([(t - listed[0][0]) / 1e9 for t, _ in listed])
    bg = background(frames)
    counts = {"too_small": 0, "not_vehicle_size": 0, "merged": 0}
    per_frame = [find_blobs(i, f, bg, view, cfg, counts) for i, f in enumerate(frames)]
    n_tracks = link(per_frame, times_s, cfg)
    lengths = headings(per_frame, times_s, cfg)
    taught = teacher_regions(frames, view, teacher, cfg) if teacher is not None else [[] for _ in frames]

    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    images, annotations = [], []
    n = {"vehicles": 0, "with_heading": 0, "ignored_too_big": 0, "ignored_off_ground": 0, "ignored_short_track": 0,
         "ignored_no_pixel": 0, "ignored_small": 0, "ignored_teacher": 0, "from_tracks": 0, "tracks_off_view": 0}
    for i, ((t_ns, path), frame) in enumerate(zip(listed, frames, strict=True)):
        grey = cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
        shown = np.where(view.roi, grey, np.uint8(round(float(grey[view.roi].mean())))).astype(np.uint8)
        name = f"images/{camera}_{path.stem.replace(' ', '_')}.png"
        if not cv2.imwrite(str(out_dir / name), shown):
            raise ValueError(f"cannot write {out_dir / name}")
        images.append({"id": i, "file_name": name, "width": ws, "height": hs, "camera": camera, "kind": "fisheye"
                       if masks.meta.get("kind") == "fisheye" else masks.meta.get("kind", "pinhole"),
                       "t_ns": t_ns, "principal_point": [c + COCO_PIXEL_OFFSET for c in view.principal_point],
                       "source": str(path)})
        for b in per_frame[i]:
            x1, y1, x2, y2 = b.box
            ann = {"id": len(annotations), "image_id": i, "category_id": 0,
                   "bbox": [float(x1), float(y1), float(x2 - x1), float(y2 - y1)]}
            crowd = b.status != "vehicle" or lengths.get(b.track, 0) < cfg.min_track_frames
            uv = None if crowd else view.to_pixel(b.centre_xy, tuple(int(c) for c in b.box))
            if crowd or uv is None:
                ann["iscrowd"] = 1
                key = {"too_big": "ignored_too_big", "off_ground": "ignored_off_ground",
                       "too_small": "ignored_small"}.get(b.status)
                n[key or ("ignored_no_pixel" if not crowd else "ignored_short_track")] += 1
            else:
                ann["bottom_center"] = [float(uv[0] + COCO_PIXEL_OFFSET), float(uv[1] + COCO_PIXEL_OFFSET)]
                ann["ground_xy_m"] = [round(float(c), 3) for c in b.centre_xy]
                ann["track_id"] = b.track
                n["vehicles"] += 1
                if b.heading_xy is not None:
                    jac = view.jacobian(uv)
                    if jac is not None:
                        duv = np.linalg.solve(jac, b.heading_xy)
                        ann["heading_uv"] = [float(c) for c in duv / np.linalg.norm(duv)]
                        ann["ground_yaw_rad"] = round(math.atan2(b.heading_xy[1], b.heading_xy[0]), 4)
                        n["with_heading"] += 1
            annotations.append(ann)
        taken = [b.centre_xy for b in per_frame[i] if np.all(np.isfinite(b.centre_xy))]
        for tv in tracks.at(t_ns) if tracks is not None else []:
            if taken and min(np.linalg.norm(tv.xy - t) for t in taken) < cfg.teacher_clear_m:
                continue
            lab = label_from_track(tv, view)
            if lab is None:
                n["tracks_off_view"] += 1
                continue
            x1, y1, x2, y2 = (float(c) for c in lab["box"])  # pixel-centre coordinates, as the bottom centre
            annotations.append({"id": len(annotations), "image_id": i, "category_id": 0,
                                "bbox": [x1 + COCO_PIXEL_OFFSET, y1 + COCO_PIXEL_OFFSET, x2 - x1, y2 - y1],
                                "bottom_center": [float(c + COCO_PIXEL_OFFSET) for c in lab["uv"]],
                                "ground_xy_m": [round(float(c), 3) for c in tv.xy],
                                "heading_uv": [float(c) for c in lab["heading_uv"]],
                                "ground_yaw_rad": round(tv.yaw, 4), "track_id": tv.key, "from_tracks": 1})
            n["from_tracks"] += 1
            n["vehicles"] += 1
            n["with_heading"] += 1
            taken.append(tv.xy)
        for xy, box in taught[i]:
            if taken and min(np.linalg.norm(xy - t) for t in taken) < cfg.teacher_clear_m:
                continue
            x1, y1, x2, y2 = box  # the detector's, in pixel-centre coordinates (as composite.py's teacher boxes)
            annotations.append({"id": len(annotations), "image_id": i, "category_id": 0, "iscrowd": 1,
                                "bbox": [float(x1 + COCO_PIXEL_OFFSET), float(y1 + COCO_PIXEL_OFFSET),
                                         float(x2 - x1), float(y2 - y1)]})
            n["ignored_teacher"] += 1
            taken.append(xy)
    doc = {"info": {"description": f"roadside autolabel of {camera} from {frames_dir}", "config": asdict(cfg)},
           "images": images, "annotations": annotations, "categories": [{"id": 0, "name": "vehicle"}]}
    (out_dir / "labels.json").write_text(json.dumps(doc))
    report = {"camera": camera, "frames": len(frames), "first": listed[0][1].name, "last": listed[-1][1].name,
              "tracks": n_tracks, "tracks_long_enough": sum(1 for v in lengths.values() if v >= cfg.min_track_frames),
              **n, "track_lines_after_slice": tracks.lines_after_end if tracks is not None else 0, "dropped": counts}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    if log:
        log(f"[autolabel] {camera}: {json.dumps(report)}")
    return report


def draw(labels_json: str | Path, image_id: int) -> np.ndarray:
    """An autolabelled image (BGR) with its labels: boxes (green: vehicle, grey: ignored), bottom centres
    and headings; for checking the labels by eye."""
    labels_json = Path(labels_json)
    doc = json.loads(labels_json.read_text())
    img = next(i for i in doc["images"] if i["id"] == image_id)
    canvas = cv2.cvtColor(cv2.imread(str(labels_json.parent / img["file_name"]), cv2.IMREAD_GRAYSCALE),
                          cv2.COLOR_GRAY2BGR)
    for a in doc["annotations"]:
        if a["image_id"] != image_id:
            continue
        x, y, w, h = (int(round(c)) for c in a["bbox"])
        colour = (128, 128, 128) if a.get("iscrowd") else (0, 255, 0)
        cv2.rectangle(canvas, (x, y), (x + w, y + h), colour, 1)
        if "bottom_center" in a:
            p = np.array(a["bottom_center"]) - COCO_PIXEL_OFFSET
            cv2.circle(canvas, (int(p[0]), int(p[1])), 2, (0, 0, 255), -1)
            if "heading_uv" in a:
                q = p + 12 * np.array(a["heading_uv"])
                cv2.arrowedLine(canvas, (int(p[0]), int(p[1])), (int(q[0]), int(q[1])), (0, 0, 255), 1)
    return canvas


def check_truth(frames_dir: str | Path, recording: str | Path, camera: str, until: time | None = None,
                tz: tzinfo = UTC) -> None:
    """ValueError unless the simulator recording has the camera and ground truth at the capture time of every frame
    in `frames_dir` (before `until`) that autolabel_camera would label with the same `until` and `tz`: what
    score_labels needs, checked before anything is written. The error names the first frame without it."""
    from sim.recording import Recording

    rec = Recording(recording)
    if camera not in rec.cameras:  # parsed: score_labels reads the camera's pose
        raise ValueError(f"truth recording {rec.path} has no camera {camera!r} (has: {', '.join(rec.camera_names)})")
    times = set()
    for n, g in enumerate(rec.ground_truth(camera), 1):
        if not isinstance(g, dict) or not isinstance(g.get("t_ns"), int):
            raise ValueError(f"truth recording {rec.path}: ground truth of {camera}, line {n}: no whole t_ns")
        times.add(g["t_ns"])
    for t_ns, path in list_frames(frames_dir, until, tz):
        if t_ns not in times:
            raise ValueError(f"{path}: the truth recording {rec.path} has no ground truth of {camera} at its capture "
                             f"time ({t_ns} ns): not a recording of these frames")


def score_labels(labels_json: str | Path, recording: str | Path, match_m: float = 1.5,
                 min_visible: float = 0.5) -> dict:
    """How right autolabel was on a simulator recording: labels (not ignored) within `match_m` of a true
    vehicle's ground centre are correct (precision; any vehicle of the frame's ground truth, parked, mostly hidden
    or outside the ROI too, one label each); true vehicles inside the labelled area (within the config's roi_m of
    the camera's foot, at least `min_visible` visible, not parked) that got a label (recall); heading error of the
    labels matched to those that have one (degrees)."""
    from sim.recording import Recording

    labels_json = Path(labels_json)
    doc = json.loads(labels_json.read_text())
    roi_m = doc["info"]["config"]["roi_m"]
    rec = Recording(recording)
    by_ann: dict[int, list[dict]] = {}
    for a in doc["annotations"]:
        by_ann.setdefault(a["image_id"], []).append(a)
    camera = doc["images"][0]["camera"]
    cam = rec.cameras[camera]
    foot = np.asarray(cam.pose.position_m[:2])
    truth = {g["t_ns"]: g for g in rec.ground_truth(camera)}
    n_lab = n_lab_ok = n_true = n_true_found = 0
    yaw_err = []
    for img in doc["images"]:
        if img["t_ns"] not in truth:
            raise ValueError(f"{img.get('source', img['file_name'])}: {rec.path} has no ground truth of {camera} at "
                             f"its capture time ({img['t_ns']} ns)")
        every = truth[img["t_ns"]]["vehicles"]
        gt = [v for v in every
              if v["in_image"] and v["visible_fraction"] >= min_visible and not v.get("parked")
              and np.hypot(*(np.asarray(v["xyz"][:2]) - foot)) <= roi_m]
        labs = [a for a in by_ann.get(img["id"], []) if not a.get("iscrowd")]
        n_lab += len(labs)
        n_true += len(gt)
        if not labs:
            continue
        lab_xy = np.array([a["ground_xy_m"] for a in labs])
        if every:  # precision: a label on any true vehicle is right, one the recall leaves out (parked, hidden) too
            d = np.linalg.norm(lab_xy[:, None] - np.array([v["xyz"][:2] for v in every])[None], axis=2)
            rows, cols = linear_sum_assignment(d)
            n_lab_ok += int((d[rows, cols] <= match_m).sum())
        if not gt:
            continue
        d = np.linalg.norm(lab_xy[:, None] - np.array([v["xyz"][:2] for v in gt])[None], axis=2)
        rows, cols = linear_sum_assignment(d)
        for r, c in zip(rows, cols, strict=True):
            if d[r, c] <= match_m:
                n_true_found += 1
                if "ground_yaw_rad" in labs[r]:
                    e = np.angle(np.exp(1j * (labs[r]["ground_yaw_rad"] - gt[c]["yaw"])))
                    yaw_err.append(abs(math.degrees(e)))
    return {"labels": n_lab, "precision": round(n_lab_ok / max(n_lab, 1), 4), "true_vehicles": n_true,
            "recall": round(n_true_found / max(n_true, 1), 4), "headings": len(yaw_err),
            "yaw_err_median_deg": round(float(np.median(yaw_err)), 2) if yaw_err else None,
            "yaw_err_p90_deg": round(float(np.percentile(yaw_err, 90)), 2) if yaw_err else None}
