"""Training data: Samples from simulator recordings and from COCO-style 2D annotations, and a batcher.

Both sources give `SampleRef`s: the labels (small arrays) in memory and the image left on disk until
`load()`, so a data set of thousands of frames costs little until it is used.

Label policy for recordings (`vehicle_weight`)
----------------------------------------------
A listed vehicle with at least one visible pixel is a label:
- positive (weight 1) when its bottom centre is in the image (`in_image`, which includes the fisheye
  image circle), `visible_px >= MIN_VISIBLE_PX` and `visible_fraction >= MIN_VISIBLE_FRACTION`
  (both measured at the recording's full resolution);
- otherwise "ignore" (weight 0): tiny, mostly hidden or with its bottom centre outside the image;
  no positive target and no penalty for detecting it.
A vehicle with no visible pixel (fully hidden) is not a label at all: nothing in the image shows it.

The 2D box is `box_visible`, the bounds of the vehicle's visible pixels (as edges, i.e. pixel bounds
grown by half a pixel), not the projected 3D box: the detector is trained, and its AP measured, on
the box a person would draw around what the image shows, which is what COCO-style annotations of
real images contain. For a partly hidden vehicle the bottom centre can therefore lie outside its box
(for example a car whose lower half is behind another); the detector's offset head regresses the box
relative to the bottom centre, so that is representable.

The heading is the image vector from the middle of the rear footprint edge to the middle of the
front edge (`corners_uv`), normalised; `size_lwh` is the true size; `vtype` indexes VEHICLE_TYPES.
An ignore vehicle whose bottom centre is outside the lens field of view (`uv` null) gets the middle
of its box's bottom edge as bottom centre.

Sample.meta from a recording: camera, kind (fisheye / pinhole), modality (visible / thermal),
principal_point (cx, cy) in the sample's pixels, t_ns, recording (folder), track_id (N,) and
parked (N,) per vehicle.

COCO-style annotation format (`samples_from_coco`, `write_coco`)
---------------------------------------------------------------
Standard COCO detection JSON: {"images": [...], "annotations": [...], "categories": [...]}.
- images: `id`, `file_name` (relative to the images folder); optional `width`, `height` (checked on
  load) and our extras `kind` ("fisheye" / "pinhole"), `principal_point` [u, v], `camera`,
  `modality`, `t_ns`.
- categories: `id`, `name`, one of car, suv_van, truck, bus, motorcycle or an alias (van, suv,
  pickup -> suv_van; motorbike -> motorcycle; vehicle -> type unknown). Another name is an error
  when an annotation uses it.
- annotations: `id`, `image_id`, `category_id`, `bbox` [x, y, w, h] (w, h > 0); optional `iscrowd`
  (1 = ignore vehicle, weight 0) and our extras:
  `bottom_rect` [[u, v] x 4], the footprint (the paper's bottom rectangle) front-left, front-right,
  rear-right, rear-left: bottom centre = mean of the four, heading = mid(front) - mid(rear);
  `bottom_center` [u, v] (takes precedence over the rectangle's mean);
  `heading_uv` [du, dv] image direction rear -> front, used when there is no `bottom_rect`;
  `lwh` [length, width, height] metres.
  Without `bottom_rect` / `bottom_center` the bottom centre is the middle of the box's bottom edge
  (a fair guess for a vehicle seen from the side, poor from above), and without `bottom_rect` /
  `heading_uv` the heading is unknown (NaN).
- All coordinates in the file use COCO's pixel convention (the image spans [0, W] x [0, H], a pixel's
  centre is at +0.5); Samples put pixel centres on integers, so reading subtracts 0.5 and writing
  adds it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from sim.recording import Recording
from training.augment import resize_sample
from training.sample import VEHICLE_TYPES, Sample

MIN_VISIBLE_PX = 40  # fewer visible pixels (at full resolution) than this: ignore
MIN_VISIBLE_FRACTION = 0.25  # less of the vehicle visible than this: ignore
COCO_PIXEL_OFFSET = 0.5  # COCO coordinate = our coordinate + 0.5
TYPE_ALIASES = {
    **{t: t for t in VEHICLE_TYPES},
    "van": "suv_van",
    "suv": "suv_van",
    "pickup": "suv_van",
    "motorbike": "motorcycle",
    "vehicle": None,  # a vehicle of unknown type
}


MAX_CACHE_BYTES = 6_000_000_000


def default_cache_bytes() -> int:
    """Decoded training images kept in memory by default: a third of the memory available now, at most
    MAX_CACHE_BYTES (run 8's 15,840 images at the network's input size take 4.7 GB; with the 1.5 GB cache of
    before, two thirds of them were decoded again from their full-size JPEGs every time they were drawn, about
    a fifth of each training step on this 2-core machine)."""
    import psutil

    return int(min(MAX_CACHE_BYTES, psutil.virtual_memory().available / 3))


@dataclass(frozen=True, eq=False)
class SampleRef:
    """One image on disk and its labels in memory; `load()` returns the Sample.

    image_path  the image file (read as grey)
    labels      Sample's label arrays (bottom_uv, box, heading_uv, size_lwh, vtype, weight) in the
                file's original pixels
    image_hw    (H, W) the image must have, or None when the source does not say
    scale       resize factor applied on load (None = original size)
    source      where it came from, for error messages
    meta        Sample.meta, in original pixels
    """

    image_path: Path
    labels: dict[str, np.ndarray]
    image_hw: tuple[int, int] | None = None
    scale: float | None = None
    source: str = ""
    meta: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.labels["bottom_uv"])

    @property
    def n_positive(self) -> int:
        return int((self.labels["weight"] > 0).sum())

    def load(self) -> Sample:
        image = read_grey(self.image_path)
        if self.image_hw is not None and image.shape != tuple(self.image_hw):
            h, w = self.image_hw
            raise ValueError(
                f"{self.image_path}: image is {image.shape[1]}x{image.shape[0]}, {self.source} says {w}x{h}"
            )
        meta = {k: (np.array(v) if isinstance(v, np.ndarray) else v) for k, v in self.meta.items()}
        labels = {k: np.array(v) for k, v in self.labels.items()}
        sample = Sample(image=image, source=self.source, meta=meta, **labels)
        return sample if self.scale is None else resize_sample(sample, self.scale)


def read_grey(path: Path) -> np.ndarray:
    """(H, W) uint8 grey image from a file (colour is converted). ValueError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: image file is missing")
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ValueError(f"{path}: cannot decode image (corrupt or not an image)")
    return image


