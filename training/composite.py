"""Training images for a real camera from simulated vehicles drawn over its real background: exact labels on
the site's own road surface, markings, kerbs and lamp posts, with no person labelling.

Per camera (one folder of frames, capture time in the file names, and the camera's lookup masks):

1. Background: the per-pixel median of the camera's frames (the training slice only, `until`), at full size.
2. Camera: the calibrated camera model and pose stored in the masks (`meta.camera`, written by `roadside
   calibrate`). Vehicles are projected through it, so a label lands where the vehicle is drawn whatever the
   calibration's error on the real ground.
3. Vehicles, placed one of two ways:
   - `placements` (the real site): a labels file of `roadside autolabel` for the same camera and slice. Each
     image gets 3-10 vehicles at the ground positions and headings of moving vehicles found there (so on the
     real lanes, going the real way), each moved along its heading by up to 5 m and given a type, size and
     colour from the simulator's mix; vehicles that would overlap are not placed. The ground is the
     calibration's plane (z = 0).
   - none: simulator traffic on the simulator site `sim_site`, in the same site frame (the same geodetic
     origin) and on its terrain; right where the simulator site is the camera's own (tests, simulated
     sites). (`sim/sites/state_ellsworth.yaml` shares the real roundabout's origin, but its roads do not
     lie on the real ones.)
   The simulator's renderer draws them through the camera over the real background instead of the simulated
   world: vehicle bodies and their shadows on the ground, occluded only by each other (the real posts and
   trees in front of a vehicle are not known, so vehicles are drawn over them).
4. Labels: the simulator's exact ground truth and label policy (training.data: a vehicle mostly hidden by
   another is an ignore region), type and size included.
5. What the labels may miss: a vehicle standing still through the whole slice is part of the background and
   would be shown unlabelled in every image. With a `teacher` (a detector), its detections on the background
   (score >= `teacher_thr`) become ignore regions of every image.
6. Output: as `roadside autolabel` writes, so `roadside train --coco` reads it: grey images at `scale` with
   everything outside the region of interest (`roi_m` from the camera's foot) set to the background's mean
   grey, and a COCO-style file; vehicles whose bottom centre is outside the region are ignore regions.
"""

from __future__ import annotations

import json
import math
import time as clock
from dataclasses import asdict, dataclass
from datetime import time
from pathlib import Path

import cv2
import numpy as np

from calibration.masks import load_masks
from training.autolabel import COCO_PIXEL_OFFSET, GroundView, background, list_frames, read_frame, teacher_regions
from training.data import recording_labels
from training.sample import VEHICLE_TYPES

ORIGIN_TOL_DEG = 1e-7  # ~1 cm: the masks and the simulator site must share the site frame


@dataclass(frozen=True)
class CompositeConfig:
    sim_site: str = "state_ellsworth"  # simulator site (name or YAML path) in the masks' site frame
    seconds: float = 60.0  # simulated traffic
    hz: float = 1.0  # images per simulated second
    seed: int = 0
    scale: float = 0.5  # output resolution relative to the frames (0.5: the detector's 640 px input)
    roi_m: float = 30.0  # shown pixels and labels within this ground distance of the camera's foot
    weather: str = "clear"  # the simulator's light on the vehicles (sim.render.sample_environment)
    shadow: float = 0.45  # how much a vehicle's shadow darkens the real ground (0: no shadows)
    max_vehicles: int = 100
    demand_scale: float = 1.0
    background_frames: int = 120  # at most this many frames (evenly spread) make the median
    teacher_thr: float = 0.5  # high: a teacher's false alarms (painted words) are what composites correct
    vehicles_per_image: tuple[int, int] = (3, 10)  # with placements: drawn uniformly in this range
    along_m: float = 5.0  # with placements: each vehicle moved along its heading by up to this

    def __post_init__(self) -> None:
        if not 0 < self.scale <= 1:
            raise ValueError(f"scale must be in (0, 1], got {self.scale}")
        for name in ("seconds", "hz", "roi_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value}")
        if self.seconds * self.hz < 1:
            raise ValueError(f"seconds {self.seconds:g} at hz {self.hz:g} is not one image")
        if not 0 <= self.shadow < 1:
            raise ValueError(f"shadow must be in [0, 1), got {self.shadow}")
        if self.seed < 0 or self.max_vehicles < 1 or self.background_frames < 1:
            raise ValueError("seed must be >= 0, max_vehicles >= 1, background_frames >= 1")
        if not 0 < self.teacher_thr <= 1:
            raise ValueError(f"teacher_thr must be in (0, 1], got {self.teacher_thr}")
        lo, hi = self.vehicles_per_image
        if not 1 <= lo <= hi:
            raise ValueError(f"vehicles_per_image must be (low, high) with 1 <= low <= high, got {(lo, hi)}")
        if not (math.isfinite(self.along_m) and self.along_m >= 0):
            raise ValueError(f"along_m must be >= 0, got {self.along_m}")


