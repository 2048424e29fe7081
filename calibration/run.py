"""`roadside calibrate`: landmark file -> lookup masks file + report (JSON and text) + plot."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.fit import CalibConfig, calibrate, check_segments, simplified_polygon, single_gross_mistake
from calibration.landmarks import (
    FAR_FROM_OTHERS_M,
    load_landmarks,
    load_segment_polygons,
    median_frame,
    median_latlon,
    validate_landmarks,
)
from calibration.masks import build_masks, calibrated_area, default_roi
from calibration.report import build_report, plot_residuals, summary_text
from calibration.site_ground import calibrate_site
from shared.geo import GeoFrame

MIN_CAMERA_HEIGHT_M = 1.0  # a fit that puts the camera lower above its ground is a wrong file, not a camera


@dataclass(frozen=True)
class CalibrateJob:
    landmarks: Path
    kind: str
    out: Path
    width: int | None = None
    height: int | None = None
    report: Path | None = None
    segments: int | None = None
    image_circle: tuple[float, float, float] | None = None
    fov_deg: float = 188.0
    origin: tuple[float, float, float] | None = None  # lat, lon, alt of the site frame
    roi: dict | None = None  # {"center_latlon": [lat, lon], "radius_m": r} or {"polygon_latlon": [...]}
    plot: Path | None = None
    image: Path | None = None
    # the site's other cameras (landmark file, kind, fisheye image circle): fit one ground surface to all
    shared_ground: tuple[tuple[Path, str, tuple[float, float, float] | None], ...] = ()
    segment_polygons: Path | None = None  # the ground segments' polygons (calibration/landmarks.py)


def _roi_local(roi: dict | None, geo: GeoFrame) -> dict | None:
    if roi is None:
        return None
    if "center_latlon" in roi:
        c = geo.to_enu(np.array([roi["center_latlon"][0]]), np.array([roi["center_latlon"][1]]), geo.alt0_m)[0]
        return {"center_m": [float(c[0]), float(c[1])], "radius_m": float(roi["radius_m"])}
    if "polygon_latlon" in roi:
        p = np.asarray(roi["polygon_latlon"], float)
        xy = geo.to_enu(p[:, 0], p[:, 1], geo.alt0_m)[:, :2]
        return {"polygon_m": xy.tolist()}
    return roi


def _other_camera(path: Path, kind: str, circle, fov_deg: float) -> tuple:
    """(Landmarks, CalibConfig) of another camera of the site (`--shared-ground`), checked as this one's."""
    lm, header = load_landmarks(path)
    _same_kind(path, header, kind, "--shared-ground ...:")
    if not header.get("width") or not header.get("height"):
        raise ValueError(f"{path}: image size unknown (the landmark file has no width and height)")
    cfg = CalibConfig(kind, int(header["width"]), int(header["height"]), image_circle=circle, fov_deg=fov_deg)
    validate_landmarks(lm, cfg.width, cfg.height, cfg.circle if cfg.kind == "fisheye" else None)
    return lm, cfg


def _same_kind(path: Path, header: dict, kind: str, given_as: str) -> None:
    """ValueError when the landmark file says it is for the other kind of camera than the command line."""
    if header.get("kind") not in (None, kind):
        raise ValueError(f"{path} is for a {header['kind']} camera, not {given_as}{kind}")


def _near_landmarks(what: str, lat: float, lon: float, lm) -> None:
    """ValueError unless (lat, lon) is a position on Earth within FAR_FROM_OTHERS_M of the landmarks (a swapped
    latitude and longitude, or another site's point)."""
    if not (math.isfinite(lat) and math.isfinite(lon) and -90 <= lat <= 90 and -180 <= lon <= 180):
        raise ValueError(f"{what} ({lat}, {lon}) is not a latitude and longitude")
    d = float(np.hypot(*median_frame(lm.latlon).to_enu(np.array([lat]), np.array([lon]), 0.0)[0, :2]))
    if d > FAR_FROM_OTHERS_M:
        raise ValueError(f"{what} ({lat}, {lon}) is {d / 1000:.1f} km from the landmarks (latitude and longitude "
                         f"swapped, or another site's?)")


