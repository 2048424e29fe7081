"""One training/evaluation image and its labelled vehicles, independent of where they came from
(a simulator recording or a user's COCO-style annotations)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

VEHICLE_TYPES = ("car", "suv_van", "truck", "bus", "motorcycle")


@dataclass
class Sample:
    """A grey image and N vehicles, all in this image's pixel coordinates.

    image       (H, W) uint8 grey
    bottom_uv   (N, 2) float: bottom centre (centre of the ground footprint) in pixels
    box         (N, 4) float: 2D box x1, y1, x2, y2 of the visible vehicle (pixels)
    heading_uv  (N, 2) float: unit vector in the image from the footprint's rear towards its front
                (NaN where unknown; such vehicles get no heading loss)
    size_lwh    (N, 3) float: length, width, height in metres (NaN where unknown)
    vtype       (N,)   int: index into VEHICLE_TYPES (-1 where unknown)
    weight      (N,)   float: 1 for a vehicle to detect, 0 for an "ignore" vehicle (mostly hidden,
                tiny): no positive target and no penalty for detecting it
    source      where it came from (file path and camera), for error messages
    meta        free-form extras (camera kind, principal point for fisheye rotation, t_ns, ...)
    """

    image: np.ndarray
    bottom_uv: np.ndarray
    box: np.ndarray
    heading_uv: np.ndarray
    size_lwh: np.ndarray
    vtype: np.ndarray
    weight: np.ndarray
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n = len(self.bottom_uv)
        self.bottom_uv = np.asarray(self.bottom_uv, np.float64).reshape(n, 2)
        self.box = np.asarray(self.box, np.float64).reshape(n, 4)
        self.heading_uv = np.asarray(self.heading_uv, np.float64).reshape(n, 2)
        self.size_lwh = np.asarray(self.size_lwh, np.float64).reshape(n, 3)
        self.vtype = np.asarray(self.vtype, np.int64).reshape(n)
        self.weight = np.asarray(self.weight, np.float64).reshape(n)
        if self.image.ndim != 2 or self.image.dtype != np.uint8:
            raise ValueError(f"{self.source}: image must be (H, W) uint8 grey, got "
                             f"{self.image.shape} {self.image.dtype}")

    def __len__(self) -> int:
        return len(self.bottom_uv)

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[:2]
