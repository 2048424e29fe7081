"""`roadside <job> ...`: parse flags into typed configs and hand them to each job's main."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

from roadside.argtypes import (
    endpoint,
    finite_float,
    port_base,
    positive_float,
    positive_int,
    score,
    site_path,
    type_weights,
)
from roadside.cli_bus import add_bus_jobs
from roadside.cli_model import add_model_jobs
from roadside.cli_site import add_site_jobs
from shared.jsonio import dumps

HEARTBEAT_S = 5.0  # `counts --live --heartbeat`: the file is touched at most this often


def _add_sim(sub) -> None:
    p = sub.add_parser("sim", help="simulate a clip of a site and write a recording")
    p.add_argument("--site", required=True, help="site name (state_ellsworth, intersection) or a site YAML path")
    p.add_argument("--seconds", type=positive_float, required=True, help="clip length, seconds")
    p.add_argument("--hz", type=positive_float, default=10.0, help="frames per second per camera")
    p.add_argument("--seed", type=int, default=0, help="random seed; the same seed gives byte-identical output")
    p.add_argument("--out", required=True, type=Path, help="output folder (must not exist unless --overwrite)")
    p.add_argument("--cameras", default="all", help="all | fisheye | thermal | pinhole | visible | NAME,NAME")
    p.add_argument("--weather", default="auto", help="auto | clear | overcast | dusk | fog | rain")
    p.add_argument("--workers", type=int, default=2, help="render processes")
    p.add_argument("--max-vehicles", type=int, default=100, help="most moving vehicles at once")
    p.add_argument("--demand-scale", type=finite_float, default=1.0, help="scale the site's traffic demand")
    p.add_argument("--type-weights", type=type_weights, default=None, metavar="TYPE=W,...",
                   help="multiply vehicle types' shares of the mix, e.g. bus=4,truck=3 (types: car, suv_van, truck, "
                        "bus, motorcycle)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--contact-sheet", type=Path, default=None, help="also draw a contact sheet PNG here")


def _run_sim(args) -> int:
    from sim.clip import ClipConfig, simulate_clip
    from sim.contact_sheet import contact_sheet

    cfg = ClipConfig(
        site=args.site,
        out=args.out,
        seconds=args.seconds,
        hz=args.hz,
        seed=args.seed,
        cameras=args.cameras,
        weather=args.weather,
        workers=args.workers,
        max_vehicles=args.max_vehicles,
        demand_scale=args.demand_scale,
        type_weights=args.type_weights,
        overwrite=args.overwrite,
    )
    if args.contact_sheet:  # checked before the clip is simulated, not after
        import cv2

        if args.contact_sheet.is_dir() or not cv2.haveImageWriter(str(args.contact_sheet)):
            raise ValueError(f"--contact-sheet {args.contact_sheet}: not an image file name OpenCV can write "
                             "(.png or .jpg)")
    summary = simulate_clip(cfg, log=lambda s: print(f"[sim] {s}", file=sys.stderr))
    if args.contact_sheet:
        contact_sheet(args.out, args.contact_sheet)
        summary["contact_sheet"] = str(args.contact_sheet)
    print(dumps(summary, indent=1))
    return 0


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the demo: the simulated State/Ellsworth roundabout through the live pipeline")
    p.add_argument("--out", type=Path, default=Path("out/demo"),
                   help="output folder: the recording, site, tracks, logs, summary.json and demo.rrd (default "
                        "out/demo; a recording already there with the same --seconds, --hz and --seed is reused)")
    p.add_argument("--seconds", type=positive_float, default=60.0, help="length of the simulated clip (default 60)")
    p.add_argument("--hz", type=positive_float, default=10.0, help="camera frame rate of the clip (default 10)")
    p.add_argument("--seed", type=int, default=2024,
                   help="seed of the simulated clip: traffic, weather, landmark clicks (default 2024, the README's "
                        "figures)")
    p.add_argument("--landmarks", type=int, default=20, help="landmarks per camera for calibration (default 20)")
    p.add_argument("--model", type=Path, help="detector ONNX (default: the shipped models/detector_fp32.onnx)")
    p.add_argument("--port-base", type=port_base, default=7451,
                   help="first bus port of the pipeline (default 7451; its services and clients take the next few; "
                        "change it when another pipeline runs on this machine)")
    p.add_argument("--pace", default="max",
                   help="playback: max (as fast as the pipeline takes frames, every frame processed: the default) or "
                        "1 (real time, as at a cabinet: a detector slower than the cameras drops frames)")


def _run_demo(args) -> int:
    from roadside.demo import DEFAULT_MODEL, DemoConfig, run_demo, summary_table

    cfg = DemoConfig(out=args.out, seconds=args.seconds, hz=args.hz, seed=args.seed, landmarks=args.landmarks,
                     model=args.model or DEFAULT_MODEL, port_base=args.port_base, pace=args.pace)
    summary = run_demo(cfg, log=lambda s: print(f"[demo] {s}", file=sys.stderr))
    print(f"\nState/Ellsworth roundabout (simulated), {cfg.seconds:g} s at {cfg.hz:g} Hz, four fisheye cameras")
    print(summary_table(summary))
    print(f"\n{args.out / 'summary.json'}\n{args.out / 'tracks.jsonl'}\n{args.out / 'demo.rrd'}")
    return 0


def _floats(n: int):
    def parse(text: str) -> tuple[float, ...]:
        try:
            vals = tuple(float(x) for x in text.split(","))
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated numbers, got {text!r}") from None
        if len(vals) != n or not all(math.isfinite(v) for v in vals):
            raise argparse.ArgumentTypeError(f"expected {n} comma-separated finite numbers, got {text!r}")
        return vals

    return parse


def _add_calibrate(sub) -> None:
    p = sub.add_parser("calibrate", help="landmarks -> lookup masks (pixel -> lat/lon) + accuracy report")
    p.add_argument(
        "--landmarks", type=Path, required=True, help="landmark file (JSON or CSV: id,u,v,lat,lon[,segment])"
    )
    p.add_argument("--kind", choices=["pinhole", "fisheye"], required=True)
    p.add_argument("--out", type=Path, required=True, help="lookup masks file to write (.npz)")
    p.add_argument("--width", type=positive_int, help="image width (default: from the landmark file)")
    p.add_argument("--height", type=positive_int, help="image height (default: from the landmark file)")
    p.add_argument("--report", type=Path, help="report JSON (default: next to --out)")
    p.add_argument("--segments", type=positive_int,
                   help="ground segments when the landmarks name none (default 2 pinhole range bands, 4 fisheye "
                        "sectors)")
    p.add_argument("--segment-polygons", type=Path,
                   help='the named ground segments\' outlines: JSON {"SEGMENT": [[LAT, LON], ...], ...}; landmarks '
                        "without a segment take the polygon they lie in")
    p.add_argument("--image-circle", type=_floats(3), help="fisheye image circle CX,CY,RADIUS in pixels")
    p.add_argument("--fov-deg", type=finite_float, default=188.0,
                   help="fisheye field of view at the image circle's edge")
    p.add_argument("--origin", type=_floats(3), help="site frame origin LAT,LON,ALT (default: the landmarks' median; "
                   "a negative latitude needs the = form: --origin=-33.86,151.21,5)")
    p.add_argument(
        "--roi-center", type=_floats(2), help="ROI centre LAT,LON (default: the camera, 25 m fisheye / 200 m; a "
        "negative latitude needs the = form: --roi-center=-33.86,151.21)"
    )
    p.add_argument("--roi-radius", type=positive_float, help="ROI radius in metres (with --roi-center; default 25)")
    p.add_argument("--plot", type=Path, help="draw residual arrows to this PNG")
    p.add_argument("--image", type=Path, help="camera frame to draw the plot on")
    p.add_argument("--shared-ground", type=_shared_ground, action="append", default=[],
                   metavar="LANDMARKS:KIND[:CX,CY,R]",
                   help="another camera of the site (its landmark file, pinhole or fisheye, a fisheye's image circle; "
                        "repeatable): one ground surface is fitted to every camera's landmarks and a pinhole camera "
                        "is refitted on it and lifted onto it (calibration/site_ground.py)")


def _shared_ground(text: str) -> tuple[Path, str, tuple[float, float, float] | None]:
    parts = text.split(":")
    circle = None
    if len(parts) >= 3 and "," in parts[-1]:
        circle = _floats(3)(parts.pop())
    if len(parts) < 2 or parts[-1] not in ("pinhole", "fisheye"):
        raise argparse.ArgumentTypeError(f"expected LANDMARKS:pinhole or LANDMARKS:fisheye[:CX,CY,R], got {text!r}")
    kind = parts.pop()
    return Path(":".join(parts)), kind, circle


def _run_calibrate(args) -> int:
    from calibration.run import CalibrateJob, run_calibration

    if args.roi_radius is not None and not args.roi_center:
        raise ValueError("--roi-radius goes with --roi-center (without it the ROI is the camera's default)")
    roi = ({"center_latlon": list(args.roi_center), "radius_m": args.roi_radius or 25.0} if args.roi_center
           else None)
    job = CalibrateJob(
        landmarks=args.landmarks,
        kind=args.kind,
        out=args.out,
        width=args.width,
        height=args.height,
        report=args.report,
        segments=args.segments,
        image_circle=args.image_circle,
        fov_deg=args.fov_deg,
        origin=args.origin,
        roi=roi,
        plot=args.plot,
        image=args.image,
        shared_ground=tuple(args.shared_ground),
        segment_polygons=args.segment_polygons,
    )
    report = run_calibration(job)
    print(report["summary"])
    print(f"masks: {args.out}\nreport: {report['report']}")
    return 0


BENCHMARKS = {"sim": "bench.sim_render", "calibration": "bench.calibration", "detector": "bench.detector",
              "fuse_track": "bench.fuse_track", "soak": "bench.soak"}


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="score the detector: on a simulator recording, or on hand-labelled real frames")
    p.add_argument("what", choices=["detector", "real", "handoff", "budget", "movements"],
                   help="detector: against a recording's ground truth; real: against hand labels (eval/real.py); "
                        "handoff: camera-region crossings kept under one id in a tracks file (no ground truth); "
                        "budget: where a simulated run's tracking accuracy goes (eval/budget.py, --demo); "
                        "movements: a simulated run's turning-movement counts against the truth (eval/movements.py, "
                        "--demo)")
    p.add_argument("--model", type=Path, help="exported ONNX detector (detector, real)")
    p.add_argument("--tracks", type=Path, help="tracks file written by fuse_track (handoff; real: score the tracks "
                   "of the footage played through the pipeline instead of a model's detections)")
    p.add_argument("--recording", type=Path, help="simulator recording (detector)")
    p.add_argument("--every", type=int, default=1, help="use every n-th frame (detector)")
    p.add_argument("--score-thr", type=score, help="lowest score kept (default: 0.05 for detector, as AP needs "
                   "the low ones; 0.3 for real: the State/Ellsworth site's fuse_track.high_score, from which "
                   "detections start tracks; its detect service keeps them down to detect.score_thr 0.2)")
    p.add_argument("--site", type=Path, default=Path("deploy/sites/state_ellsworth"),
                   help="site folder with labels/ and masks/ (real), or its site.yaml's cameras (handoff)")
    p.add_argument("--footage", type=Path, default=Path("../shared/data/state_ellsworth/sample_data"),
                   help="folder of the cameras' frame folders (real)")
    p.add_argument("--threads", type=positive_int, default=2, help="ONNX Runtime threads per inference")
    p.add_argument("--fisheye-area-deg", type=positive_float,
                   help="detector: look at fisheye frames only inside the image circle up to this angle off axis "
                        "(e.g. 90), as a camera's detect_area_px does in the detect service")
    p.add_argument("--near-m", type=positive_float, default=25.0,
                   help="detector: the near-camera metrics count vehicles and detections within this many metres "
                        "of the camera on the ground (its region, as fusion uses it)")
    p.add_argument("--near-score", type=score, default=0.3,
                   help="detector: the lowest score of a detection the near-camera metrics count (the detect "
                        "service's threshold)")
    p.add_argument("--mirror", action="store_true",
                   help="detector, real: infer each frame and its left-right mirror and average the maps "
                        "(detect.mirror)")
    p.add_argument("--votes", action="store_true",
                   help="detector, real: a vote-head model's peaks whose votes point far away are read where they "
                        "point (detect.votes)")
    p.add_argument("--raw-heads", action="store_true",
                   help="detector, real: the 2D boxes and sizes as the heads give them, without the model's box and "
                        "size calibrations")
    p.add_argument("--demo", type=Path, action="append",
                   help="budget, movements: a roadside demo output folder (objects.jsonl or tracks.jsonl, site/, "
                        "the recording; default out/demo); repeatable: each run's scores and the mean over them")
    p.add_argument("--scenario", action="append",
                   help="budget: score only this scenario (repeatable; default all: as_run, exact_lift, "
                        "true_positions, no_false_alarms, true_positions_no_false_alarms, true_long_vehicles, truth; "
                        "and without_CAMERA for any camera of the site, by name: that camera lost)")
    p.add_argument("--localize-rule", action="store_true",
                   help="budget: apply localize's footprint rule (localize.footprint_overlap, footprint_merge) to the "
                        "objects left at the replay's threshold, for a run recorded without it "
                        "(ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP=0): the exact replay of a higher threshold")
    p.add_argument("--json", action="store_true", help="print one JSON document (default: also a summary)")


def _run_eval(args) -> int:
    from shared.inference import OnnxDetector

    if args.site is not None:
        args.site = site_path(args.site)  # a folder, its site.yaml, or a name under deploy/sites/
    if args.what == "budget":
        from eval.budget import SCENARIOS, budget, budget_many

        demos = args.demo or [Path("out/demo")]
        log = None if args.json else lambda m: print(m, file=sys.stderr)
        if len(demos) == 1:
            result = budget(demos[0], args.scenario or SCENARIOS, log=log, localize_rule=args.localize_rule)
        else:
            result = budget_many(demos, args.scenario or SCENARIOS, log=log, localize_rule=args.localize_rule)
        print(dumps(result, indent=1))
        return 0
    if args.what == "movements":
        from eval.movements import as_table, evaluate_demos_movements

        result = evaluate_demos_movements(args.demo or [Path("out/demo")])
        if not args.json:
            for r in result["runs"]:
                print(f"{r['demo']}:\n{as_table(r)}", file=sys.stderr)
        print(dumps(result, indent=1))
        return 0
    if args.what == "handoff":
        from eval.tracking import handoff_without_truth
        from services.fuse_track.__main__ import camera_positions
        from shared.settings import load_settings

        if args.tracks is None:
            raise ValueError("eval handoff needs --tracks")
        settings = load_settings(args.site)
        _site_tracks([args.tracks], settings, args.site)
        positions, _ = camera_positions(settings)
        print(dumps({"tracks_file": str(args.tracks), **handoff_without_truth(args.tracks, positions)}, indent=1))
        return 0
    if args.what == "real" and args.tracks is not None:
        if args.model is not None:
            raise ValueError("eval real scores either a model's detections (--model) or a tracks file (--tracks), "
                             "not both")
        from eval.real import evaluate_tracks_real
        from shared.geo import GeoFrame
        from shared.settings import load_settings

        settings = load_settings(args.site)
        _site_tracks([args.tracks], settings, args.site)
        origin = settings.origin
        folder = args.site.parent if args.site.is_file() else args.site  # labels/ and masks/ beside its site.yaml
        result = evaluate_tracks_real(folder / "labels", args.tracks, folder / "masks",
                                      GeoFrame.from_dict(origin) if origin else None, tz=settings.ingest.tzinfo())
        line = ("{name:8s} tracks: precision {precision} recall {recall} ({labels} labels, {detections} tracks "
                f"within {result['roi_m']:g} m, {{frames}} frames)")
        return _print_eval(args, result, "per_camera", line)
    if args.model is None:
        raise ValueError(f"eval {args.what} needs --model")
    if args.what == "real":
        from eval.real import evaluate_real
        from shared.settings import load_settings

        thr = 0.3 if args.score_thr is None else args.score_thr
        curve = tuple(round(0.05 * k, 2) for k in range(1, 13))  # 0.05 ... 0.6
        det = OnnxDetector(args.model, threads=args.threads, score_thr=min(thr, *curve), mirror=args.mirror,
                           votes=args.votes, calibrated_heads=not args.raw_heads)
        has_settings = args.site.is_file() or (args.site / "site.yaml").is_file()  # a bare labels + masks folder too
        settings = load_settings(args.site) if has_settings else None
        cams = settings.cameras if settings else []
        exclude = {c.name: c.exclude_px for c in cams if c.exclude_px}
        areas = {c.name: c.detect_area_px for c in cams if c.detect_area_px}
        localize = settings.localize if settings else None
        folder = args.site.parent if args.site.is_file() else args.site  # labels/ and masks/ beside its site.yaml
        result = evaluate_real(folder / "labels", args.footage, folder / "masks", det.detect, score_thr=thr,
                               curve=curve, exclude_px=exclude, detect_area_px=areas, localize=localize)
        result["footprint_overlap"] = localize.footprint_overlap if localize else 0.0  # localize's rule (site.yaml)
        result["footprint_merge"] = bool(localize and localize.footprint_overlap > 0 and localize.footprint_merge)
        result["excluded_cameras"] = sorted(exclude)  # cameras whose exclusion zones (site.yaml) were applied
        line = ("{name:8s} precision {precision} recall {recall} ({labels} labels, {detections} detections within "
                f"{result['roi_m']:g} m)")
        return _print_eval(args, result, "per_camera", line)
    from eval.detector import evaluate

    if args.recording is None:
        raise ValueError("eval detector needs --recording")
    thr = 0.05 if args.score_thr is None else args.score_thr  # 0 is a threshold too
    det = OnnxDetector(args.model, threads=args.threads, score_thr=thr, mirror=args.mirror, votes=args.votes,
                       calibrated_heads=not args.raw_heads)
    result = evaluate(args.recording, det.detect, every=args.every, fisheye_area_deg=args.fisheye_area_deg,
                      near_m=args.near_m, near_score=args.near_score, detections_score_thr=thr)
    # the model's calibrations as applied (none with --raw-heads, or for a model exported without them)
    result["heads_calibrated"] = {"boxes": det.box_calibration is not None, "sizes": det.size_calibration is not None}
    line = ("{name:8s} ap50 {ap50} loc {loc_err_m} m yaw {yaw_err_deg} deg size {size_err_m} m ({frames} frames); "
            "false alarms at {breakdown_score_thr}: {false_alarms[box]} boxes off a found vehicle, "
            "{false_alarms[duplicate]} duplicates, {false_alarms[background]} on the background")
    return _print_eval(args, result, "per_kind", line)


def _print_eval(args, result: dict, per_key: str, line: str) -> int:
    """The JSON document on stdout, and unless --json a line per group (`line` formatted with its figures)."""
    if args.model is not None:
        result["model"] = str(args.model)
    if not args.json:
        for name, r in {"overall": result["overall"], **result[per_key]}.items():
            print(line.format(name=name, **r), file=sys.stderr)
    print(dumps(result, indent=1))
    return 0


def _add_up(sub) -> None:
    p = sub.add_parser("up", help="start the four services as OS processes (Ctrl-C stops them)")
    p.add_argument("--site", required=True, type=Path,
                   help="site folder or site.yaml (a name such as state_ellsworth means deploy/sites/NAME)")
    p.add_argument("--source", help="recording, image folders, video file or stream URL (overrides ingest.source)")
    p.add_argument("--pace", help="1 (real time), N (N x real time) or max (as fast as the pipeline goes)")
    p.add_argument("--loop", action="store_true", help="repeat the source")
    p.add_argument("--from", dest="play_from", metavar="DATETIME",
                   help="play only the recorded frames captured from then on: ISO 8601, e.g. 2023-12-19T11:00:40, or a "
                   "time of day (11:00:40, on the day of the first frame), in the site's ingest.timezone unless it "
                   "carries an offset (ingest.play_from)")
    p.add_argument("--until", dest="play_until", metavar="DATETIME", help="and before then (ingest.play_until)")
    p.add_argument("--max-frames", type=int, metavar="N", help="stop after N frames of each camera (ingest.max_frames)")
    p.add_argument("--record", type=Path, help="append tracks to this JSON-lines file")
    p.add_argument("--record-frames", type=Path, metavar="DIR",
                   help="also write every frame played, at full resolution, to DIR/<camera>/<capture ns>.jpg: "
                        "a folder --source plays back (ingest.record_dir)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override a setting in every service (repeatable)")
    p.add_argument("--no-restart", action="store_true", help="do not restart a service that dies")
    p.add_argument("--log-dir", type=Path, help="write each service's log to LOG_DIR/<service>.log")


PORTS_FREE_WAIT_S = 5.0  # `roadside up` waits this long for a pipeline that is stopping to free the ports


def _run_up(args) -> int:
    from roadside.launcher import Launcher, UpConfig

    sets = list(args.set)
    # --set values are YAML: a path is passed quoted (a JSON string is YAML), or " #" would start a comment
    if args.source:
        source = args.source if "://" in args.source else str(Path(args.source).resolve())
        sets.append(f"ingest.source={json.dumps(source)}")
    if args.pace:
        sets.append(f"ingest.pace={args.pace}")
    if args.loop:
        sets.append("ingest.loop=true")
    for field in ("play_from", "play_until"):
        if getattr(args, field):
            sets.append(f"ingest.{field}={json.dumps(getattr(args, field))}")
    if args.max_frames is not None:
        sets.append(f"ingest.max_frames={args.max_frames}")
    if args.record:
        sets.append(f"fuse_track.record={json.dumps(str(args.record.resolve()))}")
    if args.record_frames:
        sets.append(f"ingest.record_dir={json.dumps(str(args.record_frames.resolve()))}")
    site = site_path(args.site)
    from shared.bus import ports_in_use
    from shared.service import parse_sets
    from shared.settings import load_settings

    settings = load_settings(site, **parse_sets(sets))  # fail here, once, on a bad site file or flag
    busy = ports_in_use(settings.bus, PORTS_FREE_WAIT_S)
    if busy:  # each service would die on its port and be restarted, ever more slowly, until the other one stops
        raise ValueError(f"the bus's ports are in use: {', '.join(busy)}; is another pipeline running on this "
                         "machine (`roadside status` shows it)? Stop it, or give this one its own bus.port_base")
    return Launcher(UpConfig(site=site, sets=sets, restart=not args.no_restart, log_dir=args.log_dir)).run(
        log=lambda s: print(s, file=sys.stderr))


def _add_counts(sub) -> None:
    p = sub.add_parser("counts", help="turning-movement counts from tracks files, or live from the bus: the vehicles "
                       "from each leg of the junction to each, per time bin (shared/movements.py; the site file's "
                       "movements:)")
    p.add_argument("tracks", nargs="*", type=Path, help="tracks files (fuse_track.record; rotated ones too)")
    p.add_argument("--site", type=Path, required=True,
                   help="site folder or site.yaml with a movements: section (with --live also the site's name and bus)")
    p.add_argument("--bin-s", type=positive_float, default=900.0,
                   help="bin length in seconds, 1 to 604800 (a week), bins aligned to the clock (default 900: 15 "
                   "minutes)")
    p.add_argument("--json", action="store_true", help="one JSON document (with --live: one JSON line a bin)")
    p.add_argument("--csv", action="store_true",
                   help="CSV instead: start,end,observed_s,from,to,turn,vehicles, a row for each pair of legs a bin "
                   "(turn U/L/T/R), then the vehicles seen entering only (to empty) and leaving only (from empty)")
    p.add_argument("--out", type=Path,
                   help="also append the bins to this CSV file (the header when it is new), each bin written and "
                   "synced to disk as it is counted: a cabinet's record of its counts")
    p.add_argument("--live", action="store_true",
                   help="count the site's live tracks instead of files, printing each bin as it closes, until Ctrl-C, "
                   "--count or --timeout (the bins still open are printed then)")
    p.add_argument("--connect", action="append", default=[], type=endpoint,
                   help="with --live: Zenoh endpoint, the cabinet's router tcp/HOST:7447 (default: the site's bus)")
    p.add_argument("--linger-s", type=positive_float, default=10.0,
                   help="with --live: a track unseen this long (capture time) has left (default 10)")
    p.add_argument("--close-after-s", type=positive_float, default=120.0,
                   help="with --live: a bin is printed this long after its end (default 120)")
    p.add_argument("--heartbeat", type=Path,
                   help="with --live: touch this file (at most every 5 s) while Tracks messages arrive: its age says "
                   "whether the counter is counting (compose's healthcheck)")
    p.add_argument("--count", type=positive_int, help="with --live: stop after this many bins")
    p.add_argument("--timeout", type=positive_float,
                   help="with --live: stop after this many seconds without a Tracks message (fuse_track sends one a "
                   "tick, empty ones too)")


def _live_only(args, *flags: str) -> None:
    """ValueError naming the first of these flags given without --live (they mean nothing to files)."""
    for flag in flags:
        if getattr(args, flag):
            raise ValueError(f"--{flag.replace('_', '-')} goes with --live")


def _board(b: dict, legs: list[str]) -> str:
    """A bin's counts (Counts.to_json with its start and end) as a table."""
    width = max(6, *(len(leg) for leg in legs)) + 1
    span = (b["end_ns"] - b["start_ns"]) / 1e9
    seen = "" if b["observed_s"] >= span else f" (tracks for {b['observed_s']:g} s of its {span:g})"
    lines = [f"{b['start']} - {b['end']}{seen}: {b['complete_total']} vehicles through the junction, seen entering "
             "and leaving",
             "from \\ to".ljust(width) + "".join(leg.rjust(width) for leg in legs) + "entering".rjust(width + 3)
             + "  U/L/T/R"]
    for i, leg in enumerate(legs):
        lines.append(leg.ljust(width) + "".join(str(c).rjust(width) for c in b["complete"][i])
                     + str(b["entering"][leg]).rjust(width + 3) + "  " + "/".join(map(str, b["turns"][leg].values())))
    lines.append("leaving".ljust(width) + "".join(str(b["leaving"][leg]).rjust(width) for leg in legs))
    lines.append(f"  seen entering only {sum(b['entered_only'].values())}, leaving only "
                 f"{sum(b['exited_only'].values())} (counted in entering / leaving)")
    return "\n".join(lines)


