"""Detector scored on real frames against hand labels of the vehicles' bottom centres.

Labels: one JSON file per camera, `{"camera": "NE", "frames": {"<frame file name>": [[u, v], ...]}}`, the
bottom centre (the middle of the vehicle's ground footprint) of every vehicle within LABEL_RADIUS_M of the
camera's foot, in full-resolution pixels (pixel-centre convention, as the landmark files). Only frames
from the held-out slice may be labelled (`held_out_from`, a time of day).

Scoring, per camera and overall: detections and labels are lifted to the ground through the camera's
lookup masks and matched one to one (Hungarian on ground distance) within MATCH_M. A label within ROI_M of
the camera's foot is found or missed (recall); a detection within ROI_M is right when it matches a label
(precision). Vehicles between ROI_M and LABEL_RADIUS_M are labelled so that a detection just inside ROI_M
of a vehicle just outside is neither a false alarm nor a hit.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from datetime import UTC, datetime, time, tzinfo
from pathlib import Path

import cv2
import numpy as np
from scipy.optimize import linear_sum_assignment

from calibration.masks import LookupMasks, excluded, load_masks
from services.ingest.sources import capture_time_from_name
from services.localize.lift import footprint_rule, lift
from shared.decode import Detections
from shared.files import visible_files
from shared.geo import GeoFrame
from shared.settings import LocalizeSettings

ROI_M = 25.0
LABEL_RADIUS_M = 30.0
MATCH_M = 1.5


def camera_foot(masks: LookupMasks) -> np.ndarray:
    return masks.camera_position_m()[:2]


def ground_distance(masks: LookupMasks) -> np.ndarray:
    """(H, W) metres from each pixel's ground point to the camera's foot (inf where not calibrated)."""
    d = np.hypot(*(masks.xy.astype(np.float64) - camera_foot(masks)).transpose(2, 0, 1))
    return np.where(masks.valid, d, np.inf)


def load_labels(path: str | Path, width: int, height: int, held_out_from: time | None = None) -> dict:
    """{frame name: (N, 2) float64 pixels} from a label file; ValueError naming the file, frame and label."""
    path = Path(path)
    def unique_keys(pairs: list) -> dict:
        keys = [k for k, _ in pairs]
        if twice := sorted({k for k in keys if keys.count(k) > 1}):
            raise ValueError(f"{path}: {twice[0]!r} is given twice (the second would replace the first)")
        return dict(pairs)

    try:
        doc = json.loads(path.read_text(), object_pairs_hook=unique_keys)
    except (FileNotFoundError, IsADirectoryError):
        raise ValueError(f"label file not found: {path}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), dict):
        raise ValueError(f"{path}: expected {{\"camera\": ..., \"frames\": {{name: [[u, v], ...]}}}}")
    out = {}
    for name, points in doc["frames"].items():
        if not isinstance(points, list) or not all(
                isinstance(p, list) and len(p) == 2 and all(isinstance(c, int | float) and not isinstance(c, bool)
                                                            for c in p) for p in points):
            raise ValueError(f"{path}: frame {name!r}: labels must be a list of [u, v] pixel pairs, got "
                             f"{json.dumps(points)[:80]}")
        t = capture_time_from_name(name)
        if t is None:
            raise ValueError(f"{path}: frame {name!r} has no capture time in its name")
        if held_out_from is not None and datetime.fromtimestamp(t / 1e9, UTC).time() < held_out_from:
            raise ValueError(f"{path}: frame {name!r} is before {held_out_from}: only held-out frames may be labelled")
        arr = np.asarray(points, np.float64).reshape(-1, 2) if len(points) else np.zeros((0, 2))
        for k, (u, v) in enumerate(arr):
            if not (np.isfinite(u) and np.isfinite(v) and -0.5 <= u <= width - 0.5 and -0.5 <= v <= height - 0.5):
                raise ValueError(f"{path}: frame {name!r} label {k} ({u}, {v}) is outside the {width}x{height} image")
        out[name] = arr
    return out


def label_sheet(image: np.ndarray, masks: LookupMasks, zoom: int = 2, marks: np.ndarray | None = None) -> np.ndarray:
    """The part of `image` within LABEL_RADIUS_M of the camera, zoomed, with a pixel grid labelled in
    full-resolution pixels and the ROI_M (green) and LABEL_RADIUS_M (yellow) circles; `marks` (N, 2) are
    drawn as red crosses (to check labels)."""
    dist = ground_distance(masks)
    inside = dist <= LABEL_RADIUS_M
    ys, xs = np.nonzero(inside)
    if not len(xs):
        raise ValueError(f"no calibrated pixel lies within {LABEL_RADIUS_M} m of the camera")
    x0, y0 = max(0, xs.min() - 10), max(0, ys.min() - 10)
    x1, y1 = min(image.shape[1], xs.max() + 11), min(image.shape[0], ys.max() + 11)
    crop = image[y0:y1, x0:x1]
    if crop.ndim == 2:
        crop = cv2.cvtColor(crop, cv2.COLOR_GRAY2BGR)
    out = cv2.resize(crop, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    for radius, colour in ((ROI_M, (0, 200, 0)), (LABEL_RADIUS_M, (0, 220, 220))):
        ring = (dist[y0:y1, x0:x1] <= radius).astype(np.uint8)
        ring = cv2.resize(ring, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
        contours, _ = cv2.findContours(ring, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        cv2.drawContours(out, contours, -1, colour, 1)
    _grid_every(out, x0, y0, zoom, step=50)
    for u, v in ([] if marks is None else marks):
        p = (int(round((u - x0 + 0.5) * zoom)), int(round((v - y0 + 0.5) * zoom)))
        cv2.drawMarker(out, p, (0, 0, 255), cv2.MARKER_CROSS, 4 * zoom, 1)
    return out


def _grid_every(out: np.ndarray, x0: int, y0: int, zoom: int, step: int) -> None:
    """Grid lines through the centres of pixels whose coordinate is a multiple of `step`, blended at 40 %
    so the vehicles stay visible, labelled along the top and left edges."""
    lines = np.zeros(out.shape[:2], bool)
    h, w = out.shape[0] // zoom, out.shape[1] // zoom
    xs = [k for k in range(w) if (x0 + k) % step == 0]
    ys = [k for k in range(h) if (y0 + k) % step == 0]
    for k in xs:
        lines[:, int((k + 0.5) * zoom)] = True
    for k in ys:
        lines[int((k + 0.5) * zoom), :] = True
    out[lines] = (0.6 * out[lines] + 0.4 * np.array([255, 160, 0])).astype(np.uint8)
    for k in xs:
        cv2.putText(out, str(x0 + k), (int((k + 0.5) * zoom) + 2, 12), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 0), 1, cv2.LINE_AA)
    for k in ys:
        cv2.putText(out, str(y0 + k), (2, int((k + 0.5) * zoom) - 3), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
                    (255, 255, 0), 1, cv2.LINE_AA)


def _label_ground(masks: LookupMasks, labels: np.ndarray, where: object) -> np.ndarray:
    """Labels (N, 2) px -> (N, 2) ground metres in the masks' frame; ValueError for one outside the masks."""
    _, l_xy, l_ok = masks.lookup(labels)
    if not l_ok.all():
        raise ValueError(f"{where}: label {int(np.argmin(l_ok))} is outside the calibrated area")
    return l_xy


