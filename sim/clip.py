"""Simulate a clip: traffic, rendering through every camera, ground truth and landmarks, written
as a recording. Output is written to a hidden sibling folder and renamed into place at the very
end, so a failed or interrupted run never leaves a folder that looks complete. Only a recording is
ever replaced (with `overwrite`): never another folder, a file, a link or the working directory.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import shutil
import signal
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

import cv2
import numpy as np

from shared.cameras import Camera
from shared.cameras import select_cameras as select_from
from sim.groundtruth import frame_ground_truth
from sim.landmarks import LandmarkNoise, pick_landmarks
from sim.recording import FORMAT, META_FILE, VERSION
from sim.render import (
    CameraRenderer,
    Environment,
    ShadowCaster,
    World,
    build_world,
    sample_environment,
)
from sim.site import SiteSpec, load_site
from sim.traffic import VEHICLE_TYPES, TrafficHistory, check_type_weights, simulate_traffic

MAX_HZ = 60.0
CAPTURE_JITTER_S = 0.002


@dataclass(frozen=True)
class ClipConfig:
    site: str
    out: Path
    seconds: float
    hz: float = 10.0
    seed: int = 0
    cameras: str = "all"
    weather: str = "auto"
    workers: int = 2
    max_vehicles: int = 100
    demand_scale: float = 1.0
    type_weights: dict[str, float] | None = None  # vehicle type -> factor on its share of the mix
    jpeg_quality: int = 90
    overwrite: bool = False

    def validate(self) -> None:
        if not (math.isfinite(self.seconds) and self.seconds > 0):
            raise ValueError(f"--seconds must be a positive number, got {self.seconds}")
        if self.seconds > 3600:
            raise ValueError(f"--seconds must be at most 3600, got {self.seconds}")
        if not (math.isfinite(self.hz) and 0 < self.hz <= MAX_HZ):
            raise ValueError(f"--hz must be in (0, {MAX_HZ}], got {self.hz}")
        if self.seconds * self.hz < 1:
            raise ValueError(f"--seconds {self.seconds:g} at --hz {self.hz:g} is not one frame per camera")
        if self.seed < 0:
            raise ValueError(f"--seed must be >= 0, got {self.seed}")
        if self.workers < 1:
            raise ValueError(f"--workers must be >= 1, got {self.workers}")
        if not 1 <= self.max_vehicles <= 500:
            raise ValueError(f"--max-vehicles must be in [1, 500], got {self.max_vehicles}")
        check_type_weights(self.type_weights)
        if not 10 <= self.jpeg_quality <= 100:
            raise ValueError(f"--jpeg-quality must be in [10, 100], got {self.jpeg_quality}")
        if not (math.isfinite(self.demand_scale) and self.demand_scale >= 0):
            raise ValueError(f"--demand-scale must be a finite number >= 0, got {self.demand_scale}")


def select_cameras(site: SiteSpec, which: str) -> list[Camera]:
    """'all', 'fisheye', 'thermal', 'pinhole', 'visible', or a comma list of camera names."""
    return select_from(site.build_cameras(), which, f"site {site.name}")


def capture_schedule(cameras: list[Camera], seconds: float, hz: float, seed: int) -> dict[str, np.ndarray]:
    """Capture times (s from clip start) per camera: unsynchronised phases plus a small jitter."""
    out = {}
    n = int(math.floor(seconds * hz + 1e-9))
    for k, cam in enumerate(cameras):
        rng = np.random.default_rng([seed, 17, k])
        phase = rng.uniform(0, 1.0 / hz)
        t = phase + np.arange(n) / hz + np.clip(rng.normal(0, CAPTURE_JITTER_S, n), -0.004, 0.004)
        out[cam.name] = np.maximum(t, 0.0)
    return out


def _t0_ns(site: SiteSpec) -> int:
    dt = datetime.fromisoformat(site.utc_start.replace("Z", "+00:00"))
    return int(round(dt.timestamp())) * 1_000_000_000


def _render_camera(
    cam_index: int,
    cam: Camera,
    world: World,
    env: Environment,
    shadows: ShadowCaster,
    history: TrafficHistory,
    times: np.ndarray,
    t0_ns: int,
    tmp: Path,
    cfg: ClipConfig,
) -> dict:
    site = world.site
    renderer = CameraRenderer(cam, world, env, shadows, seed=cfg.seed * 1000 + cam_index)
    geo, terrain = site.geo, site.ground
    noise = LandmarkNoise()
    lm = pick_landmarks(
        cam,
        world.net.paint.features,
        terrain,
        geo,
        renderer.depth,
        np.random.default_rng([cfg.seed, 23, cam_index]),
        30,
        noise,
    )
    (tmp / "landmarks" / f"{cam.name}.json").write_text(
        json.dumps(
            {
                "camera": cam.name,
                "kind": cam.kind,
                "width": cam.width,
                "height": cam.height,
                "noise_model": noise.to_dict(),
                "landmarks": lm,
            },
            indent=1,
        )
    )
    frame_dir = tmp / "frames" / cam.name
    frame_dir.mkdir(parents=True)
    t_render = 0.0
    with (tmp / "gt" / f"{cam.name}.jsonl").open("w") as gt_file:
        for k, t in enumerate(times):
            t_ns = t0_ns + int(round(t * 1e9))
            scene = history.state_at(float(t))
            t_start = time.perf_counter()
            res = renderer.render(scene, np.random.default_rng([cfg.seed, 29, cam_index, k]))
            t_render += time.perf_counter() - t_start
            name = f"{t_ns}.jpg"
            ok, buf = cv2.imencode(".jpg", res.image, [cv2.IMWRITE_JPEG_QUALITY, cfg.jpeg_quality])
            if not ok:
                raise RuntimeError(f"JPEG encoding failed for {cam.name} frame {k}")
            (frame_dir / name).write_bytes(buf.tobytes())
            vehicles = frame_ground_truth(cam, scene, res, terrain, geo)
            gt_file.write(
                json.dumps(
                    {"t_ns": t_ns, "file": f"frames/{cam.name}/{name}", "vehicles": vehicles}, separators=(",", ":")
                )
                + "\n"
            )
    return {"camera": cam.name, "frames": len(times), "render_s": t_render}


def _worker(jobs, world, env, shadows, history, schedule, t0_ns, tmp, cfg, conn) -> None:
    try:
        stats = [
            _render_camera(i, cam, world, env, shadows, history, schedule[cam.name], t0_ns, tmp, cfg) for i, cam in jobs
        ]
        conn.send(("ok", stats))
    except BaseException as exc:  # report any failure to the parent, which cleans up
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        conn.close()


def _check_replaceable(out: Path) -> None:
    """ValueError unless what is at `out` (an absolute path) is a recording that `overwrite` may replace: a folder,
    not a link, holding a recording.json of the recording format, and neither the working directory nor above it."""
    if out.is_symlink():
        raise ValueError(f"--out {out} is a symbolic link; give the folder it points to, or another path")
    if not out.is_dir():
        raise ValueError(f"--out {out} is a file, not a folder")
    cwd = Path.cwd().resolve()
    if out == cwd or out in cwd.parents:
        raise ValueError(f"--overwrite will not replace {out}: it is the working directory or a folder above it")
    try:
        fmt = json.loads((out / META_FILE).read_text()).get("format")
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, AttributeError):
        fmt = None
    if fmt != FORMAT:
        raise ValueError(f"--overwrite replaces only a simulator recording, and {out} is not one (no {META_FILE} of "
                         f"format {FORMAT!r}); remove it yourself or choose another --out")


def _prepare_output(out: Path, overwrite: bool) -> tuple[Path, Path]:
    """Check the output folder `out` and make the hidden sibling that the recording is written to. Returns (`out`
    resolved, that sibling). ValueError when `out` is a link or a file, exists without `overwrite`, or exists and is
    not a recording that `overwrite` may replace (`_check_replaceable`)."""
    if out.is_symlink():
        raise ValueError(f"--out {out} is a symbolic link; give the folder it points to, or another path")
    out = out.resolve()
    if out.exists():
        if out.is_dir() and not overwrite:
            raise ValueError(f"output folder already exists: {out} (pass --overwrite to replace it)")
        _check_replaceable(out)
    parent = out.parent
    if not parent.is_dir():
        raise ValueError(f"output folder's parent does not exist: {parent}")
    tmp = parent / f".{out.name}.partial-{os.getpid()}"
    try:
        if tmp.exists():
            shutil.rmtree(tmp)
        tmp.mkdir()
        (tmp / "gt").mkdir()
        (tmp / "landmarks").mkdir()
    except OSError as exc:
        raise ValueError(f"cannot write to {parent}: {exc.strerror}") from None
    return out, tmp


def _move_into_place(tmp: Path, out: Path, overwrite: bool) -> None:
    """Rename the finished recording `tmp` to `out` (resolved). Something at `out` is replaced only with `overwrite`
    and only if it is still a recording (`_check_replaceable`): it is renamed aside, the new recording renamed into
    place, and the old one deleted last. Otherwise (say another run's recording appeared at `out` during this run)
    nothing is replaced or deleted: ValueError saying where the new recording is."""
    kept = f"nothing was replaced; the new recording is at {tmp}"
    if not (out.exists() or out.is_symlink()):
        try:
            os.rename(tmp, out)  # fails if a folder with files appeared at `out` since the check
        except OSError as exc:
            raise ValueError(f"cannot move the recording to {out} ({exc.strerror}); {kept}") from None
        return
    if not overwrite:
        raise ValueError(f"output folder {out} appeared during the run; {kept}")
    try:
        _check_replaceable(out)
    except ValueError as exc:
        raise ValueError(f"{exc} (it changed during the run); {kept}") from None
    try:
        old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old-", dir=out.parent))
    except OSError as exc:
        raise ValueError(f"cannot write to {out.parent} ({exc.strerror}); {kept}") from None
    try:
        os.rename(out, old)  # onto the empty folder just made
    except OSError as exc:
        old.rmdir()
        raise ValueError(f"cannot move the old recording {out} aside ({exc.strerror}); {kept}") from None
    try:
        os.rename(tmp, out)
    except OSError as exc:
        os.rename(old, out)
        raise ValueError(f"cannot move the recording to {out} ({exc.strerror}); {kept}") from None
    shutil.rmtree(old, ignore_errors=True)


def simulate_clip(cfg: ClipConfig, log: Callable[[str], None] = lambda s: None) -> dict:
    """Simulate and write one recording. Returns a summary (frames, timings). SIGTERM (a supervisor, `timeout`)
    stops it as Ctrl-C does: the render workers are stopped and the partial output removed."""
    if threading.current_thread() is not threading.main_thread():
        return _simulate_clip(cfg, log)

    def on_term(signum, _frame):
        raise SystemExit(128 + signum)

    old = signal.signal(signal.SIGTERM, on_term)
    try:
        return _simulate_clip(cfg, log)
    finally:
        signal.signal(signal.SIGTERM, old)


def _simulate_clip(cfg: ClipConfig, log: Callable[[str], None]) -> dict:
    cfg.validate()
    site = load_site(cfg.site)
    cams = select_cameras(site, cfg.cameras)
    env = sample_environment(np.random.default_rng([cfg.seed, 31]), cfg.weather)
    out, tmp = _prepare_output(Path(cfg.out), cfg.overwrite)
    wall0 = time.perf_counter()
    try:
        log(f"building the {site.name} world")
        world = build_world(site)
        log(f"simulating {cfg.seconds:g} s of traffic")
        history = simulate_traffic(
            site,
            world.net,
            cfg.seconds + 1.0 / cfg.hz + 0.2,
            cfg.seed,
            max_vehicles=cfg.max_vehicles,
            demand_scale=cfg.demand_scale,
            type_weights=cfg.type_weights,
        )
        shadows = ShadowCaster(world, env)
        schedule = capture_schedule(cams, cfg.seconds, cfg.hz, cfg.seed)
        t0 = _t0_ns(site)
        indexed = list(enumerate(cams))
        n_workers = min(cfg.workers, len(cams))
        log(f"rendering {sum(len(v) for v in schedule.values())} frames from {len(cams)} cameras ({env.name})")
        stats: list[dict] = []
        if n_workers == 1:
            stats = [
                _render_camera(i, c, world, env, shadows, history, schedule[c.name], t0, tmp, cfg) for i, c in indexed
            ]
        else:
            # Balance by pixel count; fork so the world and the traffic are shared, not pickled.
            groups: list[list] = [[] for _ in range(n_workers)]
            load = [0] * n_workers
            for i, c in sorted(indexed, key=lambda ic: -ic[1].width * ic[1].height):
                g = int(np.argmin(load))
                groups[g].append((i, c))
                load[g] += c.width * c.height
            ctx = mp.get_context("fork")
            procs = []
            for g in groups:
                parent_conn, child_conn = ctx.Pipe(duplex=False)
                p = ctx.Process(
                    target=_worker, args=(g, world, env, shadows, history, schedule, t0, tmp, cfg, child_conn)
                )
                p.start()
                child_conn.close()
                procs.append((p, parent_conn))
            errors = []
            try:
                for p, conn in procs:
                    try:
                        status, payload = conn.recv()
                    except EOFError:
                        status, payload = "error", "render worker died"
                    p.join()
                    if status == "ok":
                        stats.extend(payload)
                    else:
                        errors.append(payload)
            finally:  # stopped (SIGTERM, Ctrl-C) or failed: no worker goes on rendering into a removed folder
                for p, _ in procs:
                    if p.is_alive():
                        p.terminate()
                        p.join(5)
            if errors:
                raise RuntimeError(f"rendering failed: {errors[0]}")
        stats.sort(key=lambda s: [c.name for c in cams].index(s["camera"]))
        meta = {
            "format": FORMAT,
            "version": VERSION,
            "site": {
                "name": site.name,
                "description": site.description,
                "layout": site.layout,
                "origin": site.geo.to_dict(),
                "extent_m": site.extent_m,
            },
            "terrain": site.ground.to_dict(),
            "seed": cfg.seed,
            "hz": cfg.hz,
            "seconds": cfg.seconds,
            "t0_ns": t0,
            "environment": env.to_dict(),
            "vehicle_types": list(VEHICLE_TYPES),
            "type_weights": check_type_weights(cfg.type_weights),
            "cameras": [
                {
                    **c.to_dict(),
                    "frames": len(schedule[c.name]),
                    "frame_dir": f"frames/{c.name}",
                    "gt": f"gt/{c.name}.jsonl",
                    "landmarks": f"landmarks/{c.name}.json",
                }
                for c in cams
            ],
            "site_spec": site.model_dump(mode="json"),
        }
        (tmp / META_FILE).write_text(json.dumps(meta, indent=1))
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    _move_into_place(tmp, out, cfg.overwrite)  # on failure the finished recording stays at tmp, and it says so
    wall = time.perf_counter() - wall0
    frames = sum(s["frames"] for s in stats)
    return {
        "out": str(cfg.out),
        "frames": frames,
        "cameras": len(cams),
        "wall_s": wall,
        "frames_per_s": frames / wall if wall > 0 else 0.0,
        "per_camera": stats,
        "environment": env.name,
    }
