"""Calibration on real pinhole data (`../shared/data`), when it is present. Prints one JSON document.

    python -m bench.calibration_real [--data ../shared/data] [--draws 20] [--seed 0]

Rope3D demo (`rope3d_demo/`): the 215 surveyed ground points are the `points_lane_detection`
list of `extrinsics/<frame>.yaml` (x, y, z triples in UTM metres; the same points as its
`points_hdmap_lanes`, lane by lane). The files hold no pixel for them, so each point's pixel is its
projection through the dataset's own calibration: the camera-to-world pose of the same yaml
(`transform`, a quaternion and a translation) and `P2` of `calib/<frame>.txt`. Every point lands
inside the image and within centimetres of the ground plane of `denorm/<frame>.txt`, an independent
check that the pose is read the right way round. Our calibration is fitted on 10 of the points (a
farthest-point sample in the image, and random draws) and scored on the other 205: the mean ground
distance between `pixel_to_xy` of a point's pixel and its surveyed position. The ground there is
not one plane (heights vary by decimetres and the far points are seen at grazing angles), so the
dataset's own camera with the least-squares plane through all 215 heights is scored on the same
held-out points too: what one ground plane can do here, even with the exact camera.

OTVision (`otvision/`): each clip's `.gpkg` holds OTVision's own output, one row per tracked box:
the box (`x`, `y` its centre, `w`, `h` in pixels) and a UTM point geometry. That point is the box
centre mapped by the least-squares homography (OpenCV `findHomography`, all points, no RANSAC) of
the clip's 5 reference points (`.otrfpts`); the benchmark checks this by reproducing every row and
picking, among candidate anchors (centre, bottom centre, top-left), the one that reproduces them.
Our calibration is fitted on the same 5 reference points and applied to the same pixels; the median
distance to OTVision's points is `otvision_median_diff_m`, also split into pixels inside and
outside the reference points' hull (outside, both models extrapolate). The `.otdet` detections
(a separate detector run) are read to report which box anchor their x, y use.

Metric coordinates (UTM) enter `Landmarks` as offsets from their mean, placed in a synthetic ENU
frame (`SYNTHETIC_ORIGIN`) and converted to lat/lon there; `to_local` inverts this exactly, so
distances stay UTM grid metres (within 0.1% of ground metres at these sites).
"""

from __future__ import annotations

import argparse
import bz2
import json
import math
import sqlite3
import struct
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import yaml

from bench import first_paragraph
from calibration.fit import CalibConfig, Calibration, calibrate
from calibration.landmarks import Landmarks, validate_landmarks
from shared.geo import GeoFrame
from shared.jsonio import dumps

SYNTHETIC_ORIGIN = GeoFrame(45.0, 0.0)  # where local metric offsets are placed to become lat/lon
GPKG_ENVELOPE_DOUBLES = {0: 0, 1: 4, 2: 6, 3: 6, 4: 8}  # GeoPackage binary header: envelope code -> doubles
WKB_POINT_TYPES = {1, 1001, 2001, 3001, 0x20000001, 0x40000001, 0x60000001, 0x80000001, 0xA0000001, 0xC0000001}
# Box anchors tried when reproducing OTVision's output: name -> offset from (x, y) in units of (w, h).
OTVISION_ANCHORS = {"box centre (x, y)": (0.0, 0.0), "bottom centre (x, y + h/2)": (0.0, 0.5),
                    "top-left (x - w/2, y - h/2)": (-0.5, -0.5)}


@dataclass(frozen=True)
class RealBenchSettings:
    n_fit: int = 10  # Rope3D: landmarks the calibration is fitted on
    draws: int = 20  # Rope3D: random draws of n_fit landmarks
    seed: int = 0

    def __post_init__(self) -> None:
        if self.n_fit < 4:
            raise ValueError(f"n_fit must be >= 4, got {self.n_fit}")
        if self.draws < 0:
            raise ValueError(f"draws must be >= 0, got {self.draws}")


