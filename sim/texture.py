"""Top-down ground rasters of a site: material classes, visible albedo (RGB) and thermal level.

Raster pixel (col, row) covers site x = -extent + (col + 0.5) * res, y = extent - (row + 0.5) * res.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from sim.roads import Paint, RoadNetwork, dashes

GRASS, ASPHALT, SIDEWALK, BRICK, CURB, MARKING = range(6)
MATERIAL_NAMES = ("grass", "asphalt", "sidewalk", "brick", "curb", "marking")
# Thermal level (0..1, warmer = higher) of each material on a sunny day.
THERMAL_LEVEL = np.array([0.30, 0.62, 0.50, 0.55, 0.47, 0.55], np.float32)
PAINT_RGB = {"white": (236, 236, 230), "yellow": (226, 186, 46)}


@dataclass
class GroundRaster:
    res_m: float
    extent_m: float
    material: np.ndarray  # (S, S) uint8 material class
    albedo: np.ndarray  # (S, S, 3) uint8 RGB
    thermal: np.ndarray  # (S, S) uint8, 0..255 thermal level

    @property
    def size(self) -> int:
        return self.material.shape[0]

    def to_px(self, xy: np.ndarray) -> np.ndarray:
        """(..., 2) site metres -> (..., 2) raster (col, row) float coordinates."""
        xy = np.asarray(xy, np.float64)
        col = (xy[..., 0] + self.extent_m) / self.res_m - 0.5
        row = (self.extent_m - xy[..., 1]) / self.res_m - 0.5
        return np.stack([col, row], axis=-1)

    def material_at(self, xy: np.ndarray) -> np.ndarray:
        px = np.round(self.to_px(xy)).astype(np.int64)
        px = np.clip(px, 0, self.size - 1)
        return self.material[px[..., 1], px[..., 0]]


def _smooth_noise(rng: np.random.Generator, size: int, cells: int) -> np.ndarray:
    """Zero-mean, unit-ish std value noise with `cells` features across the raster, float32."""
    small = rng.standard_normal((cells + 1, cells + 1)).astype(np.float32)
    return cv2.resize(small, (size, size), interpolation=cv2.INTER_CUBIC)


def _polys_px(raster: GroundRaster, polys: list[np.ndarray]) -> list[np.ndarray]:
    return [np.round(raster.to_px(p) * 16).astype(np.int32) for p in polys]


def paint_ground(net: RoadNetwork, extent_m: float, seed: int, res_m: float = 0.04) -> GroundRaster:
    """Paint the site's ground: asphalt, islands, sidewalks, curbs, markings and text."""
    size = int(round(2 * extent_m / res_m))
    rng = np.random.default_rng([seed, 11])
    material = np.full((size, size), GRASS, np.uint8)
    raster = GroundRaster(res_m, extent_m, material, np.zeros((1, 1, 3), np.uint8), np.zeros((1, 1), np.uint8))
    paint: Paint = net.paint
    shift = 4  # cv2 fixed-point drawing with 4 fractional bits
    for poly in _polys_px(raster, paint.asphalt_polys):
        cv2.fillPoly(material, [poly], ASPHALT, cv2.LINE_8, shift)
    for pts, width in paint.asphalt_strokes:
        px = np.round(raster.to_px(pts)).astype(np.int32)
        cv2.polylines(material, [px], False, ASPHALT, int(round(width / res_m)), cv2.LINE_8)
    road = material == ASPHALT
    # Sidewalks: a band of concrete behind a grass verge, where nothing else is.
    dist = cv2.distanceTransform((~road).astype(np.uint8), cv2.DIST_L2, 5) * res_m
    material[(dist > 1.8) & (dist < 3.9)] = SIDEWALK
    material[(dist > 0) & (dist <= 0.16)] = CURB
    island_masks = []
    for poly, mat in paint.islands:
        m = np.zeros_like(material)
        cv2.fillPoly(m, _polys_px(raster, [poly]), 1, cv2.LINE_8, shift)
        code = {"grass": GRASS, "brick": BRICK, "concrete": SIDEWALK}[mat]
        material[m > 0] = code
        island_masks.append(m)
    for m in island_masks:  # curbs around raised islands
        edge = cv2.morphologyEx(m, cv2.MORPH_GRADIENT, np.ones((5, 5), np.uint8))
        material[(edge > 0) & (m > 0)] = CURB

    # Albedo per material with multi-scale variation.
    base = np.array(
        [[96, 104, 70], [82, 82, 84], [178, 176, 168], [158, 78, 66], [196, 196, 190], [0, 0, 0]], np.float32
    )
    low = _smooth_noise(rng, size, 24)
    mid = _smooth_noise(rng, size, 160)
    grain = rng.standard_normal((size, size), dtype=np.float32)
    albedo = base[material]
    var_scale = np.array([12, 7, 6, 8, 4, 0], np.float32)[material]
    albedo += ((0.6 * low + 0.5 * mid) * var_scale)[..., None]
    albedo += (grain * np.array([7, 4, 5, 6, 3, 0], np.float32)[material])[..., None]
    grass = material == GRASS
    albedo[grass, 0] += 8 * low[grass]  # winter grass: patches of brown
    albedo[grass, 2] -= 6 * low[grass]
    del grain, mid

    # Markings on top, slightly worn.
    mark = np.zeros((size, size), np.uint8)
    colour_idx = {"white": 1, "yellow": 2}
    for mk in paint.markings:
        pieces = [mk.points] if mk.dash is None else dashes(mk.points, *mk.dash)
        th = max(1, int(round(mk.width_m / res_m)))
        for piece in pieces:
            px = np.round(raster.to_px(piece) * 16).astype(np.int32)
            cv2.polylines(mark, [px], False, colour_idx[mk.color], th, cv2.LINE_8, shift)
    for poly, colour in paint.marking_polys:
        cv2.fillPoly(mark, _polys_px(raster, [poly]), colour_idx[colour], cv2.LINE_8, shift)
    for text, xy, yaw, height in paint.texts:
        _paint_text(mark, raster, text, xy, yaw, height)
    wear = np.clip(0.88 + 0.12 * _smooth_noise(rng, size, 300), 0.6, 1.0)
    for name, idx in colour_idx.items():
        m = mark == idx
        albedo[m] = np.asarray(PAINT_RGB[name], np.float32) * wear[m, None]
    material[mark > 0] = MARKING
    albedo = np.clip(albedo, 0, 255).astype(np.uint8)

    thermal = THERMAL_LEVEL[material] + 0.025 * low + 0.01 * _smooth_noise(rng, size, 400)
    thermal = np.clip(thermal * 255, 0, 255).astype(np.uint8)
    return GroundRaster(res_m, extent_m, material, albedo, thermal)


