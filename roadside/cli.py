"""`roadside <job> ...`: parse flags into typed configs and hand them to each job's main."""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from roadside.argtypes import finite_float, positive_float, site_path
from roadside.cli_bus import add_bus_jobs
from shared.jsonio import dumps
from shared.messages import check_name


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
    p.add_argument("--type-weights", type=_type_weights, default=None, metavar="TYPE=W,...",
                   help="multiply vehicle types' shares of the mix, e.g. bus=4,truck=3 (types: car, suv_van, truck, "
                        "bus, motorcycle)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output folder")
    p.add_argument("--contact-sheet", type=Path, default=None, help="also draw a contact sheet PNG here")


def _type_weights(text: str) -> dict[str, float]:
    """'bus=4,truck=3' -> {'bus': 4.0, 'truck': 3.0} (argparse type; the sim checks the types and values)."""
    out = {}
    for part in text.split(","):
        typ, sep, value = part.partition("=")
        typ = typ.strip()
        try:
            weight = float(value)
        except ValueError:
            sep = ""
        if not sep or not typ:
            raise argparse.ArgumentTypeError(f"expected TYPE=WEIGHT[,TYPE=WEIGHT...], got {part!r}")
        if typ in out:
            raise argparse.ArgumentTypeError(f"{typ} is given twice in {text!r}")
        out[typ] = weight
    return out


def _loss_type_weights_arg(text: str) -> dict[str, float]:
    """--loss-type-weights: `_type_weights`, or 'none' (an empty dict: no type weights, also not a checkpoint's)."""
    return {} if text.strip().lower() == "none" else _type_weights(text)


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
    summary = simulate_clip(cfg, log=lambda s: print(f"[sim] {s}", file=sys.stderr))
    if args.contact_sheet:
        contact_sheet(args.out, args.contact_sheet)
        summary["contact_sheet"] = str(args.contact_sheet)
    print(dumps(summary, indent=1))
    return 0


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="the demo: the simulated State/Ellsworth roundabout through the live pipeline")
    p.add_argument("--out", type=Path, default=Path("out/demo"))
    p.add_argument("--seconds", type=positive_float, default=60.0)
    p.add_argument("--hz", type=positive_float, default=10.0)
    p.add_argument("--seed", type=int, default=2024)
    p.add_argument("--landmarks", type=int, default=20, help="landmarks per camera for calibration")
    p.add_argument("--model", type=Path, help="detector ONNX (default: the shipped models/detector_fp32.onnx)")
    p.add_argument("--port-base", type=int, default=7451)
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
    p.add_argument("--width", type=int, help="image width (default: from the landmark file)")
    p.add_argument("--height", type=int, help="image height (default: from the landmark file)")
    p.add_argument("--report", type=Path, help="report JSON (default: next to --out)")
    p.add_argument("--segments", type=int, help="ground segments (default 2 pinhole range bands, 4 fisheye sectors)")
    p.add_argument("--image-circle", type=_floats(3), help="fisheye image circle CX,CY,RADIUS in pixels")
    p.add_argument("--fov-deg", type=finite_float, default=188.0,
                   help="fisheye field of view at the image circle's edge")
    p.add_argument("--origin", type=_floats(3), help="site frame origin LAT,LON,ALT (default: the landmarks' median)")
    p.add_argument(
        "--roi-center", type=_floats(2), help="ROI centre LAT,LON (default: the camera, 25 m fisheye / 200 m)"
    )
    p.add_argument("--roi-radius", type=finite_float, default=25.0, help="ROI radius in metres (with --roi-center)")
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

    roi = {"center_latlon": list(args.roi_center), "radius_m": args.roi_radius} if args.roi_center else None
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
    )
    report = run_calibration(job)
    print(report["summary"])
    print(f"masks: {args.out}\nreport: {report['report']}")
    return 0