def _check_scale(scale: float | None, where: object) -> None:
    if scale is not None and not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise ValueError(f"{where}: scale must be a positive number or None, got {scale!r}")


def _unit(d: np.ndarray) -> np.ndarray:
    """(2,) direction -> unit vector, NaN when it has no direction."""
    n = float(np.hypot(d[0], d[1]))
    return d / n if math.isfinite(n) and n > 1e-9 else np.full(2, np.nan)


def _rect_heading(rect: np.ndarray) -> np.ndarray:
    """Footprint corners (4, 2) front-left, front-right, rear-right, rear-left -> unit rear->front."""
    return _unit((rect[0] + rect[1]) / 2 - (rect[2] + rect[3]) / 2)


def _empty_labels() -> dict[str, list]:
    return {k: [] for k in ("bottom_uv", "box", "heading_uv", "size_lwh", "vtype", "weight")}


def _as_arrays(labels: dict[str, list]) -> dict[str, np.ndarray]:
    widths = {"bottom_uv": 2, "box": 4, "heading_uv": 2, "size_lwh": 3}
    out = {k: np.asarray(v, np.float64).reshape(-1, widths[k]) for k, v in labels.items() if k in widths}
    out["vtype"] = np.asarray(labels["vtype"], np.int64).reshape(-1)
    out["weight"] = np.asarray(labels["weight"], np.float64).reshape(-1)
    return out


# ---- recordings ---------------------------------------------------------------------------------


