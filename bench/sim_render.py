"""Simulator render rate: a State/Ellsworth clip through all 8 cameras (default 60 s at 10 Hz,
4,800 frames). Prints one JSON document. Target: the default run under 600 s on a 2-core machine.

    python -m bench.sim_render [--seconds 60] [--hz 10] [--workers 2]

`setup_s` is the time before the first frame (the world, the traffic, the shadows), `render_s` the rest
(rendering and writing the frames); `render_frames_per_s` is frames / render_s. The target applies to the
default frame count rendered by 2 workers on a machine with 2 cores only: for any other run `meets_target` is
null and `target_not_applied` says why (the setup time does not scale with frames, and more workers or cores are
not the target's machine).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from bench import bench_parser
from sim.clip import ClipConfig, simulate_clip

DEFAULT_FRAMES = 4800  # 8 cameras, 60 s at 10 Hz
TARGET_WALL_S = 600.0
TARGET_CORES = 2  # the target's machine: 2 cores, the clip rendered by 2 workers


def timings(frames: int, wall_s: float, setup_s: float | None, *, workers: int, cpu_count: int | None) -> dict:
    """The timing fields of the report for `frames` frames in `wall_s` s, `setup_s` of them before the first frame
    (None: not known, and neither is the render time), rendered by `workers` processes on `cpu_count` cores."""
    render_s = None if setup_s is None else wall_s - setup_s
    off = off_condition(frames, workers, cpu_count)
    return {
        "wall_s": round(wall_s, 1),
        "setup_s": None if setup_s is None else round(setup_s, 1),
        "render_s": None if render_s is None else round(render_s, 1),
        "frames_per_s": round(frames / wall_s, 2),
        "render_frames_per_s": round(frames / render_s, 2) if render_s else None,
        "target_wall_s": TARGET_WALL_S,
        "target_frames": DEFAULT_FRAMES,
        "target_workers": TARGET_CORES,
        "target_cpu_count": TARGET_CORES,
        "meets_target": wall_s < TARGET_WALL_S if not off else None,
        "target_not_applied": "; ".join(off) or None,
    }


def off_condition(frames: int, workers: int, cpu_count: int | None) -> list[str]:
    """How a run differs from the one the target is set for (4,800 frames, 2 workers, 2 cores); empty if it does not."""
    off = []
    if frames != DEFAULT_FRAMES:
        off.append(f"{frames} frames, not {DEFAULT_FRAMES}")
    if workers != TARGET_CORES:
        off.append(f"{workers} workers, not {TARGET_CORES}")
    if cpu_count != TARGET_CORES:
        off.append(f"{cpu_count} cores, not {TARGET_CORES}")
    return off


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("sim", __doc__, argv, module="sim_render")
    p.add_argument("--seconds", type=float, default=60.0, help="clip length in seconds (default 60)")
    p.add_argument("--hz", type=float, default=10.0, help="frames per second per camera (default 10)")
    p.add_argument("--workers", type=int, default=2, help="rendering processes (default 2)")
    p.add_argument("--seed", type=int, default=1, help="random seed (default 1)")
    p.add_argument("--weather", default="clear", help="weather of the clip (default clear)")
    args = p.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench_sim_"))
    render_start: list[float] = []

    def log(message: str) -> None:  # simulate_clip says "rendering ..." just before the first frame
        if message.startswith("rendering"):
            render_start.append(time.perf_counter())

    try:
        t0 = time.perf_counter()
        summary = simulate_clip(
            ClipConfig(
                site="state_ellsworth",
                out=tmp / "rec",
                seconds=args.seconds,
                hz=args.hz,
                seed=args.seed,
                cameras="all",
                weather=args.weather,
                workers=args.workers,
            ),
            log=log,
        )
        wall = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in (tmp / "rec").rglob("*") if f.is_file())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    setup = render_start[0] - t0 if render_start else None
    per_cam = {s["camera"]: round(s["render_s"] / max(s["frames"], 1) * 1000, 1) for s in summary["per_camera"]}
    print(
        json.dumps(
            {
                "benchmark": "sim_render",
                "site": "state_ellsworth",
                "cameras": summary["cameras"],
                "seconds": args.seconds,
                "hz": args.hz,
                "frames": summary["frames"],
                "workers": args.workers,
                "cpu_count": os.cpu_count(),
                **timings(summary["frames"], wall, setup, workers=args.workers, cpu_count=os.cpu_count()),
                "render_ms_per_frame": per_cam,
                "recording_mb": round(size / 2**20, 1),
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
