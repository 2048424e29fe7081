"""Simulator render rate: a State/Ellsworth clip through all 8 cameras (default 60 s at 10 Hz,
4,800 frames). Prints one JSON document. Target: under 600 s on a 2-core machine.

    python -m bench.sim_render [--seconds 60] [--hz 10] [--workers 2]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

from sim.clip import ClipConfig, simulate_clip


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seconds", type=float, default=60.0)
    p.add_argument("--hz", type=float, default=10.0)
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--weather", default="clear")
    args = p.parse_args(argv)
    tmp = Path(tempfile.mkdtemp(prefix="bench_sim_"))
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
            )
        )
        wall = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in (tmp / "rec").rglob("*") if f.is_file())
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
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
                "wall_s": round(wall, 1),
                "frames_per_s": round(summary["frames"] / wall, 2),
                "render_ms_per_frame": per_cam,
                "recording_mb": round(size / 2**20, 1),
                "target_wall_s": 600,
                "meets_target": wall < 600,
            },
            indent=1,
        )
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