def _bin_json(b, junction) -> dict:
    from shared.movements import iso_utc

    return {"start": iso_utc(b.start_ns), "end": iso_utc(b.end_ns), **b.to_json(junction)}


class _CountsCsv:
    """The bins as CSV rows (shared.movements.CSV_HEADER) on stdout (`--csv`) and/or appended to a file (`--out`: the
    header when the file is new or empty; each bin flushed and synced as it is written)."""

    def __init__(self, stdout: bool, path: Path | None, junction) -> None:
        import csv

        from shared.movements import CSV_HEADER

        self.junction, self.file, self.out = junction, None, None
        if stdout:
            self.out = csv.writer(sys.stdout, lineterminator="\n")
            self.out.writerow(CSV_HEADER)
        if path is not None:
            if path.is_dir():
                raise ValueError(f"--out {path}: a folder, not a file")
            try:
                self.file = open(path, "a", newline="")  # closed by close()
            except OSError as exc:
                raise ValueError(f"--out {path}: cannot append ({exc.strerror})") from None
            self.writer = csv.writer(self.file, lineterminator="\n")
            if self.file.tell() == 0:
                self.writer.writerow(CSV_HEADER)
                self._sync()

    def write(self, b) -> None:
        rows = b.csv_rows(self.junction)
        if self.out is not None:
            self.out.writerows(rows)
            sys.stdout.flush()
        if self.file is not None:
            self.writer.writerows(rows)
            self._sync()

    def _sync(self) -> None:
        self.file.flush()
        os.fsync(self.file.fileno())

    def close(self) -> None:
        if self.file is not None:
            self.file.close()


