"""Fusion and tracking cost per tick: what fuse_track computes for every closed tick (velocity hints, `Fusion.fuse`,
`Tracker.update`), timed on a synthetic roundabout with plain arrays (no Zenoh, no recording), so the figure is the
algorithm's alone. Prints one JSON document.

The scene: four cameras 30 m out on the diagonals of a 20 m ring; vehicles circulating on the ring, crossing on two
straight roads and parked beside them; every camera sees what lies within `--range` m of it, at its own capture
time in the tick (-30, -10, +10, +30 ms), placed with noise that grows with range (more along the line of sight
than across it), missing 5 % and adding false alarms. Fusion and tracker are configured as fuse_track configures
them from a site's settings (`fusion_config`, `tracker_config`): the defaults, with `roadside demo`'s
`high_score`. Per tick: milliseconds p50 / p99 / mean of the whole step and of its fusion and tracking parts,
objects in and tracks out. The load average is recorded: on a shared machine the
figures are upper bounds; compare two variants within one run or back to back.

    python -m bench.fuse_track [--vehicles 40] [--ticks 600] [--warmup 30] [--range 60] [--seed 0]
"""

from __future__ import annotations

import math
import os
import platform
import time

import numpy as np

from bench import bench_parser
from roadside.demo import DemoConfig
from services.fuse_track.__main__ import fusion_config, tracker_config
from services.fuse_track.fusion import CameraRegion, Fusion, ObjectBatch
from services.fuse_track.tracker import Tracker
from shared.jsonio import dumps
from shared.settings import FuseTrackSettings

NS_PER_MS = 1_000_000
TICK_MS = 100
CAMERAS = {"NE": (30.0, 30.0), "NW": (-30.0, 30.0), "SE": (30.0, -30.0), "SW": (-30.0, -30.0)}
OFFSETS_MS = {"NE": -30, "NW": -10, "SE": 10, "SW": 30}
RING_M = 20.0


