"""`roadside autolabel | static | area | composite`: a real site's training labels without a person labelling."""

from __future__ import annotations

import sys
from pathlib import Path

from roadside.argtypes import finite_float, positive_float, score
from shared.jsonio import dumps
from shared.messages import check_name


def add_site_jobs(sub) -> dict:
    _add_autolabel(sub)
    _add_static(sub)
    _add_area(sub)
    _add_composite(sub)
    return {"autolabel": _run_autolabel, "static": _run_static, "area": _run_area, "composite": _run_composite}


def _add_autolabel(sub) -> None:
    p = sub.add_parser("autolabel", help="training labels for a real camera from moving vehicles (no manual labels)")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (capture time in the names)")
    p.add_argument("--masks", type=Path, required=True, help="the camera's lookup masks (roadside calibrate)")
    p.add_argument("--camera", required=True, help="camera name written into the labels")
    p.add_argument("--out", type=Path, required=True, help="folder for labels.json, images/ and report.json")
    p.add_argument("--until", help="leave out frames at or after this time of day HH:MM:SS[.f] (a held-out slice), the "
                   "clock written in the file names (not moved by --timezone; names of epoch time: their UTC time)")
    p.add_argument("--roi-m", type=positive_float, default=30.0, help="label within this distance of the camera")
    p.add_argument("--truth", type=Path, help="simulator recording of these frames: score the labels against it")
    p.add_argument("--teacher", type=Path, help="detector ONNX model whose detections away from the labels become "
                   "ignore regions: parked and waiting vehicles, which the background model cannot see")
    p.add_argument("--teacher-thr", type=score, default=0.1, help="teacher detections at least this confident")
    p.add_argument("--ignore-small", action="store_true",
                   help="foreground regions too small for a vehicle become ignore regions instead of being dropped")
    p.add_argument("--tracks", type=Path, help="the pipeline's tracks of the same footage (roadside up --record): "
                   "vehicles they followed while moving become labels where the background model found none "
                   "(training/track_labels.py); only lines before the end of the labelled slice are read")
    p.add_argument("--timezone", default="UTC",
                   help="the time zone the frames' names are in, the site's ingest.timezone (IANA name, default "
                        "UTC): with --tracks (and --truth), their capture times must meet the tracks' (the truth's)")


def _add_static(sub) -> None:
    p = sub.add_parser("static", help="detections that stay at one pixel in a camera's frames: candidates for "
                                      "its exclusion zones (cameras[].exclude_px)")
    p.add_argument("--model", type=Path, required=True, help="the detector ONNX model the site runs")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (capture time in the names)")
    p.add_argument("--until", help="only frames before this time of day HH:MM:SS (leave a held-out slice alone)")
    p.add_argument("--every", type=int, default=4, help="use every n-th frame (default 4)")
    p.add_argument("--score-thr", type=score, default=0.3, help="detections at least this confident (detect's)")
    p.add_argument("--min-fraction", type=finite_float, default=0.5,
                   help="report places detected in this share of frames")
    p.add_argument("--crops", type=Path, help="folder: write the image around each place (spot_<k>.png) to look at")


def _add_area(sub) -> None:
    p = sub.add_parser("area", help="the rectangle of a camera's frames that shows anything (a fisheye's image "
                                    "circle): its cameras[].detect_area_px")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (a folder of images)")
    p.add_argument("--every", type=int, default=60, help="use every n-th frame (default 60)")
    p.add_argument("--until", help="only frames before this time of day HH:MM:SS[.f] (leave a held-out slice alone), "
                   "the clock written in the file names (names of epoch time: their UTC time)")
    p.add_argument("--level", type=finite_float, default=40.0, help="grey level above which a pixel shows something")
    p.add_argument("--share", type=finite_float, default=0.02,
                   help="a column (row) belongs to the area when more than this share of its pixels do")


def _run_area(args) -> int:
    from calibration.area import image_area, read_frames
    from services.ingest.sources import image_files

    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    if args.until:  # the names must carry their times: in time order, those before --until
        from training.autolabel import list_frames

        paths = [p for _, p in list_frames(args.frames, _time_of_day(args.until))][:: args.every]
    else:  # any images, in the order of their names
        if not args.frames.is_dir():
            raise ValueError(f"frames folder not found: {args.frames}")
        paths = sorted(image_files(args.frames))[:: args.every]  # as ingest lists them (no `._<name>` from a Mac)
    if not paths:
        raise ValueError(f"{args.frames}: no images")
    area, (w, h), n = image_area(read_frames(paths), args.level, args.share)
    print(dumps({"frames_folder": str(args.frames), "until": args.until, "frames": n, "width": w, "height": h,
                      "detect_area_px": list(area), "share_of_image": round((area[2] - area[0]) * (area[3] - area[1])
                                                                            / (w * h), 3)}, indent=1))
    return 0