def score_camera(frames: dict[str, np.ndarray], footage: Path, masks: LookupMasks,
                 detect: Callable[[np.ndarray], Detections], thresholds: tuple[float, ...] = (0.0,),
                 exclude_px: list | None = None, area_px: tuple[int, int, int, int] | None = None,
                 localize: LocalizeSettings | None = None) -> list[dict]:
    """Counts for one camera at each score threshold (detections below it left out): tp, detections
    (within ROI_M), labels (within ROI_M), and matched errors. The detector runs once per frame.
    `exclude_px`: the camera's exclusion polygons; detections there are dropped (labels there still count).
    `area_px`: the camera's `detect_area_px`, run as `detect(grey, area_px=...)` as the detect service does.
    `localize`: the site's localize settings; the detections are lifted and those inside a higher-scoring one's
    ground footprint dropped (or merged into it) as localize does, for the detections at each threshold.
    Default: localize's lift without the footprint rule."""
    loc = localize or LocalizeSettings(footprint_overlap=0.0)
    foot = camera_foot(masks)
    det_masks = replace(masks, valid=excluded(masks.valid, exclude_px)) if exclude_px else masks
    acc = [{"tp": 0, "n_det": 0, "n_lab": 0, "errors": []} for _ in thresholds]
    for name, labels in sorted(frames.items()):
        path = footage / name
        grey = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise ValueError(f"{path}: labelled frame is missing or unreadable")
        det = detect(grey) if area_px is None else detect(grey, area_px=area_px)
        l_xy = _label_ground(masks, labels, path)
        lifted = lift(det_masks, det.uv, det.heading_uv, loc.heading_step_px)
        score, size = np.asarray(det.score), np.asarray(det.size_lwh, np.float64).reshape(-1, 3)
        for a, thr in zip(acc, thresholds, strict=True):
            # what localize publishes when detect keeps what scores thr or more (the merge depends on that)
            k = np.flatnonzero(lifted.valid & (score >= thr))
            kept, xy, _ = footprint_rule(lifted.xy[k], lifted.yaw[k], size[k], score[k], loc.footprint_overlap,
                                         loc.footprint_merge)
            _count(a, xy[kept], l_xy, foot)
    return [_scores(a, len(frames)) for a in acc]