def default_data_root() -> Path:
    """`../shared/data` beside the repository root."""
    return Path(__file__).resolve().parents[2] / "shared" / "data"


def _landmarks(uv: np.ndarray, xy_local: np.ndarray, ids: list[str] | None = None) -> Landmarks:
    """(N, 2) pixels + (N, 2) local metres (east, north) -> Landmarks in SYNTHETIC_ORIGIN's frame."""
    latlon = SYNTHETIC_ORIGIN.to_geodetic(xy_local)[:, :2]
    ids = ids if ids is not None else [f"p{i:03d}" for i in range(len(uv))]
    return Landmarks(tuple(ids), np.asarray(uv, float), latlon, -np.ones(len(uv), int))


# ---- Rope3D -----------------------------------------------------------------------------------
@dataclass(frozen=True)
class Rope3DFrame:
    """One Rope3D frame: `p2` (3, 4) camera-frame metres -> pixels; camera-to-world pose
    `r_world_from_cam` (3, 3), `t_world_m` (3,) (UTM metres); surveyed `ground_points_m` (N, 3) UTM;
    `denorm` (4,) ground plane a x + b y + c z + d = 0 in camera metres; image size in pixels."""

    name: str
    p2: np.ndarray
    r_world_from_cam: np.ndarray
    t_world_m: np.ndarray
    ground_points_m: np.ndarray
    denorm: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        if self.p2.shape != (3, 4) or self.ground_points_m.ndim != 2 or self.ground_points_m.shape[1] != 3:
            raise ValueError(f"Rope3D frame {self.name}: p2 must be (3, 4) and ground points (N, 3), "
                             f"got {self.p2.shape} and {self.ground_points_m.shape}")

    def to_camera(self, points_m: np.ndarray) -> np.ndarray:
        """(N, 3) UTM metres -> (N, 3) camera metres (x right, y down, z forward)."""
        return (np.asarray(points_m, float) - self.t_world_m) @ self.r_world_from_cam

    def project(self, points_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 3) UTM metres -> ((N, 2) pixels, (N,) in front of the camera and inside the image)."""
        h = np.column_stack([self.to_camera(points_m), np.ones(len(points_m))]) @ self.p2.T
        front = h[:, 2] > 1e-6
        uv = h[:, :2] / np.where(front, h[:, 2], 1.0)[:, None]
        inside = np.all((uv >= -0.5) & (uv <= [self.width - 0.5, self.height - 0.5]), axis=1)
        return uv, front & inside

    def rays(self, uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(N, 2) pixels -> ((3,) ray origin, (N, 3) world directions), UTM metres."""
        k_inv = np.linalg.inv(self.p2[:, :3])
        origin_cam = -k_inv @ self.p2[:, 3]
        d_cam = np.column_stack([uv, np.ones(len(uv))]) @ k_inv.T
        return self.r_world_from_cam @ origin_cam + self.t_world_m, d_cam @ self.r_world_from_cam.T


def _read_bytes(path: Path) -> bytes:
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: missing")
    return path.read_bytes()


def _read_text(path: Path) -> str:
    try:
        return _read_bytes(path).decode()
    except UnicodeDecodeError:
        raise ValueError(f"{path}: not a text file") from None


def _numbers(path: Path, text: str, count: int, what: str) -> np.ndarray:
    try:
        vals = np.array([float(x) for x in text.split()], float)
    except ValueError:
        raise ValueError(f"{path}: {what} must be numbers, got {text.strip()[:80]!r}") from None
    if len(vals) != count or not np.all(np.isfinite(vals)):
        raise ValueError(f"{path}: {what} needs {count} finite numbers, got {len(vals)}: {text.strip()[:80]!r}")
    return vals


