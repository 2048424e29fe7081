"""Geometric and photometric augmentation of training Samples.

Geometry is one affine map M (2x3, source pixels -> output pixels) applied to the image with a single
`cv2.warpAffine` and to every label in closed form:

    bottom_uv   M @ [u, v, 1]                                   exact (a point stays on its pixel)
    heading_uv  the linear part of M applied, then renormalised  exact in direction
    box         bounds of the transformed ellipse inscribed in the box, clipped to the output image:
                exact for scale / flip / crop. For a rotation, the bounds of the rotated box's corners would
                be up to 1.41 times too wide and high (a square turned 45 degrees: twice the area, IoU 0.5
                with the true box), and fisheye samples are turned by any angle: trained on those, the
                network learns boxes too large for ap50 (models/README.md). A vehicle's outline is rounder
                than its box's corners, and the ellipse keeps a box's size under rotation by 90 degrees.
    meta["principal_point"]  transformed like bottom_uv, so later steps rotate about the right point

Pixel convention (docs/recording-format.md): the centre of the top-left pixel is (0, 0) and an image W
pixels wide spans u in [-0.5, W - 0.5]. cv2.warpAffine and cv2.resize use the same convention, which
is what makes the point maps exact.

A vehicle is kept while part of its box is inside the output image (every kept box has a positive
area); it stays a positive only while its bottom centre is inside too, else it becomes an "ignore"
vehicle (weight 0). One whose box left the image is dropped, even if its bottom centre is still inside
(a partly hidden vehicle whose visible part is cropped away shows nothing, like a hidden one).

The horizontal flip mirrors the scene: it turns right-hand traffic into left-hand traffic and mirrors
the camera's view of the world, which does not matter for a detector trained in image space (heading
is an image-space vector and is mirrored with the image).

Fisheye samples (meta["kind"] == "fisheye") are also rotated by a random angle about the principal
point: for a lens looking straight down this is what the same camera rolled about its optical axis
would see, so every orientation of the road is a valid training view.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np

from training.sample import Sample

GREY = 128  # padding where the output crop extends past the (warped) source image
# meta entries that hold one value per vehicle; kept in step when vehicles are dropped
PER_VEHICLE_META = ("track_id", "parked")
FISHEYE_ROTATIONS = ("any", "quarter", "off")


@dataclass(frozen=True)
class AugmentConfig:
    """Random ranges of `augment`. Intensities are grey levels (0-255) of the uint8 image.

    scale_range         zoom factor drawn uniformly from this range (1 = the sample's own resolution)
    flip_prob           probability of a horizontal flip
    fisheye_rotation    how fisheye samples are turned about the principal point: "any" (a uniform random
                        angle; boxes approximated, see the module docstring), "quarter" (a random multiple of
                        90 degrees: boxes exact) or "off"
    focus_prob          probability of centring the crop near a random positive (else uniform crop)
    focus_by_size       draw that positive with probability proportional to its 2D box size (the square root of
                        its area) instead of uniformly: the large vehicles (a bus or truck under the pole of a
                        fisheye camera), few in number, are centred more often
    photometric         apply the intensity jitter below at all (False: geometry only)
    gamma_range         gamma of (x / 255) ** gamma
    contrast_range      gain about mid grey
    brightness_range    offset, grey levels
    noise_prob          probability of adding Gaussian noise with sigma uniform in [0, noise_sigma_max]
    blur_prob           probability of a Gaussian blur with sigma uniform in blur_sigma_range_px
    """

    scale_range: tuple[float, float] = (0.7, 1.3)
    flip_prob: float = 0.5
    fisheye_rotation: str = "any"
    focus_prob: float = 0.5
    focus_by_size: bool = False
    photometric: bool = True
    gamma_range: tuple[float, float] = (0.7, 1.4)
    contrast_range: tuple[float, float] = (0.75, 1.3)
    brightness_range: tuple[float, float] = (-20.0, 20.0)
    noise_prob: float = 0.5
    noise_sigma_max: float = 5.0
    blur_prob: float = 0.15
    blur_sigma_range_px: tuple[float, float] = (0.5, 1.2)

    def __post_init__(self) -> None:
        ranges = {
            "scale_range": (self.scale_range, 1e-3),
            "gamma_range": (self.gamma_range, 1e-3),
            "contrast_range": (self.contrast_range, 0.0),
            "brightness_range": (self.brightness_range, -255.0),
            "blur_sigma_range_px": (self.blur_sigma_range_px, 1e-3),
        }
        for name, (pair, low) in ranges.items():
            if len(pair) != 2 or not all(math.isfinite(x) for x in pair) or not low <= pair[0] <= pair[1]:
                raise ValueError(f"AugmentConfig.{name} must be (lo, hi) with {low} <= lo <= hi, got {pair}")
        for name in ("flip_prob", "focus_prob", "noise_prob", "blur_prob"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"AugmentConfig.{name} must be in [0, 1], got {p}")
        if self.fisheye_rotation not in FISHEYE_ROTATIONS:
            raise ValueError(f"AugmentConfig.fisheye_rotation must be one of {FISHEYE_ROTATIONS}, "
                             f"got {self.fisheye_rotation!r}")
        if not 0.0 <= self.noise_sigma_max < 128:
            raise ValueError(f"AugmentConfig.noise_sigma_max must be in [0, 128), got {self.noise_sigma_max}")


def _affine3(m: np.ndarray) -> np.ndarray:
    return np.vstack([np.asarray(m, np.float64).reshape(2, 3), [0.0, 0.0, 1.0]])


def _translate(du: float, dv: float) -> np.ndarray:
    return np.array([[1.0, 0.0, du], [0.0, 1.0, dv], [0.0, 0.0, 1.0]])


def _subset(sample: Sample, keep: np.ndarray, weight: np.ndarray | None = None) -> Sample:
    """The sample with only the vehicles in boolean mask `keep` (and optionally new weights)."""
    meta = dict(sample.meta)
    for key in PER_VEHICLE_META:
        if key in meta:
            meta[key] = np.asarray(meta[key])[keep]
    return replace(
        sample,
        bottom_uv=sample.bottom_uv[keep],
        box=sample.box[keep],
        heading_uv=sample.heading_uv[keep],
        size_lwh=sample.size_lwh[keep],
        vtype=sample.vtype[keep],
        weight=(sample.weight if weight is None else weight)[keep],
        meta=meta,
    )


def transform_labels(sample: Sample, m: np.ndarray, image: np.ndarray) -> Sample:
    """The labels of `sample` mapped by affine `m` (2x3, sample pixels -> pixels of `image`), with
    `image` as the new image. Vehicles are kept, turned into ignores or dropped as the module says."""
    m = np.asarray(m, np.float64).reshape(2, 3)
    a, t = m[:, :2], m[:, 2]
    h, w = image.shape[:2]
    uv = sample.bottom_uv @ a.T + t
    heading = sample.heading_uv @ a.T
    with np.errstate(invalid="ignore", divide="ignore"):
        heading = heading / np.linalg.norm(heading, axis=1, keepdims=True)
    centre = (sample.box[:, :2] + sample.box[:, 2:]) / 2 @ a.T + t
    half = (sample.box[:, 2:] - sample.box[:, :2]) / 2  # the inscribed ellipse's half axes
    half = np.sqrt((half**2) @ (a**2).T)  # bounds of the mapped ellipse: sqrt(sum_j a_ij^2 half_j^2)
    lo = np.clip(centre - half, -0.5, [w - 0.5, h - 0.5])
    hi = np.clip(centre + half, -0.5, [w - 0.5, h - 0.5])
    box = np.concatenate([lo, hi], axis=1)
    inside = (uv[:, 0] >= -0.5) & (uv[:, 0] < w - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < h - 0.5)
    overlaps = (hi[:, 0] > lo[:, 0]) & (hi[:, 1] > lo[:, 1])
    keep = overlaps
    meta = dict(sample.meta)
    if meta.get("principal_point") is not None:
        meta["principal_point"] = tuple(float(x) for x in a @ np.asarray(meta["principal_point"], float) + t)
    moved = replace(sample, image=image, bottom_uv=uv, box=box, heading_uv=heading, meta=meta)
    return _subset(moved, keep, np.where(inside, sample.weight, 0.0))


def warp_sample(sample: Sample, m: np.ndarray, out_hw: tuple[int, int], border: int = GREY) -> Sample:
    """Warp image and labels by affine `m` (2x3, sample pixels -> output pixels) into an image of
    out_hw = (H, W); bilinear, `border` grey outside the source."""
    out_h, out_w = int(out_hw[0]), int(out_hw[1])
    if out_h <= 0 or out_w <= 0:
        raise ValueError(f"out_hw must be positive, got {out_hw}")
    m = np.asarray(m, np.float64).reshape(2, 3)
    image = cv2.warpAffine(
        sample.image, m, (out_w, out_h), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=border
    )
    return transform_labels(sample, m, image)


def resize_sample(sample: Sample, scale: float) -> Sample:
    """Image and labels resized by `scale` (0.5 halves both sides; sizes are rounded to whole pixels
    and the labels follow the actual per-axis factor). Area averaging when shrinking."""
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"{sample.source}: scale must be a positive number, got {scale}")
    h, w = sample.shape
    new_w, new_h = max(1, round(w * scale)), max(1, round(h * scale))
    sx, sy = new_w / w, new_h / h
    interp = cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR
    image = cv2.resize(sample.image, (new_w, new_h), interpolation=interp)
    # pixel edges scale about the image corner: u' + 0.5 = s (u + 0.5)
    m = np.array([[sx, 0.0, 0.5 * (sx - 1)], [0.0, sy, 0.5 * (sy - 1)]])
    return transform_labels(sample, m, image)


def _crop_start(lo: float, hi: float, size: int, rng: np.random.Generator, centre: float | None) -> float:
    """Left (or top) edge of a crop `size` wide over content spanning [lo, hi]: inside the content
    when it is wider than the crop, else placing the whole content somewhere inside the crop."""
    a, b = (lo, hi - size) if hi - lo >= size else (hi - size, lo)
    if centre is None:
        return float(rng.uniform(a, b))
    return float(np.clip(centre - size / 2 + rng.uniform(-0.4, 0.4) * size, a, b))


def random_affine(
    sample: Sample, rng: np.random.Generator, out_hw: tuple[int, int], config: AugmentConfig
) -> np.ndarray:
    """Draw the augmentation's affine map (2x3, sample pixels -> out_hw crop pixels)."""
    h, w = sample.shape
    out_h, out_w = out_hw
    m = np.eye(3)
    if config.fisheye_rotation != "off" and sample.meta.get("kind") == "fisheye":
        pp = sample.meta.get("principal_point")
        cx, cy = ((w - 1) / 2, (h - 1) / 2) if pp is None else (float(pp[0]), float(pp[1]))
        if config.fisheye_rotation == "quarter":
            c, s = [(1.0, 0.0), (0.0, 1.0), (-1.0, 0.0), (0.0, -1.0)][int(rng.integers(4))]
        else:
            angle = rng.uniform(0.0, 2.0 * math.pi)
            c, s = math.cos(angle), math.sin(angle)
        m = _translate(cx, cy) @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ _translate(-cx, -cy) @ m
    zoom = rng.uniform(*config.scale_range)
    m = np.diag([zoom, zoom, 1.0]) @ m
    if rng.random() < config.flip_prob:
        m = np.diag([-1.0, 1.0, 1.0]) @ m
    edges = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [w - 0.5, h - 0.5, 1.0], [-0.5, h - 0.5, 1.0]])
    warped = edges @ m.T
    lo, hi = warped[:, :2].min(0), warped[:, :2].max(0)
    centre = None
    positives = np.flatnonzero(sample.weight > 0)
    if len(positives) and rng.random() < config.focus_prob:
        p = None
        if config.focus_by_size:
            size = np.sqrt(np.prod(np.clip(sample.box[positives, 2:] - sample.box[positives, :2], 1.0, None), axis=1))
            p = size / size.sum()
        centre = m[:2] @ np.append(sample.bottom_uv[rng.choice(positives, p=p)], 1.0)
    u0 = _crop_start(lo[0], hi[0], out_w, rng, None if centre is None else centre[0])
    v0 = _crop_start(lo[1], hi[1], out_h, rng, None if centre is None else centre[1])
    # the crop's edge u0 becomes the output's edge -0.5
    m = _translate(-u0 - 0.5, -v0 - 0.5) @ m
    return m[:2]