def _writable_file(what: str, path: Path | None) -> None:
    """ValueError, before the fit, for an output that cannot be written: a folder, or a file on the way to it."""
    if path is None:
        return
    if path.is_dir():
        raise ValueError(f"{what} {path} is a folder, not a file")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ValueError(f"{what} {path}: {parent} is a file, not a folder")
            break


def camera_height_m(cal) -> float:
    """How high the fitted camera is above the ground it lifts pixels onto, at its foot."""
    pos = cal.camera.pose.position_m
    if cal.ground is not None:
        return float(pos[2] - cal.ground.height(pos[None, :2])[0])
    return float(pos[2] - np.median(cal.planes[:, 0] * pos[0] + cal.planes[:, 1] * pos[1] + cal.planes[:, 2]))


def _fit_failure(cal, lm) -> str | None:
    """Why a fit says the landmark file is wrong rather than the camera (the camera under its ground, a third of
    the landmarks rejected), or None."""
    height = camera_height_m(cal)
    if height < MIN_CAMERA_HEIGHT_M:
        return (f"the fit puts the camera {height:.1f} m above the ground it sees, under it or on it: pixels "
                "mirrored (u counted from the right), u and v swapped, or the landmarks of another camera? A roadside "
                "camera looks down from a pole")
    if len(cal.rejected) >= 3 and 3 * len(cal.rejected) > len(lm):  # a third: not a few slips, a wrong file
        return (f"{len(cal.rejected)} of {len(lm)} landmarks disagree with the rest beyond what clicking and map "
                f"errors explain: latitude and longitude swapped, pixels from another camera or image size, or the "
                f"wrong --kind? ({', '.join(i for i, _ in cal.rejected[:5])} ...)")
    return None


def _typo(lm, k: int, off_m: float) -> str:
    """What `single_gross_mistake`'s landmark k, off_m metres from where the others place its pixel, is taken for."""
    off = f"{off_m:.0f} m from" if math.isfinite(off_m) else "far from"
    return (f"landmark {lm.ids[k]!r}: its map point is {off}"
            " where the other landmarks place its pixel: a typo in its latitude or longitude?")


def _site_check(main: str, geo: GeoFrame, own: dict):
    """`calibrate_site`'s check of every camera of a --shared-ground run (this one's landmarks are `main`), on its
    own fit and after each refit on the site's surface: `_fit_failure`, and the one landmark with a typo when that
    is why (`single_gross_mistake`, and without it the fit does not fail). A camera that fails is refused, not left
    out: its file is a mistake to fix. On its own a camera is fitted without its segments (the site's surface
    replaces them); one that fails so is judged again as its own run judges it, with its segments (`own`: name ->
    its landmarks as given, and the polygons of its segments), so a ramp its segments hold is no mistake; one that
    passes so is not judged again on its refits, which start from the fit without them (as before these checks)."""

    excused: set[str] = set()  # cameras whose own run passes with their segments: not judged on a fit without them

    def check(name: str, cal, lm, cfg) -> str | None:
        if name in excused:
            return None
        failure = _fit_failure(cal, lm)
        if failure is not None and cal.ground is None:
            full, polygons = own[name]
            if (full.segment >= 0).any() and _fit_failure(calibrate(full, cfg, geo, polygons), full) is None:
                excused.add(name)
                return None
        if failure is None:
            return None
        typo = single_gross_mistake(lm, cfg, geo)
        if typo is not None and _fit_failure(calibrate(lm, cfg, geo, exclude=typo[0]), lm) is None:
            failure = (f"{_typo(lm, *typo)} With it the fit fails, without it the others agree: correct it or leave "
                       "it out")
        if name == main:
            return failure
        return (f"{failure}. Its landmarks would bend the site's ground surface the other cameras are refitted on "
                "and lifted onto: correct the file, or leave it out of --shared-ground")

    return check