class Scene:
    """Vehicles of the synthetic roundabout; `positions(t_s)` -> (V, 2) m and headings (V,) rad."""

    def __init__(self, n: int, rng: np.random.Generator) -> None:
        if n < 4:
            raise ValueError(f"vehicles must be at least 4, got {n}")
        self.n_ring = n // 2
        self.n_road = (n - self.n_ring) * 3 // 4
        self.n_parked = n - self.n_ring - self.n_road
        self.ring_phase = np.linspace(0, 2 * np.pi, self.n_ring, endpoint=False) + rng.uniform(0, 0.2, self.n_ring)
        self.ring_speed = rng.uniform(6.0, 8.0, self.n_ring)
        self.road_axis = rng.integers(0, 2, self.n_road)  # 0: east-west road, 1: north-south road
        self.road_start = rng.uniform(-80, 80, self.n_road)
        self.road_speed = rng.choice([-1.0, 1.0], self.n_road) * rng.uniform(8.0, 12.0, self.n_road)
        self.parked = np.column_stack([rng.uniform(-50, 50, self.n_parked), rng.choice([-45.0, 45.0], self.n_parked)])

    def positions(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        a = self.ring_phase + self.ring_speed * t_s / RING_M
        ring = RING_M * np.column_stack([np.cos(a), np.sin(a)])
        s = (self.road_start + self.road_speed * t_s + 80) % 160 - 80  # wraps round within +-80 m
        lane = np.where(self.road_speed > 0, -1.75, 1.75)
        road = np.where(self.road_axis[:, None] == 0, np.column_stack([s, lane]), np.column_stack([lane, s]))
        xy = np.concatenate([ring, road, self.parked])
        yaw = np.concatenate([a + np.pi / 2, np.where(self.road_axis == 0, 0.0, np.pi / 2)
                              + (self.road_speed < 0) * np.pi, np.zeros(self.n_parked)])
        return xy, yaw


def camera_frame(scene: Scene, camera: str, t_ns: int, range_m: float, rng: np.random.Generator) -> ObjectBatch:
    """What one camera reports at t_ns: its vehicles within range_m, noisy, 5 % missed, plus false alarms."""
    xy, yaw = scene.positions(t_ns / 1e9)
    pos = np.asarray(CAMERAS[camera])
    v = xy - pos
    rng_m = np.hypot(v[:, 0], v[:, 1])
    seen = (rng_m <= range_m) & (rng.random(len(xy)) > 0.05)
    xy, yaw, v, rng_m = xy[seen], yaw[seen], v[seen], rng_m[seen]
    u = v / np.maximum(rng_m, 1e-9)[:, None]
    along, across = 0.1 + 0.01 * rng_m, 0.05 + 0.004 * rng_m
    xy = xy + u * (along * rng.standard_normal(len(xy)))[:, None] + np.column_stack([-u[:, 1], u[:, 0]]) * (
        across * rng.standard_normal(len(xy)))[:, None]
    n_false = rng.poisson(2.0)
    xy = np.concatenate([xy, pos + rng.uniform(-range_m, range_m, (n_false, 2)) * 0.7])
    yaw = np.concatenate([yaw, rng.uniform(-np.pi, np.pi, n_false)])
    n = len(xy)
    size = np.column_stack([rng.uniform(4.0, 5.5, n), rng.uniform(1.7, 2.0, n), rng.uniform(1.4, 1.9, n)])
    score = np.concatenate([rng.uniform(0.3, 0.95, n - n_false), rng.uniform(0.3, 0.5, n_false)])
    return ObjectBatch.from_frame(camera, t_ns, xy, yaw, size, rng.integers(0, 3, n), score)


def run(vehicles: int, ticks: int, warmup: int, range_m: float, seed: int) -> dict:
    rng = np.random.default_rng(seed)
    scene = Scene(vehicles, rng)
    cfg = FuseTrackSettings(high_score=DemoConfig().high_score)
    fusion = Fusion([CameraRegion(name, pos) for name, pos in CAMERAS.items()], fusion_config(cfg))
    tracker = Tracker(tracker_config(cfg))
    total, fuse, track, n_in, n_out = [], [], [], [], []
    for k in range(warmup + ticks):
        t_ref = (k * TICK_MS + TICK_MS // 2) * NS_PER_MS
        batches = [camera_frame(scene, c, t_ref + OFFSETS_MS[c] * NS_PER_MS, range_m, rng) for c in CAMERAS]
        t0 = time.perf_counter()
        objects = ObjectBatch.concat(batches)  # as fuse_track's fuse_and_track does
        fused = fusion.fuse(objects, t_ref, tracker.velocity_hints(objects))
        t1 = time.perf_counter()
        state = tracker.update(fused, t_ref)
        t2 = time.perf_counter()
        if k >= warmup:
            total.append(t2 - t0)
            fuse.append(t1 - t0)
            track.append(t2 - t1)
            n_in.append(len(objects))
            n_out.append(len(state))

    def ms(x: list[float]) -> dict:
        a = np.asarray(x) * 1e3
        return {"p50": round(float(np.median(a)), 4), "p99": round(float(np.percentile(a, 99)), 4),
                "mean": round(float(a.mean()), 4)}

    return {"tick_ms": ms(total), "fuse_ms": ms(fuse), "track_ms": ms(track),
            "objects_per_tick": round(float(np.mean(n_in)), 1), "tracks_per_tick": round(float(np.mean(n_out)), 1)}


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("fuse_track", __doc__, argv)
    p.add_argument("--vehicles", type=int, default=40, help="vehicles in the scene (default 40)")
    p.add_argument("--ticks", type=int, default=600, help="ticks timed (default 600: a minute at 10 Hz)")
    p.add_argument("--warmup", type=int, default=30, help="ticks run first and not timed (tracks are born)")
    p.add_argument("--range", type=float, default=60.0, dest="range_m", help="each camera's range, m (default 60)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args(argv)
    for name in ("vehicles", "ticks"):
        if getattr(a, name) < 1:
            p.error(f"--{name} must be at least 1, got {getattr(a, name)}")
    if a.warmup < 0:
        p.error(f"--warmup must be >= 0, got {a.warmup}")
    if not (math.isfinite(a.range_m) and a.range_m > 0):
        p.error(f"--range must be a finite number > 0, got {a.range_m}")
    try:
        result = run(a.vehicles, a.ticks, a.warmup, a.range_m, a.seed)
    except ValueError as exc:
        p.error(str(exc))
    doc = {"benchmark": "fuse_track", "vehicles": a.vehicles, "ticks": a.ticks, "cameras": len(CAMERAS),
           "range_m": a.range_m, "seed": a.seed, **result, "load_avg_1m": round(os.getloadavg()[0], 2),
           "python": platform.python_version(), "numpy": np.__version__}
    print(dumps(doc, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