def read_rope3d_calib(path: Path) -> np.ndarray:
    """`P2: 12 numbers` (KITTI style) -> (3, 4) projection matrix, camera metres -> pixels."""
    for line in _read_text(path).splitlines():
        key, _, rest = line.partition(":")
        if key.strip() == "P2":
            p2 = _numbers(path, rest, 12, "P2").reshape(3, 4)
            if not (p2[0, 0] > 0 and p2[1, 1] > 0 and p2[2, 2] > 0):
                raise ValueError(f"{path}: P2 focal lengths must be > 0, got {p2[0, 0]}, {p2[1, 1]}")
            return p2
    raise ValueError(f"{path}: no 'P2:' line")


def read_rope3d_denorm(path: Path) -> np.ndarray:
    """`a b c d` -> (4,) ground plane a x + b y + c z + d = 0, camera metres, (a, b, c) unit."""
    plane = _numbers(path, _read_text(path), 4, "the ground plane (a b c d)")
    norm = float(np.linalg.norm(plane[:3]))
    if not 0.9 < norm < 1.1:
        raise ValueError(f"{path}: ground plane normal must have unit length, got {norm:.3f}")
    return plane / norm


def _quat_to_matrix(w: float, x: float, y: float, z: float) -> np.ndarray:
    n = math.sqrt(w * w + x * x + y * y + z * z)
    w, x, y, z = w / n, x / n, y / n, z / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def read_rope3d_extrinsics(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Extrinsics yaml -> (r_world_from_cam (3, 3), t_world_m (3,), ground points (N, 3) UTM metres)."""
    try:
        doc = yaml.safe_load(_read_text(path))
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: not valid YAML: {exc}") from None
    try:
        tr, rot = doc["transform"]["translation"], doc["transform"]["rotation"]
        t = np.array([float(tr[k]) for k in "xyz"])
        q = [float(rot[k]) for k in "wxyz"]
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"{path}: needs transform.translation x, y, z and transform.rotation w, x, y, z") from None
    if not (np.all(np.isfinite(t)) and all(math.isfinite(v) for v in q) and any(q)):
        raise ValueError(f"{path}: transform must be finite with a non-zero quaternion, got {t.tolist()}, {q}")
    raw = doc.get("points_lane_detection") if isinstance(doc, dict) else None
    if not isinstance(raw, list) or not raw:
        raise ValueError(f"{path}: no 'points_lane_detection' list (the surveyed ground points)")
    try:
        flat = np.array([float(v) for v in raw])
    except (TypeError, ValueError):
        raise ValueError(f"{path}: points_lane_detection must hold numbers") from None
    if len(flat) % 3 or not np.all(np.isfinite(flat)):
        raise ValueError(f"{path}: points_lane_detection must be finite x, y, z triples, got {len(flat)} values")
    return _quat_to_matrix(*q), t, flat.reshape(-1, 3)


def _image_size(path: Path) -> tuple[int, int]:
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) if path.is_file() else None
    if img is None:
        raise ValueError(f"{path}: missing or not a readable image (needed for the image size)")
    return int(img.shape[1]), int(img.shape[0])


def load_rope3d(root: Path) -> list[Rope3DFrame]:
    """Every frame listed in `root/demo.txt`, from calib/, denorm/, extrinsics/ and image_2/."""
    root = Path(root)
    listing = root / "demo.txt"
    if not listing.is_file():
        raise ValueError(f"{listing}: missing (the list of frame names)")
    names = [s.strip() for s in listing.read_text().splitlines() if s.strip()]
    if not names:
        raise ValueError(f"{listing}: lists no frame")
    frames = []
    for name in names:
        r, t, pts = read_rope3d_extrinsics(root / "extrinsics" / f"{name}.yaml")
        width, height = _image_size(root / "image_2" / f"{name}.jpg")
        frames.append(Rope3DFrame(name, read_rope3d_calib(root / "calib" / f"{name}.txt"), r, t, pts,
                                  read_rope3d_denorm(root / "denorm" / f"{name}.txt"), width, height))
    return frames


def farthest_point_sample(uv: np.ndarray, k: int, start: int) -> np.ndarray:
    """(N, 2) pixels -> (k,) indices: `start`, then repeatedly the point farthest from those chosen."""
    chosen = [start]
    d = np.linalg.norm(uv - uv[start], axis=1)
    for _ in range(k - 1):
        i = int(np.argmax(d))
        chosen.append(i)
        d = np.minimum(d, np.linalg.norm(uv - uv[i], axis=1))
    return np.array(chosen)


def _lsq_plane_errors(frame: Rope3DFrame, uv: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Ground error (N,) m at `pts` (N, 3) seen at `uv` (N, 2) of the dataset's own camera with the
    least-squares height plane through all its surveyed points."""
    allp = frame.ground_points_m
    centre = allp[:, :2].mean(axis=0)
    (a, b, c), *_ = np.linalg.lstsq(np.column_stack([allp[:, :2] - centre, np.ones(len(allp))]), allp[:, 2], rcond=None)
    c -= a * centre[0] + b * centre[1]
    o, d = frame.rays(uv)
    t = (a * o[0] + b * o[1] + c - o[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    return np.linalg.norm(o[:2] + t[:, None] * d[:, :2] - pts[:, :2], axis=1)


def _score_rope3d(lm: Landmarks, xy: np.ndarray, fit_idx: np.ndarray, cfg: CalibConfig) -> dict:
    rest = np.setdiff1d(np.arange(len(lm)), fit_idx)
    sub = lm.subset(fit_idx)
    try:
        validate_landmarks(sub, cfg.width, cfg.height)
        t0 = time.perf_counter()
        cal = calibrate(sub, cfg, SYNTHETIC_ORIGIN)
        fit_s = time.perf_counter() - t0
    except ValueError as exc:
        return {"failed": str(exc)}
    got, ok = cal.pixel_to_xy(lm.uv[rest])
    err = np.linalg.norm(got - xy[rest], axis=1)
    return {"heldout_mean_m": float(np.mean(err[ok])) if ok.any() else None,
            "heldout_median_m": float(np.median(err[ok])) if ok.any() else None,
            "heldout_p90_m": float(np.percentile(err[ok], 90)) if ok.any() else None,
            "heldout_valid": float(ok.mean()), "n_heldout": int(len(rest)), "rejected": [i for i, _ in cal.rejected],
            "fit_s": fit_s, "focal_px": cal.camera.fx, "camera_height_m": float(cal.camera.pose.position_m[2]),
            "_cal": cal}


def rope3d_benchmark(frame: Rope3DFrame, settings: RealBenchSettings) -> dict:
    """Fit on `settings.n_fit` surveyed points, score on the rest (see the module docstring)."""
    uv, ok = frame.project(frame.ground_points_m)
    pts = frame.ground_points_m[ok]
    uv = uv[ok]
    if len(pts) < settings.n_fit + 1:
        raise ValueError(f"Rope3D frame {frame.name}: {len(pts)} surveyed points in the image, "
                         f"need more than {settings.n_fit}")
    off_plane = np.abs(frame.to_camera(pts) @ frame.denorm[:3] + frame.denorm[3])
    xy = pts[:, :2] - pts[:, :2].mean(axis=0)
    lm = _landmarks(uv, xy)
    cfg = CalibConfig("pinhole", frame.width, frame.height)
    rng = np.random.default_rng(settings.seed)
    fps = farthest_point_sample(uv, settings.n_fit, int(rng.integers(len(uv))))
    best = _score_rope3d(lm, xy, fps, cfg)
    if "failed" in best:
        raise ValueError(f"Rope3D frame {frame.name}: calibration on the farthest-point sample failed: "
                         f"{best['failed']}")
    cal: Calibration = best.pop("_cal")
    rest = np.setdiff1d(np.arange(len(uv)), fps)
    draws = []
    for k in range(settings.draws):
        idx = np.random.default_rng([settings.seed, k]).choice(len(uv), settings.n_fit, replace=False)
        row = _score_rope3d(lm, xy, idx, cfg)
        row.pop("_cal", None)
        draws.append(row)
    means = [r["heldout_mean_m"] for r in draws if r.get("heldout_mean_m") is not None]
    return {
        "frame": frame.name, "image_size": [frame.width, frame.height], "surveyed_points": len(frame.ground_points_m),
        "surveyed_points_in_image": int(ok.sum()), "ground_points_off_denorm_plane_mean_m": float(off_plane.mean()),
        "fit_points": [lm.ids[i] for i in fps], **best,
        "true_camera_lsq_plane_mean_m": float(np.mean(_lsq_plane_errors(frame, uv[rest], pts[rest]))),
        "true_focal_px": [float(frame.p2[0, 0]), float(frame.p2[1, 1])],
        "segments": len(cal.planes),
        "random_draws_mean_m": float(np.mean(means)) if means else None,
        "random_draws_std_m": float(np.std(means)) if means else None,
        "random_draws": draws,
    }


# ---- OTVision ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class OtRefPoints:
    """`ids` (N,), `uv` (N, 2) pixels, `utm` (N, 2) easting/northing metres in UTM `zone` + `hemisphere`."""

    ids: tuple[str, ...]
    uv: np.ndarray
    utm: np.ndarray
    zone: int
    hemisphere: str

    def __post_init__(self) -> None:
        n = len(self.ids)
        if self.uv.shape != (n, 2) or self.utm.shape != (n, 2):
            raise ValueError(f"reference points: {n} ids, uv {self.uv.shape}, utm {self.utm.shape} do not match")


@dataclass(frozen=True)
class OtBoxes:
    """Boxes with a frame number: `frame` (N,) int, `xywh` (N, 4) pixels, `utm` (N, 2) metres or empty (0, 2)."""

    frame: np.ndarray
    xywh: np.ndarray
    utm: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.frame)
        if self.xywh.shape != (n, 4) or self.utm.shape not in ((n, 2), (0, 2)):
            raise ValueError(f"boxes: frame {self.frame.shape}, xywh {self.xywh.shape} and utm {self.utm.shape} "
                             "do not match")


def read_otrfpts(path: Path) -> OtRefPoints:
    """OTVision reference points: `{"1": {"x_px", "y_px", "lon_utm", "lat_utm", "zone_utm", "hemisphere"}}`."""
    try:
        doc = json.loads(_read_text(path))
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or not doc:
        raise ValueError(f"{path}: expected an object of reference points")
    ids, uv, utm, zones = [], [], [], set()
    for key, p in doc.items():
        try:
            vals = [float(p[k]) for k in ("x_px", "y_px", "lon_utm", "lat_utm")]
            zones.add((int(p["zone_utm"]), str(p["hemisphere"]).upper()))
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{path}: reference point {key!r} needs numbers x_px, y_px, lon_utm, lat_utm, "
                             "zone_utm and a hemisphere") from None
        if not all(math.isfinite(v) for v in vals):
            raise ValueError(f"{path}: reference point {key!r} must be finite, got {vals}")
        ids.append(str(key))
        uv.append(vals[:2])
        utm.append(vals[2:])
    if len(zones) != 1:
        raise ValueError(f"{path}: reference points mix UTM zones {sorted(zones)}")
    zone, hemisphere = zones.pop()
    return OtRefPoints(tuple(ids), np.array(uv), np.array(utm), zone, hemisphere)


def read_otdet(path: Path) -> tuple[OtBoxes, dict]:
    """OTVision detections (bz2 or plain JSON) -> (boxes as stored, metadata). Normalized boxes are
    scaled to pixels with the video size."""
    raw = _read_bytes(path)
    try:
        doc = json.loads(bz2.decompress(raw) if raw[:3] == b"BZh" else raw)
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path}: not bz2/plain JSON detections: {exc}") from None
    try:
        meta, data = doc["metadata"], doc["data"]
        width, height = float(meta["video"]["width"]), float(meta["video"]["height"])
        scale = [width, height, width, height] if meta.get("detection", {}).get("normalized_bbox") else [1.0] * 4
        frames, boxes = [], []
        for key, fr in data.items():
            for det in fr["detections"]:
                frames.append(int(key))
                boxes.append([float(det[k]) * s for k, s in zip("xywh", scale, strict=True)])
    except (KeyError, TypeError, ValueError, AttributeError):
        raise ValueError(f"{path}: needs metadata.video width/height and data {{frame: {{detections: "
                         "[{x, y, w, h}]}}}}") from None
    if not (width > 0 and height > 0):
        raise ValueError(f"{path}: video size must be positive, got {width}x{height}")
    return OtBoxes(np.array(frames, int), np.array(boxes, float).reshape(-1, 4), np.zeros((0, 2))), meta


