"""A long run of the whole pipeline: does memory stay flat and do the tracks keep coming (`roadside bench soak`)?

A cabinet runs for months. This starts `roadside up` on a looping source (capture times shifted each time round, so
event time keeps increasing; the tracks file rotated by size so the disk stays bounded), and every `--sample-s`
seconds reads each service process's resident memory (psutil; a restarted service is a new process and is counted)
and the services' Status reports on the bus (shared/status.py: messages in and out, bad input). After `--minutes`
it stops the pipeline with SIGTERM and prints one JSON document: per service the memory at the end of the warm-up,
at the end and at most, its growth in MB per hour after the warm-up (least-squares slope), CPU seconds, restarts,
counts and bad input; the tracks messages per second and the frames ingest published. The rate is the Tracks
messages counted between the first and the last sample whose fuse_track report counted any, over the time between
those two samples (`tracks_rate_window_s`): the start-up before the first tick and the shutdown after the last sample
are left out (`minutes` is the whole run's, with both).

    python -m bench.soak --site out/demo/site --source out/demo/recording [--minutes 30] [--pace 1]
                         [--sample-s 30] [--warmup-s 120] [--out out/soak] [--set SECTION.FIELD=VALUE ...]

At `--pace 1` a four-camera site offers 40 frames/s, more than a CPU-only detector takes: detect's latest-only ring
drops the rest, as at a real cabinet. The load average is recorded; other work on the machine shows in it.
"""

from __future__ import annotations

import os
import platform
import signal
import subprocess
import sys
import time
from collections import Counter
from itertools import pairwise
from pathlib import Path

import numpy as np
import psutil

from bench import bench_parser
from roadside.argtypes import site_path
from shared.jsonio import dumps
from shared.messages import SERVICES

RECORD_ROTATE_MB = 16  # the tracks file of a long run rotates at this size, two old files kept
STATUS_TIMEOUT_S = 2.0


def service_processes(launcher_pid: int) -> dict[int, str]:
    """pid -> service name of the launcher's service processes (`python -m services.<name>`) running now."""
    found = {}
    try:
        children = psutil.Process(launcher_pid).children(recursive=True)
    except psutil.NoSuchProcess:
        return found
    for child in children:
        try:
            cmd = child.cmdline()
        except (psutil.NoSuchProcess, psutil.AccessDenied, psutil.ZombieProcess):
            continue
        name = next((c.split(".", 1)[1] for c in cmd if c.startswith("services.")), None)
        if name in SERVICES:
            found[child.pid] = name
    return found


def growth_mb_per_hour(series: list[tuple[float, float]]) -> float | None:
    """Least-squares slope of (seconds, MB) samples, in MB per hour; None with fewer than 3 samples."""
    if len(series) < 3:
        return None
    t, mb = np.array(series, dtype=float).T
    if np.ptp(t) <= 0:
        return None
    return float(np.polyfit(t, mb, 1)[0] * 3600.0)


def summarize(samples: list[dict], warmup_s: float) -> dict:
    """Per service, from samples `{"t_s", "rss_mb": {service: {pid: MB}}, "status": {service: report dict}}`:
    memory after the warm-up (the sum over the service's processes alive at each sample), growth, restarts,
    and the counts and bad input of its newest report (a restarted service counts from its restart)."""
    out = {}
    for service in SERVICES:
        series = [(s["t_s"], sum(s["rss_mb"][service].values())) for s in samples if s["rss_mb"].get(service)]
        after = [(t, mb) for t, mb in series if t >= warmup_s]
        pids = {pid for s in samples for pid in s["rss_mb"].get(service, {})}
        reports = [s["status"][service] for s in samples if service in s.get("status", {})]
        last = reports[-1] if reports else {}
        out[service] = {
            "rss_mb_after_warmup": round(after[0][1], 1) if after else None,
            "rss_mb_end": round(series[-1][1], 1) if series else None,
            "rss_mb_max": round(max(mb for _, mb in series), 1) if series else None,
            "growth_mb_per_hour": None if (g := growth_mb_per_hour(after)) is None else round(g, 2),
            "processes": len(pids),
            "restarts": max(len(pids) - 1, 0),
            "peak_rss_mb": last.get("peak_rss_mb"),
            "cpu_s": last.get("cpu_s"),
            "counts": _counts_by_name(last["counts"]) if last else None,
            "bad": sum(last.get("bad", {}).values()) if last else None,
        }
    return out


def tracks_rate(samples: list[dict]) -> tuple[float | None, float | None]:
    """(Tracks messages per second, seconds) between the first and the last sample whose fuse_track report counted
    any (`tracks_out` > 0); (None, None) with fewer than two such samples or none apart in time. A count that falls
    from one such sample to the next is a restarted fuse_track counting from its restart."""
    counted = []
    for s in samples:
        report = s.get("status", {}).get("fuse_track") or {}
        if n := _counts_by_name(report.get("counts") or {}).get("tracks_out", 0):
            counted.append((s["t_s"], n))
    if len(counted) < 2 or not counted[-1][0] > counted[0][0]:
        return None, None
    published = sum(n - prev if n >= prev else n for (_, prev), (_, n) in pairwise(counted))
    window = counted[-1][0] - counted[0][0]
    return published / window, window


def _counts_by_name(counts: dict[str, int]) -> dict[str, int]:
    """Counts summed over cameras (`frames_out.NE` + `frames_out.NW` -> `frames_out`)."""
    total: Counter[str] = Counter()
    for name, n in counts.items():
        total[name.split(".")[0]] += n
    return dict(sorted(total.items()))