def vehicle_weight(vehicle: dict) -> float | None:
    """The label policy (module docstring): 1.0 positive, 0.0 ignore, None not a label."""
    if vehicle["visible_px"] <= 0 or vehicle["box_visible"] is None:
        return None
    if (
        vehicle["in_image"]
        and vehicle["uv"] is not None
        and vehicle["visible_px"] >= MIN_VISIBLE_PX
        and vehicle["visible_fraction"] >= MIN_VISIBLE_FRACTION
    ):
        return 1.0
    return 0.0


def recording_labels(vehicles: list[dict], where: str) -> tuple[dict[str, np.ndarray], list[int], list[bool]]:
    """A recording frame's ground-truth vehicles -> (Sample label arrays, track ids, parked flags), with the
    label policy of the module docstring (box_visible, ignores); ValueError naming `where` and the vehicle when a
    value is missing, not a number, not finite (a NaN) or out of order (a box's x2 < x1)."""
    labels = _empty_labels()
    ids, parked = [], []
    for v in vehicles:
        try:
            weight = vehicle_weight(v)
            if weight is None:
                continue
            # a NaN would become a positive label and stop the training at its batch, naming no file
            at = f"{where}: vehicle {v.get('id')}"
            x1, y1, x2, y2 = _numbers(v["box_visible"], (4,), "box_visible", at)
            if x2 < x1 or y2 < y1:
                raise ValueError(f"{at}: box_visible must be [x1, y1, x2, y2] with x1 <= x2 and y1 <= y2, got "
                                 f"{v['box_visible']!r}")
            box = [x1 - 0.5, y1 - 0.5, x2 + 0.5, y2 + 0.5]  # pixel bounds -> edges
            if v["uv"] is not None:
                uv = _numbers(v["uv"], (2,), "uv", at)
                corners = v["corners_uv"]
                if isinstance(corners, list) and any(c is None for c in corners):
                    heading = np.full(2, np.nan)  # a corner the camera cannot project (behind a pinhole camera)
                else:
                    heading = _rect_heading(_numbers(corners, (4, 2), "corners_uv", at))
            else:  # the corners may be outside the lens model's valid range
                uv = [(box[0] + box[2]) / 2, box[3]]
                heading = np.full(2, np.nan)
            lwh = _numbers(v["lwh"], (3,), "lwh", at)
            if (lwh <= 0).any():
                raise ValueError(f"{at}: lwh must be positive metres, got {v['lwh']!r}")
            if v["type"] not in VEHICLE_TYPES:
                raise ValueError(f"{at} has unknown type {v['type']!r}")
            labels["bottom_uv"].append([float(uv[0]), float(uv[1])])
            labels["box"].append([float(x) for x in box])
            labels["heading_uv"].append(heading)
            labels["size_lwh"].append([float(x) for x in lwh])
            labels["vtype"].append(VEHICLE_TYPES.index(v["type"]))
            labels["weight"].append(weight)
            ids.append(int(v["id"]))
            parked.append(bool(v["parked"]))
        except KeyError as exc:
            raise ValueError(f"{where}: vehicle {v.get('id')} has no {exc}") from None
        except (TypeError, ValueError) as exc:
            if str(exc).startswith(where):
                raise
            raise ValueError(f"{where}: vehicle {v.get('id')} is malformed: {exc}") from None
    return _as_arrays(labels), ids, parked