def decode_gpkg_point(blob: bytes) -> tuple[float, float]:
    """GeoPackage binary geometry (header + WKB point) -> (x, y); NaN for an empty point."""
    if len(blob) < 8 or blob[:2] != b"GP":
        raise ValueError("not a GeoPackage geometry (no 'GP' magic)")
    flags = blob[3]
    envelope = (flags >> 1) & 0b111
    if envelope not in GPKG_ENVELOPE_DOUBLES:
        raise ValueError(f"invalid envelope code {envelope}")
    wkb = blob[8 + 8 * GPKG_ENVELOPE_DOUBLES[envelope]:]
    if len(wkb) < 21:
        raise ValueError(f"WKB point too short ({len(wkb)} bytes)")
    order = "<" if wkb[0] == 1 else ">"
    (kind,) = struct.unpack(order + "I", wkb[1:5])
    if kind not in WKB_POINT_TYPES:
        raise ValueError(f"geometry type {kind} is not a point")
    x, y = struct.unpack(order + "dd", wkb[5:21])
    return x, y


def read_gpkg_boxes(path: Path) -> tuple[OtBoxes, int]:
    """OTVision's GeoPackage -> (rows with frame, box x, y, w, h and the point geometry (N, 2)), srs id)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: missing")
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        tables = con.execute("SELECT table_name, column_name, srs_id FROM gpkg_geometry_columns").fetchall()
        if len(tables) != 1:
            raise ValueError(f"{path}: expected one feature table, found {len(tables)}")
        table, column, srs = tables[0]
        q = f'SELECT frame, x, y, w, h, "{column}" FROM "{table}" ORDER BY fid'
        rows = con.execute(q).fetchall()
    except sqlite3.DatabaseError as exc:
        raise ValueError(f"{path}: not an OTVision GeoPackage ({exc})") from None
    finally:
        con.close()
    frames, boxes, pts = [], [], []
    for n, (fr, x, y, w, h, geom) in enumerate(rows, 1):
        try:
            frames.append(int(fr))
            boxes.append([float(x), float(y), float(w), float(h)])
            pts.append(decode_gpkg_point(bytes(geom)))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: row {n} of {table!r}: bad frame, box or geometry ({exc})") from None
    boxes_px = np.array(boxes, float).reshape(-1, 4)
    return OtBoxes(np.array(frames, int), boxes_px, np.array(pts, float).reshape(-1, 2)), srs


def _iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, 4), (M, 4) corner boxes -> (N, M) intersection over union."""
    lo = np.maximum(a[:, None, :2], b[None, :, :2])
    hi = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(hi - lo, 0, None), axis=2)
    area = lambda q: np.prod(q[:, 2:] - q[:, :2], axis=1)  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None, :] - inter, 1e-9)


