"""Detector accuracy on a simulator recording, per camera kind and overall.

- `ap50`: VOC07 average precision (11-point interpolation) at IoU 0.5 on 2D boxes, the detections matched to the
  boxes as COCO's evaluation matches them (`match_frame`: a detection whose best box is taken may take the next
  free one it overlaps by 0.5; VOC would count it a duplicate). Ground truth follows
  the training label policy (`training.data.vehicle_weight`): positives must be found; a detection on
  an "ignore" vehicle (tiny, mostly hidden) is neither a hit nor a false alarm (VOC's "difficult").
- For the detections matched to a positive (IoU >= 0.5): `loc_err_m`, the ground distance between the
  detected bottom centre lifted to the ground through the recording's exact pixel -> ground lookup and
  the true bottom centre; `yaw_err_deg`, the angle between the true heading and the detected image-space
  heading carried to the ground (the bottom centre and a point a few pixels along the heading, both
  lifted; full circle, so a reversed heading is 180 deg; `yaw_axis_err_deg`: the same modulo 180 deg, the
  error of the heading's axis alone); `size_err_m`, the mean absolute length, width
  and height difference (`size_err_l2_m`: the norm of the 3D difference); `type_acc`.
- Where the AP goes, at the detect service's default score threshold (`BREAKDOWN_SCORE`):
  `false_alarms`, the detections that count and match nothing, split into `box` (on a vehicle to detect
  that nothing matched: found, but its 2D box misses IoU 0.5), `duplicate` (on a vehicle already matched)
  and `background` (on none); `recall_by_size`, per size band of the vehicles to detect (the square root of the
  2D box's area, original pixels), the share matched at IoU 0.5 (`matched`) and the share with a detection
  whose bottom centre is within a third of that size (`found`, whatever its box). A detection is "on" a vehicle
  by that same test alone (bottom centre within a third of the vehicle's size, at least 2 px), never by how
  its box overlaps the vehicle's: a box that overlaps the next car in a row does not find that car. So a
  vehicle matched by a detection whose bottom centre lies farther off is matched but not found.
- Near the camera, on the ground, as fusion uses a camera (each keeps the objects of its own region, around its
  pole): the vehicles to detect within `near_m` (default 25 m) of the camera's ground point, and the detections
  scoring at least `near_score` (default `BREAKDOWN_SCORE`) whose bottom centre lifts to within it. A detection
  and a vehicle match within `NEAR_GATE_M` on the ground (Hungarian, over all the frame's vehicles);
  `near_recall` is the share of those vehicles matched, `near_precision` the share of those detections matched
  to a vehicle to detect (one matched to an "ignore" vehicle counts neither way), `near_f1` the two's harmonic
  mean, `near_loc_err_m` the matched vehicles' ground distance; `near_by_type`, per vehicle type (the label's),
  `positives`, `recall` and `loc_err_median_m` (a 12 m bus's bottom centre is where the detector fails most: it
  puts the point at one end). Whole-image ap50 can rank models the other way
  round: a run that found twice as many small, far vehicles lost the near ones and tracked far worse
  (`models/README.md`).
"""

from __future__ import annotations

import itertools
import math
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from shared.decode import Detections
from shared.ground import ground_lookup
from shared.messages import VEHICLE_TYPES
from shared.raster import bilinear, bilinear_cells
from sim.recording import Recording
from training.data import samples_from_recording

IOU_MATCH = 0.5
BREAKDOWN_SCORE = 0.3  # the detect service's default threshold
SIZE_BANDS_PX = (0.0, 20.0, 45.0, math.inf)  # sqrt of the 2D box area, original pixels
NEAR_FRACTION = 1 / 3  # a detection "on" a vehicle: bottom centre within this share of its size
HEADING_STEP_PX = 6.0  # pixels along the detected heading for the second lifted point
NEAR_M = 25.0  # the paper's ROI radius around a camera
NEAR_GATE_M = 1.5  # ground distance for a detection to be on a vehicle (the tracking evaluation's gate)