def samples_from_recording(
    path: str | Path, cameras: Sequence[str] | None = None, every: int = 1, scale: float | None = None
) -> list[SampleRef]:
    """SampleRefs for every `every`-th frame of the given cameras (None = all) of a recording, in
    camera then time order. `scale` resizes images and labels on load (0.5 = half size)."""
    rec = Recording(path)
    if not (isinstance(every, int) and every >= 1):
        raise ValueError(f"{rec.path}: every must be an integer >= 1, got {every!r}")
    _check_scale(scale, rec.path)
    entries = {c["name"]: c for c in rec.meta["cameras"]}
    names = list(entries) if cameras is None else list(cameras)
    unknown = [n for n in names if n not in entries]
    if unknown:
        raise ValueError(f"{rec.path}: no camera {', '.join(map(repr, unknown))} (has: {', '.join(entries)})")
    refs = []
    for name in names:
        entry = entries[name]
        gt_path = rec.path / entry["gt"]
        frames = rec.ground_truth(name)
        for line in range(0, len(frames), every):
            frame = frames[line]
            where = f"{gt_path}:{line + 1}"
            try:
                image_path = rec.path / frame["file"]
                t_ns = int(frame["t_ns"])
                vehicles = frame["vehicles"]
            except (KeyError, TypeError) as exc:
                raise ValueError(f"{where}: frame record has no {exc}") from None
            if not image_path.is_file():
                raise ValueError(f"{where}: image file {image_path} is missing")
            labels, ids, parked = recording_labels(vehicles, where)
            meta = {
                "camera": name,
                "kind": entry["kind"],
                "modality": entry.get("modality", "visible"),
                "principal_point": (float(entry["cx"]), float(entry["cy"])),
                "t_ns": t_ns,
                "recording": str(rec.path),
                "track_id": np.asarray(ids, np.int64),
                "parked": np.asarray(parked, bool),
            }
            refs.append(
                SampleRef(
                    image_path=image_path,
                    labels=labels,
                    image_hw=(int(entry["height"]), int(entry["width"])),
                    scale=scale,
                    source=f"{image_path} ({name})",
                    meta=meta,
                )
            )
    return refs


# ---- COCO-style annotations ---------------------------------------------------------------------


def _numbers(value: object, shape: tuple[int, ...], what: str, where: str) -> np.ndarray:
    """`value` as a finite float array of `shape`, else ValueError saying what is wrong."""
    try:
        arr = np.asarray(value, np.float64)
    except (TypeError, ValueError):
        arr = None
    if arr is None or arr.shape != shape:
        want = " x ".join(map(str, shape))
        raise ValueError(f"{where}: {what} must be {want} numbers, got {value!r}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{where}: {what} must be finite, got {value!r}")
    return arr


def _coco_type(name: object, cat_id: object, where: str) -> int:
    key = str(name).strip().lower()
    if key not in TYPE_ALIASES:
        known = ", ".join(sorted(TYPE_ALIASES))
        raise ValueError(f"{where}: category {name!r} (id {cat_id}) is not a vehicle type we know (known: {known})")
    t = TYPE_ALIASES[key]
    return -1 if t is None else VEHICLE_TYPES.index(t)


def _coco_vehicle(ann: dict, vtype: int, where: str) -> dict[str, object]:
    """One annotation -> label values in our pixel convention."""
    x, y, w, h = _numbers(ann["bbox"], (4,), "bbox", where)
    if w <= 0 or h <= 0:
        raise ValueError(f"{where}: bbox width and height must be > 0, got {ann['bbox']!r}")
    x -= COCO_PIXEL_OFFSET
    y -= COCO_PIXEL_OFFSET
    box = [x, y, x + w, y + h]
    bottom = np.array([x + w / 2, y + h])
    heading = np.full(2, np.nan)
    if ann.get("bottom_rect") is not None:
        rect = _numbers(ann["bottom_rect"], (4, 2), "bottom_rect", where) - COCO_PIXEL_OFFSET
        bottom = rect.mean(axis=0)
        heading = _rect_heading(rect)
    elif ann.get("heading_uv") is not None:
        heading = _unit(_numbers(ann["heading_uv"], (2,), "heading_uv", where))
        if not np.isfinite(heading).all():
            raise ValueError(f"{where}: heading_uv must be a non-zero vector, got {ann['heading_uv']!r}")
    if ann.get("bottom_center") is not None:
        bottom = _numbers(ann["bottom_center"], (2,), "bottom_center", where) - COCO_PIXEL_OFFSET
    lwh = np.full(3, np.nan)
    if ann.get("lwh") is not None:
        lwh = _numbers(ann["lwh"], (3,), "lwh", where)
        if (lwh <= 0).any():
            raise ValueError(f"{where}: lwh must be positive metres, got {ann['lwh']!r}")
    weight = 0.0 if ann.get("iscrowd") else 1.0
    return {"bottom_uv": bottom, "box": box, "heading_uv": heading, "size_lwh": lwh, "vtype": vtype, "weight": weight}