def otdet_anchor(det: OtBoxes, out: OtBoxes, min_iou: float = 0.7) -> dict:
    """Which anchor the detections' (x, y) use, judged by how many centre-anchored output boxes
    find a detection of the same frame with IoU >= min_iou under each reading."""
    def corners(b: np.ndarray, centre: bool) -> np.ndarray:
        xy = b[:, :2] - (b[:, 2:] / 2 if centre else 0.0)
        return np.column_stack([xy, xy + b[:, 2:]])

    ref = corners(out.xywh, True)
    share = {}
    for name, centre in (("centre", True), ("top_left", False)):
        cand = corners(det.xywh, centre)
        hit = 0
        for f in np.unique(out.frame):
            a, b = ref[out.frame == f], cand[det.frame == f]
            if len(a) and len(b):
                hit += int((_iou(a, b).max(axis=1) >= min_iou).sum())
        share[name] = hit / max(len(ref), 1)
    return {"anchor": max(share, key=share.get), "matched_share": share}


def otvision_benchmark(ref: OtRefPoints, out: OtBoxes, width: int, height: int) -> dict:
    """Reproduce OTVision's output from its reference points, then compare ours on the same pixels."""
    off = ref.utm.mean(axis=0)
    xy_ref = ref.utm - off
    truth = out.utm - off
    h_mat, _ = cv2.findHomography(ref.uv, xy_ref, 0)
    if h_mat is None:
        raise ValueError("OpenCV found no homography for the reference points")
    reproduced = {}
    for name, (du, dv) in OTVISION_ANCHORS.items():
        px = out.xywh[:, :2] + out.xywh[:, 2:] * [du, dv]
        d = np.linalg.norm(cv2.perspectiveTransform(px[None], h_mat)[0] - truth, axis=1)
        reproduced[name] = float(np.median(d))
    anchor = min(reproduced, key=reproduced.get)
    du, dv = OTVISION_ANCHORS[anchor]
    px = out.xywh[:, :2] + out.xywh[:, 2:] * [du, dv]
    lm = _landmarks(ref.uv, xy_ref, list(ref.ids))
    cfg = CalibConfig("pinhole", width, height)
    validate_landmarks(lm, width, height)
    t0 = time.perf_counter()
    cal = calibrate(lm, cfg, SYNTHETIC_ORIGIN)
    fit_s = time.perf_counter() - t0
    got, ok = cal.pixel_to_xy(px)
    diff = np.linalg.norm(got - truth, axis=1)
    hull = cv2.convexHull(ref.uv.astype(np.float32))
    inside = np.array([cv2.pointPolygonTest(hull, (float(u), float(v)), False) >= 0 for u, v in px], bool)
    ref_ours, _ = cal.pixel_to_xy(ref.uv)
    ref_h = cv2.perspectiveTransform(ref.uv[None].astype(float), h_mat)[0]
    bottom = out.xywh[:, :2] + out.xywh[:, 2:] * [du, dv + 0.5]
    got_b, ok_b = cal.pixel_to_xy(bottom)
    diff_b = np.linalg.norm(got_b - cv2.perspectiveTransform(bottom[None], h_mat)[0], axis=1)

    def med(m: np.ndarray) -> float | None:
        return float(np.median(diff[m & ok])) if (m & ok).any() else None

    return {
        "mapped_pixel": anchor, "reproduced_median_m": reproduced,
        "n_boxes": len(px), "valid": float(ok.mean()), "median_diff_m": med(np.ones(len(px), bool)),
        "mean_diff_m": float(np.mean(diff[ok])) if ok.any() else None,
        "p90_diff_m": float(np.percentile(diff[ok], 90)) if ok.any() else None,
        "inside_refpts_hull": int(inside.sum()), "median_diff_inside_hull_m": med(inside),
        "median_diff_outside_hull_m": med(~inside),
        "median_diff_bottom_centre_m": float(np.median(diff_b[ok_b])) if ok_b.any() else None,
        "refpts_residual_ours_m": np.linalg.norm(ref_ours - xy_ref, axis=1).round(4).tolist(),
        "refpts_residual_otvision_m": np.linalg.norm(ref_h - xy_ref, axis=1).round(4).tolist(),
        "fit_s": fit_s, "focal_px": cal.camera.fx, "k1": cal.camera.dist[0],
        "camera_height_m": float(cal.camera.pose.position_m[2]), "rejected": [i for i, _ in cal.rejected],
        "_diff": diff[ok], "_inside": inside[ok],
    }


