"""The heads' calibrations of an exported detector (shared/heads_calibration.py): fitted after training on the
detections of training recordings that match a vehicle, and written into the ONNX files' metadata.

Why (models/README.md, "Calibrated boxes and sizes"): the size head pulls every type towards the mean vehicle (run
11's sizes were no better than each type's median size), and on fisheye frames the 2D box head keeps boxes too
square and off centre, though the other heads know the vehicle's axis, size and type and its place in the image
shows how a fisheye draws it. Two small maps correct them:
- sizes: per predicted type, each true log size on the head's three log sizes, by least absolute deviations (the
  conditional median: the eval scores the absolute error), over the detections matched as the eval matches them
  (VOC, IoU 0.5, with the calibrated boxes);
- boxes: the log change of width and height and the centre's move (in box sizes) on `box_features`, by least
  squares, over each vehicle's best detection at IoU 0.3 or more (near misses included: the map is there to turn
  them into hits). Not made to commute with mirroring the image: traffic keeps to one side, and a map fitted on
  each pair and its mirror lost pinhole ap50 on a validation recording (903: 0.607 against 0.632).
Fitted on training recordings only; the held-out ones score it.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from shared.decode import Detections
from shared.heads_calibration import (
    BOX_CALIBRATION_KEY,
    MAX_BOX_LOG_CHANGE,
    MIN_SIZE_M,
    SIZE_CALIBRATION_KEY,
    BoxCalibration,
    SizeCalibration,
    box_features,
    box_sides,
)

MIN_PAIRS = 50  # a type with fewer matched detections keeps the size head's sizes
MIN_BOX_PAIRS = 200  # fewer matched detections than this fit no box calibration
BOX_IOU = 0.3  # a detection overlapping a vehicle's box this much is a pair for the box fit
BOX_RIDGE = 1e-6  # ridge on the box map (times the pairs), the intercept free: numerical only (1e-3 did worse)
L1_ITERATIONS = 50
L1_EPS = 1e-3  # residuals below this (log units) weigh as this in the reweighted least squares


def check_recordings(recordings: Sequence[str | Path], every: int) -> None:
    """ValueError naming the first recording that cannot be opened or has no camera, or an `every` below 1: what
    would otherwise stop a calibration only after its detector has been loaded (or exported)."""
    from sim.recording import Recording

    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"every must be a whole number >= 1, got {every!r}")
    if not recordings:
        raise ValueError("no recording to fit the calibrations on")
    for path in recordings:
        if not Recording(path).camera_names:
            raise ValueError(f"recording {path} has no camera")


def collect_frames(detect: Callable[[np.ndarray], Detections], recordings: Sequence[str | Path], every: int = 4,
                   log=None) -> list[tuple[Detections, object, tuple[int, int]]]:
    """(detections with the heads' own boxes and sizes, the frame's Sample without its image, (width, height)) for
    every `every`-th frame of each recording's cameras."""
    from training.data import samples_from_recording

    frames = []
    for rec in recordings:
        for ref in samples_from_recording(rec, every=every):
            s = ref.load()
            shape = (s.image.shape[1], s.image.shape[0])
            frames.append((detect(s.image), s, shape))
            s.image = s.image[:0, :0]  # the labels are kept, not the pixels
        if log:
            log(f"[heads] {rec}: {len(frames)} frames so far")
    return frames


def box_pairs(frames: Sequence[tuple[Detections, object, tuple[int, int]]]) -> tuple[np.ndarray, np.ndarray]:
    """(features (N, K), targets (N, 4)) for the box fit: per frame, each vehicle to detect and the highest-scoring
    detection left that overlaps its box at BOX_IOU or more (greedy by score)."""
    from eval.detector import match_frame

    feats, targets = [], []
    for det, s, (width, height) in frames:
        gt_of, _ = match_frame(det, s.box, s.weight, min_iou=BOX_IOU)
        rows = np.flatnonzero(gt_of >= 0)
        if not len(rows):
            continue
        cols = gt_of[rows]
        d = det.select(rows)
        feats.append(box_features(d, width, height))
        wh = box_sides(d.box, width)
        true = s.box[cols]
        true_wh = box_sides(true, width)
        move = ((true[:, 0:2] + true[:, 2:4]) / 2 - (d.box[:, 0:2] + d.box[:, 2:4]) / 2) / wh
        targets.append(np.column_stack([np.log(true_wh / wh), move]))
    if not feats:
        return np.zeros((0, 0)), np.zeros((0, 4))
    return np.concatenate(feats), np.concatenate(targets)