def samples_from_coco(
    json_path: str | Path, images_dir: str | Path | None = None, scale: float | None = None
) -> list[SampleRef]:
    """SampleRefs from a COCO-style file (format in the module docstring), in the file's image order;
    images without annotations become samples without vehicles. `images_dir` defaults to the JSON
    file's folder. Raises ValueError naming the file (and the image or annotation) that is wrong."""
    json_path = Path(json_path)
    images_dir = json_path.parent if images_dir is None else Path(images_dir)
    _check_scale(scale, json_path)
    try:
        doc = json.loads(json_path.read_text())
    except FileNotFoundError:
        raise ValueError(f"{json_path}: annotation file is missing") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"{json_path}: not valid JSON: {exc}") from None
    if not isinstance(doc, dict):
        raise ValueError(f"{json_path}: expected a JSON object with images, annotations, categories")
    for key in ("images", "annotations", "categories"):
        if not isinstance(doc.get(key), list):
            raise ValueError(f"{json_path}: missing or not a list: {key!r}")

    def an_id(value: object, what: str) -> object:
        if isinstance(value, bool) or not isinstance(value, int | str):
            raise ValueError(f"{json_path}: {what} must be a number or a string, got {value!r}")
        return value

    categories: dict[object, str] = {}
    for k, cat in enumerate(doc["categories"]):
        if not isinstance(cat, dict) or "id" not in cat or "name" not in cat:
            raise ValueError(f"{json_path}: categories[{k}] needs 'id' and 'name', got {cat!r}")
        if an_id(cat["id"], f"categories[{k}] id") in categories:
            raise ValueError(f"{json_path}: category id {cat['id']!r} appears twice")
        categories[cat["id"]] = cat["name"]

    images: dict[object, dict] = {}
    for k, img in enumerate(doc["images"]):
        if not isinstance(img, dict) or "id" not in img or "file_name" not in img:
            raise ValueError(f"{json_path}: images[{k}] needs 'id' and 'file_name', got {img!r}")
        if an_id(img["id"], f"images[{k}] id") in images:
            raise ValueError(f"{json_path}: image id {img['id']!r} appears twice")
        for key in ("width", "height"):
            v = img.get(key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v <= 0):
                raise ValueError(f"{json_path}: image {img['id']!r}: {key} must be a whole number of pixels > 0, "
                                 f"got {v!r}")
        images[img["id"]] = img

    per_image: dict[object, dict[str, list]] = {i: _empty_labels() for i in images}
    annotation_ids: set[object] = set()
    for k, ann in enumerate(doc["annotations"]):
        if not isinstance(ann, dict):
            raise ValueError(f"{json_path}: annotations[{k}] must be an object, got {ann!r}")
        if "id" in ann:
            if an_id(ann["id"], f"annotations[{k}] id") in annotation_ids:
                raise ValueError(f"{json_path}: annotation id {ann['id']!r} appears twice (the vehicle would count "
                                 "twice)")
            annotation_ids.add(ann["id"])
        where = f"{json_path}: annotation {ann.get('id', f'#{k}')}"
        missing = [key for key in ("image_id", "category_id", "bbox") if key not in ann]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(missing)}")
        an_id(ann["image_id"], f"annotation {ann.get('id', f'#{k}')} image_id")
        an_id(ann["category_id"], f"annotation {ann.get('id', f'#{k}')} category_id")
        if ann["image_id"] not in images:
            raise ValueError(f"{where}: image_id {ann['image_id']!r} is not in images")
        if ann["category_id"] not in categories:
            raise ValueError(f"{where}: category_id {ann['category_id']!r} is not in categories")
        vtype = _coco_type(categories[ann["category_id"]], ann["category_id"], where)
        vehicle = _coco_vehicle(ann, vtype, where)
        img = images[ann["image_id"]]
        if img.get("width") and img.get("height"):
            x0, y0, x1, y1 = vehicle["box"]
            if x1 <= -0.5 or y1 <= -0.5 or x0 >= img["width"] - 0.5 or y0 >= img["height"] - 0.5:
                raise ValueError(f"{where}: bbox {ann['bbox']!r} lies outside the {img['width']}x{img['height']} "
                                 "image")
        for key, value in vehicle.items():
            per_image[ann["image_id"]][key].append(value)
    boxes = [np.asarray(ann["bbox"], float) for ann in doc["annotations"]]
    if boxes and all(b[0] + b[2] <= 1.0 and b[1] + b[3] <= 1.0 for b in boxes):
        raise ValueError(f"{json_path}: every bbox lies within 0-1: COCO boxes are in pixels, not normalised "
                         "coordinates")

    refs = []
    for image_id, img in images.items():
        where = f"{json_path}: image {image_id!r}"
        image_path = images_dir / str(img["file_name"])
        if not image_path.is_file():
            raise ValueError(f"{where}: image file {image_path} is missing")
        hw = None
        if img.get("width") is not None and img.get("height") is not None:
            hw = (int(img["height"]), int(img["width"]))
        meta: dict = {k: img[k] for k in ("camera", "kind", "modality", "t_ns") if img.get(k) is not None}
        if img.get("principal_point") is not None:
            pp = _numbers(img["principal_point"], (2,), "principal_point", where) - COCO_PIXEL_OFFSET
            meta["principal_point"] = (float(pp[0]), float(pp[1]))
        meta["annotations"] = str(json_path)
        refs.append(
            SampleRef(
                image_path=image_path,
                labels=_as_arrays(per_image[image_id]),
                image_hw=hw,
                scale=scale,
                source=f"{image_path} ({json_path.name} image {image_id!r})",
                meta=meta,
            )
        )
    return refs


