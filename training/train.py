"""Train the detector on simulator recordings and/or COCO-style annotation files.

Every image is shrunk so its longer side is at most `DetectorConfig.input_long_side` (the size the
detect service feeds the network), then augmented random crops are trained with the paper's loss. The
learning rate follows a one-cycle cosine schedule over the run; with `minutes` the schedule follows
the clock (fraction of the budget spent) or the steps (fraction of `steps` taken), whichever is further along,
so a run on a busy machine still ends on time with the schedule complete, and so does one that `steps` ends
first. Writes `model.pt` (config + weights), `train_log.jsonl` (loss parts every `log_every`
steps) and `train.json` (the settings, data and timing).

`device` "cuda" trains on a GPU (the PyTorch installed must have CUDA; the `train` extra's pinned wheel is
CPU-only); `workers` > 0 prepares the augmented batches in that many background processes, which a GPU needs
to be kept busy. With workers the order in which their batches arrive is not reproducible; with
`workers=0` (the default) a seed reproduces the run on the CPU.

Every `save_every` steps the run also writes `resume.pt` (weights, optimizer state, step, training time spent):
the same settings again with `resume` continue an interrupted run where that file left it, on the same schedule
(`train_log.jsonl` keeps its records up to that step). The batches drawn after a resume are not those the
interrupted run would have drawn. A run started without `resume` refuses a folder that holds an earlier run's
`model.pt` or `resume.pt` unless `overwrite` is set; with it, it removes the earlier `resume.pt` first, so that a
resume never goes back to a run that is not the last one.
"""

from __future__ import annotations

import json
import math
import multiprocessing
import queue
import signal
import time
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import numpy as np
import torch

from shared.cameras import select_cameras
from shared.inference import input_scale
from sim.recording import Recording
from training.augment import AugmentConfig, augment
from training.data import (
    Batcher,
    SampleRef,
    default_cache_bytes,
    samples_from_coco,
    samples_from_recording,
    too_few_samples,
)
from training.loss import LossConfig, detector_loss
from training.model import Detector, DetectorConfig, count_macs, load_detector, save_detector
from training.sample import Sample
from training.targets import build_targets

WARMUP_STEPS = 20  # steps timed before the step count is fixed (when a time budget is given)


