"""Weight-space interpolation of a fine-tune with the model it started from.

A fine-tune that learns something new (run 16 in models/README.md: buses near a fisheye pole) often forgets some
of what its starting model knew (SUVs and vans in queues). The two lie in one basin of the loss, so the weights
in between, (1 - w) * base + w * tuned, keep a share of each (Wortsman et al., "Robust fine-tuning of zero-shot
models", 2022: WiSE-FT). The result has the base's architecture: a head only the fine-tune has (a vote head
added with `--init`) is left out; batch-norm statistics are interpolated like the weights. The input size
(`input_long_side`, a preprocessing setting a fine-tune may change with `--input-long-side`) is the fine-tune's.
"""

from __future__ import annotations

import math
from dataclasses import asdict

from training.model import Detector, DetectorConfig

ADDED_HEADS = ("axis_head", "vote_head")  # a fine-tune may add these to its starting model (training/train.py)
PREPROCESSING = ("input_long_side",)  # a fine-tune may change these without changing the weights' shapes


def mix_detectors(base: Detector, tuned: Detector, weight: float) -> Detector:
    """A new detector with the base's architecture and (1 - weight) * base + weight * tuned as its weights.

    ValueError (naming what differs) unless weight is in [0, 1] and the two share the base's architecture: the same
    config but for heads the fine-tune added and its input size (the fine-tune's is taken), every tensor of the base
    in the fine-tune with the same shape."""
    if not (isinstance(weight, (int, float)) and math.isfinite(weight) and 0.0 <= weight <= 1.0):
        raise ValueError(f"mix weight must be a number in [0, 1], got {weight!r}")
    b_cfg, t_cfg = asdict(base.config), asdict(tuned.config)
    for name, value in b_cfg.items():
        if name in ADDED_HEADS and value and not t_cfg[name]:
            raise ValueError(f"the base model has the {name.removesuffix('_head')} head, the fine-tuned one does not")
        if name not in ADDED_HEADS + PREPROCESSING and t_cfg[name] != value:
            raise ValueError(f"the models differ in {name} ({value!r} against {t_cfg[name]!r}): "
                             f"not a fine-tune of that base")
    tuned_state = tuned.state_dict()
    mixed = {}
    for key, value in base.state_dict().items():
        other = tuned_state.get(key)
        if other is None or other.shape != value.shape:
            raise ValueError(f"the fine-tuned model has no tensor {key} of shape {tuple(value.shape)}")
        # batch-norm's counter of batches seen is an integer: the base's is kept
        mixed[key] = (1.0 - weight) * value + weight * other if value.is_floating_point() else value.clone()
    out = Detector(DetectorConfig(**{**b_cfg, **{name: t_cfg[name] for name in PREPROCESSING}}))
    out.load_state_dict(mixed)
    return out.eval()