BENCHMARKS = {"sim": "bench.sim_render", "calibration": "bench.calibration", "detector": "bench.detector",
              "fuse_track": "bench.fuse_track"}


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train the detector on recordings and/or COCO-style annotations (needs torch)")
    p.add_argument("--recording", action="append", default=[],
                   help="simulator recording folder (repeatable); PATH@fisheye, @thermal, @pinhole, @visible or "
                        "@NE,NW: only those cameras")
    p.add_argument("--coco", action="append", default=[], help="COCO-style annotation JSON (repeatable)")
    p.add_argument("--out", required=True, help="output folder (model.pt, train_log.jsonl, train.json)")
    p.add_argument("--steps", type=int, help="number of steps (default 4000, or as many as --minutes allows)")
    p.add_argument("--minutes", type=positive_float,
                   help="time budget: the learning-rate schedule follows the clock to its end (with --steps too, "
                        "whichever comes first ends the run)")
    p.add_argument("--batch-size", type=int, default=16)
    p.add_argument("--crop", type=int, default=256)
    p.add_argument("--lr", type=positive_float, default=2e-3)
    p.add_argument("--every", type=int, default=1, help="use every n-th frame")
    p.add_argument("--center", choices=["bottom", "box"], default="bottom", help="box: the 2D-box-centre ablation")
    p.add_argument("--no-topk", action="store_true", help="ablation: plain mean squared heat-map loss")
    p.add_argument("--heat-loss", choices=["mse", "focal"],
                   help="heat-map loss: mse (the paper's squared error with TopK, the default) or focal (CenterNet's "
                        "penalty-reduced focal loss; training/loss.py); with --init, the checkpoint's")
    p.add_argument("--stride", type=int, default=4, choices=[1, 2, 4])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--init", help="model.pt to start from (fine-tuning); its network settings are kept")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted run in --out from its resume.pt (saved every 500 steps): the same "
                        "command again with --resume; the schedule and a --minutes budget go on from where it was")
    p.add_argument("--axis-head", action="store_true",
                   help="predict the heading's axis too (training/model.py); with --init, adds it to that model")
    p.add_argument("--vote-head", action="store_true",
                   help="train the centre votes (--beta-vote) in a head of their own rather than the offset head "
                        "(training/model.py; detect.votes lets decoding use them); with --init, adds it to that model")
    p.add_argument("--beta-heading", type=positive_float,
                   help="weight of the heading term (default 0.01, the paper's; with --init, the checkpoint's)")
    p.add_argument("--beta-size", type=positive_float,
                   help="weight of the size term (default 0.01, the paper's; with --init, the checkpoint's)")
    p.add_argument("--beta-vtype", type=positive_float,
                   help="weight of the type term (default 0.01, the paper's; with --init, the checkpoint's)")
    p.add_argument("--beta-offset", type=positive_float,
                   help="weight of the sub-cell offset term (default 0.1; with --init, the checkpoint's)")
    p.add_argument("--beta-box", type=finite_float,
                   help="extra weight of the 2D box (width, height, centre offset); default 0, the paper's loss "
                        "(with --init, the checkpoint's)")
    p.add_argument("--beta-vote", type=finite_float,
                   help="weight of the centre votes: every cell of a vehicle's 2D box trained to point at its centre "
                        "(training/targets.py); default 0 (with --init, the checkpoint's)")
    p.add_argument("--loss-type-weights", type=_loss_type_weights_arg, metavar="TYPE=W,...",
                   help="with --heat-loss focal: the cells of these vehicle types' vehicles weigh W times in the loss "
                        "(e.g. bus=4,truck=2; the others 1; with --init, the checkpoint's; 'none': all 1)")
    p.add_argument("--fisheye-rotation", choices=["any", "quarter", "off"], default="any",
                   help="augmentation: turn fisheye crops about the principal point by any angle (2D boxes "
                        "approximated), by multiples of 90 degrees (boxes exact) or not at all")
    p.add_argument("--input-long-side", type=int,
                   help="network input: images shrunk so their longer side is at most this (default 640, or the "
                        "--init model's); with --init, the starting weights are kept")
    p.add_argument("--focus-by-size", action="store_true",
                   help="augmentation: centre the crops on large vehicles more often (chance proportional to "
                        "their 2D box size)")
    p.add_argument("--device", default="cpu",
                   help="cpu (default), cuda or cuda:N (needs a PyTorch with CUDA; the train extra's is CPU-only)")
    p.add_argument("--workers", type=int, default=0,
                   help="processes preparing batches in the background (a GPU needs several; 0: in this process, "
                        "reproducible from --seed)")
    p.add_argument("--train-only", default="",
                   help="with --init: train only these heads (comma-separated: heat, size, heading, vtype, offset, "
                        "axis), the rest frozen; e.g. offset sharpens localization and leaves detection as it is")