def _site_tracks(paths: list[Path], settings, site: Path):
    """The tracks files read (`shared.movements.read_tracks`); ValueError when they hold no tracks line, or tracks of
    another site than `settings`' (a site file at `site`)."""
    from shared.movements import read_tracks

    read = read_tracks(paths)
    if not read.times_ns:
        why = f"; {read.bad[0]}" if read.bad else ""
        raise ValueError(f"no tracks line in {', '.join(map(str, paths))} ({read.lines} lines{why})")
    if read.sites - {settings.site}:
        raise ValueError(f"the tracks are of site {', '.join(sorted(read.sites))}, {site} is site {settings.site}: "
                         "give the tracks' own site")
    return read


def _run_counts(args) -> int:
    from shared.movements import binned, movements
    from shared.settings import load_settings

    if args.csv and args.json:
        raise ValueError("counts: --csv or --json, not both")
    site = site_path(args.site)
    settings = load_settings(site)
    if settings.movements is None:
        raise ValueError(f"{site}: the site file has no movements: section (the junction's centre, legs and radii; "
                         "deploy/sites/README.md)")
    junction = settings.movements.junction()
    if args.live:
        if args.tracks:
            raise ValueError("counts --live counts the bus's tracks, not files: give one or the other")
        return _run_counts_live(args, settings, junction)
    _live_only(args, "connect", "heartbeat", "count", "timeout")
    if not args.tracks:
        raise ValueError("counts needs tracks files (or --live)")
    read = _site_tracks(args.tracks, settings, site)
    found = movements(read.positions, junction)
    bins = binned(found, args.bin_s, read.times_ns)
    legs = junction.names
    doc = {"site": settings.site, "legs": legs, "bin_s": args.bin_s, "lines": read.lines, "bad_lines": read.bad_lines,
           "bad": read.bad, "movements": len(found), "bins": [_bin_json(b, junction) for b in bins]}
    table = _CountsCsv(args.csv, args.out, junction)
    try:
        for b in bins:
            table.write(b)
    finally:
        table.close()
    if args.json:
        print(dumps(doc, indent=1))
        return 0
    if not args.csv:
        for b in doc["bins"]:
            print(_board(b, legs))
    for line in read.bad:
        print(f"skipped: {line}", file=sys.stderr)
    if not found:
        print("no vehicle went through the junction in these tracks", file=sys.stderr)
    return 0