@dataclass(frozen=True)
class TrainConfig:
    recordings: tuple[str, ...] = ()
    coco: tuple[str, ...] = ()  # COCO-style annotation files (images next to them or in `images_dir`)
    out: str = "out/train"
    steps: int = 4000
    minutes: float | None = None  # time budget: fewer steps if the budget would be exceeded
    batch_size: int = 16
    crop: int = 256
    lr: float = 2e-3
    weight_decay: float = 1e-4
    every: int = 1  # use every n-th frame of each recording's camera and every n-th image of each COCO file
    center: str = "bottom"  # "box": the 2D-box centre instead of the bottom centre (the paper's ablation)
    seed: int = 0
    init: str | None = None  # model.pt to start from (fine-tuning); its network config replaces `model`
    add_axis_head: bool = False  # with `init`: give the starting model an axis head (new, the rest kept)
    add_vote_head: bool = False  # with `init`: give the starting model a vote head (new, the rest kept)
    input_long_side: int | None = None  # network input size (longer side); with `init`, replaces its (weights kept)
    threads: int = 2
    device: str = "cpu"  # "cpu", "cuda" or "cuda:N"
    workers: int = 0  # background processes preparing batches (0: in this process, reproducible)
    log_every: int = 25
    save_every: int = 500  # steps between the saves of model.pt and resume.pt
    resume: bool = False  # continue the run in `out` from its resume.pt (the same settings; see the module doc)
    overwrite: bool = False  # without `resume`: replace an earlier run's model.pt and resume.pt in `out`
    # heads to train, the rest frozen (weights and batch-norm statistics): e.g. ("offset",) sharpens the
    # localization of a trained model without touching what it detects; () trains everything
    train_only: tuple[str, ...] = ()
    model: DetectorConfig = field(default_factory=DetectorConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    augment: AugmentConfig = field(default_factory=AugmentConfig)

    def __post_init__(self) -> None:
        if not self.recordings and not self.coco:
            raise ValueError("no training data: give at least one recording or COCO annotation file")
        for name in ("steps", "batch_size", "crop", "threads", "log_every", "every", "save_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.workers < 0:
            raise ValueError(f"workers must be >= 0, got {self.workers}")
        if self.device != "cpu" and not self.device.startswith("cuda"):
            raise ValueError(f"device must be cpu, cuda or cuda:N, got {self.device!r}")
        if self.crop % 32:
            raise ValueError(f"crop must be a multiple of 32, got {self.crop}")
        if self.input_long_side is not None and self.input_long_side < 32:
            raise ValueError(f"input_long_side must be >= 32, got {self.input_long_side}")
        if self.minutes is not None and not self.minutes > 0:
            raise ValueError(f"minutes must be > 0, got {self.minutes}")
        if self.train_only and self.init is None:
            raise ValueError("train_only needs a trained model to start from (init): the frozen parts would stay "
                             "random")


def recording_spec(spec: str) -> tuple[str, str | None]:
    """'PATH' or 'PATH@SELECTION' -> (PATH, SELECTION or None). SELECTION: a camera kind (fisheye,
    pinhole), a modality (thermal, visible) or a comma list of camera names. A folder whose own name has
    an '@' is taken whole."""
    path, at, which = spec.rpartition("@")
    if not at or Path(spec).is_dir():
        return spec, None
    if not which.strip():
        raise ValueError(f"recording {spec!r}: nothing after '@' (a camera kind, modality or comma list of names)")
    return path, which.strip()


def training_refs(cfg: TrainConfig) -> list[SampleRef]:
    """SampleRefs of all the training data, each at the network's input scale."""
    refs: list[SampleRef] = []
    for spec in cfg.recordings:
        path, which = recording_spec(spec)
        rec = Recording(path)
        for cam in select_cameras(list(rec.cameras.values()), which or "all", str(rec.path)):
            scale = input_scale(cam.width, cam.height, cfg.model.input_long_side)
            refs += samples_from_recording(path, [cam.name], every=cfg.every, scale=scale)
    for path in cfg.coco:
        for ref in samples_from_coco(path)[:: cfg.every]:
            h, w = ref.image_hw if ref.image_hw is not None else ref.load().shape
            refs.append(replace(ref, scale=input_scale(w, h, cfg.model.input_long_side)))
    if not refs:
        raise ValueError("the training data has no images")
    return refs


def batch_arrays(samples: list[Sample], stride: int, center: str) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Images (B, 1, H, W) uint8 and the stacked targets of a batch, as NumPy arrays (cheap to pass between
    processes)."""
    images = np.stack([s.image for s in samples])[:, None]
    targets = [build_targets(s, stride, center) for s in samples]
    return images, {k: np.stack([t[k] for t in targets]) for k in targets[0]}


def to_tensors(images: np.ndarray, targets: dict[str, np.ndarray],
               device: torch.device | str = "cpu") -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """batch_arrays' output as tensors on `device`, the images scaled to [0, 1]."""
    x = torch.from_numpy(images).to(device, non_blocking=True).float() / 255.0
    return x, {k: torch.from_numpy(v).to(device, non_blocking=True) for k, v in targets.items()}


def _prepare_batches(refs: list[SampleRef], aug, batch_size: int, seed: int, stride: int, center: str,
                     out: multiprocessing.Queue, cache_bytes: int) -> None:
    """A worker process: endless shuffled epochs of augmented batches (batch_arrays) into `out`."""
    # a forked worker inherits its parent's signal handlers; one that catches SIGTERM (a service, a test runner)
    # would let terminate() leave it running and the parent hang at exit joining it
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C stops the parent, which stops the workers
    torch.set_num_threads(1)
    batcher = Batcher(refs, aug, batch_size, np.random.default_rng(seed), cache_bytes=cache_bytes)
    while True:
        for samples in batcher:
            out.put(batch_arrays(samples, stride, center))


class BackgroundBatches:
    """Batches prepared by `workers` processes (each its own shuffle and augmentation, seeded seed·1000 + i),
    in the order they come. Iterate for batch_arrays' tuples; close() stops the workers. When no batch has come
    for 5 s and a worker has died (bad image, out of memory), the training stops with its exit code instead of
    hanging; the others' batches keep it going until then."""

    def __init__(self, refs: list[SampleRef], aug, batch_size: int, seed: int, stride: int, center: str,
                 workers: int, cache_bytes: int) -> None:
        ctx = multiprocessing.get_context("fork" if "fork" in multiprocessing.get_all_start_methods() else "spawn")
        self.queue = ctx.Queue(maxsize=4 * workers)
        self.procs = [ctx.Process(target=_prepare_batches, daemon=True,
                                  args=(refs, aug, batch_size, seed * 1000 + i, stride, center, self.queue,
                                        cache_bytes))
                      for i in range(workers)]
        for proc in self.procs:
            proc.start()

    def __iter__(self):
        while True:
            try:
                yield self.queue.get(timeout=5.0)
            except queue.Empty:
                dead = [p for p in self.procs if not p.is_alive()]
                if dead:
                    raise RuntimeError(f"a batch-preparing worker died (exit code {dead[0].exitcode}); "
                                       "run with workers=0 to see its error") from None

    def close(self) -> None:
        for proc in self.procs:
            proc.terminate()
        for proc in self.procs:
            proc.join(timeout=5)
            if proc.is_alive():  # SIGTERM caught or stuck: a daemon left alive would hang this process's exit
                proc.kill()
                proc.join(timeout=5)
        self.queue.close()
        self.queue.cancel_join_thread()  # nothing this process put needs flushing


def _lr(step: int, total: int, peak: float) -> float:
    warm = max(1, min(200, total // 20))
    if step < warm:
        return peak * (step + 1) / warm
    return peak * 0.5 * (1 + math.cos(math.pi * (step - warm) / max(1, total - warm)))


def _lr_at(frac: float, peak: float) -> float:
    """The same one-cycle schedule over a fraction of a time budget (robust to a busy machine)."""
    warm = 0.03
    if frac < warm:
        return peak * max(frac, 1e-3) / warm
    return peak * 0.5 * (1 + math.cos(math.pi * min(1.0, (frac - warm) / (1 - warm))))


def trainable(model: Detector, heads: tuple[str, ...], log=print) -> list[torch.nn.Parameter]:
    """Put the model in training mode and return the parameters to optimise: all of them, or with `heads` only
    those heads' (the rest keep their weights and, in eval mode, their batch-norm statistics, so what they
    output is unchanged). ValueError naming an unknown head."""
    if not heads:
        model.train()
        return list(model.parameters())
    heads = tuple(dict.fromkeys(heads))  # a head named twice is trained once
    unknown = sorted(set(heads) - set(model.heads))
    if unknown:
        raise ValueError(f"train_only: no head {unknown} in this model (heads: {', '.join(model.heads)})")
    model.eval()
    for p in model.parameters():
        p.requires_grad_(False)
    params = []
    for name in heads:
        model.heads[name].train()
        for p in model.heads[name].parameters():
            p.requires_grad_(True)
            params.append(p)
    log(f"[train] training only the {', '.join(heads)} head(s): {sum(p.numel() for p in params)} parameters, "
        "the rest frozen")
    return params


RESUME_FILE = "resume.pt"
# settings that must be those of the interrupted run for its resume to continue the same training
# (as given to `train`: `model` before a starting model's or an input size's replace it)
RESUME_SAME = ("recordings", "coco", "init", "model", "input_long_side", "add_axis_head", "add_vote_head", "steps",
               "minutes", "batch_size", "crop", "lr", "weight_decay", "every", "center", "train_only", "loss",
               "augment", "seed")


def _resume_settings(cfg: TrainConfig) -> dict:
    return json.loads(json.dumps({k: getattr(cfg, k) for k in RESUME_SAME}, default=lambda o: asdict(o)))


def save_resume(path: Path, model: Detector, opt: torch.optim.Optimizer, step: int, elapsed_s: float,
                settings: dict) -> None:
    """Write what `resume` needs, atomically (a run killed while writing keeps the previous file). settings: the
    run's `_resume_settings`, as given."""
    tmp = path.with_name(path.name + ".partial")
    torch.save({"model_config": asdict(model.config),
                "model": {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()},
                "optimizer": opt.state_dict(), "step": step, "elapsed_s": elapsed_s,
                "settings": settings}, tmp)
    tmp.replace(path)


def load_resume(path: Path, settings: dict) -> tuple[dict, Detector]:
    """The state saved by save_resume and its model with the saved weights; FileNotFoundError or ValueError naming
    the problem (no file, not a resume file, settings (`_resume_settings` of the run as given) that differ from the
    interrupted run's)."""
    if not path.is_file():
        raise FileNotFoundError(f"resume: no {path} (a run writes it every save_every steps): start the run again "
                                f"with --overwrite instead of --resume")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
        keys = {"model_config", "model", "optimizer", "step", "elapsed_s", "settings"}
        if not isinstance(state, dict) or not keys <= set(state):
            raise KeyError(sorted(keys - set(state)) if isinstance(state, dict) else "not a dict")
        if not isinstance(state["settings"], dict):
            raise TypeError("its settings are not a mapping")
        if not (isinstance(state["step"], int) and state["step"] >= 0 and math.isfinite(float(state["elapsed_s"]))):
            raise TypeError(f"step {state['step']!r} and elapsed_s {state['elapsed_s']!r} must be numbers")
        model = Detector(DetectorConfig(**state["model_config"]))
        model.load_state_dict(state["model"])
    except Exception as exc:  # torch raises unpickling and zip errors of its own kinds
        raise ValueError(f"{path}: not a resume file ({type(exc).__name__}: {exc})") from None
    differ = [k for k in RESUME_SAME if state["settings"].get(k) != settings[k]]
    if differ:
        raise ValueError(f"resume: {', '.join(differ)} differ from the interrupted run's ("
                         + "; ".join(f"{k} was {state['settings'].get(k)!r}" for k in differ) + ")")
    return state, model


def _trimmed_log(path: Path, step: int) -> None:
    """Keep the records of a training log up to `step` (a torn last line left by a kill is dropped), rewritten
    atomically."""
    kept = []
    for line in path.read_text().splitlines() if path.is_file() else []:
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(rec, dict) and rec.get("step", 0) <= step:
            kept.append(line)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text("".join(line + "\n" for line in kept))
    tmp.replace(path)


def train(cfg: TrainConfig, log=print) -> dict:
    """Run one training; returns the summary also written to `out/train.json`."""
    device = torch.device(cfg.device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device {cfg.device}: this PyTorch has no CUDA (torch {torch.__version__})")
    out = Path(cfg.out)
    earlier = [name for name in ("model.pt", RESUME_FILE) if (out / name).is_file()]
    if earlier and not cfg.resume and not cfg.overwrite:
        raise ValueError(f"{out} holds an earlier run's {' and '.join(earlier)}: give --resume to continue that run "
                         "or --overwrite to replace it")
    out.mkdir(parents=True, exist_ok=True)
    given = _resume_settings(cfg)  # before a starting model or an input size changes cfg.model
    torch.manual_seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    rng = np.random.default_rng(cfg.seed)
    if cfg.init is not None and not cfg.resume:  # a resumed run's weights come from its resume.pt
        if not Path(cfg.init).is_file():
            raise FileNotFoundError(f"init model not found: {cfg.init}")
        model = load_detector(cfg.init)
        new_heads = [name for name, add in (("axis", cfg.add_axis_head), ("vote", cfg.add_vote_head))
                     if add and not getattr(model.config, f"{name}_head")]
        if new_heads:
            start = model
            model = Detector(replace(start.config, **{f"{name}_head": True for name in new_heads}))
            missing, unexpected = model.load_state_dict(start.state_dict(), strict=False)
            if unexpected or any(not k.startswith(tuple(f"heads.{name}." for name in new_heads)) for k in missing):
                raise ValueError(f"{cfg.init}: weights do not fit the network with the new {' and '.join(new_heads)} "
                                 f"head (missing {missing}, unexpected {unexpected})")
            untrained = [name for name in new_heads if cfg.train_only and name not in cfg.train_only]
            if untrained:  # it would stay random, and be saved and exported so
                raise ValueError(f"train_only ({', '.join(cfg.train_only)}) leaves the new {' and '.join(untrained)} "
                                 f"head random and frozen: name it in train_only too")
            for name in new_heads:
                log(f"[train] added {'an' if name[0] in 'aeiou' else 'a'} {name} head to the starting model")
        if cfg.input_long_side is not None and cfg.input_long_side != model.config.input_long_side:
            log(f"[train] input size {model.config.input_long_side} -> {cfg.input_long_side} px (longer side)")
            model.config = replace(model.config, input_long_side=cfg.input_long_side)
        cfg = replace(cfg, model=model.config)  # input size and stride follow the starting model
        log(f"[train] starting from {cfg.init}")
    else:
        if cfg.input_long_side is not None:
            cfg = replace(cfg, model=replace(cfg.model, input_long_side=cfg.input_long_side))
        model = Detector(cfg.model)
    resumed = None
    if cfg.resume:
        resumed, model = load_resume(out / RESUME_FILE, given)
        cfg = replace(cfg, model=model.config)
        # fresh random streams: the interrupted run's would repeat its first batches
        torch.manual_seed(cfg.seed + resumed["step"])
        rng = np.random.default_rng((cfg.seed, resumed["step"]))
        log(f"[train] resuming {out} at step {resumed['step']} ({resumed['elapsed_s'] / 60:.1f} min spent)")
    refs = training_refs(cfg)
    n_pos = sum(r.n_positive for r in refs)
    log(f"[train] {len(refs)} images, {n_pos} vehicles to detect")
    if cfg.batch_size > len(refs):  # here, not in a batch-preparing worker, where it would end as "a worker died"
        raise ValueError(too_few_samples(len(refs), cfg.batch_size))
    aug = partial(augment, out_hw=(cfg.crop, cfg.crop), config=cfg.augment)
    if cfg.workers:  # started before CUDA is touched: forked workers must not inherit a CUDA context
        # a resumed run's workers get other seeds: the interrupted run's would repeat its first batches
        seed = cfg.seed if resumed is None else cfg.seed + 100_003 * resumed["step"]
        background = BackgroundBatches(refs, aug, cfg.batch_size, seed, cfg.model.stride, cfg.center,
                                       cfg.workers, default_cache_bytes() // cfg.workers)
        batches = iter(background)
    else:
        background = None
        batcher = Batcher(refs, aug, cfg.batch_size, rng)
        batches = (batch_arrays(samples, cfg.model.stride, cfg.center)
                   for _ in iter(int, 1) for samples in batcher)  # endless epochs
    # channels-last activations: oneDNN's convolutions skip a layout reorder per layer (measured on this 2-core
    # CPU: 0.60 -> 0.35 s per step of 12 crops of 256x256)
    model.to(device, memory_format=torch.channels_last)
    params = trainable(model, cfg.train_only, log)
    opt = torch.optim.AdamW(params, lr=cfg.lr, weight_decay=cfg.weight_decay)
    total = cfg.steps
    budget_s = None if cfg.minutes is None else cfg.minutes * 60
    step, t_start = 0, time.perf_counter()
    log_file = None  # opened after the first step: a run that fails on its data keeps the last log
    if resumed is not None:
        opt.load_state_dict(resumed["optimizer"])
        step = resumed["step"]
        t_start -= resumed["elapsed_s"]  # the schedule and the budget go on from the time already spent
        _trimmed_log(out / "train_log.jsonl", step)
        log_file = open(out / "train_log.jsonl", "a")  # closed in finally
    first_step = step
    if not cfg.resume and (out / RESUME_FILE).is_file():
        # an earlier run's: a resume of this one must not go back to it. Removed only once this run has its model
        # and data: a fresh start that fails on a typo must not lose an interrupted run's state
        (out / RESUME_FILE).unlink()
        log(f"[train] removed the earlier run's {out / RESUME_FILE}")

    def lr_now() -> float:
        if budget_s is None:
            return _lr(step, total, cfg.lr)
        # whichever of the clock and the steps ends the run: its last steps get the schedule's low end
        return _lr_at(max(step / total, (time.perf_counter() - t_start) / budget_s), cfg.lr)

    def done() -> bool:
        return step >= total or (budget_s is not None and time.perf_counter() - t_start >= budget_s)

    try:
        for arrays in batches:
            if done():
                break
            images, targets = to_tensors(*arrays, device)
            images = images.contiguous(memory_format=torch.channels_last)
            lr = lr_now()
            for g in opt.param_groups:
                g["lr"] = lr
            loss, parts = detector_loss(model(images), targets, cfg.loss, cfg.model.stride)
            if not torch.isfinite(loss):
                raise RuntimeError(f"loss became {loss.item()} at step {step}: lower the learning rate")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(params, 5.0)
            opt.step()
            step += 1
            if step - first_step == WARMUP_STEPS:
                if budget_s is not None and resumed is None:
                    per_step = (time.perf_counter() - t_start) / WARMUP_STEPS
                    in_budget = int(budget_s / per_step)
                    ends = "the clock ends the run" if in_budget < total else f"the {total} steps end the run first"
                    log(f"[train] {per_step:.2f} s per step: about {min(in_budget, total)} steps "
                        f"in {cfg.minutes:g} min ({ends})")
            if step % cfg.log_every == 0 or done():
                rec = {"step": step, "lr": lr, "s": time.perf_counter() - t_start,
                       **{k: round(v, 6) for k, v in parts.items()}}
                if log_file is None:
                    log_file = open(out / "train_log.jsonl", "w")  # closed in finally
                log_file.write(json.dumps(rec) + "\n")
                log_file.flush()
                log(f"[train] step {step} loss {parts['total']:.4f} heat {parts['heat']:.4f}")
            if step % cfg.save_every == 0:
                save_detector(model, out / "model.pt", asdict(cfg.loss))
                save_resume(out / RESUME_FILE, model, opt, step, time.perf_counter() - t_start, given)
    finally:
        if background is not None:
            background.close()
        if log_file is not None:
            log_file.close()
    model.eval()
    save_detector(model, out / "model.pt", asdict(cfg.loss))
    save_resume(out / RESUME_FILE, model, opt, step, time.perf_counter() - t_start, given)
    summary = {
        "steps": step,
        "seconds": round(time.perf_counter() - t_start, 1),
        "images": len(refs),
        "vehicles": n_pos,
        "macs_per_512x512": count_macs(model.cpu(), 512, 512),
        "device": cfg.device,
        "workers": cfg.workers,
        "config": json.loads(json.dumps(asdict(cfg), default=str)),
    }
    (out / "train.json").write_text(json.dumps(summary, indent=1))
    return summary