def _run_static(args) -> int:
    import cv2

    from calibration.area import read_frames
    from eval.static import crop, static_detections
    from shared.inference import OnnxDetector
    from training.autolabel import list_frames

    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    paths = [p for _, p in list_frames(args.frames, _time_of_day(args.until))][:: args.every]
    det = OnnxDetector(args.model, score_thr=args.score_thr, spin=False)
    images = (grey for _, grey in read_frames(paths))
    result = static_detections(images, det.detect, min_fraction=args.min_fraction)
    if args.crops is not None:
        args.crops.mkdir(parents=True, exist_ok=True)
        last = cv2.imread(str(paths[-1]), cv2.IMREAD_GRAYSCALE)
        for k, spot in enumerate(result["spots"]):
            cv2.imwrite(str(args.crops / f"spot_{k}.png"), crop(last, spot["uv"]))
    print(dumps({"frames_folder": str(args.frames), "until": args.until, **result}, indent=1))
    return 0


def _time_of_day(text: str | None):
    from datetime import time

    if not text:
        return None
    try:
        return time.fromisoformat(text)
    except ValueError:
        raise ValueError(f"--until must be a time of day HH:MM:SS, got {text!r}") from None


def _teacher(model: Path | None, score_thr: float):
    """The detect function of a teacher model (autolabel, composite), None without one."""
    if model is None:
        return None
    from shared.inference import OnnxDetector

    return OnnxDetector(model, score_thr=score_thr, spin=False).detect


def _run_autolabel(args) -> int:
    from shared.settings import IngestSettings
    from training.autolabel import AutolabelConfig, autolabel_camera, score_labels

    until = _time_of_day(args.until)
    tz = IngestSettings(timezone=args.timezone).tzinfo()  # an unknown zone named before any work
    check_name("camera", args.camera)  # it names files: no '/'
    cfg = AutolabelConfig(roi_m=args.roi_m, teacher_thr=args.teacher_thr, ignore_small=args.ignore_small)
    if args.truth:  # checked before any output is written: the camera, and truth at every frame's time
        from training.autolabel import check_truth

        check_truth(args.frames, args.truth, args.camera, until, tz)
    teacher = _teacher(args.teacher, cfg.teacher_thr)
    # the tracks file is read there, up to the end of the labelled slice only
    report = autolabel_camera(args.frames, args.masks, args.out, args.camera, until, cfg,
                              log=lambda m: print(m, file=sys.stderr), teacher=teacher, tracks=args.tracks, tz=tz)
    if args.truth:
        report["score"] = score_labels(args.out / "labels.json", args.truth)
        (args.out / "report.json").write_text(dumps(report, indent=1))
    print(dumps(report, indent=1))
    return 0


def _add_composite(sub) -> None:
    p = sub.add_parser("composite", help="training images for a real camera: simulated vehicles drawn over its "
                       "real background, with exact labels")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (capture time in the names)")
    p.add_argument("--masks", type=Path, required=True,
                   help="the camera's lookup masks (roadside calibrate; they carry the camera model)")
    p.add_argument("--camera", required=True, help="camera name written into the labels")
    p.add_argument("--out", type=Path, required=True, help="folder for labels.json, images/ and report.json")
    p.add_argument("--until", help="background from frames before this time of day HH:MM:SS only (training slice)")
    p.add_argument("--placements", type=Path, help="where vehicles go: a roadside autolabel labels.json of this "
                   "camera (positions and headings of the moving vehicles it found); without it, simulator traffic "
                   "of --sim-site")
    p.add_argument("--sim-site", default="state_ellsworth",
                   help="simulator site in the masks' site frame (name or YAML path): its traffic where no "
                   "--placements are given, and its vehicle models")
    p.add_argument("--seconds", type=positive_float, default=60.0, help="simulated traffic")
    p.add_argument("--hz", type=positive_float, default=1.0, help="images per simulated second")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--demand-scale", type=positive_float, default=1.0, help="more (> 1) or less traffic")
    p.add_argument("--roi-m", type=positive_float, default=30.0, help="shown and labelled within this distance "
                   "of the camera")
    p.add_argument("--teacher", type=Path, help="detector ONNX model whose detections on the background become "
                   "ignore regions: vehicles standing through the whole slice are in the background")
    p.add_argument("--teacher-thr", type=score, default=0.5, help="teacher detections at least this confident")


def _run_composite(args) -> int:
    from training.composite import CompositeConfig, composite_camera

    until = _time_of_day(args.until)
    check_name("camera", args.camera)  # it names files: no '/'
    cfg = CompositeConfig(sim_site=args.sim_site, seconds=args.seconds, hz=args.hz, seed=args.seed,
                          roi_m=args.roi_m, demand_scale=args.demand_scale, teacher_thr=args.teacher_thr)
    teacher = _teacher(args.teacher, cfg.teacher_thr)
    report = composite_camera(args.frames, args.masks, args.out, args.camera, until, cfg,
                              log=lambda m: print(m, file=sys.stderr), teacher=teacher, placements=args.placements)
    print(dumps(report, indent=1))
    return 0
