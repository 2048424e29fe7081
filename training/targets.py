"""Training targets of one sample at the detector's output resolution (H / stride, W / stride).

Each vehicle contributes a Gaussian exp(-d^2 / sigma^2), sigma = 0.5 * sqrt(2D box diagonal in pixels) as in the
paper but at least MIN_SIGMA_CELLS output cells (at stride 4 a small vehicle's Gaussian would otherwise light one
cell, and training learns far more slowly: measured peak 0.28 vs 0.53 after 200 steps on the same crops), with d
the input-pixel distance from an output cell's centre to the vehicle's centre (its bottom centre, or its 2D box
centre for the paper's ablation); the cell containing the centre is set to 1 so every vehicle has an exact
peak whatever the stride. Vehicles combine by maximum, and each cell's regression targets come from the
vehicle with the highest value there (its owner), weighted by that value. Cell centres follow
shared.decode.cell_centres, so decode(targets) gives back the labelled vehicles.

Votes: every cell whose centre lies inside exactly one vehicle's 2D box (a vehicle to detect, the cell not owned by
another vehicle's Gaussian and not ignored) also gets that vehicle's offset, pointing from the cell to the vehicle's
centre however far it is, with `vote_weight` 1 there. A network that puts its peak at one end of a long vehicle (a
bus seen from above) can then still point at the centre; the loss uses these cells only with beta_vote > 0.
"""

from __future__ import annotations

import numpy as np

from shared.decode import BOX_SCALE_PX, cell_centres, cell_of
from training.sample import Sample

CENTERS = ("bottom", "box")
MIN_SIGMA_CELLS = 1.5  # at stride > 1 a small vehicle's Gaussian would cover one cell: too sparse to learn
WINDOW_SIGMAS = 3.0  # Gaussians are cut at 3 sigma (exp(-9) ~ 1e-4)
IGNORE_RADIUS_SIGMAS = 2.0  # a weight-0 vehicle masks its 2D box and cells within 2 sigma of its centre ...
IGNORE_KEEP_HEAT = 0.05  # ... except where a vehicle to detect has a target at least this high


def gaussian_sigma_px(box: np.ndarray) -> np.ndarray:
    """(N,) sigma in pixels for (N, 4) x1, y1, x2, y2 boxes: half the square root of the diagonal."""
    return 0.5 * np.sqrt(np.hypot(box[:, 2] - box[:, 0], box[:, 3] - box[:, 1]))


def _window(centre: float, radius: float, n: int, stride: int) -> slice:
    """Cells along one axis whose centres lie within radius of centre (clipped to 0..n)."""
    lo = max(0, int(np.ceil((centre - radius - (stride - 1) / 2) / stride)))
    hi = min(n, int(np.floor((centre + radius - (stride - 1) / 2) / stride)) + 1)
    return slice(lo, max(lo, hi))