def load_placements(labels_json: str | Path) -> np.ndarray:
    """(N, 3) x, y (site metres), yaw (rad) of the labelled moving vehicles in a `roadside autolabel` file."""
    path = Path(labels_json)
    if not path.is_file():
        raise ValueError(f"placements file not found: {path}")
    try:
        anns = json.loads(path.read_text())["annotations"]
        rows = [[*a["ground_xy_m"], a["ground_yaw_rad"]] for a in anns
                if "ground_xy_m" in a and "ground_yaw_rad" in a]
    except (json.JSONDecodeError, UnicodeDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not a roadside autolabel labels file ({exc})") from None
    out = np.asarray(rows, np.float64).reshape(-1, 3)
    if not len(out) or not np.isfinite(out).all():
        raise ValueError(f"{path}: no vehicle with a ground position and heading (ground_xy_m, ground_yaw_rad)")
    return out


def _corners(xy: np.ndarray, yaw: float, lw: tuple[float, float]) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    local = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]]) * (np.asarray(lw) / 2)
    return xy + local @ np.array([[c, s], [-s, c]])


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether two convex quadrilaterals (4, 2) overlap (separating axis test)."""
    for poly in (a, b):
        for k in range(4):
            edge = poly[(k + 1) % 4] - poly[k]
            axis = np.array([-edge[1], edge[0]])
            pa, pb = a @ axis, b @ axis
            if pa.max() <= pb.min() or pb.max() <= pa.min():
                return False
    return True


def placed_scene(pool: np.ndarray, rng: np.random.Generator, cfg: CompositeConfig, t_s: float):
    """A SceneState of vehicles at pool positions (moved along their heading), none overlapping another."""
    from sim.traffic import VEHICLE_TYPES as SIM_TYPES
    from sim.traffic import SceneState, sample_vehicle

    want = int(rng.integers(cfg.vehicles_per_image[0], cfg.vehicles_per_image[1] + 1))
    xy, yaw, infos, shapes = [], [], [], []
    for k in rng.permutation(len(pool))[: want * 4]:
        if len(infos) == want:
            break
        info = sample_vehicle(rng, len(infos) + 1)
        a = float(pool[k, 2] + rng.normal(0, 0.05))
        p = pool[k, :2] + rng.uniform(-cfg.along_m, cfg.along_m) * np.array([math.cos(a), math.sin(a)])
        shape = _corners(p, a, (info.length_m + 0.6, info.width_m + 0.4))  # a little room around each
        if any(_overlap(shape, other) for other in shapes):
            continue
        xy.append(p)
        yaw.append(a)
        infos.append(info)
        shapes.append(shape)
    n = len(infos)
    return SceneState(
        t_s=t_s, ids=np.arange(1, n + 1), xy=np.asarray(xy, np.float64).reshape(n, 2),
        yaw=np.asarray(yaw, np.float64),
        lwh=np.array([[i.length_m, i.width_m, i.height_m] for i in infos]).reshape(n, 3),
        speed=np.zeros(n), velocity=np.zeros((n, 2)),
        type_idx=np.array([SIM_TYPES.index(i.type) for i in infos], np.int64),
        colors=np.array([i.color for i in infos], np.uint8).reshape(n, 3), parked=np.zeros(n, bool),
        ped_xy=np.zeros((0, 2)), ped_yaw=np.zeros(0), ped_color=np.zeros((0, 3), np.uint8))


def real_background(frames_dir: str | Path, size: tuple[int, int], until: time | None,
                    max_frames: int) -> tuple[np.ndarray, int]:
    """(H, W, 3) uint8 BGR median of at most `max_frames` frames (evenly spread) before `until`, frames used."""
    listed = list_frames(frames_dir, until)
    pick = np.unique(np.linspace(0, len(listed) - 1, min(max_frames, len(listed))).round().astype(int))
    return background([read_frame(listed[i][1], size) for i in pick]), len(pick)


def _check_same_frame(masks_meta: dict, site, masks_path: Path) -> None:
    geo = masks_meta.get("geo_origin") or {}
    ours = site.geo.to_dict()
    try:
        same = (abs(float(geo["lat_deg"]) - ours["lat_deg"]) < ORIGIN_TOL_DEG
                and abs(float(geo["lon_deg"]) - ours["lon_deg"]) < ORIGIN_TOL_DEG)
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{masks_path}: the masks carry no geodetic origin (meta.geo_origin)") from None
    if not same:
        raise ValueError(f"{masks_path}: site origin {geo['lat_deg']}, {geo['lon_deg']} is not simulator site "
                         f"{site.name!r}'s ({ours['lat_deg']}, {ours['lon_deg']}): composites need one site frame")


def backdrop_renderer(cam, world, env, shadows, bg_bgr: np.ndarray, shadow: float, seed: int):
    """A simulator CameraRenderer for `cam` whose static scene is the real image `bg_bgr`: depth is the
    ground's (no simulated scenery in front of the vehicles), shadows fall on every ground pixel, and the
    sensor adds its blur and noise but no vignetting or tint (the real image has its own)."""
    from sim.render import CameraRenderer

    r = CameraRenderer(cam, world, env, shadows, seed=seed)
    h, w = cam.height, cam.width
    if bg_bgr.shape != (h, w, 3):
        raise ValueError(f"background is {bg_bgr.shape[1]}x{bg_bgr.shape[0]}, camera {cam.name} is {w}x{h}")
    pts, t, hit = world.site.ground.intersect(cam.pose.position_m, r.dirs.reshape(-1, 3),
                                              max_range_m=world.site.extent_m * 3)
    valid = r.valid.reshape(-1)
    ground = hit & valid
    r.background = bg_bgr.astype(np.float32)
    r.depth = np.where(valid, np.where(ground, t, np.inf), 0.0).astype(np.float32).reshape(h, w)
    r.shadow_gain = np.where(ground, np.float32(shadow), np.float32(0.0)).reshape(h, w)
    shadow_map = shadows.to_px(pts[:, :2]).astype(np.float32)
    shadow_map[~ground] = -10.0
    r.shadow_map = shadow_map.reshape(h, w, 2)
    r.gain = np.where(r.valid[..., None], 1.0, 0.0).astype(np.float32)
    r.offset = np.zeros_like(r.gain)
    return r


def composite_camera(frames_dir: str | Path, masks_path: str | Path, out_dir: str | Path, camera: str,
                     until: time | None = None, cfg: CompositeConfig | None = None, log=print,
                     teacher=None, placements: str | Path | None = None) -> dict:
    """Write `out_dir`/images/*.png and `out_dir`/labels.json (COCO-style) for one camera; returns the report
    (also in `out_dir`/report.json). `teacher`: a detector (grey image -> detections with score, uv, box)
    whose detections on the background become ignore regions (module doc, step 5); None: no teacher.
    `placements`: a `roadside autolabel` labels file of this camera (module doc, step 3)."""
    from shared.cameras import Camera
    from sim.groundtruth import frame_ground_truth
    from sim.render import ShadowCaster, build_world, sample_environment
    from sim.site import load_site
    from sim.traffic import simulate_traffic

    cfg = cfg or CompositeConfig()
    wall0 = clock.perf_counter()
    masks_path = Path(masks_path)
    masks = load_masks(masks_path)
    if not isinstance(masks.meta.get("camera"), dict) or "fx" not in masks.meta["camera"]:
        raise ValueError(f"{masks_path}: the masks carry no camera model (meta.camera): build them with "
                         f"roadside calibrate")
    cam = Camera.from_dict({**masks.meta["camera"], "name": camera})
    if (cam.width, cam.height) != (masks.shape[1], masks.shape[0]):
        raise ValueError(f"{masks_path}: camera model is {cam.width}x{cam.height}, masks "
                         f"{masks.shape[1]}x{masks.shape[0]}")
    pool = load_placements(placements) if placements is not None else None
    site = load_site(cfg.sim_site)
    _check_same_frame(masks.meta, site, masks_path)
    if pool is not None:  # the calibration's ground plane, not the simulator site's terrain
        site = site.model_copy(update={"terrain": {}})
    view = GroundView(masks, cfg.scale, cfg.roi_m)
    ws, hs = view.valid.shape[1], view.valid.shape[0]
    bg, n_bg = real_background(frames_dir, view.size, until, cfg.background_frames)

    world = build_world(site)
    env = sample_environment(np.random.default_rng([cfg.seed, 31]), cfg.weather)
    hz = cfg.hz
    times = np.arange(int(math.floor(cfg.seconds * hz + 1e-9))) / hz
    history = None
    if pool is None:
        history = simulate_traffic(site, world.net, cfg.seconds + 1.0 / hz, cfg.seed,
                                   max_vehicles=cfg.max_vehicles, demand_scale=cfg.demand_scale)
    shadows = ShadowCaster(world, env)
    renderer = backdrop_renderer(cam, world, env, shadows, bg, cfg.shadow, seed=cfg.seed)

    bg_small = cv2.resize(cv2.cvtColor(bg, cv2.COLOR_BGR2GRAY), (ws, hs), interpolation=cv2.INTER_AREA)
    fill = np.uint8(round(float(bg_small[view.roi].mean()))) if view.roi.any() else np.uint8(128)
    ignore_boxes = []
    if teacher is not None:  # the background is one frame for autolabel's teacher step
        bg_at_scale = cv2.resize(bg, (ws, hs), interpolation=cv2.INTER_AREA)
        ignore_boxes = [box for _, box in teacher_regions([bg_at_scale], view, teacher, cfg)[0]]

    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    s, o = cfg.scale, COCO_PIXEL_OFFSET
    images, annotations = [], []
    n = {"vehicles": 0, "ignored_hidden": 0, "ignored_outside_roi": 0, "ignored_teacher": 0}
    for i, t in enumerate(times):
        if history is None:
            scene = placed_scene(pool, np.random.default_rng([cfg.seed, 37, i]), cfg, float(t))
        else:
            scene = history.state_at(float(t))
        res = renderer.render(scene, np.random.default_rng([cfg.seed, 29, i]))
        vehicles = frame_ground_truth(cam, scene, res, site.ground, site.geo)
        labels, _, _ = recording_labels(vehicles, f"{camera} composite frame {i}")
        grey = cv2.resize(cv2.cvtColor(res.image, cv2.COLOR_BGR2GRAY), (ws, hs), interpolation=cv2.INTER_AREA)
        shown = np.where(view.roi, grey, fill).astype(np.uint8)
        name = f"images/{camera}_{i:05d}.png"
        if not cv2.imwrite(str(out_dir / name), shown):
            raise ValueError(f"cannot write {out_dir / name}")
        images.append({"id": i, "file_name": name, "width": ws, "height": hs, "camera": camera, "kind": cam.kind,
                       "t_ns": int(round(t * 1e9)),
                       "principal_point": [c + o for c in view.principal_point]})
        for k in range(len(labels["weight"])):
            # COCO coordinates (pixel centres at +0.5) scale as they are: COCO = (q + 0.5) * scale
            coco_uv = (labels["bottom_uv"][k] + o) * s
            x1, y1, x2, y2 = (labels["box"][k] + o) * s
            ann = {"id": len(annotations), "image_id": i, "category_id": int(labels["vtype"][k]) + 1,
                   "bbox": [round(float(x1), 2), round(float(y1), 2), round(float(x2 - x1), 2),
                            round(float(y2 - y1), 2)]}
            u, v = int(round(coco_uv[0] - o)), int(round(coco_uv[1] - o))
            inside = 0 <= u < ws and 0 <= v < hs and bool(view.roi[v, u])
            if labels["weight"][k] <= 0 or not inside:
                ann["iscrowd"] = 1
                n["ignored_hidden" if inside else "ignored_outside_roi"] += 1
            else:
                ann["bottom_center"] = [round(float(c), 3) for c in coco_uv]
                if np.isfinite(labels["heading_uv"][k]).all():
                    ann["heading_uv"] = [round(float(c), 6) for c in labels["heading_uv"][k]]
                ann["lwh"] = [round(float(c), 3) for c in labels["size_lwh"][k]]
                n["vehicles"] += 1
            annotations.append(ann)
        for box in ignore_boxes:
            x1, y1, x2, y2 = (c + o for c in box)
            annotations.append({"id": len(annotations), "image_id": i, "category_id": 0, "iscrowd": 1,
                                "bbox": [x1, y1, x2 - x1, y2 - y1]})
            n["ignored_teacher"] += 1
    categories = [{"id": 0, "name": "vehicle"}] + [{"id": k + 1, "name": v} for k, v in enumerate(VEHICLE_TYPES)]
    doc = {"info": {"description": f"roadside composite of {camera}: simulated vehicles over {frames_dir}",
                    "config": asdict(cfg), "environment": env.to_dict(),
                    "placements": None if placements is None else str(placements)},
           "images": images, "annotations": annotations, "categories": categories}
    (out_dir / "labels.json").write_text(json.dumps(doc))
    report = {"camera": camera, "images": len(images), "background_frames": n_bg,
              "placements": None if pool is None else len(pool), **n,
              "teacher_regions": len(ignore_boxes), "wall_s": round(clock.perf_counter() - wall0, 1)}
    (out_dir / "report.json").write_text(json.dumps(report, indent=1))
    if log:
        log(f"[composite] {camera}: {json.dumps(report)}")
    return report
