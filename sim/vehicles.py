"""3D shapes of vehicles and pedestrians as oriented boxes in the object's own frame
(x forward, y left, z up, origin at the bottom centre on the ground)."""

from __future__ import annotations

import numpy as np

PART_KINDS = ("body", "cabin", "wheel", "cargo", "chassis", "busbody", "rider", "head", "legs", "torso")


def vehicle_parts(vtype: str, length: float, width: float, height: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(P, 3) centres, (P, 3) half sizes, (P,) part kind indices for a vehicle."""
    l, w, h = length, width, height
    parts: list[tuple[float, float, float, float, float, float, str]] = []  # x0 x1 y0 y1 z0 z1 kind

    def wheels(xs, r, half_w=0.12):
        for x in xs:
            for side in (-1, 1):
                y = side * (w / 2 - half_w - 0.02)
                parts.append((x - r, x + r, y - half_w, y + half_w, 0.0, 2 * r, "wheel"))

    if vtype in ("car", "suv_van"):
        suv = vtype == "suv_van"
        clear, r = (0.22, 0.37) if suv else (0.17, 0.32)
        hb = clear + (0.52 if suv else 0.5) * (h - clear)
        parts.append((-l / 2, l / 2, -w / 2, w / 2, clear, hb, "body"))
        cx0, cx1 = (-0.46 * l, 0.2 * l) if suv else (-0.3 * l, 0.16 * l)
        parts.append((cx0, cx1, -w / 2 + 0.09, w / 2 - 0.09, hb, h, "cabin"))
        wheels((l / 2 - 0.85, -l / 2 + 0.9), r)
    elif vtype == "truck":
        parts.append((l / 2 - 2.0, l / 2, -w / 2 + 0.05, w / 2 - 0.05, 0.55, min(2.75, h), "cabin"))
        parts.append((-l / 2, l / 2 - 2.15, -w / 2, w / 2, 0.95, h, "cargo"))
        parts.append((-l / 2 + 0.3, l / 2 - 0.3, -w / 2 + 0.3, w / 2 - 0.3, 0.45, 0.95, "chassis"))
        wheels((l / 2 - 1.2, -l / 2 + 1.6, -l / 2 + 2.7), 0.5, 0.16)
    elif vtype == "bus":
        parts.append((-l / 2, l / 2, -w / 2, w / 2, 0.35, h, "busbody"))
        wheels((l / 2 - 2.4, -l / 2 + 3.0), 0.5, 0.16)
    elif vtype == "motorcycle":
        parts.append((-l / 2 + 0.3, l / 2 - 0.3, -0.2, 0.2, 0.35, 0.95, "body"))
        parts.append((-0.5, 0.05, -0.22, 0.22, 0.95, h - 0.27, "rider"))
        parts.append((-0.35, -0.08, -0.14, 0.14, h - 0.29, h, "head"))
        for x in (l / 2 - 0.34, -l / 2 + 0.34):
            parts.append((x - 0.32, x + 0.32, -0.06, 0.06, 0.0, 0.64, "wheel"))
    else:
        raise ValueError(f"unknown vehicle type {vtype!r}")
    return _to_arrays(parts)


def pedestrian_parts(height: float = 1.75) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    parts = [
        (-0.12, 0.12, -0.16, 0.16, 0.0, 0.48 * height, "legs"),
        (-0.13, 0.13, -0.23, 0.23, 0.48 * height, 0.86 * height, "torso"),
        (-0.1, 0.1, -0.09, 0.09, 0.87 * height, height, "head"),
    ]
    return _to_arrays(parts)


def _to_arrays(parts) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.array([p[:6] for p in parts], float)
    centre = np.stack([(a[:, 0] + a[:, 1]) / 2, (a[:, 2] + a[:, 3]) / 2, (a[:, 4] + a[:, 5]) / 2], 1)
    half = np.stack([(a[:, 1] - a[:, 0]) / 2, (a[:, 3] - a[:, 2]) / 2, (a[:, 5] - a[:, 4]) / 2], 1)
    kinds = np.array([PART_KINDS.index(p[6]) for p in parts], np.int64)
    return centre, half, kinds