UNLIMITED_STEPS = 10**9  # with --minutes alone the clock ends the run


LOSS_FLAGS = ("heat_loss", "beta_size", "beta_heading", "beta_vtype", "beta_offset", "beta_box", "beta_vote")


def _loss_type_weights(given: dict[str, float]) -> tuple[float, ...] | None:
    """{'bus': 4} -> one weight per VEHICLE_TYPES entry (1 for those not named); {} ('none') -> None; ValueError
    naming an unknown type or a weight that is not a finite number > 0."""
    from shared.messages import VEHICLE_TYPES

    if not given:
        return None
    unknown = sorted(set(given) - set(VEHICLE_TYPES))
    if unknown:
        raise ValueError(f"--loss-type-weights: unknown vehicle type(s) {', '.join(unknown)}; the types are "
                         f"{', '.join(VEHICLE_TYPES)}")
    bad = [f"{t}={w}" for t, w in given.items() if not (math.isfinite(w) and w > 0)]
    if bad:
        raise ValueError(f"--loss-type-weights: weights must be finite numbers > 0, got {', '.join(bad)}")
    return tuple(float(given.get(t, 1.0)) for t in VEHICLE_TYPES)


def _train_loss(args, loss_config):
    """The run's LossConfig: the paper's defaults, or with --init the settings that checkpoint was trained with
    (fine-tuning keeps its loss), then whatever the command line gives."""
    from training.model import checkpoint_loss

    base = {}
    if args.init is not None and Path(args.init).is_file():
        base = checkpoint_loss(args.init) or {}
        if base:
            print(f"[train] loss settings of {args.init}: {base} (flags given here replace them)")
    given = {("heat" if name == "heat_loss" else name): getattr(args, name) for name in LOSS_FLAGS
             if getattr(args, name) is not None}
    if args.no_topk:
        given["topk_fraction"] = None
    if args.loss_type_weights is not None:
        given["type_weights"] = _loss_type_weights(args.loss_type_weights)
    try:
        return loss_config(**{**base, **given})
    except TypeError as exc:  # a checkpoint written by a later version with settings this one lacks
        raise ValueError(f"{args.init}: loss settings {base} are not this version's ({exc})") from None


def _run_train(args) -> int:
    try:
        from training.train import TrainConfig, train
    except ImportError as exc:
        raise RuntimeError(f"training needs the train extra (pip install -e '.[train]'): {exc}") from exc
    from training.augment import AugmentConfig
    from training.loss import LossConfig
    from training.model import DetectorConfig

    cfg = TrainConfig(recordings=tuple(args.recording), coco=tuple(args.coco), out=args.out,
                      steps=args.steps or (UNLIMITED_STEPS if args.minutes else 4000),
                      minutes=args.minutes, batch_size=args.batch_size, crop=args.crop, lr=args.lr, every=args.every,
                      center=args.center, seed=args.seed, init=args.init, resume=args.resume,
                      add_axis_head=args.axis_head, add_vote_head=args.vote_head,
                      input_long_side=args.input_long_side, device=args.device, workers=args.workers,
                      train_only=tuple(h.strip() for h in args.train_only.split(",") if h.strip()),
                      augment=AugmentConfig(fisheye_rotation=args.fisheye_rotation, focus_by_size=args.focus_by_size),
                      model=DetectorConfig(stride=args.stride, axis_head=args.axis_head, vote_head=args.vote_head),
                      loss=_train_loss(args, LossConfig))
    print(dumps(train(cfg), indent=1))
    return 0


def _add_export(sub) -> None:
    p = sub.add_parser("export", help="export a trained detector to fp32 and fp16 ONNX (needs torch)")
    p.add_argument("model", type=Path, help="model.pt written by roadside train")
    p.add_argument("--out", type=Path, required=True, help="fp32 ONNX file; the fp16 copy gets a _fp16 suffix")
    p.add_argument("--calibration-recording", type=Path, action="append", default=[],
                   help="a training recording (repeat for more) on which to fit the box and size calibrations written "
                        "into both files' metadata (training/heads_calibration.py); never a held-out one")
    p.add_argument("--calibration-every", type=int, default=4,
                   help="every N-th frame of those recordings (default 4)")