def _count(acc: dict, d_xy: np.ndarray, l_xy: np.ndarray, foot: np.ndarray, d_cov: np.ndarray | None = None) -> None:
    """Add one frame's counts to `acc` (tp, n_det, n_lab, errors): detections d_xy and labels l_xy in site
    metres, matched one to one within MATCH_M; only those within ROI_M of the camera's foot count. With d_cov (the
    detections' or tracks' position covariances, (N, 2, 2)), each true positive's squared Mahalanobis distance from
    its label goes to acc["nees"]."""
    l_in = np.hypot(*(l_xy - foot).T) <= ROI_M
    d_in = np.hypot(*(d_xy - foot).T) <= ROI_M
    acc["n_det"] += int(d_in.sum())
    acc["n_lab"] += int(l_in.sum())
    if len(d_xy) and len(l_xy):
        cost = np.linalg.norm(d_xy[:, None] - l_xy[None], axis=2)
        rows, cols = linear_sum_assignment(np.where(cost <= MATCH_M, cost, 1e6))
        for r, c in zip(rows, cols, strict=True):
            if cost[r, c] > MATCH_M:
                continue
            if l_in[c]:
                acc["tp"] += 1
                acc["n_det"] += int(not d_in[r])  # a hit on a vehicle inside from just outside: a detection too
                acc["errors"].append(cost[r, c])
                if d_cov is not None and np.isfinite(d_cov[r]).all():
                    e = d_xy[r] - l_xy[c]
                    acc.setdefault("nees", []).append(float(e @ np.linalg.solve(d_cov[r], e)))
            elif d_in[r]:
                acc["n_det"] -= 1  # a hit on a vehicle just outside the ROI is not a false alarm


def _scores(acc: dict, frames: int) -> dict:
    tp, n_det, n_lab, errors = acc["tp"], acc["n_det"], acc["n_lab"], acc["errors"]
    return {"frames": frames, "labels": n_lab, "detections": n_det, "true_positives": tp,
            "precision": round(tp / n_det, 4) if n_det else None, "recall": round(tp / n_lab, 4) if n_lab else None,
            "loc_err_median_m": round(float(np.median(errors)), 3) if errors else None}


