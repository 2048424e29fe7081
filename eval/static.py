"""Detections that stay put: candidates for a camera's exclusion zones (`cameras[].exclude_px`).

A painted word, a lamp head or a pole the detector mistakes for a vehicle is detected at the same pixel frame
after frame. `static_detections` runs a detector over a camera's recorded frames, groups the bottom centres
that lie within `radius_px` of each other across frames, and reports each group seen in at least
`min_fraction` of the frames, with a square polygon ready for site.yaml. A parked vehicle stays put too: look at
each candidate (`crop` gives the image around it) before excluding it; only what is never a vehicle belongs in
an exclusion zone, and a zone small enough that vehicles driving over the spot are dropped only while their
bottom centre is on it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np

from shared.decode import Detections


@dataclass
class StaticSpot:
    """A place detections keep coming back to. uv: the mean bottom centre (px); frames: in how many of the frames
    it was detected; fraction: frames / all frames; score: the mean score there; exclude_px: a square of
    `2 * half_px` pixels around uv for site.yaml."""

    uv: tuple[float, float]
    frames: int
    fraction: float
    score: float
    exclude_px: list[list[float]]

    def as_dict(self) -> dict:
        return {"uv": [round(c, 1) for c in self.uv], "frames": self.frames, "fraction": round(self.fraction, 3),
                "score": round(self.score, 3), "exclude_px": self.exclude_px}


def static_detections(images: Iterable[np.ndarray], detect: Callable[[np.ndarray], Detections],
                      radius_px: float = 6.0, min_fraction: float = 0.5, half_px: float = 7.5) -> dict:
    """Run `detect` on every image and return {"frames": N, "spots": [StaticSpot.as_dict(), ...]} for the places
    detected in at least `min_fraction` of the N frames (most frequent first). A detection joins the nearest
    group whose running mean is within `radius_px` and which has nothing yet from this frame; else it starts one."""
    if not radius_px > 0:
        raise ValueError(f"radius_px must be > 0, got {radius_px}")
    if not 0 < min_fraction <= 1:
        raise ValueError(f"min_fraction must be within (0, 1], got {min_fraction}")
    sums = np.zeros((0, 2))
    counts = np.zeros(0, np.int64)
    scores = np.zeros(0)
    n = 0
    for image in images:
        det = detect(image)
        n += 1
        taken = np.zeros(len(counts), bool)
        for uv, score in zip(det.uv, det.score, strict=True):
            if len(counts):
                d = np.hypot(*(sums / counts[:, None] - uv).T)
                d[taken] = np.inf
                k = int(np.argmin(d))
                if d[k] <= radius_px:
                    sums[k] += uv
                    counts[k] += 1
                    scores[k] += score
                    taken[k] = True
                    continue
            sums = np.vstack([sums, uv])
            counts = np.append(counts, 1)
            scores = np.append(scores, score)
            taken = np.append(taken, True)
    if n == 0:
        raise ValueError("no frames to look at")
    spots = []
    for k in np.argsort(-counts, kind="stable"):
        if counts[k] < min_fraction * n:
            break
        u, v = sums[k] / counts[k]
        square = [[round(u - half_px, 1), round(v - half_px, 1)], [round(u + half_px, 1), round(v - half_px, 1)],
                  [round(u + half_px, 1), round(v + half_px, 1)], [round(u - half_px, 1), round(v + half_px, 1)]]
        spots.append(StaticSpot((float(u), float(v)), int(counts[k]), counts[k] / n, float(scores[k] / counts[k]),
                                square).as_dict())
    return {"frames": n, "radius_px": radius_px, "min_fraction": min_fraction, "spots": spots}


def crop(image: np.ndarray, uv: tuple[float, float], half: int = 48, zoom: int = 3) -> np.ndarray:
    """The image around uv (clipped at the borders), enlarged `zoom` times, for looking at a candidate."""
    u, v = round(uv[0]), round(uv[1])
    h, w = image.shape[:2]
    part = image[max(v - half, 0):min(v + half, h), max(u - half, 0):min(u + half, w)]
    return part.repeat(zoom, axis=0).repeat(zoom, axis=1)