def _add_mix(sub) -> None:
    p = sub.add_parser("mix", help="interpolate a fine-tuned detector's weights with those of the model it started "
                                   "from (needs torch)")
    p.add_argument("base", type=Path, help="the starting model (model.pt), e.g. models/detector.pt")
    p.add_argument("tuned", type=Path, help="its fine-tune (roadside train --init BASE)")
    p.add_argument("--weight", type=float, required=True,
                   help="the fine-tune's share in [0, 1]: (1 - w) * base + w * tuned (training/mix.py)")
    p.add_argument("--out", type=Path, required=True, help="model.pt to write (the base's architecture)")


def _run_mix(args) -> int:
    from training.mix import mix_detectors
    from training.model import checkpoint_loss, load_detector, save_detector

    mixed = mix_detectors(load_detector(args.base), load_detector(args.tuned), args.weight)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_detector(mixed, args.out, loss=checkpoint_loss(args.base))
    print(f"{args.out}: {1 - args.weight:g} x {args.base} + {args.weight:g} x {args.tuned}")
    return 0


def _run_export(args) -> int:
    from training.export import export_onnx
    from training.model import load_detector

    if not args.model.is_file():
        raise ValueError(f"model not found: {args.model}")
    fp16 = args.out.with_name(args.out.stem + "_fp16" + args.out.suffix)
    export_onnx(load_detector(args.model), args.out, fp16)
    print(f"fp32: {args.out}\nfp16: {fp16}")
    if args.calibration_recording:
        _heads_calibration([args.out, fp16], args.calibration_recording, args.calibration_every)
    return 0


def _add_calibrate_heads(sub) -> None:
    p = sub.add_parser("calibrate-heads",
                       help="fit an exported detector's box and size calibrations on training recordings and write "
                            "them into its ONNX files (training/heads_calibration.py; roadside export "
                            "--calibration-recording does it on export; needs onnx, the train extra)")
    p.add_argument("model", type=Path, nargs="+",
                   help="the fp32 ONNX file (fitted on), then any copies to write the same calibration into (its fp16)")
    p.add_argument("--recording", type=Path, action="append", required=True,
                   help="a training recording (repeat for more); never a held-out one")
    p.add_argument("--every", type=int, default=4, help="every N-th frame of those recordings (default 4)")


def _run_calibrate_heads(args) -> int:
    missing = [str(p) for p in args.model if not p.is_file()]
    if missing:
        raise ValueError(f"model not found: {', '.join(missing)}")
    _heads_calibration(args.model, args.recording, args.every)
    return 0


def _heads_calibration(paths: list[Path], recordings: list[Path], every: int) -> None:
    from training.heads_calibration import BOX_IOU, calibrate_files

    r = calibrate_files(paths, recordings, every, log=print)
    print(f"box and size calibrations written into {', '.join(map(str, paths))}:\n"
          f"  boxes: {r['boxes'].pairs} detections at IoU {BOX_IOU:g} or more with a vehicle, at IoU 0.5 or more "
          f"{r['box_pairs_at_iou50_before']:.3f} -> {r['box_pairs_at_iou50_after']:.3f} of them\n"
          f"  sizes: matched detections per type {list(r['sizes'].pairs)}, their mean size error "
          f"{r['size_error_before']:.3f} -> {r['size_error_after']:.3f} m")


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="score the detector: on a simulator recording, or on hand-labelled real frames")
    p.add_argument("what", choices=["detector", "real", "handoff", "budget"],
                   help="detector: against a recording's ground truth; real: against hand labels (eval/real.py); "
                        "handoff: camera-region crossings kept under one id in a tracks file (no ground truth); "
                        "budget: where a simulated run's tracking accuracy goes (eval/budget.py, --demo)")
    p.add_argument("--model", type=Path, help="exported ONNX detector (detector, real)")
    p.add_argument("--tracks", type=Path, help="tracks file written by fuse_track (handoff; real: score the tracks "
                   "of the footage played through the pipeline instead of a model's detections)")
    p.add_argument("--recording", type=Path, help="simulator recording (detector)")
    p.add_argument("--every", type=int, default=1, help="use every n-th frame (detector)")
    p.add_argument("--score-thr", type=finite_float, help="lowest score kept (default: 0.05 for detector, as AP needs "
                   "the low ones; the detect service's 0.3 for real)")
    p.add_argument("--site", type=Path, default=Path("deploy/sites/state_ellsworth"),
                   help="site folder with labels/ and masks/ (real), or its site.yaml's cameras (handoff)")
    p.add_argument("--footage", type=Path, default=Path("../shared/data/state_ellsworth/sample_data"),
                   help="folder of the cameras' frame folders (real)")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--fisheye-area-deg", type=positive_float,
                   help="detector: look at fisheye frames only inside the image circle up to this angle off axis "
                        "(e.g. 90), as a camera's detect_area_px does in the detect service")
    p.add_argument("--near-m", type=positive_float, default=25.0,
                   help="detector: the near-camera metrics count vehicles and detections within this many metres "
                        "of the camera on the ground (its region, as fusion uses it)")
    p.add_argument("--near-score", type=finite_float, default=0.3,
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
                   help="budget: a roadside demo output folder (objects.jsonl, site/, the recording; default "
                        "out/demo); repeatable: each run's budget and the mean over them")
    p.add_argument("--scenario", action="append",
                   help="budget: score only this scenario (repeatable; default all: as_run, exact_lift, "
                        "true_positions, no_false_alarms, true_positions_no_false_alarms, true_long_vehicles, truth)")
    p.add_argument("--localize-rule", action="store_true",
                   help="budget: apply localize's footprint rule (localize.footprint_overlap, footprint_merge) to the "
                        "objects left at the replay's threshold, for a run recorded without it "
                        "(ROADSIDE_LOCALIZE__FOOTPRINT_OVERLAP=0): the exact replay of a higher threshold")
    p.add_argument("--json", action="store_true", help="print one JSON document (default: also a summary)")