def _overall(per: dict[str, dict]) -> dict:
    tot = {k: sum(p[k] for p in per.values()) for k in ("frames", "labels", "detections", "true_positives")}
    return {**tot, "precision": round(tot["true_positives"] / tot["detections"], 4) if tot["detections"] else None,
            "recall": round(tot["true_positives"] / tot["labels"], 4) if tot["labels"] else None}


def evaluate_real(labels_dir: str | Path, footage: str | Path, masks_dir: str | Path,
                  detect: Callable[[np.ndarray], Detections], held_out_from: time | None = time(11, 0, 40),
                  folder_pattern: str = "gs_State_Ellsworth_{camera}", score_thr: float = 0.0,
                  curve: tuple[float, ...] = (), exclude_px: dict[str, list] | None = None,
                  detect_area_px: dict[str, tuple[int, int, int, int]] | None = None,
                  localize: LocalizeSettings | None = None) -> dict:
    """Per camera and overall precision / recall within ROI_M for every `labels_dir`/*.json, for the
    detections scoring at least `score_thr`; `curve`: overall precision / recall at these thresholds too
    (a model's whole trade-off, from the same detector pass; `detect` must keep scores that low).
    `exclude_px`: per camera, the site's exclusion polygons (`cameras[].exclude_px`): detections there are
    dropped as localize drops them. `detect_area_px`: per camera, the site's `cameras[].detect_area_px`.
    `localize`: the site's localize settings (`score_camera`)."""
    labels_dir, footage, masks_dir = Path(labels_dir), Path(footage), Path(masks_dir)
    files = visible_files(labels_dir, "*.json")
    if not files:
        raise ValueError(f"no label files in {labels_dir}")
    if not footage.is_dir():
        raise ValueError(f"footage folder not found: {footage}")
    thresholds = (score_thr, *curve)
    per_thr: list[dict] = [{} for _ in thresholds]
    for f in files:
        camera = f.stem
        masks = load_masks(masks_dir / f"{camera}.npz")
        h, w = masks.shape
        frames = load_labels(f, w, h, held_out_from)
        rows = score_camera(frames, footage / folder_pattern.format(camera=camera), masks, detect, thresholds,
                            (exclude_px or {}).get(camera), (detect_area_px or {}).get(camera), localize)
        for acc, row in zip(per_thr, rows, strict=True):
            acc[camera] = row
    out = {"roi_m": ROI_M, "match_m": MATCH_M, "score_thr": score_thr, "overall": _overall(per_thr[0]),
           "per_camera": per_thr[0]}
    if curve:
        out["curve"] = [{"score_thr": t, **{k: v for k, v in _overall(p).items() if k != "frames"}}
                        for t, p in zip(curve, per_thr[1:], strict=True)]
    return out


def tracks_at(lines: list, t_ns: int, max_gap_ns: int) -> tuple[np.ndarray, np.ndarray] | None:
    """Track positions (M, 2) at capture time t_ns from tracks lines sorted by time (eval.tracking.TrackLine),
    and their position covariances (M, 2, 2; NaN where the tracks carry none): interpolated between the two lines
    around t_ns, a track in only one of them taken from it when it is the nearer one; None when no line lies within
    max_gap_ns of t_ns."""
    times = [ln.t_ns for ln in lines]
    i = int(np.searchsorted(times, t_ns))
    near = [lines[j] for j in (i - 1, i) if 0 <= j < len(lines) and abs(times[j] - t_ns) <= max_gap_ns]
    if not near:
        return None

    def rows(line) -> dict:  # track identity -> position and covariance (6 values)
        return dict(zip(line.keys(), np.hstack([line.xy.reshape(-1, 2), line.cov.reshape(-1, 4)]), strict=True))

    if len(near) == 1 or near[1].t_ns == near[0].t_ns:
        out = list(rows(near[0]).values())
    else:
        a, b = near
        w = (t_ns - a.t_ns) / (b.t_ns - a.t_ns)
        pa, pb = rows(a), rows(b)
        out = [(1 - w) * pa[k] + w * pb[k] if k in pb else pa[k] for k in pa if k in pb or w <= 0.5]
        out += [pb[k] for k in pb if k not in pa and w > 0.5]
    both = np.array(out, np.float64).reshape(-1, 6)
    return both[:, :2], both[:, 2:].reshape(-1, 2, 2)