def _otvision_clips(root: Path) -> list[dict]:
    clips = []
    gpkgs = sorted(Path(root).glob("*.gpkg"))
    if not gpkgs:
        raise ValueError(f"{root}: no .gpkg file")
    for gpkg in gpkgs:
        ref = read_otrfpts(gpkg.with_suffix(".otrfpts"))
        det, meta = read_otdet(gpkg.with_suffix(".otdet"))
        out, srs = read_gpkg_boxes(gpkg)
        width, height = int(meta["video"]["width"]), int(meta["video"]["height"])
        row = otvision_benchmark(ref, out, width, height)
        clips.append({"clip": gpkg.stem, "srs_id": srs, "utm_zone": f"{ref.zone}{ref.hemisphere}",
                      "otdet_version": meta.get("otdet_version"), "otdet_xy": otdet_anchor(det, out), **row})
    return clips


# ---- entry points -------------------------------------------------------------------------------
def _rounded(v):
    if isinstance(v, float):
        return round(v, 4)
    if isinstance(v, dict):
        return {k: _rounded(x) for k, x in v.items() if not k.startswith("_")}
    if isinstance(v, list):
        return [_rounded(x) for x in v]
    return v


def real_data_rows(data_root: Path, settings: RealBenchSettings | None = None) -> dict:
    """Both real-data benchmarks; a `<dataset>_skipped` reason (and None figures) when data is absent."""
    settings = settings or RealBenchSettings()
    data_root = Path(data_root)
    out: dict = {"benchmark": "calibration_real", "data_root": str(data_root), "n_fit": settings.n_fit,
                 "draws": settings.draws, "seed": settings.seed}
    t0 = time.perf_counter()
    rope = data_root / "rope3d_demo"
    out["rope3d_heldout_mean_m"] = out["rope3d_heldout_mean_m_random_draws"] = None
    if rope.is_dir():
        rows = [rope3d_benchmark(f, settings) for f in load_rope3d(rope)]
        out["rope3d_heldout_mean_m"] = float(np.mean([r["heldout_mean_m"] for r in rows]))
        draws = [r["random_draws_mean_m"] for r in rows if r["random_draws_mean_m"] is not None]
        out["rope3d_heldout_mean_m_random_draws"] = float(np.mean(draws)) if draws else None
        out["rope3d_true_camera_lsq_plane_mean_m"] = float(np.mean([r["true_camera_lsq_plane_mean_m"] for r in rows]))
        out["rope3d"] = rows
    else:
        out["rope3d_skipped"] = f"no Rope3D demo at {rope}"
    t1 = time.perf_counter()
    ot = data_root / "otvision"
    out["otvision_median_diff_m"] = None
    if ot.is_dir():
        clips = _otvision_clips(ot)
        out["otvision_median_diff_m"] = float(np.median(np.concatenate([c["_diff"] for c in clips])))
        inside = np.concatenate([c["_diff"][c["_inside"]] for c in clips])
        out["otvision_median_diff_inside_hull_m"] = float(np.median(inside)) if len(inside) else None
        out["otvision"] = clips
    else:
        out["otvision_skipped"] = f"no OTVision data at {ot}"
    t2 = time.perf_counter()
    out["elapsed_s"] = {"rope3d": t1 - t0, "otvision": t2 - t1}
    return _rounded(out)


def main(settings: RealBenchSettings, data_root: Path) -> int:
    print(dumps(real_data_rows(data_root, settings), indent=1))
    return 0


if __name__ == "__main__":
    p = argparse.ArgumentParser(prog="python -m bench.calibration_real", description=first_paragraph(__doc__))
    p.add_argument("--data", type=Path, default=default_data_root(), help="the shared data folder")
    p.add_argument("--n-fit", type=int, default=10)
    p.add_argument("--draws", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    raise SystemExit(main(RealBenchSettings(a.n_fit, a.draws, a.seed), a.data))