def _run_eval(args) -> int:
    from shared.inference import OnnxDetector

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
    if args.what == "handoff":
        from eval.tracking import handoff_without_truth
        from services.fuse_track.__main__ import camera_positions
        from shared.settings import load_settings

        if args.tracks is None:
            raise ValueError("eval handoff needs --tracks")
        positions, _ = camera_positions(load_settings(args.site))
        print(dumps({"tracks_file": str(args.tracks), **handoff_without_truth(args.tracks, positions)}, indent=1))
        return 0
    if args.what == "real" and args.tracks is not None:
        if args.model is not None:
            raise ValueError("eval real scores either a model's detections (--model) or a tracks file (--tracks), "
                             "not both")
        from eval.real import evaluate_tracks_real
        from shared.geo import GeoFrame
        from shared.settings import load_settings

        origin = load_settings(args.site).origin
        result = evaluate_tracks_real(args.site / "labels", args.tracks, args.site / "masks",
                                      GeoFrame.from_dict(origin) if origin else None)
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
        result = evaluate_real(args.site / "labels", args.footage, args.site / "masks", det.detect, score_thr=thr,
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
                      near_m=args.near_m, near_score=args.near_score)
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


def _add_autolabel(sub) -> None:
    p = sub.add_parser("autolabel", help="training labels for a real camera from moving vehicles (no manual labels)")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (capture time in the names)")
    p.add_argument("--masks", type=Path, required=True, help="the camera's lookup masks (roadside calibrate)")
    p.add_argument("--camera", required=True, help="camera name written into the labels")
    p.add_argument("--out", type=Path, required=True, help="folder for labels.json, images/ and report.json")
    p.add_argument("--until", help="leave out frames at or after this time of day HH:MM:SS (a held-out slice)")
    p.add_argument("--roi-m", type=positive_float, default=30.0, help="label within this distance of the camera")
    p.add_argument("--truth", type=Path, help="simulator recording of these frames: score the labels against it")
    p.add_argument("--teacher", type=Path, help="detector ONNX model whose detections away from the labels become "
                   "ignore regions: parked and waiting vehicles, which the background model cannot see")
    p.add_argument("--teacher-thr", type=finite_float, default=0.1, help="teacher detections at least this confident")
    p.add_argument("--ignore-small", action="store_true",
                   help="foreground regions too small for a vehicle become ignore regions instead of being dropped")
    p.add_argument("--tracks", type=Path, help="the pipeline's tracks of the same footage (roadside up --record): "
                   "vehicles they followed while moving become labels where the background model found none "
                   "(training/track_labels.py)")