def evaluate_tracks_real(labels_dir: str | Path, tracks: str | Path, masks_dir: str | Path,
                         site_geo: GeoFrame | None = None, held_out_from: time | None = time(11, 0, 40),
                         max_gap_ms: float = 250.0, tz: tzinfo = UTC) -> dict:
    """The pipeline's tracks (a tracks file of the recorded footage played through it) scored against the hand
    labels like detections (`evaluate_real`): at each labelled frame's capture time the tracks, interpolated
    between the ticks around it, are matched to that camera's labels within MATCH_M, within ROI_M of its
    foot. Frames with no tracks line within `max_gap_ms` are counted apart (`frames_without_tracks`), not
    scored. `site_geo`: the tracks' site frame when it differs from the masks' own. `tz`: the time zone of the
    frames' names, as ingest read them (`ingest.timezone`)."""
    from eval.tracking import covariance_measure, load_tracks

    labels_dir, masks_dir = Path(labels_dir), Path(masks_dir)
    files = visible_files(labels_dir, "*.json")
    if not files:
        raise ValueError(f"no label files in {labels_dir}")
    lines = sorted(load_tracks(tracks), key=lambda ln: ln.t_ns)
    if not lines:
        raise ValueError(f"{tracks}: no tracks lines")
    per, missing, nees = {}, 0, []
    for f in files:
        masks = load_masks(masks_dir / f"{f.stem}.npz")
        to_site = site_geo is not None and site_geo != masks.geo
        foot = masks.geo.reframe(camera_foot(masks), site_geo)[0] if to_site else camera_foot(masks)
        acc = {"tp": 0, "n_det": 0, "n_lab": 0, "errors": [], "nees": []}
        frames = load_labels(f, masks.shape[1], masks.shape[0], held_out_from)
        scored = 0
        for name, labels in sorted(frames.items()):
            at = tracks_at(lines, capture_time_from_name(name, tz), round(max_gap_ms * 1e6))
            if at is None:
                missing += 1
                continue
            l_xy = _label_ground(masks, labels, f"{f}: {name}")
            l_xy = masks.geo.reframe(l_xy, site_geo) if to_site else l_xy
            _count(acc, at[0], l_xy, foot, at[1])
            scored += 1
        per[f.stem] = _scores(acc, scored)
        nees.extend(acc["nees"])
    if not any(p["frames"] for p in per.values()):
        def when(t_ns: int) -> str:
            return datetime.fromtimestamp(t_ns / 1e9, UTC).isoformat(timespec="seconds")

        raise ValueError(f"{tracks}: no tracks within {max_gap_ms:g} ms of any labelled frame ({missing} frames): the "
                         f"tracks run {when(lines[0].t_ns)} to {when(lines[-1].t_ns)} UTC; are they the real site's "
                         "held-out footage played through the pipeline?")
    return {"roi_m": ROI_M, "match_m": MATCH_M, "tracks_file": str(tracks), "frames_without_tracks": missing,
            "overall": _overall(per), "per_camera": per,
            # the tracks' own position uncertainty (xy_cov) against the hand labels (eval.tracking's pos_cov_*; the
            # labels' own error, a click on the frame lifted to the ground, counts as the tracks')
            **covariance_measure(np.array(nees))}