def _rounded(values: Iterable[float], nd: int = 3) -> list[float]:
    return [round(float(x), nd) for x in values]


def write_coco(
    samples: Iterable[Sample | SampleRef], json_path: str | Path, images_dir: str | Path, image_ext: str = ".png"
) -> Path:
    """Write samples as a COCO-style file (format in the module docstring) and one image per sample
    (`image_ext` .png, lossless, or .jpg) in `images_dir`. Bottom centre, heading (as `heading_uv`)
    and size are written where known; weight-0 vehicles as `iscrowd` 1. Returns the JSON path."""
    json_path, images_dir = Path(json_path), Path(images_dir)
    if json_path.is_dir() or json_path.suffix.lower() != ".json":
        raise ValueError(f"{json_path}: the annotation file to write must be named *.json (not a folder)")
    if image_ext not in (".png", ".jpg"):
        raise ValueError(f"{json_path}: image_ext must be .png or .jpg, got {image_ext!r}")
    images_dir.mkdir(parents=True, exist_ok=True)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    categories = [{"id": i + 1, "name": t} for i, t in enumerate(VEHICLE_TYPES)]
    unknown_id = len(VEHICLE_TYPES) + 1
    images, annotations = [], []
    uses_unknown = False
    o = COCO_PIXEL_OFFSET
    for image_id, item in enumerate(samples, 1):
        sample = item.load() if isinstance(item, SampleRef) else item
        name = f"{json_path.stem}_{image_id:06d}{image_ext}"  # two files' images may share a folder
        if not cv2.imwrite(str(images_dir / name), sample.image):
            raise ValueError(f"{images_dir / name}: cannot write image")
        h, w = sample.shape
        entry: dict = {"id": image_id, "file_name": name, "width": w, "height": h}
        for key in ("camera", "kind", "modality", "t_ns"):
            if sample.meta.get(key) is not None:
                entry[key] = sample.meta[key]
        if sample.meta.get("principal_point") is not None:
            entry["principal_point"] = _rounded(np.asarray(sample.meta["principal_point"], float) + o, 4)
        images.append(entry)
        for k in range(len(sample)):
            x1, y1, x2, y2 = sample.box[k]
            vtype = int(sample.vtype[k])
            uses_unknown |= vtype < 0
            ann: dict = {
                "id": len(annotations) + 1,
                "image_id": image_id,
                "category_id": unknown_id if vtype < 0 else vtype + 1,
                "bbox": _rounded([x1 + o, y1 + o, x2 - x1, y2 - y1]),
                "area": round(float((x2 - x1) * (y2 - y1)), 3),
                "iscrowd": int(sample.weight[k] <= 0),
                "bottom_center": _rounded(sample.bottom_uv[k] + o),
            }
            if np.isfinite(sample.heading_uv[k]).all():
                ann["heading_uv"] = _rounded(sample.heading_uv[k], 6)
            if np.isfinite(sample.size_lwh[k]).all():
                ann["lwh"] = _rounded(sample.size_lwh[k])
            annotations.append(ann)
    if uses_unknown:
        categories.append({"id": unknown_id, "name": "vehicle"})
    doc = {"images": images, "annotations": annotations, "categories": categories}
    json_path.write_text(json.dumps(doc, indent=1))
    return json_path