def _add_static(sub) -> None:
    p = sub.add_parser("static", help="detections that stay at one pixel in a camera's frames: candidates for "
                                      "its exclusion zones (cameras[].exclude_px)")
    p.add_argument("--model", type=Path, required=True, help="the detector ONNX model the site runs")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (capture time in the names)")
    p.add_argument("--until", help="only frames before this time of day HH:MM:SS (leave a held-out slice alone)")
    p.add_argument("--every", type=int, default=4, help="use every n-th frame (default 4)")
    p.add_argument("--score-thr", type=finite_float, default=0.3, help="detections at least this confident (detect's)")
    p.add_argument("--min-fraction", type=finite_float, default=0.5,
                   help="report places detected in this share of frames")
    p.add_argument("--crops", type=Path, help="folder: write the image around each place (spot_<k>.png) to look at")


def _add_area(sub) -> None:
    p = sub.add_parser("area", help="the rectangle of a camera's frames that shows anything (a fisheye's image "
                                    "circle): its cameras[].detect_area_px")
    p.add_argument("--frames", type=Path, required=True, help="one camera's frames (a folder of images)")
    p.add_argument("--every", type=int, default=60, help="use every n-th frame (default 60)")
    p.add_argument("--level", type=finite_float, default=40.0, help="grey level above which a pixel shows something")
    p.add_argument("--share", type=finite_float, default=0.02,
                   help="a column (row) belongs to the area when more than this share of its pixels do")