def _run_counts_live(args, settings, junction) -> int:
    import signal
    import threading

    from roadside.cli_bus import asking_bus
    from shared.client import TrackClient
    from shared.movements import LiveCounts

    live = LiveCounts(junction, args.bin_s, args.linger_s, args.close_after_s)
    legs = junction.names
    stop = threading.Event()
    before = {}
    if threading.current_thread() is threading.main_thread():  # Ctrl-C and SIGTERM end the stream between messages
        for sig in (signal.SIGINT, signal.SIGTERM):
            before[sig] = signal.signal(sig, lambda *_: stop.set())
    shown = 0

    def show(bins) -> bool:  # True once --count bins are out
        nonlocal shown
        for b in bins:
            table.write(b)
            if not args.csv:
                doc = _bin_json(b, junction)
                print(dumps({"site": settings.site, **doc}) if args.json else _board(doc, legs), flush=True)
            shown += 1
            if args.count and shown >= args.count:
                return True
        return False

    table = _CountsCsv(args.csv, args.out, junction)
    try:
        with TrackClient(settings.site, args.connect or None, asking_bus(settings.bus)) as client:
            print(f"counting the live tracks of site {settings.site} in {args.bin_s:g} s bins", file=sys.stderr,
                  flush=True)
            beat = -math.inf
            for tracks in client.stream(timeout_s=args.timeout, stop=stop, latest=False):
                if args.heartbeat is not None and time.monotonic() - beat >= HEARTBEAT_S:
                    args.heartbeat.touch()
                    beat = time.monotonic()
                if show(live.update(tracks)):
                    return 0
        show(live.flush())
        return 0
    finally:
        table.close()
        for sig, handler in before.items():
            signal.signal(sig, handler)