def build_targets(sample: Sample, stride: int, center: str = "bottom") -> dict[str, np.ndarray]:
    """Targets for one sample, (h, w) = (H / stride, W / stride):

    heat          (h, w)    float32 Gaussian heat map, 1 at each vehicle's centre cell
    ignore        (h, w)    bool    cells left out of the heat loss (around weight-0 vehicles)
    weight        (h, w)    float32 regression weight: the owning vehicle's heat value (0: no owner)
    size          (5, h, w) float32 length, width, height (m), box width, height (px / BOX_SCALE_PX)
    size_mask     (5, h, w) bool    size channels known at the cell (lwh unknown where the label is NaN)
    heading       (2, h, w) float32 image-space unit vector rear -> front
    heading_mask  (h, w)    bool    heading known at the cell (also the mask of `axis`)
    axis          (2, h, w) float32 the heading's axis as the doubled-angle vector (hu^2 - hv^2, 2 hu hv)
    vtype         (h, w)    int64   vehicle type index, -1 where no owner or unknown
    offset        (4, h, w) float32 (u - cell_u) / stride, (v - cell_v) / stride, (box_cx - u) / box_w,
                                    (box_cy - v) / box_h, (u, v) the centre in input pixels; also at vote cells
    vote_weight   (h, w)    float32 1 at the cells voting for a vehicle's centre (module docstring), else 0
    Unknown values are stored as 0 and masked, so no NaN reaches the loss.
    """
    if center not in CENTERS:
        raise ValueError(f"center must be one of {CENTERS}, got {center!r}")
    height, width = sample.shape
    if stride < 1 or height % stride or width % stride:
        raise ValueError(f"{sample.source}: image {width}x{height} is not divisible by stride {stride}")
    box_wh = sample.box[:, 2:4] - sample.box[:, 0:2]
    if (box_wh <= 0).any():
        bad = int(np.argmax((box_wh <= 0).any(axis=1)))
        raise ValueError(f"{sample.source}: vehicle {bad} has an empty 2D box {sample.box[bad].tolist()}")
    h, w = height // stride, width // stride
    cu, cv = cell_centres(w, stride), cell_centres(h, stride)
    box_centre = (sample.box[:, 0:2] + sample.box[:, 2:4]) / 2
    centre = sample.bottom_uv if center == "bottom" else box_centre
    sigma = np.maximum(gaussian_sigma_px(sample.box), MIN_SIGMA_CELLS * stride)
    peak_cell = cell_of(centre, stride)  # (N, 2) column, row

    heat = np.zeros((h, w), np.float64)
    owner = np.full((h, w), -1, np.int64)
    ignore = np.zeros((h, w), bool)
    for i in range(len(sample)):
        positive = sample.weight[i] > 0
        # the window always reaches the centre's own cell, even for a box a few pixels wide
        radius = max(WINDOW_SIGMAS * sigma[i], stride) if positive else IGNORE_RADIUS_SIGMAS * sigma[i]
        rows = _window(centre[i, 1], radius, h, stride)
        cols = _window(centre[i, 0], radius, w, stride)
        du, dv = cu[cols] - centre[i, 0], cv[rows] - centre[i, 1]
        d2 = dv[:, None] ** 2 + du[None, :] ** 2
        if not positive:
            ignore[rows, cols] |= d2 <= radius**2
            half_w, half_h = box_wh[i] / 2
            ignore[_window(box_centre[i, 1], half_h, h, stride), _window(box_centre[i, 0], half_w, w, stride)] = True
            continue
        g = np.exp(-d2 / sigma[i] ** 2)
        pc, pr = peak_cell[i, 0] - cols.start, peak_cell[i, 1] - rows.start
        if 0 <= pr < g.shape[0] and 0 <= pc < g.shape[1]:
            g[pr, pc] = 1.0
        better = g > heat[rows, cols]
        heat[rows, cols] = np.where(better, g, heat[rows, cols])
        owner[rows, cols] = np.where(better, i, owner[rows, cols])
    ignore &= heat < IGNORE_KEEP_HEAT

    # votes: cells inside exactly one positive vehicle's box, unless another vehicle's Gaussian owns them
    in_boxes = np.zeros((h, w), np.int64)
    box_owner = np.full((h, w), -1, np.int64)
    for i in np.flatnonzero(sample.weight > 0):
        half_w, half_h = box_wh[i] / 2
        cells = _window(box_centre[i, 1], half_h, h, stride), _window(box_centre[i, 0], half_w, w, stride)
        in_boxes[cells] += 1
        box_owner[cells] = i
    voting = (in_boxes == 1) & ~ignore & ((owner < 0) | (owner == box_owner))
    owned = owner >= 0
    idx = owner[owned]
    size_all = np.concatenate([sample.size_lwh, box_wh / BOX_SCALE_PX], axis=1)

    size = np.zeros((5, h, w), np.float32)
    size_mask = np.zeros((5, h, w), bool)
    size_mask[:, owned] = np.isfinite(size_all[idx]).T
    size[:, owned] = np.nan_to_num(size_all[idx], nan=0.0).T
    heading = np.zeros((2, h, w), np.float32)
    heading_mask = np.zeros((h, w), bool)
    heading_known = np.isfinite(sample.heading_uv).all(axis=1)
    heading_mask[owned] = heading_known[idx]
    heading[:, owned] = np.where(heading_known[:, None], np.nan_to_num(sample.heading_uv), 0.0)[idx].T
    hu, hv = heading
    axis = np.stack([hu * hu - hv * hv, 2 * hu * hv]).astype(np.float32)
    vtype = np.full((h, w), -1, np.int64)
    vtype[owned] = sample.vtype[idx]
    offset = np.zeros((4, h, w), np.float32)
    pointing = owned | voting  # a voting cell is unowned or owned by the vehicle it votes for
    who = np.where(owned, owner, box_owner)[pointing]
    offset[0, pointing] = (centre[who, 0] - np.broadcast_to(cu[None, :], (h, w))[pointing]) / stride
    offset[1, pointing] = (centre[who, 1] - np.broadcast_to(cv[:, None], (h, w))[pointing]) / stride
    offset[2:, pointing] = ((box_centre - centre) / box_wh)[who].T
    return {"heat": heat.astype(np.float32), "ignore": ignore, "weight": heat.astype(np.float32), "size": size,
            "size_mask": size_mask, "heading": heading, "heading_mask": heading_mask, "axis": axis, "vtype": vtype,
            "offset": offset, "vote_weight": voting.astype(np.float32)}
