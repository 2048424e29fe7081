"""JSON documents for other programs: strict JSON (RFC 8259 has no NaN or Infinity, which Python's json writes
by default and most parsers refuse). An undefined figure (a ratio of nothing, a mean of no values) is null."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np


def strict(obj: Any) -> Any:
    """`obj` with every non-finite float (and NumPy scalar or array) replaced by None, containers copied."""
    if isinstance(obj, float | np.floating):
        return float(obj) if math.isfinite(obj) else None
    if isinstance(obj, np.integer | np.bool_):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, dict):
        return {k: strict(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [strict(v) for v in obj]
    return obj


def dumps(obj: Any, **kw: Any) -> str:
    """json.dumps of `strict(obj)`; raises ValueError rather than write a non-finite number."""
    return json.dumps(strict(obj), allow_nan=False, **kw)