VIZ_FRAMES_MARGIN_NS = 10**9  # viz --frames: frames this much before the first / after the last tracks are kept too


def _add_viz(sub) -> None:
    p = sub.add_parser("viz", help="turn a tracks file, or the live tracks, into a Rerun .rrd (trajectories over the "
                       "site map)")
    p.add_argument("tracks", type=Path, nargs="?", help="tracks JSON-lines file (fuse_track.record); or --live")
    p.add_argument("--out", type=Path, required=True, help=".rrd file to write")
    p.add_argument("--site", type=Path, help="site folder or site.yaml (its origin places lat/lon rows; with --live "
                   "also the site's name and bus)")
    p.add_argument("--live", action="store_true", help="subscribe to the site's live tracks instead of reading a "
                   "file, until Ctrl-C, --count or --timeout (needs --site)")
    p.add_argument("--connect", action="append", default=[], type=endpoint,
                   help="with --live: Zenoh endpoint, the cabinet's router tcp/HOST:7447 (default: the site's local "
                   "fuse_track)")
    p.add_argument("--viewer", help="with --live: also stream to a running Rerun viewer at this URL (e.g. "
                   "rerun+http://127.0.0.1:9876/proxy)")
    p.add_argument("--count", type=int, help="with --live: stop after this many messages")
    p.add_argument("--timeout", type=finite_float, help="with --live: stop after this many seconds without tracks")
    p.add_argument("--basemap", type=Path, help="world file (YAML/JSON: image + corners) of an orthophoto, or a folder "
                   "holding one such world file and its image")
    p.add_argument("--recording", type=Path, help="simulator recording: draw its site's ground as the map")
    p.add_argument("--frames", help="also log the camera frames of this source (recording, image folders; needs "
                   "--site for the camera names) with the detections of --model: those captured within the tracks "
                   f"file's time span (+- {VIZ_FRAMES_MARGIN_NS / 1e9:g} s)")
    p.add_argument("--model", type=Path, help="ONNX detector for the logged frames' detections")
    p.add_argument("--frames-every", type=int, help="log every n-th frame of each camera (default 5)")