def run_calibration(job: CalibrateJob) -> dict:
    """Fit, then write the masks, the report and the plot; every input is checked before anything is written."""
    lm, header = load_landmarks(job.landmarks)
    _same_kind(job.landmarks, header, job.kind, "--kind ")
    for flag, given, declared in (("--width", job.width, header.get("width")),
                                  ("--height", job.height, header.get("height"))):
        if given and declared and int(given) != int(declared):
            raise ValueError(f"{flag} {given} but {job.landmarks} says its pixels are of a {header.get('width')}x"
                             f"{header.get('height')} image: give the size the landmarks were clicked on")
    width = job.width or header.get("width")
    height = job.height or header.get("height")
    if not width or not height:
        raise ValueError(f"image size unknown: pass --width and --height (not in {job.landmarks})")
    cfg = CalibConfig(
        job.kind, int(width), int(height), job.segments, image_circle=job.image_circle, fov_deg=job.fov_deg
    )
    validate_landmarks(lm, cfg.width, cfg.height, cfg.circle if cfg.kind == "fisheye" else None)
    if job.origin is not None:
        _near_landmarks("--origin", job.origin[0], job.origin[1], lm)
        geo = GeoFrame(*job.origin)
    else:
        geo = median_frame(lm.latlon)
    if job.roi is not None and "center_latlon" in job.roi:
        _near_landmarks("the ROI centre", *map(float, job.roi["center_latlon"]), lm)
        if not (math.isfinite(job.roi["radius_m"]) and job.roi["radius_m"] > 0):
            raise ValueError(f"the ROI radius must be > 0 m, got {job.roi['radius_m']}")
    polygons_xy = None
    if job.segment_polygons is not None:
        polygons_xy = {k: simplified_polygon(geo.to_enu(p[:, 0], p[:, 1], geo.alt0_m)[:, :2], k)
                       for k, p in load_segment_polygons(job.segment_polygons).items()}
    if (lm.segment >= 0).any() or polygons_xy:
        if job.segments is not None:
            named_by = [w for w, given in (("the landmarks' segment column", (lm.segment >= 0).any()),
                                           ("--segment-polygons", bool(polygons_xy))) if given]
            raise ValueError(f"--segments {job.segments}, but the segments are named ({', '.join(named_by)}): "
                             "leave --segments out")
        if job.shared_ground and polygons_xy:
            raise ValueError("--segment-polygons with --shared-ground: the site's ground surface replaces this "
                             "camera's planes, so its segments would not be used")
        if not job.shared_ground:  # (the report says a segment column is then unused)
            check_segments(lm, lm.to_local(geo), polygons_xy)
    report_path = job.report or job.out.with_suffix(".report.json")
    for what, path in (("--out", job.out), ("--report", report_path), ("--plot", job.plot)):
        _writable_file(what, path)
    if job.plot is not None:
        import cv2

        if not cv2.haveImageWriter(str(job.plot)):
            raise ValueError(f"--plot {job.plot}: not an image file name OpenCV can write (.png or .jpg)")
    image = None
    if job.plot and job.image:
        import cv2

        image = cv2.imread(str(job.image))
        if image is None:
            raise ValueError(f"cannot read image {job.image}")
        if image.shape[:2] != (cfg.height, cfg.width):
            raise ValueError(f"--image is {image.shape[1]}x{image.shape[0]}, the landmarks are for a "
                             f"{cfg.width}x{cfg.height} image: give a frame of the camera at the size they were "
                             "clicked on")
    t0 = time.perf_counter()
    if job.shared_ground:
        if cfg.kind == "fisheye":
            raise ValueError("--shared-ground moves pinhole and thermal cameras onto the site's ground surface; a "
                             "fisheye camera keeps its own planes (calibration/site_ground.py): calibrate it "
                             "without --shared-ground, and give its landmarks to the pinhole cameras' runs")
        given = {str(path): _other_camera(path, kind, circle, job.fov_deg) for path, kind, circle in job.shared_ground}
        # the site's surface is the ground: no camera's own segments
        others = [(path, other.without_segments(), other_cfg) for path, (other, other_cfg) in given.items()]
        for path, other, _ in others:  # one site: another site's file would bend its ground surface
            far = median_latlon(other.latlon)
            _near_landmarks(f"--shared-ground {path} (its landmarks' median)", float(far[0]), float(far[1]), lm)
        # the site's surface replaces this camera's planes: its segment column is not used (the report says so)
        # every camera's fit is checked before its landmarks shape the surface, and after each refit on it
        cal = calibrate_site([(str(job.landmarks), lm.without_segments(), cfg), *others], geo,
                             check=_site_check(str(job.landmarks), geo, {
                                 str(job.landmarks): (lm, polygons_xy),
                                 **{path: (other, None) for path, (other, _) in given.items()}}))[str(job.landmarks)]
    else:
        cal = calibrate(lm, cfg, geo, polygons_xy)
    failure = _fit_failure(cal, lm)
    if failure is not None:
        # One mistyped digit of a latitude or longitude (tens of metres off) drags the whole fit and fails it on
        # good landmarks: if leaving one landmark out makes the others agree, it is that one's mistake.
        typo = single_gross_mistake(lm, cfg, geo)
        if typo is None:
            raise ValueError(failure)
        k = typo[0]
        culprit = _typo(lm, *typo)
        if job.shared_ground:  # the site's surface is fitted to every camera's landmarks: fix the file first
            raise ValueError(f"{culprit} With it the fit fails, without it the others agree: correct it or leave it "
                             f"out")
        cal = calibrate(lm, cfg, geo, polygons_xy, exclude=k)
        failure = _fit_failure(cal, lm)
        if failure is not None:
            raise ValueError(f"{culprit} Without it the fit still fails: {failure}")
        cal.rejected = [(lid, f"{reason}; with it the fit of all the landmarks failed, without it the others agree: "
                              "a typo in its latitude or longitude?" if lid == lm.ids[k] else reason)
                        for lid, reason in cal.rejected]
    t_fit = time.perf_counter() - t0
    xy = lm.to_local(geo)
    area = calibrated_area(cal, xy)
    t0 = time.perf_counter()
    # the camera the landmarks name: a site file that gives one camera another's masks is refused (localize)
    masks = build_masks(cal, lm.digest(), area, {"landmarks_file": str(job.landmarks),
                                                 "landmarks_camera": header.get("camera")})
    t_masks = time.perf_counter() - t0
    roi = _roi_local(job.roi, geo) or default_roi(cal)
    report = build_report(cal, lm, cfg, roi)
    report.update(
        {
            "masks": str(job.out),
            "landmarks_hash": lm.digest(),
            "fit_s": round(t_fit, 3),
            "masks_s": round(t_masks, 3),
            "calibrated_area": area,
            # where the ground comes from: this camera's own planes, or the site's surface (--shared-ground; the
            # leave-one-out then refits this camera on the surface without the landmark, the surface keeping it)
            "ground": cal.ground.to_dict() if cal.ground is not None else "planes",
        }
    )
    masks.save(job.out)
    report_path.parent.mkdir(parents=True, exist_ok=True)
    tmp = report_path.with_name(report_path.name + ".partial")
    try:
        tmp.write_text(json.dumps(report, indent=1))
        tmp.replace(report_path)
    finally:
        tmp.unlink(missing_ok=True)
    report["report"] = str(report_path)
    report["summary"] = summary_text(report)
    if job.plot:
        job.plot.parent.mkdir(parents=True, exist_ok=True)
        plot_residuals(cal, lm, image, str(job.plot))
    return report