# ---- batches ------------------------------------------------------------------------------------


def too_few_samples(n: int, batch_size: int) -> str:
    """What to say when `n` samples do not fill one batch of `batch_size` (training keeps whole batches only)."""
    return (f"{n} samples, fewer than one batch of {batch_size}: give --batch-size {n} or less, or more data "
            f"(more images, a smaller --every)")


class Batcher:
    """Shuffled epochs of augmented Samples, prepared in this process (training runs torch in the same
    process on few cores, so data preparation stays a small, synchronous cost).

    Loaded samples (grey image at the refs' scale and labels) are cached in memory up to `cache_bytes`
    of image data (default `default_cache_bytes()`), so JPEGs are decoded once; ~3000 images of 512x384 take
    ~600 MB. `augment(sample,
    rng)` must return a new Sample and leave its input alone (training.augment.augment does), e.g.
    `functools.partial(augment, out_hw=(256, 256))`; with `augment=None` the loaded (cached) Samples
    themselves are yielded, not to be modified. Iterating gives one epoch of lists of `batch_size`
    Samples (the last, shorter batch only when `drop_last` is False); the rng drives both the
    shuffle and the augmentation, so a seed reproduces the epoch.
    """

    def __init__(
        self,
        refs: Sequence[SampleRef],
        augment: Callable[[Sample, np.random.Generator], Sample] | None,
        batch_size: int,
        rng: np.random.Generator,
        shuffle: bool = True,
        drop_last: bool = True,
        cache_bytes: int | None = None,
    ) -> None:
        if len(refs) == 0:
            raise ValueError("Batcher: no samples (refs is empty)")
        if not (isinstance(batch_size, int) and batch_size >= 1):
            raise ValueError(f"Batcher: batch_size must be an integer >= 1, got {batch_size!r}")
        if drop_last and batch_size > len(refs):
            raise ValueError(too_few_samples(len(refs), batch_size))
        if cache_bytes is None:
            cache_bytes = default_cache_bytes()
        if cache_bytes < 0:
            raise ValueError(f"Batcher: cache_bytes must be >= 0, got {cache_bytes}")
        self.refs = list(refs)
        self.augment = augment
        self.batch_size = batch_size
        self.rng = rng
        self.shuffle = shuffle
        self.drop_last = drop_last
        self.cache_bytes = cache_bytes
        self._cache: dict[int, Sample] = {}
        self._cached_bytes = 0

    def __len__(self) -> int:
        n = len(self.refs)
        return n // self.batch_size if self.drop_last else -(-n // self.batch_size)

    @property
    def cached_bytes(self) -> int:
        return self._cached_bytes

    def sample(self, index: int) -> Sample:
        """The loaded (not augmented) sample `index`, from the cache when it is there."""
        if index in self._cache:
            return self._cache[index]
        sample = self.refs[index].load()
        if self._cached_bytes + sample.image.nbytes <= self.cache_bytes:
            self._cache[index] = sample
            self._cached_bytes += sample.image.nbytes
        return sample

    def __iter__(self) -> Iterator[list[Sample]]:
        order = self.rng.permutation(len(self.refs)) if self.shuffle else np.arange(len(self.refs))
        for start in range(0, len(order), self.batch_size):
            chunk = order[start : start + self.batch_size]
            if self.drop_last and len(chunk) < self.batch_size:
                return
            batch = [self.sample(int(i)) for i in chunk]
            yield batch if self.augment is None else [self.augment(s, self.rng) for s in batch]
