"""Where a camera's image shows anything: the rectangle around a fisheye's image circle, for the site file's
`cameras[].detect_area_px` (the detector then skips the black sides; `roadside area`).

The brightest value of every pixel over a sample of frames (a pixel of the circle is lit in some frame, the black
outside never is); the columns (rows) where more than `share` of the rows (columns) are brighter than `level`
bound the rectangle.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import cv2
import numpy as np


def image_area(images: Iterable[tuple[str, np.ndarray]], level: float = 40.0,
               share: float = 0.02) -> tuple[tuple[int, int, int, int], tuple[int, int], int]:
    """(x0, y0, x1, y1) with x1, y1 exclusive, the image size (width, height) and the number of frames, from
    (name, grey or BGR image) pairs. ValueError naming the frame for one of another size, and when no pixel is
    brighter than `level` (all frames dark)."""
    if not 0 <= level < 255:
        raise ValueError(f"level must be within [0, 255), got {level}")
    if not 0 <= share < 1:
        raise ValueError(f"share must be within [0, 1), got {share}")
    brightest, n = None, 0
    for name, img in images:
        grey = img if img.ndim == 2 else cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
        if brightest is None:
            brightest = grey.copy()
        elif grey.shape != brightest.shape:
            raise ValueError(f"{name}: {grey.shape[1]}x{grey.shape[0]}, the frames before it are "
                             f"{brightest.shape[1]}x{brightest.shape[0]}")
        else:
            np.maximum(brightest, grey, out=brightest)
        n += 1
    if brightest is None:
        raise ValueError("no frames")
    lit = brightest > level
    cols = np.flatnonzero(lit.mean(axis=0) > share)
    rows = np.flatnonzero(lit.mean(axis=1) > share)
    if not len(cols) or not len(rows):
        raise ValueError(f"no pixel of the {n} frame(s) is brighter than {level:g}: all dark (night?), or lower "
                         "the level")
    h, w = brightest.shape
    return (int(cols[0]), int(rows[0]), int(cols[-1]) + 1, int(rows[-1]) + 1), (w, h), n


def read_frames(paths: list[Path]) -> Iterable[tuple[str, np.ndarray]]:
    """(path, grey image) of each file, read as needed; ValueError naming a file that is not a readable image."""
    for p in paths:
        img = cv2.imread(str(p), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise ValueError(f"{p}: not a readable image")
        yield str(p), img