def fit_box_calibration(features: np.ndarray, targets: np.ndarray, min_pairs: int = MIN_BOX_PAIRS) -> BoxCalibration:
    """The box map by ridge-regularised least squares (module docstring); ValueError with fewer than min_pairs."""
    features = np.asarray(features, np.float64)
    targets = np.asarray(targets, np.float64)
    if features.ndim != 2 or targets.shape != (len(features), 4):
        raise ValueError(f"fit_box_calibration: features (N, K) and targets (N, 4), got {features.shape} and "
                         f"{targets.shape}")
    if len(features) < min_pairs:
        raise ValueError(f"fit_box_calibration: {len(features)} matched detections, fewer than {min_pairs}")
    if not (np.isfinite(features).all() and np.isfinite(targets).all()):
        raise ValueError("fit_box_calibration: features and targets must be finite")
    ridge = BOX_RIDGE * len(features) * np.eye(features.shape[1])
    ridge[0, 0] = 0.0
    coef = np.linalg.solve(features.T @ features + ridge, features.T @ targets)
    return BoxCalibration(coef, len(features))


def size_pairs(frames: Sequence[tuple[Detections, object, tuple[int, int]]],
               boxes: BoxCalibration | None = None) -> dict[str, np.ndarray]:
    """{"pred": (N, 3) m, "vtype": (N,), "true": (N, 3) m} of the detections matched to a vehicle as `roadside eval
    detector` matches them (VOC, IoU 0.5), with `boxes` applied first when given."""
    from eval.detector import match_frame

    pred, vtype, true = [], [], []
    for det, s, (width, height) in frames:
        if boxes is not None:
            det = boxes.apply(det, width, height)
        gt_of, _ = match_frame(det, s.box, s.weight)
        hit = np.flatnonzero(gt_of >= 0)
        ok = hit[np.isfinite(s.size_lwh[gt_of[hit]]).all(axis=1)]
        pred.append(det.size_lwh[ok])
        vtype.append(det.vtype[ok])
        true.append(s.size_lwh[gt_of[ok]])
    if not pred or not sum(len(p) for p in pred):
        raise ValueError("no detection matched a vehicle: no size to fit")
    return {"pred": np.concatenate(pred).reshape(-1, 3), "vtype": np.concatenate(vtype).astype(np.int64),
            "true": np.concatenate(true).reshape(-1, 3)}


def least_absolute(x: np.ndarray, y: np.ndarray, iterations: int = L1_ITERATIONS) -> np.ndarray:
    """(K,) coefficients b minimising sum |y - x b| (x (N, K), y (N,)), by iteratively reweighted least squares."""
    w = np.ones(len(y))
    b = np.zeros(x.shape[1])
    for _ in range(iterations):
        sw = np.sqrt(w)
        b = np.linalg.lstsq(x * sw[:, None], y * sw, rcond=None)[0]
        w = 1.0 / np.maximum(np.abs(y - x @ b), L1_EPS)
    return b


def fit_size_calibration(pred: np.ndarray, vtype: np.ndarray, true: np.ndarray, num_types: int,
                         min_pairs: int = MIN_PAIRS) -> SizeCalibration:
    """Per type t with at least `min_pairs` matched detections: log true_k ~ a + b . log pred, by least absolute
    deviations (module docstring); pred, true (N, 3) m, vtype (N,) the predicted type."""
    pred = np.asarray(pred, np.float64).reshape(-1, 3)
    true = np.asarray(true, np.float64).reshape(-1, 3)
    vtype = np.asarray(vtype, np.int64).reshape(-1)
    if not len(pred) == len(true) == len(vtype):
        raise ValueError(f"fit_size_calibration: {len(pred)} predicted sizes, {len(true)} true, {len(vtype)} types")
    if not (np.isfinite(pred).all() and np.isfinite(true).all() and (true > 0).all()):
        raise ValueError("fit_size_calibration: sizes must be finite and the true ones > 0")
    if min_pairs < 5:
        raise ValueError(f"min_pairs must be >= 5 (4 coefficients per size), got {min_pairs}")
    calib = SizeCalibration.identity(num_types)
    coef, pairs = calib.coef.copy(), list(calib.pairs)
    for t in range(num_types):
        mine = vtype == t
        if mine.sum() < min_pairs:
            continue
        x = np.column_stack([np.ones(int(mine.sum())), np.log(np.maximum(pred[mine], MIN_SIZE_M))])
        for k in range(3):
            coef[t, k] = least_absolute(x, np.log(true[mine, k]))
        pairs[t] = int(mine.sum())
    return SizeCalibration(coef, tuple(pairs))