def box_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(N, M) IoU of boxes x1, y1, x2, y2 (edges)."""
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod(np.clip(rb - lt, 0, None), axis=2)
    area = lambda x: np.prod(np.clip(x[:, 2:] - x[:, :2], 0, None), axis=1)  # noqa: E731
    return inter / np.maximum(area(a)[:, None] + area(b)[None, :] - inter, 1e-9)


def voc07_ap(scores: np.ndarray, hits: np.ndarray, n_pos: int) -> float:
    """11-point interpolated average precision (PASCAL VOC 2007)."""
    if n_pos == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(hits[order])
    fp = np.cumsum(~hits[order])
    recall = tp / n_pos
    precision = tp / np.maximum(tp + fp, 1)
    ap = 0.0
    for t in np.linspace(0, 1, 11):
        p = precision[recall >= t]
        ap += (p.max() if len(p) else 0.0) / 11
    return float(ap)


def match_frame(det: Detections, box: np.ndarray, weight: np.ndarray,
                min_iou: float = IOU_MATCH) -> tuple[np.ndarray, np.ndarray]:
    """Greedy matching by score, as COCO's evaluation matches (not VOC's): each detection, highest score first, takes
    the positive it overlaps most among those still free, by `min_iou` or more; a detection that matches no free
    positive but overlaps an ignore vehicle by `min_iou` does not count. Per detection: its matched positive
    (index, -1 none) and whether it counts at all."""
    gt_of = -np.ones(len(det), int)
    counts = np.ones(len(det), bool)
    if len(det) == 0 or len(box) == 0:
        return gt_of, counts
    iou = box_iou(det.box, box)
    taken = np.zeros(len(box), bool)
    for i in np.argsort(-det.score, kind="stable"):
        pos = (weight > 0) & ~taken
        cand = np.where(pos, iou[i], -1.0)
        j = int(np.argmax(cand))
        if cand[j] >= min_iou:
            gt_of[i], taken[j] = j, True
        elif (iou[i][weight == 0] >= min_iou).any():
            counts[i] = False
    return gt_of, counts


class GroundLifter:
    """Bilinear lookup into a camera's exact pixel -> ground map."""

    def __init__(self, xyz: np.ndarray, valid: np.ndarray) -> None:
        self.xyz = np.where(valid[..., None], xyz, np.nan)

    def __call__(self, uv: np.ndarray) -> np.ndarray:
        cells = bilinear_cells(uv, *self.xyz.shape[:2])
        return np.where(cells[4][:, None], bilinear(self.xyz, cells), np.nan)


