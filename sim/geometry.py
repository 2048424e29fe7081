"""Plane-curve helpers for the road network: polylines, Bezier curves, arcs, resampling."""

from __future__ import annotations

import numpy as np


def line(a: np.ndarray, b: np.ndarray, step_m: float = 0.5) -> np.ndarray:
    """Points from a to b (inclusive), (N, 2)."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    n = max(2, int(np.ceil(np.linalg.norm(b - a) / step_m)) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return a + t * (b - a)


def bezier(p0, p1, p2, p3, n: int = 80) -> np.ndarray:
    """Cubic Bezier through control points, (n, 2)."""
    t = np.linspace(0.0, 1.0, n)[:, None]
    p0, p1, p2, p3 = (np.asarray(p, float) for p in (p0, p1, p2, p3))
    return (1 - t) ** 3 * p0 + 3 * (1 - t) ** 2 * t * p1 + 3 * (1 - t) * t**2 * p2 + t**3 * p3


def hermite(a, ta, b, tb, stiffness: float = 0.4) -> np.ndarray:
    """A smooth curve from a (unit tangent ta) to b (unit tangent tb), as a cubic Bezier."""
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = stiffness * np.linalg.norm(b - a)
    return bezier(a, a + c * np.asarray(ta), b - c * np.asarray(tb), b)


def arc(center, radius: float, a0: float, a1: float, step_m: float = 0.5) -> np.ndarray:
    """Counter-clockwise (a1 > a0) or clockwise arc, angles in radians, (N, 2)."""
    n = max(2, int(np.ceil(abs(a1 - a0) * radius / step_m)) + 1)
    a = np.linspace(a0, a1, n)
    return np.asarray(center, float) + radius * np.stack([np.cos(a), np.sin(a)], axis=1)


def concat(*parts: np.ndarray) -> np.ndarray:
    """Join polylines, dropping a point that repeats the previous part's last point."""
    out = [parts[0]]
    for p in parts[1:]:
        if np.linalg.norm(p[0] - out[-1][-1]) < 1e-6:
            p = p[1:]
        out.append(p)
    return np.concatenate(out, axis=0)


def arclength(points: np.ndarray) -> np.ndarray:
    d = np.linalg.norm(np.diff(points, axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(d)])


def resample(points: np.ndarray, step_m: float) -> np.ndarray:
    """Resample a polyline at a uniform arc-length step, (N, 2)."""
    s = arclength(points)
    n = max(2, int(np.ceil(s[-1] / step_m)) + 1)
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, 0]), np.interp(t, s, points[:, 1])], axis=1)


def curvature(points: np.ndarray) -> np.ndarray:
    """Unsigned curvature (1/m) at each point of a uniformly resampled polyline."""
    d1 = np.gradient(points, axis=0)
    d2 = np.gradient(d1, axis=0)
    num = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    den = np.maximum(np.linalg.norm(d1, axis=1) ** 3, 1e-12)
    return num / den


def rot2(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


def rect(center, length: float, width: float, yaw: float) -> np.ndarray:
    """Corners (4, 2) of an oriented rectangle: front-left, front-right, rear-right, rear-left."""
    h = np.array(
        [[length / 2, width / 2], [length / 2, -width / 2], [-length / 2, -width / 2], [-length / 2, width / 2]]
    )
    return np.asarray(center, float) + h @ rot2(yaw).T