def _paint_text(mark: np.ndarray, raster: GroundRaster, text: str, xy: np.ndarray, yaw: float, height_m: float) -> None:
    """Paint `text` on the ground, its baseline along `yaw`, readable from a driver heading `yaw`.

    Road text is elongated along the direction of travel (like real pavement lettering)."""
    scale = 4
    (tw, th), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 12)
    patch = np.zeros((th + 40, tw + 40), np.uint8)
    cv2.putText(patch, text, (20, th + 20), cv2.FONT_HERSHEY_SIMPLEX, scale, 255, 12, cv2.LINE_AA)
    # Patch coords -> site metres: the reading direction runs across the lane (to the driver's
    # right), the letters' up direction points along the travel direction (yaw).
    width_m = 2.6
    fwd = np.array([math.cos(yaw), math.sin(yaw)])
    right = np.array([math.sin(yaw), -math.cos(yaw)])
    sx = width_m / patch.shape[1]
    sy = height_m / patch.shape[0]
    origin = np.asarray(xy, float) - right * width_m / 2 + fwd * height_m / 2
    # site = origin + right * (px * sx) - fwd * (py * sy); then to raster coords.
    a = np.array([[right[0] * sx, -fwd[0] * sy], [right[1] * sx, -fwd[1] * sy]]) / raster.res_m
    a[1] *= -1
    o = raster.to_px(origin)
    m = np.hstack([a, o[:, None]]).astype(np.float32)
    corners = np.array([[0, 0], [patch.shape[1], 0], [0, patch.shape[0]], [patch.shape[1], patch.shape[0]]], float)
    mapped = corners @ a.T + o
    x0, y0 = np.floor(mapped.min(0)).astype(int) - 2
    x1, y1 = np.ceil(mapped.max(0)).astype(int) + 2
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1, mark.shape[1]), min(y1, mark.shape[0])
    if x1 <= x0 or y1 <= y0:
        return
    m[:, 2] -= [x0, y0]
    warped = cv2.warpAffine(patch, m, (x1 - x0, y1 - y0), flags=cv2.INTER_LINEAR)
    region = mark[y0:y1, x0:x1]
    region[warped > 110] = 1