def write_calibrations(paths: Sequence[str | Path], sizes: SizeCalibration | None = None,
                       boxes: BoxCalibration | None = None) -> None:
    """Set the given calibrations in the metadata of each ONNX file (the other metadata kept)."""
    import onnx

    for path in paths:
        proto = onnx.load(str(path))
        props = {p.key: p.value for p in proto.metadata_props}
        if sizes is not None:
            props[SIZE_CALIBRATION_KEY] = sizes.to_json()
        if boxes is not None:
            props[BOX_CALIBRATION_KEY] = boxes.to_json()
        del proto.metadata_props[:]
        onnx.helper.set_model_props(proto, props)
        onnx.save(proto, str(path))


def mean_size_error(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean absolute length, width and height difference (m), as `roadside eval detector`'s size_err_m."""
    return float(np.abs(np.asarray(pred) - np.asarray(true)).mean()) if len(pred) else float("nan")


def calibrate_files(paths: Sequence[str | Path], recordings: Sequence[str | Path], every: int = 4,
                    log=None) -> dict:
    """Fit both calibrations of the exported detector `paths[0]` (its heads' own outputs, at the eval's score
    threshold 0.05) on the training `recordings` and write them into every file of `paths` (the fp32 file and its
    fp16 copy). Returns what was fitted and how the fitted detections changed."""
    try:
        import onnx  # noqa: F401  (write_calibrations needs it: a missing onnx is found before the work, not after)
    except ImportError as exc:
        raise RuntimeError("calibrating the heads needs onnx (the train extra: pip install -e '.[train]'): "
                           f"{exc}") from exc
    from shared.inference import OnnxDetector

    if not paths:
        raise ValueError("calibrate_files: no model file given")
    check_recordings(recordings, every)
    det = OnnxDetector(paths[0], score_thr=0.05, calibrated_heads=False)
    frames = collect_frames(det.detect, recordings, every, log=log)
    feats, targets = box_pairs(frames)
    boxes = fit_box_calibration(feats, targets)
    pairs = size_pairs(frames, boxes)
    sizes = fit_size_calibration(pairs["pred"], pairs["vtype"], pairs["true"], int(det.config["num_types"]))
    write_calibrations(paths, sizes, boxes)
    change = feats @ boxes.coef
    true_centre, true_wh = targets[:, 2:4], np.exp(targets[:, 0:2])  # in the heads' own box's units
    after_wh = np.exp(np.clip(change[:, 0:2], -MAX_BOX_LOG_CHANGE, MAX_BOX_LOG_CHANGE))
    iou_before = _iou(np.zeros_like(true_centre), np.ones_like(true_wh), true_centre, true_wh)
    iou_after = _iou(change[:, 2:4], after_wh, true_centre, true_wh)
    return {"sizes": sizes, "boxes": boxes, "size_error_before": mean_size_error(pairs["pred"], pairs["true"]),
            "size_error_after": mean_size_error(sizes.apply(pairs["pred"], pairs["vtype"]), pairs["true"]),
            "box_pairs_at_iou50_before": float(np.mean(iou_before >= 0.5)),
            "box_pairs_at_iou50_after": float(np.mean(iou_after >= 0.5))}


def _iou(centre_a: np.ndarray, wh_a: np.ndarray, centre_b: np.ndarray, wh_b: np.ndarray) -> np.ndarray:
    """(N,) IoU of boxes given by centres and sizes (N, 2) each."""
    lo = np.maximum(centre_a - wh_a / 2, centre_b - wh_b / 2)
    hi = np.minimum(centre_a + wh_a / 2, centre_b + wh_b / 2)
    inter = np.prod(np.clip(hi - lo, 0, None), axis=1)
    return inter / (np.prod(wh_a, axis=1) + np.prod(wh_b, axis=1) - inter)