def jitter_intensity(image: np.ndarray, rng: np.random.Generator, config: AugmentConfig) -> np.ndarray:
    """Gamma, contrast, brightness, then occasional blur and noise, on a (H, W) uint8 image (a new array)."""
    gamma = rng.uniform(*config.gamma_range)
    gain = rng.uniform(*config.contrast_range)
    offset = rng.uniform(*config.brightness_range)
    levels = 255.0 * (np.arange(256) / 255.0) ** gamma
    lut = np.clip((levels - 128.0) * gain + 128.0 + offset, 0, 255).round().astype(np.uint8)
    out = cv2.LUT(image, lut)
    if rng.random() < config.blur_prob:
        out = cv2.GaussianBlur(out, (0, 0), rng.uniform(*config.blur_sigma_range_px))
    if rng.random() < config.noise_prob and config.noise_sigma_max > 0:
        sigma = rng.uniform(0.0, config.noise_sigma_max)
        noisy = out.astype(np.float32) + rng.normal(0.0, sigma, out.shape).astype(np.float32)
        out = np.clip(noisy, 0, 255).round().astype(np.uint8)
    return out


def augment(
    sample: Sample,
    rng: np.random.Generator,
    out_hw: tuple[int, int] = (256, 256),
    config: AugmentConfig | None = None,
) -> Sample:
    """A random out_hw = (H, W) training view of `sample` (which is not modified): fisheye rotation,
    zoom, flip and crop as one exact affine warp, then intensity jitter. See the module docstring."""
    config = config or AugmentConfig()
    m = random_affine(sample, rng, out_hw, config)
    out = warp_sample(sample, m, out_hw)
    if config.photometric:
        out = replace(out, image=jitter_intensity(out.image, rng, config))
    return out