def _tracks_span(path: Path) -> tuple[int, int] | None:
    """(first, last) capture time in ns of the valid messages of a tracks file, read as the sink reads them
    (shared.tracks_file); None when the file cannot be read or has none."""
    from shared.tracks_file import file_lines, parse_tracks_message

    times = []
    try:
        for _, line in file_lines(path):
            try:
                times.append(parse_tracks_message(json.loads(line)).t_ns)
            except ValueError:  # bad JSON or a bad message: the sink passes it over too
                continue
    except ValueError:  # the file cannot be opened: the sink says so
        return None
    return (min(times), max(times)) if times else None


def _frames_within(source, span: tuple[int, int] | None, cameras, margin_ns: int = VIZ_FRAMES_MARGIN_NS,
                   counts: dict | None = None):
    """The frames of `source` (SourceFrames in capture-time order per camera) captured within `span` (first, last
    ns) widened by `margin_ns` on each side; all of them when `span` is None. Stops reading once every one of
    `cameras` has passed the span's end. `counts` (a dict) gets the frames read and kept."""
    counts = {} if counts is None else counts
    counts.update(read=0, kept=0)
    if span is None:
        for sf in source:
            counts["read"] += 1
            counts["kept"] += 1
            yield sf
        return
    lo, hi = span[0] - margin_ns, span[1] + margin_ns
    waiting, past = set(cameras), set()
    for sf in source:
        counts["read"] += 1
        if sf.t_capture_ns > hi:
            past.add(sf.camera)
            if waiting and waiting <= past:
                return
            continue
        if sf.t_capture_ns < lo:
            continue
        counts["kept"] += 1
        yield sf