def _angle_diff(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs((a - b + np.pi) % (2 * np.pi) - np.pi)


def best_f1(scores: np.ndarray, hits: np.ndarray, n_pos: int) -> dict:
    """The operating point: the score threshold with the highest F1 (precision and recall of detections at
    or above it, IoU 0.5), to set the detect service's `score_thr` from a held-out recording."""
    if n_pos == 0 or len(scores) == 0:
        return {"best_f1": None, "best_f1_score_thr": None, "best_f1_precision": None, "best_f1_recall": None}
    order = np.argsort(-scores, kind="stable")
    tp = np.cumsum(hits[order])
    precision = tp / np.arange(1, len(order) + 1)
    recall = tp / n_pos
    f1 = 2 * precision * recall / np.maximum(precision + recall, 1e-12)
    # a threshold keeps every detection with the same score: look only at the last of each run of equal scores
    last = np.r_[scores[order][1:] != scores[order][:-1], True]
    k = int(np.flatnonzero(last)[np.argmax(f1[last])])
    return {"best_f1": round(float(f1[k]), 4), "best_f1_score_thr": round(float(scores[order][k]), 4),
            "best_f1_precision": round(float(precision[k]), 4), "best_f1_recall": round(float(recall[k]), 4)}


def size_of_boxes(box: np.ndarray) -> np.ndarray:
    """Square root of each 2D box's area (x1, y1, x2, y2 edges)."""
    return np.sqrt(np.prod(np.clip(box[:, 2:] - box[:, :2], 0, None), axis=1))


def breakdown_frame(det: Detections, box: np.ndarray, bottom_uv: np.ndarray, weight: np.ndarray,
                    gt_of: np.ndarray, counts: np.ndarray) -> tuple[dict[str, int], np.ndarray, np.ndarray]:
    """At `BREAKDOWN_SCORE`: the frame's false alarms by kind ({"box", "duplicate", "background"}) and,
    per label, whether it is matched and whether a detection lies on it (its bottom centre within a third of the
    label's size, at least 2 px, whatever its box; see the module docstring)."""
    keep = det.score >= BREAKDOWN_SCORE
    size = np.maximum(size_of_boxes(box), 1.0)
    near = np.zeros((len(det), len(box)), bool)
    if len(det) and len(box):
        dist = np.linalg.norm(det.uv[:, None, :] - bottom_uv[None, :, :], axis=2)
        near = dist <= np.maximum(NEAR_FRACTION * size, 2.0)[None]
    matched_any = np.zeros(len(box), bool)
    matched_any[gt_of[(gt_of >= 0) & keep]] = True
    alarms = {"box": 0, "duplicate": 0, "background": 0}
    for i in np.nonzero(keep & counts & (gt_of < 0))[0]:
        on = near[i] & (weight > 0)
        if (on & ~matched_any).any():
            alarms["box"] += 1
        elif on.any():
            alarms["duplicate"] += 1
        else:
            alarms["background"] += 1
    found = (near & keep[:, None]).any(axis=0) if len(det) else np.zeros(len(box), bool)
    return alarms, matched_any, found


def near_frame(det_xy: np.ndarray, label_xy: np.ndarray, positive: np.ndarray, centre: np.ndarray,
               near_m: float) -> dict[str, object]:
    """One frame's counts for the near-camera metrics (module docstring): `det_xy` (N, 2) the kept detections'
    lifted bottom centres (NaN off the ground), `label_xy` (M, 2) every labelled vehicle's, `positive` (M,) the
    vehicles to detect, `centre` the camera's ground point."""
    finite = np.isfinite(det_xy).all(axis=1)
    det_near = finite & (np.linalg.norm(np.where(finite[:, None], det_xy, 0.0) - centre, axis=1) <= near_m)
    label_near = positive & (np.linalg.norm(label_xy - centre, axis=1) <= near_m)
    det_of = np.full(len(det_xy), -1)
    dist = np.full(len(label_xy), np.nan)
    if finite.any() and len(label_xy):
        d = np.linalg.norm(det_xy[finite][:, None] - label_xy[None], axis=2)
        i, j = linear_sum_assignment(np.where(d <= NEAR_GATE_M, d, 1e9))
        ok = d[i, j] <= NEAR_GATE_M
        det_of[np.flatnonzero(finite)[i[ok]]] = j[ok]
        dist[j[ok]] = d[i[ok], j[ok]]
    on = det_of >= 0
    on_positive = np.zeros(len(det_xy), bool)
    on_positive[on] = positive[det_of[on]]
    return {"positives": int(label_near.sum()), "found": int((label_near & np.isfinite(dist)).sum()),
            "detections": int((det_near & (on_positive | ~on)).sum()), "true": int((det_near & on_positive).sum()),
            "loc": list(dist[label_near & np.isfinite(dist)]), "label_dist": np.where(label_near, dist, -1.0)}


def evaluate(recording: str | Path, detect: Callable[[np.ndarray], Detections], every: int = 1,
             cameras: list[str] | None = None, log=None, fisheye_area_deg: float | None = None,
             near_m: float = NEAR_M, near_score: float = BREAKDOWN_SCORE, detections_score_thr: float = 0.0) -> dict:
    """Score `detect(grey image) -> Detections` (original pixels) on every `every`-th frame. With
    `fisheye_area_deg`, fisheye frames are detected as `detect(grey, area_px=...)` inside the image circle up to
    that angle off axis (`Camera.image_area_px`), as a site's `detect_area_px` has the detect service do.
    `near_m`, `near_score`: the near-camera metrics (module docstring). `detections_score_thr`: the score `detect`
    keeps detections from; a figure counted at a lower score is at this one, and says so."""
    if not near_m > 0:
        raise ValueError(f"near_m must be > 0, got {near_m!r}")
    rec = Recording(recording)
    names = cameras or rec.camera_names
    modality = {c["name"]: c.get("modality", "visible") for c in rec.meta["cameras"]}
    per: dict[str, dict] = {}
    t_total, n_frames = 0.0, 0
    for name in names:
        cam = rec.cameras[name]
        kind = "thermal" if modality[name] == "thermal" else cam.kind
        lift = GroundLifter(*ground_lookup(cam, rec.terrain))
        truth = {g["t_ns"]: g for g in rec.ground_truth(name)}
        area = cam.image_area_px(fisheye_area_deg) if fisheye_area_deg is not None and cam.kind == "fisheye" else None
        acc = per.setdefault(kind, {"scores": [], "hits": [], "n_pos": 0, "loc": [], "yaw": [], "size": [],
                                    "size_l2": [], "type": [], "frames": 0, "alarms": Counter(),
                                    "pos_size": [], "pos_matched": [], "pos_found": [], "near": Counter(),
                                    "near_loc": [], "near_type": [], "near_dist": []})
        for ref in samples_from_recording(rec.path, [name], every=every):
            sample = ref.load()
            t0 = time.perf_counter()
            det = detect(sample.image) if area is None else detect(sample.image, area_px=area)
            t_total += time.perf_counter() - t0
            n_frames += 1
            acc["frames"] += 1
            gt_of, counts = match_frame(det, sample.box, sample.weight)
            acc["scores"] += list(det.score[counts])
            acc["hits"] += list(gt_of[counts] >= 0)
            acc["n_pos"] += int((sample.weight > 0).sum())
            alarms, matched_any, found = breakdown_frame(det, sample.box, sample.bottom_uv, sample.weight, gt_of,
                                                         counts)
            acc["alarms"].update(alarms)
            pos = sample.weight > 0
            acc["pos_size"] += list(size_of_boxes(sample.box[pos]))
            acc["pos_matched"] += list(matched_any[pos])
            acc["pos_found"] += list(found[pos])
            by_id = {v["id"]: v for v in truth[ref.meta["t_ns"]]["vehicles"]}
            kept = det.score >= near_score
            label_xy = np.array([by_id[int(t)]["xyz"][:2] for t in ref.meta["track_id"]], float).reshape(-1, 2)
            near = near_frame(lift(det.uv[kept])[:, :2], label_xy, pos, cam.pose.position_m[:2], near_m)
            acc["near_loc"] += near.pop("loc")
            label_dist = near.pop("label_dist")  # per label: -1 not counted, NaN missed, else the distance
            acc["near_type"] += list(sample.vtype[label_dist != -1.0])
            acc["near_dist"] += list(label_dist[label_dist != -1.0])
            acc["near"].update(near)
            hit = np.nonzero(gt_of >= 0)[0]
            if len(hit) == 0:
                continue
            g = gt_of[hit]
            gts = [by_id[int(ref.meta["track_id"][j])] for j in g]
            xyz_true = np.array([v["xyz"] for v in gts])
            p0 = lift(det.uv[hit])
            acc["loc"] += list(np.linalg.norm(p0[:, :2] - xyz_true[:, :2], axis=1))
            p1 = lift(det.uv[hit] + HEADING_STEP_PX * det.heading_uv[hit])
            yaw = np.arctan2(p1[:, 1] - p0[:, 1], p1[:, 0] - p0[:, 0])
            acc["yaw"] += list(np.degrees(_angle_diff(yaw, np.array([v["yaw"] for v in gts]))))
            d = det.size_lwh[hit] - np.array([v["lwh"] for v in gts])
            acc["size"] += list(np.abs(d).mean(axis=1))
            acc["size_l2"] += list(np.linalg.norm(d, axis=1))
            acc["type"] += list(det.vtype[hit] == sample.vtype[g])
        if log:
            log(f"[eval] {name}: {acc['frames']} frames so far for {kind}")

    def stat(values: list, fn) -> float | None:
        x = np.asarray(values, float)
        return round(float(fn(x)), 4) if np.isfinite(x).any() else None

    def summary(accs: list[dict]) -> dict:
        scores = np.concatenate([np.asarray(a["scores"], float) for a in accs])
        hits = np.concatenate([np.asarray(a["hits"], bool) for a in accs])
        n_pos = sum(a["n_pos"] for a in accs)
        pool = {k: [x for a in accs for x in a[k]] for k in ("loc", "yaw", "size", "size_l2", "type")}
        return {
            "frames": sum(a["frames"] for a in accs),
            "positives": n_pos,
            "ap50": round(voc07_ap(scores, hits, n_pos), 4),
            "matched": len(pool["loc"]),
            "loc_err_m": stat(pool["loc"], np.nanmean),
            "loc_err_median_m": stat(pool["loc"], np.nanmedian),
            "yaw_err_deg": stat(pool["yaw"], np.nanmean),
            "yaw_err_median_deg": stat(pool["yaw"], np.nanmedian),
            # the heading's axis alone (front and back not told apart): the error modulo 180 degrees
            "yaw_axis_err_deg": stat(np.minimum(pool["yaw"], 180.0 - np.asarray(pool["yaw"], float)), np.nanmean),
            "yaw_axis_err_median_deg": stat(np.minimum(pool["yaw"], 180.0 - np.asarray(pool["yaw"], float)),
                                            np.nanmedian),
            "size_err_m": stat(pool["size"], np.nanmean),
            "size_err_l2_m": stat(pool["size_l2"], np.nanmean),
            "type_acc": stat(pool["type"], np.nanmean),
            **best_f1(scores, hits, n_pos),
            "detections_score_thr": detections_score_thr,
            "breakdown_score_thr": max(BREAKDOWN_SCORE, detections_score_thr),
            "false_alarms": {k: sum(a["alarms"][k] for a in accs) for k in ("box", "duplicate", "background")},
            "recall_by_size": by_size(accs),
            **near_summary(accs),
        }

    def near_summary(accs: list[dict]) -> dict:
        n = Counter()
        for a in accs:
            n.update(a["near"])
        loc = [x for a in accs for x in a["near_loc"]]
        recall = n["found"] / n["positives"] if n["positives"] else None
        precision = n["true"] / n["detections"] if n["detections"] else None
        f1 = None if recall is None or precision is None else \
            2 * precision * recall / (precision + recall) if precision + recall else 0.0
        vtype = np.array([x for a in accs for x in a["near_type"]], np.int64)
        dist = np.array([x for a in accs for x in a["near_dist"]], float)
        by_type = {}
        name = np.array([VEHICLE_TYPES[t] if 0 <= t < len(VEHICLE_TYPES) else "unknown" for t in vtype.tolist()])
        for t in [*VEHICLE_TYPES, "unknown"]:  # all indices off the list counted together as unknown
            d = dist[name == t]
            if not len(d):
                continue
            found = d[np.isfinite(d)]
            by_type[t] = {
                "positives": len(d), "recall": round(len(found) / len(d), 4),
                "loc_err_median_m": round(float(np.median(found)), 4) if len(found) else None}
        return {"near_m": near_m, "near_score_thr": max(near_score, detections_score_thr),
                "near_positives": n["positives"],
                "near_recall": None if recall is None else round(recall, 4),
                "near_precision": None if precision is None else round(precision, 4),
                "near_f1": None if f1 is None else round(f1, 4),
                "near_loc_err_m": stat(loc, np.mean) if loc else None, "near_by_type": by_type}

    def by_size(accs: list[dict]) -> list[dict]:
        size = np.array([x for a in accs for x in a["pos_size"]], float)
        matched = np.array([x for a in accs for x in a["pos_matched"]], bool)
        found = np.array([x for a in accs for x in a["pos_found"]], bool)
        bands = []
        for lo, hi in itertools.pairwise(SIZE_BANDS_PX):
            sel = (size >= lo) & (size < hi)
            bands.append({"size_px": [lo, hi if math.isfinite(hi) else None], "positives": int(sel.sum()),
                          "matched": round(float(matched[sel].mean()), 4) if sel.any() else None,
                          "found": round(float(found[sel].mean()), 4) if sel.any() else None})
        return bands

    out = {"recording": str(rec.path), "every": every, "fisheye_area_deg": fisheye_area_deg,
           "overall": summary(list(per.values()))}
    out["per_kind"] = {k: summary([a]) for k, a in sorted(per.items())}
    out["detect_ms_per_frame"] = round(1e3 * t_total / max(n_frames, 1), 2)
    return out
