"""Bilinear sampling of per-pixel maps (lookup masks, exact ground lookups) at sub-pixel positions.
Pixel centres are at whole numbers, as in shared/cameras.py."""

from __future__ import annotations

import numpy as np


def bilinear_cells(uv: np.ndarray, height: int, width: int):
    """For (N, 2) positions: the top-left neighbour (v0, u0) of each, the fractions (fu, fv) as (N, 1)
    columns, and `inside` (N,): finite and within the outermost pixel centres."""
    uv = np.asarray(uv, np.float64).reshape(-1, 2)
    finite = np.all(np.isfinite(uv), axis=1)
    u = np.where(finite, uv[:, 0], -1.0)
    v = np.where(finite, uv[:, 1], -1.0)
    inside = finite & (u >= 0) & (v >= 0) & (u <= width - 1) & (v <= height - 1)
    u0 = np.clip(np.floor(u).astype(np.int64), 0, width - 2)
    v0 = np.clip(np.floor(v).astype(np.int64), 0, height - 2)
    fu = np.clip(u - u0, 0, 1)[:, None]
    fv = np.clip(v - v0, 0, 1)[:, None]
    return v0, u0, fu, fv, inside


def bilinear(grid: np.ndarray, cells) -> np.ndarray:
    """Sample an (H, W) or (H, W, C) map at `bilinear_cells` output -> (N, 1) or (N, C) float64; NaN in a
    neighbour propagates. Indexing comes first, so the whole map is never converted."""
    v0, u0, fu, fv, _ = cells
    a00, a01 = grid[v0, u0], grid[v0, u0 + 1]
    a10, a11 = grid[v0 + 1, u0], grid[v0 + 1, u0 + 1]
    if a00.ndim == 1:
        a00, a01, a10, a11 = (x[:, None] for x in (a00, a01, a10, a11))
    return (a00 * (1 - fu) + a01 * fu) * (1 - fv) + (a10 * (1 - fu) + a11 * fu) * fv
