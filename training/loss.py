"""The paper's multi-task loss: total = heat + beta_size * size + beta_heading * heading + beta_vtype * vtype
+ beta_offset * offset (+ beta_box * box and beta_vote * vote, both off by default).

heat     per-cell squared error over cells not ignored, averaged over the top `topk_fraction` of the batch's
         INPUT pixels' worth of cells (hard-example selection; None averages all of them: the paper's
         ablation). The paper's output is at stride 1, so its "top 1 % of pixels" is k = 1 % of the pixels;
         at output stride s a cell stands for s*s pixels, so the same k is topk_fraction * s*s of the cells.
         Taking 1 % of the cells instead at stride 4 keeps fewer cells than a batch has positive cells: the
         selection then holds almost no hard negatives and training settles on a flat heat map (measured:
         every cell near a vehicle stuck at 0.36 after 1,000 steps).
size     squared error of log(pred) vs log(target), summed over channels with a known target
heading  squared error, summed over the two components
axis     (models with an axis head) the same for the doubled-angle axis vector, weighted by beta_heading too
vtype    cross-entropy of the logits
offset   squared error, summed over the four components
box      (beta_box > 0 only) the 2D box's part of size and offset again: log-space error of the box width and
         height plus the squared error of the box centre's offset, so the box can be weighted above the 3D
         size without changing the rest (the 2D box is what ap50 scores; the paper has no such term)
vote     (beta_vote > 0 only) Huber error (1 cell) of the vote head (a model without one: the offset's first two
         channels) at the targets' vote cells
         (training/targets.py: every cell of a vehicle's 2D box points at its centre), a plain mean over them: a
         peak at the end of a long vehicle can still give its centre
The regression terms are weighted per cell by the targets' `weight` (and masks) and divided by the sum of
those weights, so they are means per vehicle cell.
With `type_weights` (one per vehicle type) every cell a vehicle owns (its heat-map window) counts that many times
in every term, the focal heat term's peak and the cells around it included: rare or hard types (a 12 m bus seen
from above) weigh more. The focal term stays divided by the number of peaks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from shared.messages import VEHICLE_TYPES
from training.model import SIZE_EPS

WEIGHT_FLOOR = 1e-6
HEAT_LOSSES = ("mse", "focal")
FOCAL_ALPHA = 2.0
FOCAL_BETA = 4.0
FOCAL_CLAMP = 1e-4  # keeps a term at 0 (not NaN) for a batch without any weighted cell


@dataclass(frozen=True)
class LossConfig:
    """topk_fraction: share of non-ignored heat pixels per batch kept for the heat term (None: all).
    beta_*: weights of the regression and classification terms (the paper uses 0.01 for size, heading, type;
    offset is this project's addition for stride > 1). type_weights: None, or one weight > 0 per vehicle type
    (`VEHICLE_TYPES` order) for the cells each type's vehicles own (module docstring)."""

    topk_fraction: float | None = 0.01
    beta_size: float = 0.01
    beta_heading: float = 0.01
    beta_vtype: float = 0.01
    beta_offset: float = 0.1
    beta_box: float = 0.0
    beta_vote: float = 0.0
    heat: str = "mse"
    type_weights: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.type_weights is not None:
            try:
                w = tuple(float(x) for x in self.type_weights)
            except (TypeError, ValueError):
                w = ()
            if len(w) != len(VEHICLE_TYPES) or not all(math.isfinite(x) and x > 0 for x in w):
                raise ValueError(f"type_weights must be {len(VEHICLE_TYPES)} finite numbers > 0 (one per type of "
                                 f"{VEHICLE_TYPES}), got {self.type_weights!r}")
            object.__setattr__(self, "type_weights", w)
            if self.heat != "focal":
                raise ValueError("type_weights need the focal heat loss (heat='focal')")
        if self.topk_fraction is not None and not 0 < self.topk_fraction <= 1:
            raise ValueError(f"topk_fraction must be in (0, 1] or None, got {self.topk_fraction}")
        if self.heat not in HEAT_LOSSES:
            raise ValueError(f"heat must be one of {HEAT_LOSSES}, got {self.heat!r}")
        for name in ("beta_size", "beta_heading", "beta_vtype", "beta_offset", "beta_box", "beta_vote"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")


def heat_loss(pred: torch.Tensor, target: torch.Tensor, ignore: torch.Tensor,
              topk_fraction: float | None) -> torch.Tensor:
    """Mean squared error over the round(topk_fraction * n) largest of the n non-ignored pixels (at least one);
    all n when topk_fraction is None. pred, target (B, h, w) float; ignore (B, h, w) bool."""
    err = ((pred - target) ** 2)[~ignore]
    if err.numel() == 0:
        return pred.sum() * 0.0
    if topk_fraction is None:
        return err.mean()
    k = max(1, round(topk_fraction * err.numel()))
    return torch.topk(err, k, sorted=False).values.mean()


def focal_heat_loss(pred: torch.Tensor, target: torch.Tensor, ignore: torch.Tensor,
                    cell_weight: torch.Tensor | None = None) -> torch.Tensor:
    """CenterNet's penalty-reduced focal loss over the non-ignored cells, each times `cell_weight` (default 1),
    divided by the number of peak cells (target == 1, at least one). pred, target, cell_weight (B, h, w) float;
    ignore (B, h, w) bool."""
    p = pred.clamp(FOCAL_CLAMP, 1 - FOCAL_CLAMP)
    keep = ~ignore
    pos = (target >= 1.0) & keep
    neg = (target < 1.0) & keep
    w = torch.ones_like(p) if cell_weight is None else cell_weight
    pos_loss = -(w * torch.log(p) * (1 - p) ** FOCAL_ALPHA)[pos].sum()
    neg_loss = -(w * torch.log(1 - p) * p**FOCAL_ALPHA * (1 - target) ** FOCAL_BETA)[neg].sum()
    return (pos_loss + neg_loss) / pos.sum().clamp(min=1)


def _weighted(err: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
    """sum(weight * err) / sum(weight) for per-cell err and weight (B, h, w)."""
    return (weight * err).sum() / weight.sum().clamp(min=WEIGHT_FLOOR)


def detector_loss(outputs: dict[str, torch.Tensor], targets: dict[str, torch.Tensor],
                  config: LossConfig | None = None, stride: int = 1) -> tuple[torch.Tensor, dict[str, float]]:
    """Total loss and its parts (floats, unweighted by beta, plus "total") for logging.

    outputs: Detector.forward of a batch (heat (B, 1, h, w), size (B, 5, h, w), ... vtype logits);
    targets: build_targets of each sample stacked on a leading batch axis, as tensors; stride: the
    output stride (the TopK share counts input pixels, see the module docstring).
    """
    cfg = config or LossConfig()
    weight = targets["weight"]
    cell_weight = None
    if cfg.type_weights is not None:  # the cells a vehicle owns weigh as its type
        table = torch.tensor(cfg.type_weights, dtype=weight.dtype, device=weight.device)
        owned = targets["vtype"] >= 0
        cell_weight = torch.where(owned, table[targets["vtype"].clamp(min=0, max=len(table) - 1)],
                                  torch.ones_like(weight))
        weight = weight * cell_weight
    topk = None if cfg.topk_fraction is None else min(1.0, cfg.topk_fraction * stride * stride)
    if cfg.heat == "focal":
        heat = focal_heat_loss(outputs["heat"][:, 0], targets["heat"], targets["ignore"], cell_weight)
    else:
        heat = heat_loss(outputs["heat"][:, 0], targets["heat"], targets["ignore"], topk)
    size_mask = targets["size_mask"].to(weight.dtype)
    log_err = (torch.log(outputs["size"]) - torch.log(targets["size"].clamp(min=SIZE_EPS))) ** 2
    size = _weighted((log_err * size_mask).sum(dim=1), weight * (size_mask.sum(dim=1) > 0))
    heading_err = ((outputs["heading"] - targets["heading"]) ** 2).sum(dim=1)
    heading = _weighted(heading_err, weight * targets["heading_mask"])
    axis = heading * 0.0
    if "axis" in outputs:
        axis = _weighted(((outputs["axis"] - targets["axis"]) ** 2).sum(dim=1), weight * targets["heading_mask"])
    vtype_known = targets["vtype"] >= 0
    ce = F.cross_entropy(outputs["vtype"], targets["vtype"].clamp(min=0), reduction="none")
    vtype = _weighted(ce, weight * vtype_known)
    offset_err = (outputs["offset"] - targets["offset"]) ** 2
    offset = _weighted(offset_err.sum(dim=1), weight)
    box_known = size_mask[:, 3:5].sum(dim=1) > 0
    box = _weighted((log_err * size_mask)[:, 3:5].sum(dim=1) + offset_err[:, 2:4].sum(dim=1), weight * box_known)
    voted = outputs["vote"] if "vote" in outputs else outputs["offset"][:, :2]
    vote_err = F.smooth_l1_loss(voted, targets["offset"][:, :2], reduction="none", beta=1.0)
    vote = _weighted(vote_err.sum(dim=1), targets["vote_weight"])
    total = (heat + cfg.beta_size * size + cfg.beta_heading * (heading + axis) + cfg.beta_vtype * vtype
             + cfg.beta_offset * offset + cfg.beta_box * box + cfg.beta_vote * vote)
    parts = {"heat": heat, "size": size, "heading": heading, "axis": axis, "vtype": vtype, "offset": offset,
             "box": box, "vote": vote, "total": total}
    return total, {name: float(value.detach()) for name, value in parts.items()}
