"""`roadside train | export | mix | calibrate-heads | coco`: the detector's training, export and heads' calibration,
and a recording's labels as COCO-style annotations."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

from roadside.argtypes import finite_float, positive_float, positive_int, type_weights
from shared.jsonio import dumps


def add_model_jobs(sub) -> dict:
    _add_train(sub)
    _add_export(sub)
    _add_calibrate_heads(sub)
    _add_mix(sub)
    _add_coco(sub)
    return {"train": _run_train, "export": _run_export, "calibrate-heads": _run_calibrate_heads, "mix": _run_mix,
            "coco": _run_coco}


def _add_coco(sub) -> None:
    p = sub.add_parser("coco", help="a simulator recording's labels as a COCO-style annotation file and its images "
                       "(docs/annotations.md): what `roadside train --coco` reads")
    p.add_argument("recording", type=Path, help="simulator recording (roadside sim)")
    p.add_argument("--cameras", help="comma list of its cameras (default: all)")
    p.add_argument("--out", type=Path, required=True,
                   help="the JSON file to write; its images go beside it, where --coco looks for them")
    p.add_argument("--every", type=positive_int, default=10, help="every N-th frame of each camera (default 10)")
    p.add_argument("--jpeg", action="store_true", help="write the images as JPEG (default PNG, lossless)")


def _run_coco(args) -> int:
    from training.data import samples_from_recording, write_coco

    cameras = [c.strip() for c in args.cameras.split(",") if c.strip()] if args.cameras else None
    samples = samples_from_recording(args.recording, cameras, every=args.every)
    if not samples:
        raise ValueError(f"{args.recording}: no frames")
    out = write_coco(samples, args.out, args.out.parent, ".jpg" if args.jpeg else ".png")
    doc = json.loads(out.read_text())
    print(f"{out}: {len(doc['images'])} images, {len(doc['annotations'])} vehicles "
          f"({sum(a.get('iscrowd', 0) for a in doc['annotations'])} to ignore), the images beside it")
    return 0


def _loss_type_weights_arg(text: str) -> dict[str, float]:
    """--loss-type-weights: `type_weights`, or 'none' (an empty dict: no type weights, also not a checkpoint's)."""
    return {} if text.strip().lower() == "none" else type_weights(text)


def _add_train(sub) -> None:
    p = sub.add_parser("train", help="train the detector on recordings and/or COCO-style annotations (needs torch)")
    p.add_argument("--recording", action="append", default=[],
                   help="simulator recording folder (repeatable); PATH@fisheye, @thermal, @pinhole, @visible or "
                        "@NE,NW: only those cameras")
    p.add_argument("--coco", action="append", default=[], help="COCO-style annotation JSON (repeatable)")
    p.add_argument("--out", required=True, help="output folder (model.pt, train_log.jsonl, train.json)")
    p.add_argument("--steps", type=positive_int, help="number of steps (default 4000, or as many as --minutes allows)")
    p.add_argument("--minutes", type=positive_float,
                   help="time budget: the learning-rate schedule follows the clock to its end (with --steps too, it "
                        "follows the clock or the steps, whichever is further along, and that one ends the run)")
    p.add_argument("--batch-size", type=int, default=16,
                   help="samples per step (default 16); at most the number of training images and frames")
    p.add_argument("--crop", type=int, default=256,
                   help="side of the square training crops in pixels, a multiple of 32 (default 256)")
    p.add_argument("--lr", type=positive_float, default=2e-3, help="peak learning rate (default 0.002)")
    p.add_argument("--every", type=int, default=1,
                   help="use every n-th frame of each recording's camera and every n-th image of each COCO file "
                        "(default 1: all)")
    p.add_argument("--center", choices=["bottom", "box"], default="bottom",
                   help="the point trained for: bottom (the vehicle's bottom centre, default) or box (the 2D-box-"
                        "centre ablation)")
    p.add_argument("--no-topk", action="store_true", help="ablation: plain mean squared heat-map loss")
    p.add_argument("--heat-loss", choices=["mse", "focal"],
                   help="heat-map loss: mse (the paper's squared error with TopK, the default) or focal (CenterNet's "
                        "penalty-reduced focal loss; training/loss.py); with --init, the checkpoint's")
    p.add_argument("--stride", type=int, default=4, choices=[1, 2, 4],
                   help="output stride of the network (default 4)")
    p.add_argument("--seed", type=int, default=0,
                   help="seeds the shuffle, augmentation and initial weights (default 0)")
    p.add_argument("--init", help="model.pt to start from (fine-tuning); its network settings are kept")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted run in --out from its resume.pt (saved every 500 steps): the same "
                        "command again with --resume; the schedule and a --minutes budget go on from where it was")
    p.add_argument("--overwrite", action="store_true",
                   help="replace the model.pt and resume.pt an earlier run left in --out (without it, or --resume, "
                        "such a folder is refused)")
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
                        "approximated, the default), by multiples of 90 degrees (boxes exact) or not at all")
    p.add_argument("--input-long-side", type=int,
                   help="network input: images shrunk so their longer side is at most this (default 640, or the "
                        "--init model's); with --init, the starting weights are kept")
    p.add_argument("--focus-by-size", action="store_true",
                   help="augmentation: centre the crops on large vehicles more often (chance proportional to "
                        "their 2D box size)")
    p.add_argument("--device", default="cpu",
                   help="cpu (default), cuda or cuda:N (needs a PyTorch with CUDA; the train extra's is CPU-only)")
    p.add_argument("--workers", type=int, default=0,
                   help="processes preparing batches in the background (a GPU needs several; 0, the default: in "
                        "this process, reproducible from --seed)")
    p.add_argument("--train-only", default="",
                   help="with --init: train only these heads (comma-separated: heat, size, heading, vtype, offset, "
                        "axis), the rest frozen; e.g. offset sharpens localization and leaves detection as it is "
                        "(default: all)")


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
                      overwrite=args.overwrite,
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
    p.add_argument("--calibration-every", type=positive_int, default=4,
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
    try:
        from training.mix import mix_detectors
        from training.model import checkpoint_loss, load_detector, save_detector
    except ImportError as exc:
        raise RuntimeError(f"mix needs the train extra (pip install -e '.[train]'): {exc}") from exc

    mixed = mix_detectors(load_detector(args.base), load_detector(args.tuned), args.weight)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_detector(mixed, args.out, loss=checkpoint_loss(args.base))
    print(f"{args.out}: {1 - args.weight:g} x {args.base} + {args.weight:g} x {args.tuned}")
    return 0


def _run_export(args) -> int:
    try:
        from onnxconverter_common import float16  # noqa: F401  (the fp16 copy needs it: checked before any work)

        from training.export import export_onnx
        from training.model import load_detector
    except ImportError as exc:
        raise RuntimeError(f"export needs the train extra (pip install -e '.[train]'): {exc}") from exc

    if not args.model.is_file():
        raise ValueError(f"model not found: {args.model}")
    if args.calibration_recording:  # a typo found now, not after the export
        from training.heads_calibration import check_recordings

        check_recordings(args.calibration_recording, args.calibration_every)
    model = load_detector(args.model)
    fp16 = args.out.with_name(args.out.stem + "_fp16" + args.out.suffix)
    # written under other names and renamed into place only when everything succeeded: an export or calibration
    # that fails leaves the files already at --out as they were
    paths = [args.out, fp16]
    partial = [p.with_name(f".{p.stem}.partial{p.suffix}") for p in paths]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    try:
        export_onnx(model, partial[0], partial[1])
        if args.calibration_recording:
            _heads_calibration(partial, args.calibration_recording, args.calibration_every, shown=paths)
        for tmp, path in zip(partial, paths, strict=True):
            os.replace(tmp, path)
    finally:
        for tmp in partial:
            tmp.unlink(missing_ok=True)
    print(f"fp32: {args.out}\nfp16: {fp16}")
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


def _heads_calibration(paths: list[Path], recordings: list[Path], every: int, shown: list[Path] | None = None) -> None:
    """Fit and write the calibrations into `paths`; the report names `shown` (the files they become) if given."""
    from training.heads_calibration import BOX_IOU, calibrate_files

    r = calibrate_files(paths, recordings, every, log=print)
    print(f"box and size calibrations written into {', '.join(map(str, shown or paths))}:\n"
          f"  boxes: {r['boxes'].pairs} detections at IoU {BOX_IOU:g} or more with a vehicle, at IoU 0.5 or more "
          f"{r['box_pairs_at_iou50_before']:.3f} -> {r['box_pairs_at_iou50_after']:.3f} of them\n"
          f"  sizes: matched detections per type {list(r['sizes'].pairs)}, their mean size error "
          f"{r['size_error_before']:.3f} -> {r['size_error_after']:.3f} m")
