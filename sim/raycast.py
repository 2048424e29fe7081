"""Vectorised ray casting against oriented boxes and spheres (float32, world frame)."""

from __future__ import annotations

import numpy as np


def ray_boxes(
    origin: np.ndarray,
    dirs: np.ndarray,
    centers: np.ndarray,
    halves: np.ndarray,
    yaws: np.ndarray,
    t_max: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays (origin (3,), dirs (M, 3) unit) with boxes rotated by yaw about z.

    Returns t (M,) float32 (inf where nothing is hit before t_max), box index (M,) int64 (-1),
    and the hit face's outward normal in the world frame (M, 3) float32.
    """
    m = len(dirs)
    t_best = np.full(m, np.inf, np.float32) if t_max is None else t_max.astype(np.float32).copy()
    idx = np.full(m, -1, np.int64)
    normal = np.zeros((m, 3), np.float32)
    if m == 0 or len(centers) == 0:
        return np.where(idx >= 0, t_best, np.inf).astype(np.float32), idx, normal
    dirs = dirs.astype(np.float32, copy=False)
    for b in range(len(centers)):
        c, s = np.cos(yaws[b]), np.sin(yaws[b])
        o = origin - centers[b]
        ol = np.array([c * o[0] + s * o[1], -s * o[0] + c * o[1], o[2]], np.float32)
        # Cull rays that pass far from the box's bounding sphere.
        rad = float(np.linalg.norm(halves[b]))
        to_c = -o
        dist = float(np.linalg.norm(to_c))
        if dist > rad:
            cos_lim = np.sqrt(max(0.0, 1 - (rad / dist) ** 2))
            cand = np.nonzero(dirs @ (to_c / dist).astype(np.float32) >= cos_lim - 1e-4)[0]
        else:
            cand = np.arange(m)
        if cand.size == 0:
            continue
        d = dirs[cand]
        dl = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], 1)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv = 1.0 / np.where(np.abs(dl) < 1e-9, 1e-9, dl)
            h = halves[b].astype(np.float32)
            t1 = (-h - ol) * inv
            t2 = (h - ol) * inv
        tn = np.minimum(t1, t2)
        tf = np.maximum(t1, t2)
        t_near = tn.max(axis=1)
        t_far = tf.min(axis=1)
        hit = (t_far >= t_near) & (t_near > 1e-3) & (t_near < t_best[cand])
        if not hit.any():
            continue
        sel = cand[hit]
        axis = tn[hit].argmax(axis=1)
        nl = np.zeros((len(sel), 3), np.float32)
        nl[np.arange(len(sel)), axis] = -np.sign(dl[hit, axis])
        nw = np.stack([c * nl[:, 0] - s * nl[:, 1], s * nl[:, 0] + c * nl[:, 1], nl[:, 2]], 1)
        t_best[sel] = t_near[hit]
        idx[sel] = b
        normal[sel] = nw
    t_out = np.where(idx >= 0, t_best, np.inf).astype(np.float32)
    return t_out, idx, normal


def ray_spheres(
    origin: np.ndarray, dirs: np.ndarray, centers: np.ndarray, radii: np.ndarray, t_max: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest hit of rays with spheres: t (M,), sphere index (M,), unit normal (M, 3)."""
    m = len(dirs)
    t_best = np.full(m, np.inf, np.float32) if t_max is None else t_max.astype(np.float32).copy()
    idx = np.full(m, -1, np.int64)
    normal = np.zeros((m, 3), np.float32)
    dirs = dirs.astype(np.float32, copy=False)
    for k in range(len(centers)):
        oc = (origin - centers[k]).astype(np.float32)
        dist = float(np.linalg.norm(oc))
        r = float(radii[k])
        if dist <= r:
            continue
        cos_lim = np.sqrt(max(0.0, 1 - (r / dist) ** 2))
        cand = np.nonzero(dirs @ (-oc / dist) >= cos_lim - 1e-4)[0]
        if cand.size == 0:
            continue
        b = dirs[cand] @ oc
        disc = b * b - (dist * dist - r * r)
        t = -b - np.sqrt(np.maximum(disc, 0))
        hit = (disc >= 0) & (t > 1e-3) & (t < t_best[cand])
        sel = cand[hit]
        t_best[sel] = t[hit]
        idx[sel] = k
        p = origin + dirs[sel] * t[hit, None]
        normal[sel] = (p - centers[k]) / r
    t_out = np.where(idx >= 0, t_best, np.inf).astype(np.float32)
    return t_out, idx, normal
