"""Corrections of two of the detector's heads, fitted after training and kept in the exported model's metadata.

- `SizeCalibration`: per vehicle type, the size head's (l, w, h) mapped in log space to better sizes.
- `BoxCalibration`: the 2D box (its width, height and centre) corrected by a linear map of what the other heads
  say about the vehicle (its heading's axis in the image, its 3D size and type) and where it lies in the image.

Both are fitted on matched detections of training recordings (training/heads_calibration.py) and applied by
`shared.inference.OnnxDetector` after decoding, for the eval and the detect service alike; a model exported
without them decodes as before. NumPy only (the detect service runs without PyTorch).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace

import numpy as np

from shared.decode import Detections

SIZE_CALIBRATION_KEY = "size_calibration"  # ONNX metadata: a SizeCalibration as JSON
BOX_CALIBRATION_KEY = "box_calibration"  # ONNX metadata: a BoxCalibration as JSON
MIN_SIZE_M = 0.05  # sizes below this are read as this before a calibration takes their logarithm
MIN_BOX_FRACTION = 1e-4  # box sides below this fraction of the image width are read as this (logarithms, ratios)
MAX_BOX_LOG_CHANGE = 2.0  # a box side is changed by at most e^2 either way (a bound on the linear map's reach)


@dataclass(frozen=True)
class SizeCalibration:
    """coef (C, 3, 4) float64: for a detection typed t (its argmax type), log s'_k = coef[t, k, 0] +
    sum_j coef[t, k, 1 + j] * log s_j, with s = (l, w, h) from the size head (m) and s' the calibrated size; a type
    without enough pairs to fit keeps the identity (0, e_k). pairs (C,) int: the matched detections each type's
    rows were fitted on (0: identity)."""

    coef: np.ndarray
    pairs: tuple[int, ...]

    def __post_init__(self) -> None:
        coef = np.asarray(self.coef, np.float64)
        if coef.ndim != 3 or coef.shape[1:] != (3, 4) or len(coef) == 0:
            raise ValueError(f"SizeCalibration.coef must have shape (C, 3, 4), got {coef.shape}")
        if not np.isfinite(coef).all():
            raise ValueError("SizeCalibration.coef must be finite")
        pairs = tuple(int(p) for p in self.pairs)
        if len(pairs) != len(coef) or min(pairs) < 0:
            raise ValueError(f"SizeCalibration.pairs must be {len(coef)} counts >= 0, got {self.pairs!r}")
        object.__setattr__(self, "coef", coef)
        object.__setattr__(self, "pairs", pairs)

    @classmethod
    def identity(cls, num_types: int) -> SizeCalibration:
        coef = np.zeros((num_types, 3, 4))
        coef[:, :, 1:] = np.eye(3)
        return cls(coef, (0,) * num_types)

    def apply(self, size_lwh: np.ndarray, vtype: np.ndarray) -> np.ndarray:
        """size_lwh (N, 3) m from the size head, vtype (N,) int type index -> (N, 3) float64 calibrated sizes (m);
        a type index outside the calibration keeps its size."""
        size = np.asarray(size_lwh, np.float64).reshape(-1, 3)
        vtype = np.asarray(vtype, np.int64).reshape(-1)
        if len(vtype) != len(size):
            raise ValueError(f"SizeCalibration.apply: {len(size)} sizes but {len(vtype)} types")
        known = (vtype >= 0) & (vtype < len(self.coef))
        out = size.copy()
        if not known.any():
            return out
        # the size head ends in a ReLU: a zero would have no logarithm (MIN_SIZE_M, as the fit clamps it)
        log_s = np.log(np.maximum(size[known], MIN_SIZE_M))
        c = self.coef[vtype[known]]  # (M, 3, 4)
        out[known] = np.exp(c[:, :, 0] + np.einsum("mkj,mj->mk", c[:, :, 1:], log_s))
        return out

    def to_json(self) -> str:
        return json.dumps({"coef": np.round(self.coef, 6).tolist(), "pairs": list(self.pairs)})

    @classmethod
    def from_json(cls, text: str, where: str = "size calibration") -> SizeCalibration:
        try:
            d = json.loads(text)
            return cls(np.asarray(d["coef"], np.float64), tuple(d["pairs"]))
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a size calibration ({exc})") from None


def box_sides(box: np.ndarray, width: int) -> np.ndarray:
    """(N, 2) width and height of boxes x1, y1, x2, y2 (N, 4) in an image `width` pixels wide, each at least
    MIN_BOX_FRACTION of that width (the maps take their logarithms and divide by them)."""
    return np.maximum(box[:, 2:4] - box[:, 0:2], MIN_BOX_FRACTION * width)


def box_features(det: Detections, width: int, height: int) -> np.ndarray:
    """(N, 17 + C) float64: what the box calibration reads of each detection in an image of width x height pixels
    (C: the number of types). In order: 1; the box's log width and height as fractions of the image width; the box
    centre's offset from the bottom centre in box widths and heights; the heading's axis in the image (cos 2a,
    sin 2a); the log length, width and height (m, the size head's own); the type probabilities (C); the bottom
    centre's place (u, v from the image centre in image widths and heights, its radius r); the axis relative to the
    direction from the image centre (cos 2(a - phi), sin 2(a - phi)), and the same times r. The place terms let the
    map follow a fisheye's radial geometry, where a box's shape depends on where and which way a vehicle lies."""
    if not (width > 0 and height > 0):
        raise ValueError(f"box_features: image size must be > 0, got {width} x {height}")
    n = len(det)
    wh = box_sides(det.box, width)
    centre = (det.box[:, 0:2] + det.box[:, 2:4]) / 2
    a = np.arctan2(det.heading_uv[:, 1], det.heading_uv[:, 0])
    # from the image centre, (width - 1) / 2 in pixel-centre coordinates
    rel = np.stack([(det.uv[:, 0] - (width - 1) / 2) / width, (det.uv[:, 1] - (height - 1) / 2) / height], axis=1)
    r = np.hypot(rel[:, 0], rel[:, 1])
    phi = np.arctan2(rel[:, 1], rel[:, 0])
    turn = 2 * (a - phi)
    return np.column_stack([
        np.ones(n), np.log(wh / width), (centre - det.uv) / wh, np.cos(2 * a), np.sin(2 * a),
        np.log(np.maximum(det.size_lwh, MIN_SIZE_M)), det.vtype_prob, rel, r, np.cos(turn), np.sin(turn),
        r * np.cos(turn), r * np.sin(turn)])


@dataclass(frozen=True)
class BoxCalibration:
    """coef (K, 4) float64 on `box_features` (K = 17 + C): the features times coef give, per detection, the log
    change of the box's width and of its height and the move of its centre in box widths and heights (the box
    before the change). pairs: the matched detections it was fitted on."""

    coef: np.ndarray
    pairs: int

    def __post_init__(self) -> None:
        coef = np.asarray(self.coef, np.float64)
        if coef.ndim != 2 or coef.shape[1] != 4 or coef.shape[0] < 18:
            raise ValueError(f"BoxCalibration.coef must have shape (17 + C, 4), C >= 1, got {coef.shape}")
        if not np.isfinite(coef).all():
            raise ValueError("BoxCalibration.coef must be finite")
        if int(self.pairs) < 0:
            raise ValueError(f"BoxCalibration.pairs must be >= 0, got {self.pairs!r}")
        object.__setattr__(self, "coef", coef)
        object.__setattr__(self, "pairs", int(self.pairs))

    @property
    def num_types(self) -> int:
        return self.coef.shape[0] - 17

    def apply(self, det: Detections, width: int, height: int) -> Detections:
        """The detections of a width x height image with their 2D boxes corrected; all else as given."""
        if det.vtype_prob.shape[1] != self.num_types:
            raise ValueError(f"BoxCalibration: fitted for {self.num_types} types, the detections have "
                             f"{det.vtype_prob.shape[1]}")
        if len(det) == 0:
            return det
        change = box_features(det, width, height) @ self.coef
        wh = box_sides(det.box, width)
        centre = (det.box[:, 0:2] + det.box[:, 2:4]) / 2 + change[:, 2:4] * wh
        wh = wh * np.exp(np.clip(change[:, 0:2], -MAX_BOX_LOG_CHANGE, MAX_BOX_LOG_CHANGE))
        return replace(det, box=np.concatenate([centre - wh / 2, centre + wh / 2], axis=1))

    def to_json(self) -> str:
        return json.dumps({"coef": np.round(self.coef, 6).tolist(), "pairs": self.pairs})

    @classmethod
    def from_json(cls, text: str, where: str = "box calibration") -> BoxCalibration:
        try:
            d = json.loads(text)
            return cls(np.asarray(d["coef"], np.float64), d["pairs"])
        except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{where}: not a box calibration ({exc})") from None
