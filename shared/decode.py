"""Detections from the detector's output maps: 3x3 max-pool peaks, a score threshold and a top-k.

NumPy only (the detect service runs it next to ONNX Runtime, without PyTorch). Pixel convention as in
shared/cameras.py: pixel (col, row) covers [col - 0.5, col + 0.5). An output cell j at stride s covers input
pixels j*s .. j*s + s - 1, so its centre is at j*s + (s - 1) / 2.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

BOX_SCALE_PX = 32.0  # the size head predicts 2D box width and height in input pixels / BOX_SCALE_PX
HEADING_EPS = 1e-12
PEAK_KERNEL = np.ones((3, 3), np.uint8)
EARLIER_KERNEL = np.array([[1, 1, 1], [1, 0, 0], [0, 0, 0]], np.uint8)  # the 3x3 neighbours before a cell
VOTE_MIN_CELLS = 1.5  # a peak whose vote points further than this (output cells) is moved to the vehicle's centre
PAD_MULTIPLE = 32  # a network input's sides are padded to a multiple of this (its deepest stride)
CONFIG_KEY = "detector_config"  # ONNX metadata written by training.export: the DetectorConfig as JSON


def model_stride(metadata: Mapping[str, str]) -> int:
    """Output stride of an exported model from its metadata (onnxruntime: session.get_modelmeta().
    custom_metadata_map), read as the detect service reads it (`detector_config`)."""
    if CONFIG_KEY not in metadata:
        raise ValueError(f"model metadata has no {CONFIG_KEY!r} (not written by training.export?): {sorted(metadata)}")
    return detector_config(metadata[CONFIG_KEY], "the model")["stride"]


def detector_config(text: str, path: Path | str) -> dict:
    """A model's `CONFIG_KEY` metadata (training.export: the DetectorConfig as JSON), the keys read here checked:
    ValueError naming the file, at start, rather than a traceback or every frame refused later."""
    try:
        config = json.loads(text)
        if not isinstance(config, dict):
            raise ValueError(f"not a JSON object: {text[:80]!r}")
        if "stride" not in config:
            raise ValueError(f"no 'stride' in {sorted(config)}")
        # the input is padded to a multiple of PAD_MULTIPLE: the output maps cover it exactly at a stride dividing it
        _whole(config, "stride", lambda v: v >= 1 and PAD_MULTIPLE % v == 0, f">= 1 dividing {PAD_MULTIPLE}")
        _whole(config, "input_long_side", lambda v: v >= PAD_MULTIPLE, f">= {PAD_MULTIPLE}")
        _whole(config, "num_types", lambda v: v >= 1, ">= 1")
    except (KeyError, TypeError, AttributeError, ValueError) as e:
        raise ValueError(f"{path}: metadata {CONFIG_KEY}: {e}") from e
    return config


def _whole(config: dict, key: str, ok, what: str) -> None:
    """ValueError unless `config[key]` (where present) is a whole number (not a bool) for which `ok` holds."""
    if key in config:
        v = config[key]
        if isinstance(v, bool) or not isinstance(v, int) or not ok(v):
            raise ValueError(f"{key} must be a whole number {what}, got {v!r}")


def cell_centres(n: int, stride: int) -> np.ndarray:
    """(n,) float64 input-pixel coordinate of the centres of n output cells along one axis."""
    return np.arange(n, dtype=np.float64) * stride + (stride - 1) / 2


def cell_of(coord: np.ndarray, stride: int) -> np.ndarray:
    """Index of the output cell that contains each input-pixel coordinate (same shape, int64)."""
    return np.floor((np.asarray(coord, np.float64) + 0.5) / stride).astype(np.int64)


@dataclass
class Detections:
    """N detections, struct of arrays, in the pixels of one image.

    score       (N,)    float64 heat-map peak value in [0, 1]
    uv          (N, 2)  float64 bottom centre (pixels)
    box         (N, 4)  float64 2D box x1, y1, x2, y2 (pixels)
    heading_uv  (N, 2)  float64 unit vector from the footprint's rear towards its front (image space)
    size_lwh    (N, 3)  float64 length, width, height (m)
    vtype       (N,)    int64 argmax of vtype_prob (index into training.sample.VEHICLE_TYPES)
    vtype_prob  (N, C)  float64 class probabilities
    """

    score: np.ndarray
    uv: np.ndarray
    box: np.ndarray
    heading_uv: np.ndarray
    size_lwh: np.ndarray
    vtype: np.ndarray
    vtype_prob: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.score)
        expected = {"score": (n,), "uv": (n, 2), "box": (n, 4), "heading_uv": (n, 2), "size_lwh": (n, 3),
                    "vtype": (n,)}
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"Detections.{name} must have shape {shape}, got {getattr(self, name).shape}")
        if self.vtype_prob.ndim != 2 or len(self.vtype_prob) != n:
            raise ValueError(f"Detections.vtype_prob must have shape ({n}, C), got {self.vtype_prob.shape}")

    def __len__(self) -> int:
        return len(self.score)

    def select(self, index: np.ndarray) -> Detections:
        """The detections at `index` (int indices or a boolean mask), in that order."""
        return Detections(self.score[index], self.uv[index], self.box[index], self.heading_uv[index],
                          self.size_lwh[index], self.vtype[index], self.vtype_prob[index])

    def scaled(self, sx: float, sy: float, dx: float = 0.0, dy: float = 0.0) -> Detections:
        """The same detections in another image where u' = sx*u + dx and v' = sy*v + dy (e.g. the original
        image of a resized or cropped network input); headings are rescaled by (sx, sy) and renormalised."""
        if not (sx > 0 and sy > 0):
            raise ValueError(f"scale factors must be > 0, got sx={sx}, sy={sy}")
        scale, shift = np.array([sx, sy]), np.array([dx, dy])
        heading = self.heading_uv * scale
        heading /= np.maximum(np.linalg.norm(heading, axis=1, keepdims=True), HEADING_EPS)
        return Detections(self.score.copy(), self.uv * scale + shift, self.box * np.tile(scale, 2) + np.tile(shift, 2),
                          heading, self.size_lwh.copy(), self.vtype.copy(), self.vtype_prob.copy())


def peak_mask(heat: np.ndarray) -> np.ndarray:
    """(h, w) bool: cells equal to the maximum of their 3x3 neighbourhood, but for a cell next to such a cell of the
    same value before it in row-major order (a tie: an fp16 model rounds two nearly equal cells of one vehicle to
    the same value, which gave two detections one cell apart). A -inf cell is never a peak."""
    heat = np.ascontiguousarray(heat, np.float32)
    # a grey dilation is the 3x3 max pool; OpenCV's default border leaves edge cells to their inner neighbours
    # (25 times faster than numpy's sliding-window maximum: 0.1 against 2.8 ms at 160x120)
    peak = heat == cv2.dilate(heat, PEAK_KERNEL)
    # the largest peak among the neighbours before each cell (none can exceed a peak's own value): equal is a tie
    before = cv2.dilate(np.where(peak, heat, -np.inf).astype(np.float32), EARLIER_KERNEL,
                        borderType=cv2.BORDER_CONSTANT, borderValue=-np.inf)
    return peak & (before != heat)


def decode(heat: np.ndarray, size: np.ndarray, heading: np.ndarray, vtype_prob: np.ndarray, offset: np.ndarray,
           stride: int, score_thr: float = 0.3, top_k: int = 100, axis: np.ndarray | None = None,
           vote: np.ndarray | None = None, vote_min_cells: float = VOTE_MIN_CELLS) -> Detections:
    """Detections of one image from the exported model's outputs without the batch axis:
    heat (1, h, w), size (5, h, w), heading (2, h, w), vtype_prob (C, h, w), offset (4, h, w), and the optional
    axis (2, h, w) of a model with an axis head; coordinates in input pixels. Peaks at or above score_thr, the
    top_k highest first (ties in row-major order).

    With `axis` ((cos 2a, sin 2a) of the heading angle a), the heading is the axis direction (cos a, sin a),
    turned round where it points away from the heading head's vector (which then only gives the sign).

    With `vote` (2, h, w) (a model with a vote head: at every cell of a vehicle's 2D box, the way to its centre in
    cells), a peak whose vote points further than `vote_min_cells` lies away from its vehicle's centre (the near
    end of a bus seen from its pole): it is read at the cell its vote points to instead (position, box, size,
    heading and type there; its own score), and of detections that then lie within half the smaller side of a
    higher-scoring one's 2D box, where one of the two was moved, only the higher-scoring one is kept."""
    if heat.ndim != 3 or heat.shape[0] != 1:
        raise ValueError(f"heat must have shape (1, h, w), got {heat.shape}")
    h, w = heat.shape[1:]
    maps = [("size", size, 5), ("heading", heading, 2), ("offset", offset, 4),
            ("vtype_prob", vtype_prob, vtype_prob.shape[0])]
    maps += [(name, arr, 2) for name, arr in (("axis", axis), ("vote", vote)) if arr is not None]
    for name, arr, c in maps:
        if arr.shape != (c, h, w):
            raise ValueError(f"{name} must have shape ({c}, {h}, {w}), got {arr.shape}")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    if top_k < 0:
        raise ValueError(f"top_k must be >= 0, got {top_k}")
    hm = heat[0].astype(np.float64)
    rows, cols = np.nonzero(peak_mask(hm) & (hm >= score_thr))
    order = np.argsort(-hm[rows, cols], kind="stable")[:top_k]
    rows, cols = rows[order], cols[order]
    score = hm[rows, cols]
    moved = np.zeros(len(rows), bool)
    if vote is not None:
        v = vote[:, rows, cols].astype(np.float64)
        moved = np.hypot(v[0], v[1]) > vote_min_cells
        rows = np.where(moved, np.clip(np.rint(rows + v[1]), 0, h - 1).astype(np.int64), rows)
        cols = np.where(moved, np.clip(np.rint(cols + v[0]), 0, w - 1).astype(np.int64), cols)
    off = offset[:, rows, cols].astype(np.float64)
    uv = np.stack([cell_centres(w, stride)[cols] + off[0] * stride, cell_centres(h, stride)[rows] + off[1] * stride],
                  axis=1)
    box_wh = size[3:5, rows, cols].astype(np.float64).T * BOX_SCALE_PX
    box_c = uv + off[2:4].T * box_wh
    hd = heading[:, rows, cols].astype(np.float64).T
    # a NaN heading (a broken model) gives no heading even where the axis replaces it below: its sign comes from it
    finite = np.isfinite(hd).all(axis=1)
    if axis is not None:
        half = np.arctan2(axis[1, rows, cols], axis[0, rows, cols]).astype(np.float64) / 2
        direction = np.stack([np.cos(half), np.sin(half)], axis=1)
        flip = (direction * hd).sum(axis=1) < 0
        direction[flip] *= -1
        hd = direction
    norm = np.linalg.norm(hd, axis=1, keepdims=True)
    hd /= np.maximum(norm, HEADING_EPS)
    prob = vtype_prob[:, rows, cols].astype(np.float64).T
    keep = _kept_after_votes(uv, box_wh, moved) if moved.any() else np.arange(len(uv))
    keep = keep[(norm[keep, 0] > HEADING_EPS) & finite[keep]]  # a peak with no heading gives no ground yaw: left out
    return Detections(score=score[keep], uv=uv[keep],
                      box=np.concatenate([box_c - box_wh / 2, box_c + box_wh / 2], axis=1)[keep],
                      heading_uv=hd[keep], size_lwh=size[0:3, rows, cols].astype(np.float64).T[keep],
                      vtype=prob.argmax(axis=1)[keep], vtype_prob=prob[keep])


def _kept_after_votes(uv: np.ndarray, box_wh: np.ndarray, moved: np.ndarray) -> np.ndarray:
    """Indices (highest score first, as given) of the detections kept after votes moved some: one lying within
    half the smaller side of a kept, higher-scoring detection's box, where either was moved, is dropped."""
    kept: list[int] = []
    for i in range(len(uv)):
        near = [j for j in kept if (moved[i] or moved[j])
                and np.hypot(*(uv[i] - uv[j])) < 0.5 * min(box_wh[j, 0], box_wh[j, 1])]
        if not near:
            kept.append(i)
    return np.array(kept, np.int64)