def _viz_frames(args, span: tuple[int, int] | None = None, counts: dict | None = None):
    """(camera, t_ns, grey image, detections) of every n-th frame of each camera of --frames captured within `span`
    (the tracks file's, `_frames_within`); the flags, the site, the model and the source are checked at once (before
    any output is written), the frames read as they are taken."""
    from services.ingest.sources import open_source
    from shared.inference import OnnxDetector
    from shared.settings import load_settings

    if args.site is None or args.model is None:
        raise ValueError("viz --frames needs --site (camera names) and --model (detections)")
    if args.frames_every < 1:
        raise ValueError(f"--frames-every must be >= 1, got {args.frames_every}")
    settings = load_settings(site_path(args.site))
    cams = [c.name for c in settings.cameras]
    det = OnnxDetector(args.model, threads=2, score_thr=settings.detect.score_thr)
    # the frames' capture times as ingest gives them: from the names in the site's time zone, or its frame rate
    source = open_source(str(args.frames), cams, {}, settings.ingest.fps, settings.ingest.tzinfo())
    return _viz_frame_rows(args, settings, det, _frames_within(source, span, cams, counts=counts))


def _viz_frame_rows(args, settings, det, source):
    import cv2
    import numpy as np

    seen: dict[str, int] = {}
    for sf in source:
        k = seen[sf.camera] = seen.get(sf.camera, -1) + 1
        if k % args.frames_every:
            continue
        if sf.error:
            raise ValueError(sf.error)
        grey = sf.image
        if grey is None:
            grey = cv2.imdecode(np.frombuffer(sf.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE)
        if grey is None:
            raise ValueError(f"{sf.origin}: not a readable image")
        if grey.ndim == 3:
            grey = cv2.cvtColor(grey, cv2.COLOR_BGR2GRAY)
        yield sf.camera, sf.t_capture_ns, grey, det.detect(grey, area_px=settings.camera(sf.camera).detect_area_px)


def _run_viz(args) -> int:
    from services.rerun_sink import tracks_file_to_rrd

    if args.live:
        return _run_viz_live(args)
    if args.tracks is None:
        raise ValueError("viz needs a tracks file, or --live to subscribe to the live tracks")
    _live_only(args, "connect", "viewer", "count", "timeout")
    origin = junction = None
    if args.site:
        from shared.settings import load_settings

        settings = load_settings(site_path(args.site))
        origin = settings.origin
        junction = settings.movements.junction() if settings.movements is not None else None
    basemap = args.basemap
    if args.recording:
        from roadside.demo import site_basemap
        from sim.recording import Recording

        basemap = site_basemap(args.recording)
        origin = origin or Recording(args.recording).meta["site"]["origin"]
    if not args.frames and (args.model or args.frames_every is not None):
        raise ValueError("--model and --frames-every go with --frames (the camera frames to log)")
    args.frames_every = 5 if args.frames_every is None else args.frames_every
    frame_counts: dict = {}
    span = _tracks_span(args.tracks) if args.frames else None
    frames = _viz_frames(args, span, frame_counts) if args.frames else None
    import signal

    # SIGTERM as Ctrl-C: the conversion stops and its partial file is removed (an existing .rrd is kept)
    before = signal.signal(signal.SIGTERM, signal.default_int_handler)
    try:
        summary = tracks_file_to_rrd(args.tracks, args.out, site_origin=origin, basemap=basemap, frames=frames,
                                     junction=junction, site=settings.site if args.site else None)
    finally:
        signal.signal(signal.SIGTERM, before)
    print(dumps(summary, indent=1))
    if frame_counts.get("read") and not frame_counts.get("kept"):
        print(f"roadside viz: warning: none of the {frame_counts['read']} frames of {args.frames} read lies within "
              f"the tracks' time span (+- {VIZ_FRAMES_MARGIN_NS / 1e9:g} s): another clip, or another clock?",
              file=sys.stderr)
    if summary["messages"] == 0:  # the .rrd holds the map alone: say so, as --live does when nothing came
        why = (f"; line {summary['first_bad_line']}: {summary['first_bad_reason']}" if summary["bad_lines"] else "")
        print(f"roadside viz: no valid tracks line in {args.tracks} ({summary['lines']} lines{why})", file=sys.stderr)
        return 1
    return 0


def _run_viz_live(args) -> int:
    """`roadside viz --live`: the site's live tracks into an .rrd (and a viewer), until Ctrl-C / SIGTERM, --count or
    --timeout; the file holds every message received before the stop."""
    import signal
    import threading

    import rerun as rr

    from services.rerun_sink import live
    from shared.client import TrackClient
    from shared.settings import load_settings

    if args.tracks is not None or args.recording or args.frames:
        raise ValueError("--live takes no tracks file, --recording or --frames")
    if args.site is None:
        raise ValueError("--live needs --site (the site's name, origin and bus)")
    if args.count is not None and args.count < 1:
        raise ValueError(f"--count must be >= 1, got {args.count}")
    if args.timeout is not None and not args.timeout > 0:
        raise ValueError(f"--timeout must be > 0, got {args.timeout}")
    settings = load_settings(site_path(args.site))
    if args.out.is_dir():
        raise ValueError(f"--out {args.out} is a folder, not an .rrd file")
    basemap = None
    if args.basemap:  # read before the bus is joined or any file is written
        from services.rerun_sink.basemap import Basemap
        from shared.geo import GeoFrame

        basemap = Basemap.from_world_file(args.basemap, GeoFrame.from_dict(settings.origin) if settings.origin
                                          else None)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    partial = args.out.with_name(args.out.name + ".partial")  # an existing .rrd is replaced when the stream ends
    with TrackClient(settings.site, args.connect or None, settings.bus) as client:
        rec = rr.RecordingStream("roadside")
        sinks = [rr.FileSink(str(partial))] + ([rr.GrpcSink(args.viewer)] if args.viewer else [])
        rec.set_sinks(*sinks)
        rec.send_recording_name(f"{settings.site} live")

        def messages():
            for n, tracks in enumerate(client.stream(timeout_s=args.timeout, stop=stop, latest=False), 1):
                yield tracks
                if args.count and n >= args.count:
                    return

        try:
            summary = live(messages(), rec, site_origin=settings.origin, basemap=basemap,
                           junction=settings.movements.junction() if settings.movements is not None else None)
        finally:
            try:
                rec.flush()
            except Exception as exc:  # a viewer that cannot be reached: the file is complete all the same
                print(f"roadside viz: warning: {exc}", file=sys.stderr)
            rec.disconnect()
            partial.replace(args.out)
        summary["bad_messages"] = client.bad.total
    print(dumps({"site": settings.site, "rrd": str(args.out), **summary}, indent=1))
    if not summary["messages"]:
        print("roadside viz: no tracks received", file=sys.stderr)
    return 0 if summary["messages"] else 1


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark; prints one JSON document")
    p.add_argument("name", choices=sorted(BENCHMARKS))
    p.add_argument("args", nargs=argparse.REMAINDER, help="flags passed to the benchmark")


def _run_bench(args) -> int:
    import importlib

    return importlib.import_module(BENCHMARKS[args.name]).main(args.args)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="roadside", description="Roadside traffic perception")
    sub = parser.add_subparsers(dest="job", required=True)
    _add_sim(sub)
    _add_demo(sub)
    _add_calibrate(sub)
    _add_bench(sub)
    model_runners = add_model_jobs(sub)  # train, export, calibrate-heads, mix: the detector
    site_runners = add_site_jobs(sub)  # autolabel, static, area, composite: a real site's labels
    _add_eval(sub)
    _add_up(sub)
    bus_runners = add_bus_jobs(sub)  # tracks, status, health: what a running pipeline says
    _add_viz(sub)
    _add_counts(sub)
    args = parser.parse_args(argv)
    runners = {"sim": _run_sim, "demo": _run_demo, "calibrate": _run_calibrate, "bench": _run_bench,
               "eval": _run_eval, "up": _run_up, "viz": _run_viz, "counts": _run_counts, **model_runners,
               **site_runners, **bus_runners}
    try:
        return runners[args.job](args)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"roadside {args.job}: error: {exc}", file=sys.stderr)
        return 2
    except BrokenPipeError:  # the reader went away (`| head`): nothing more to say, and nowhere to say it
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # what is left in its buffer goes nowhere
        return 0
    except OSError as exc:  # a file it cannot read or write: a folder where a file belongs, no permission, a full disk
        print(f"roadside {args.job}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"roadside {args.job}: interrupted", file=sys.stderr)
        return 130
