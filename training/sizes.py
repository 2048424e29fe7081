"""The size calibration of an exported detector (`shared.decode.SizeCalibration`): fitted after training, on the
detections of the training recordings that match a vehicle, and written into the ONNX files' metadata.

Why: the size head is trained with a squared error in log space, weighted by the heat map, and its sizes came out
no better than each type's median size (run 11 on the held-out recordings, mean absolute l/w/h error: 0.334 m
against 0.295 m on fisheye frames, 0.308 against 0.200 m thermal, 0.329 against 0.310 m pinhole). A small
per-type map of the head's three log sizes to each true log size, fitted by least absolute deviations (the
conditional median: the eval scores the absolute error), keeps what the head knows within a type and corrects its
pull towards the mean of all types. Fitted on training recordings only; the held-out ones score it
(models/README.md).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from shared.decode import MIN_SIZE_M, SIZE_CALIBRATION_KEY, Detections, SizeCalibration

MIN_PAIRS = 50  # a type with fewer matched detections keeps the size head's sizes
L1_ITERATIONS = 50
L1_EPS = 1e-3  # residuals below this (log units) weigh as this in the reweighted least squares


def collect_pairs(detect: Callable[[np.ndarray], Detections], recordings: Sequence[str | Path], every: int = 4,
                  log=None) -> dict[str, np.ndarray]:
    """Run `detect` (grey image -> Detections with the size head's own sizes) on every `every`-th frame of each
    recording's cameras; the detections matched to a vehicle (VOC matching at IoU 0.5, as `roadside eval detector`)
    give {"pred": (N, 3) m, "vtype": (N,) predicted type, "true": (N, 3) m}."""
    from eval.detector import match_frame
    from training.data import samples_from_recording

    pred, vtype, true = [], [], []
    for rec in recordings:
        for ref in samples_from_recording(rec, every=every):
            s = ref.load()
            det = detect(s.image)
            gt_of, _ = match_frame(det, s.box, s.weight)
            hit = np.flatnonzero(gt_of >= 0)
            ok = hit[np.isfinite(s.size_lwh[gt_of[hit]]).all(axis=1)]
            pred.append(det.size_lwh[ok])
            vtype.append(det.vtype[ok])
            true.append(s.size_lwh[gt_of[ok]])
        if log:
            log(f"[sizes] {rec}: {sum(len(p) for p in pred)} matched detections so far")
    if not pred or not sum(len(p) for p in pred):
        raise ValueError(f"no detection matched a vehicle in {', '.join(map(str, recordings))}: nothing to fit")
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


def write_size_calibration(paths: Sequence[str | Path], calib: SizeCalibration) -> None:
    """Set the calibration in the metadata of each ONNX file (the other metadata kept)."""
    import onnx

    for path in paths:
        proto = onnx.load(str(path))
        props = {p.key: p.value for p in proto.metadata_props}
        props[SIZE_CALIBRATION_KEY] = calib.to_json()
        del proto.metadata_props[:]
        onnx.helper.set_model_props(proto, props)
        onnx.save(proto, str(path))


def calibrate_files(paths: Sequence[str | Path], recordings: Sequence[str | Path], every: int = 4,
                    log=None) -> tuple[SizeCalibration, float, float]:
    """Fit the size calibration of the exported detector `paths[0]` (its size head's own sizes, at the eval's score
    threshold 0.05) on the training `recordings` and write it into every file of `paths` (the fp32 file and its
    fp16 copy). Returns the calibration and the mean size error of the fitted detections before and after (m)."""
    from shared.inference import OnnxDetector

    if not paths:
        raise ValueError("calibrate_files: no model file given")
    if not recordings:
        raise ValueError("calibrate_files: no recording to fit the size calibration on")
    det = OnnxDetector(paths[0], score_thr=0.05, calibrated_sizes=False)
    pairs = collect_pairs(det.detect, recordings, every, log=log)
    calib = fit_size_calibration(pairs["pred"], pairs["vtype"], pairs["true"], int(det.config["num_types"]))
    write_size_calibration(paths, calib)
    fitted = calib.apply(pairs["pred"], pairs["vtype"])
    return calib, size_errors(pairs["pred"], pairs["true"]), size_errors(fitted, pairs["true"])


def size_errors(pred: np.ndarray, true: np.ndarray) -> float:
    """Mean absolute length, width and height difference (m), as `roadside eval detector`'s size_err_m."""
    return float(np.abs(np.asarray(pred) - np.asarray(true)).mean()) if len(pred) else float("nan")