def sample(launcher_pid: int, session, site: str, t_s: float) -> dict:
    """Memory of every service process now, and the newest Status report of each service."""
    from shared.status import collect_status

    rss: dict[str, dict[int, float]] = {s: {} for s in SERVICES}
    for pid, service in service_processes(launcher_pid).items():
        try:
            rss[service][pid] = round(psutil.Process(pid).memory_info().rss / 2**20, 1)
        except psutil.NoSuchProcess:
            continue
    reports, _ = collect_status(session, site, STATUS_TIMEOUT_S)
    status = {}
    for r in reports:  # a restarted service may answer twice for a while: the newest report
        if r.service not in status or status[r.service]["t_capture_ns"] < r.t_capture_ns:
            status[r.service] = r.model_dump(include={"t_capture_ns", "counts", "bad", "cpu_s", "peak_rss_mb"})
    return {"t_s": round(t_s, 1), "rss_mb": rss, "status": status}


def run(site: Path, source: str, minutes: float, pace: str, sample_s: float, warmup_s: float, out: Path,
        sets: list[str], log=print) -> dict:
    import zenoh

    from shared.bus import zenoh_config
    from shared.service import parse_sets
    from shared.settings import BusSettings, load_settings

    settings = load_settings(site, **parse_sets(sets))  # as the services will read it: a bad --set fails here
    out.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "roadside", "up", "--site", str(site), "--source", source, "--pace", pace, "--loop",
           "--record", str(out / "tracks.jsonl"), "--log-dir", str(out / "logs"),
           "--set", "ingest.wait_extra_peers=0", "--set", f"fuse_track.record_rotate_mb={RECORD_ROTATE_MB}",
           "--set", "fuse_track.record_keep=2"]
    for s in sets:
        cmd += ["--set", s]
    samples: list[dict] = []
    with open(out / "up.log", "w") as up_log:
        proc = subprocess.Popen(cmd, stdout=up_log, stderr=up_log, start_new_session=True)
    session = zenoh.open(zenoh_config(BusSettings(port_base=settings.bus.port_base), None, 0))
    t0 = time.monotonic()
    exit_code = None
    try:
        while time.monotonic() - t0 < minutes * 60:
            time.sleep(max(0.0, min(sample_s, minutes * 60 - (time.monotonic() - t0))))
            if (exit_code := proc.poll()) is not None:
                log(f"roadside up ended by itself (exit {exit_code}); see {out / 'up.log'}")
                break
            samples.append(sample(proc.pid, session, settings.site, time.monotonic() - t0))
            s = samples[-1]
            log(f"{s['t_s']:7.0f} s  " + "  ".join(f"{k} {sum(v.values()):.0f} MB" for k, v in s["rss_mb"].items()))
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                exit_code = proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                exit_code = proc.wait()
        session.close()
    elapsed = time.monotonic() - t0
    services = summarize(samples, warmup_s)
    tracks_out = (services["fuse_track"]["counts"] or {}).get("tracks_out", 0)
    rate, window = tracks_rate(samples)
    return {
        "bench": "soak", "site": str(site), "source": source, "pace": pace, "minutes": round(elapsed / 60, 2),
        "sample_s": sample_s, "warmup_s": warmup_s, "samples": len(samples), "launcher_exit_code": exit_code,
        "frames_published": (services["ingest"]["counts"] or {}).get("frames_out", 0),
        "tracks_messages": tracks_out, "tracks_per_s": None if rate is None else round(rate, 2),
        "tracks_rate_window_s": None if window is None else round(window, 1),
        "services": services,
        "series_rss_mb": {svc: [[s["t_s"], round(sum(s["rss_mb"][svc].values()), 1)] for s in samples]
                          for svc in SERVICES},
        "machine": {"cpus": os.cpu_count(), "python": platform.python_version(),
                    "load_avg_1m": round(os.getloadavg()[0], 2)},
    }


def main(argv: list[str] | None = None) -> int:
    p = bench_parser("soak", __doc__, argv)
    p.add_argument("--site", type=Path, default=Path("out/demo/site"), help="site folder (default: the demo's)")
    p.add_argument("--source", default="out/demo/recording", help="recording or footage, played in a loop")
    p.add_argument("--minutes", type=float, default=30.0, help="how long to run (default 30)")
    p.add_argument("--pace", default="1", help="1 (real time, default), N or max")
    p.add_argument("--sample-s", type=float, default=30.0, help="seconds between samples (default 30)")
    p.add_argument("--warmup-s", type=float, default=120.0,
                   help="samples before this are left out of the growth (models loading, rings filling; default 120)")
    p.add_argument("--out", type=Path, default=Path("out/soak"), help="tracks, logs (default out/soak)")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="passed to roadside up (repeatable)")
    a = p.parse_args(argv)
    for name in ("minutes", "sample_s"):
        if not getattr(a, name) > 0:
            p.error(f"--{name.replace('_', '-')} must be > 0")
    if not a.warmup_s >= 0:
        p.error("--warmup-s must be >= 0")
    try:
        a.site = site_path(a.site)
    except ValueError as exc:
        p.error(str(exc))
    if "://" not in a.source and not Path(a.source).exists():
        p.error(f"source not found: {a.source}")
    doc = run(a.site, a.source, a.minutes, a.pace, a.sample_s, a.warmup_s, a.out, a.sets,
              log=lambda m: print(m, file=sys.stderr, flush=True))
    print(dumps(doc, indent=1))
    return 0 if doc["launcher_exit_code"] in (0, None) and doc["samples"] else 1


if __name__ == "__main__":
    sys.exit(main())