def _run_area(args) -> int:
    from calibration.area import image_area, read_frames
    from services.ingest.sources import IMAGE_SUFFIXES

    if args.every < 1:
        raise ValueError(f"--every must be >= 1, got {args.every}")
    if not args.frames.is_dir():
        raise ValueError(f"frames folder not found: {args.frames}")
    paths = sorted(p for p in args.frames.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)[:: args.every]
    if not paths:
        raise ValueError(f"{args.frames}: no images")
    area, (w, h), n = image_area(read_frames(paths), args.level, args.share)
    print(dumps({"frames_folder": str(args.frames), "frames": n, "width": w, "height": h,
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
    from training.autolabel import AutolabelConfig, autolabel_camera, score_labels

    until = _time_of_day(args.until)
    check_name("camera", args.camera)  # it names files: no '/'
    cfg = AutolabelConfig(roi_m=args.roi_m, teacher_thr=args.teacher_thr, ignore_small=args.ignore_small)
    if args.truth:  # checked before any output is written
        from sim.recording import Recording

        if args.camera not in Recording(args.truth).cameras:
            raise ValueError(f"--truth {args.truth} has no camera {args.camera!r}")
    teacher = _teacher(args.teacher, cfg.teacher_thr)
    tracks = None
    if args.tracks:
        from training.track_labels import TrackTeacher

        tracks = TrackTeacher(args.tracks)
    report = autolabel_camera(args.frames, args.masks, args.out, args.camera, until, cfg,
                              log=lambda m: print(m, file=sys.stderr), teacher=teacher, tracks=tracks)
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
    p.add_argument("--teacher-thr", type=finite_float, default=0.5, help="teacher detections at least this confident")


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


def _add_up(sub) -> None:
    p = sub.add_parser("up", help="start the four services as OS processes (Ctrl-C stops them)")
    p.add_argument("--site", required=True, type=Path,
                   help="site folder or site.yaml (a name such as state_ellsworth means deploy/sites/NAME)")
    p.add_argument("--source", help="recording, image folders, video file or stream URL (overrides ingest.source)")
    p.add_argument("--pace", help="1 (real time), N (N x real time) or max (as fast as the pipeline goes)")
    p.add_argument("--loop", action="store_true", help="repeat the source")
    p.add_argument("--record", type=Path, help="append tracks to this JSON-lines file")
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
    if args.record:
        sets.append(f"fuse_track.record={json.dumps(str(args.record.resolve()))}")
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


def _add_viz(sub) -> None:
    p = sub.add_parser("viz", help="turn a tracks file, or the live tracks, into a Rerun .rrd (trajectories over the "
                       "site map)")
    p.add_argument("tracks", type=Path, nargs="?", help="tracks JSON-lines file (fuse_track.record); or --live")
    p.add_argument("--out", type=Path, required=True, help=".rrd file to write")
    p.add_argument("--site", type=Path, help="site folder or site.yaml (its origin places lat/lon rows; with --live "
                   "also the site's name and bus)")
    p.add_argument("--live", action="store_true", help="subscribe to the site's live tracks instead of reading a "
                   "file, until Ctrl-C, --count or --timeout (needs --site)")
    p.add_argument("--connect", action="append", default=[],
                   help="with --live: Zenoh endpoint, the cabinet's router tcp/HOST:7447 (default: the site's local "
                   "fuse_track)")
    p.add_argument("--viewer", help="with --live: also stream to a running Rerun viewer at this URL (e.g. "
                   "rerun+http://127.0.0.1:9876/proxy)")
    p.add_argument("--count", type=int, help="with --live: stop after this many messages")
    p.add_argument("--timeout", type=finite_float, help="with --live: stop after this many seconds without tracks")
    p.add_argument("--basemap", type=Path, help="world file (YAML/JSON: image + corners) of an orthophoto")
    p.add_argument("--recording", type=Path, help="simulator recording: draw its site's ground as the map")
    p.add_argument("--frames", help="also log the camera frames of this source (recording, image folders; needs "
                   "--site for the camera names) with the detections of --model")
    p.add_argument("--model", type=Path, help="ONNX detector for the logged frames' detections")
    p.add_argument("--frames-every", type=int, default=5, help="log every n-th frame of each camera")


def _viz_frames(args):
    """(camera, t_ns, grey image, detections) of every n-th frame of each camera of --frames; the flags, the site,
    the model and the source are checked at once (before any output is written), the frames read as they are
    taken."""
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
    return _viz_frame_rows(args, settings, det, open_source(str(args.frames), cams, {}))


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
    for flag in ("connect", "viewer", "count", "timeout"):
        if getattr(args, flag):
            raise ValueError(f"--{flag} goes with --live")
    origin = None
    if args.site:
        from shared.settings import load_settings

        origin = load_settings(site_path(args.site)).origin
    basemap = args.basemap
    if args.recording:
        from roadside.demo import site_basemap
        from sim.recording import Recording

        basemap = site_basemap(args.recording)
        origin = origin or Recording(args.recording).meta["site"]["origin"]
    frames = _viz_frames(args) if args.frames else None
    print(dumps(tracks_file_to_rrd(args.tracks, args.out, site_origin=origin, basemap=basemap, frames=frames),
                     indent=1))
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
    args.out.parent.mkdir(parents=True, exist_ok=True)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    rec = rr.RecordingStream("roadside")
    sinks = [rr.FileSink(str(args.out))] + ([rr.GrpcSink(args.viewer)] if args.viewer else [])
    rec.set_sinks(*sinks)
    rec.send_recording_name(f"{settings.site} live")
    with TrackClient(settings.site, args.connect or None, settings.bus) as client:
        def messages():
            for n, tracks in enumerate(client.stream(timeout_s=args.timeout, stop=stop), 1):
                yield tracks
                if args.count and n >= args.count:
                    return

        try:
            summary = live(messages(), rec, site_origin=settings.origin, basemap=args.basemap)
        finally:
            rec.flush()
            rec.disconnect()
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
    _add_train(sub)
    _add_autolabel(sub)
    _add_static(sub)
    _add_area(sub)
    _add_composite(sub)
    _add_export(sub)
    _add_calibrate_heads(sub)
    _add_mix(sub)
    _add_eval(sub)
    _add_up(sub)
    bus_runners = add_bus_jobs(sub)  # tracks, status, health: what a running pipeline says
    _add_viz(sub)
    args = parser.parse_args(argv)
    runners = {"sim": _run_sim, "demo": _run_demo, "calibrate": _run_calibrate, "bench": _run_bench,
               "train": _run_train, "autolabel": _run_autolabel, "static": _run_static, "area": _run_area,
               "composite": _run_composite, "export": _run_export, "calibrate-heads": _run_calibrate_heads,
               "mix": _run_mix, "eval": _run_eval, "up": _run_up,
               "viz": _run_viz, **bus_runners}
    try:
        return runners[args.job](args)
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"roadside {args.job}: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # a file it cannot read or write: a folder where a file belongs, no permission, a full disk
        print(f"roadside {args.job}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"roadside {args.job}: interrupted", file=sys.stderr)
        return 130
