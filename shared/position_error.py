"""How well a camera places a vehicle on the ground: the error model the fusion weighs positions by.

A camera sees the direction to a vehicle well and its distance poorly, the more so the farther: a fisheye looking
down from a pole maps a pixel to centimetres on the ground beneath it and to metres along the ground near its
image circle's edge, and a forward-looking camera's range grows with the tangent of a grazing ray. So the error of
a ground position has two parts, along the line from the camera and across it, each growing with the range.
`services/fuse_track/fusion.py` weighs each member of a fused object by the inverse of that covariance: two cameras
that see a vehicle from different sides pin it down where neither alone does.
"""

from __future__ import annotations

import numpy as np

# The position error of a fused object's members, by range from their camera: (range m, sigma along the line from
# the camera m, sigma across it m), linear in between and constant beyond the ends. Measured with the shipped
# (run-11) detector on the validation recording's fisheye objects (seed 77, scoring 0.3 or more, matched to a
# vehicle seen at least 30 % within 5 m): 1.48 x the median absolute error of each 10 m band at its centre, made
# non-decreasing with range (beyond 60 m the 5 m matching window cuts the errors along the line short) and carried
# on to 0 and 90 m (docs/pipeline.md, "Along and across the line of sight").
POSITION_SIGMA: tuple[tuple[float, float, float], ...] = (
    (0.0, 0.25, 0.40), (15.0, 0.27, 0.44), (25.0, 0.62, 0.47), (35.0, 1.2, 0.50), (45.0, 1.6, 0.58),
    (55.0, 1.9, 0.70), (65.0, 2.0, 0.70), (90.0, 2.5, 0.80))


def check_position_sigma(rows: object) -> tuple[tuple[float, float, float], ...]:
    """A position model (FusionConfig.position_sigma) as a tuple of float triples; ValueError naming the row."""
    try:
        table = np.asarray(rows, np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"position_sigma must be rows of (range_m, along_m, across_m), got {rows!r}") from None
    if table.ndim != 2 or table.shape[1] != 3 or len(table) == 0:
        raise ValueError(f"position_sigma must be rows of (range_m, along_m, across_m), got shape {table.shape}")
    for i, (rng, along, across) in enumerate(table):
        if not (np.isfinite(rng) and rng >= 0 and np.isfinite(along) and along > 0 and np.isfinite(across)
                and across > 0):
            raise ValueError(f"position_sigma row {i} ({rng}, {along}, {across}): the range must be >= 0 m and "
                             "both sigmas finite and > 0 m")
        if i and rng <= table[i - 1, 0]:
            raise ValueError(f"position_sigma row {i}: ranges must increase, {rng} m after {table[i - 1, 0]} m")
    return tuple((float(a), float(b), float(c)) for a, b, c in table)


def position_information(xy: np.ndarray, camera_xy: np.ndarray, table: np.ndarray) -> np.ndarray:
    """(N, 2, 2) inverse covariance of ground positions xy (N, 2) seen by cameras standing at camera_xy (N, 2),
    from a position model (FusionConfig.position_sigma as an (K, 3) array): along and across the line from the
    camera (a position at the camera itself: along east)."""
    u = xy - camera_xy
    r = np.hypot(u[:, 0], u[:, 1])
    u = np.where((r > 1e-9)[:, None], u / np.maximum(r, 1e-9)[:, None], [1.0, 0.0])
    v = np.stack([-u[:, 1], u[:, 0]], axis=1)
    along = np.interp(r, table[:, 0], table[:, 1]) ** -2
    across = np.interp(r, table[:, 0], table[:, 2]) ** -2
    return (along[:, None, None] * u[:, :, None] * u[:, None, :]
            + across[:, None, None] * v[:, :, None] * v[:, None, :])
