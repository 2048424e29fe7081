"""`roadside up`: the four services as separate OS processes, no Docker.

Starts fuse_track, localize, detect, then ingest (`python -m services.<name> --site ... --set ...`),
each with its own process group. A service that dies is restarted after `restart_delay_s` (like
compose's `restart: unless-stopped`), the delay doubling (up to `max_restart_delay_s`) while it keeps dying
within `stable_s` of its start, so that one that cannot run does not spin; the others are watched (and restarted)
meanwhile. A configuration error (exit 2) ends the run, its reason shown from the service's log. Ingest finishing
its source (exit 0; told to stop, it exits 143) ends the run: the others get `drain_s` to finish the frames in
flight, then SIGTERM. Ctrl-C, SIGTERM or SIGHUP (a closed terminal) stops everything cleanly (SIGTERM, then SIGKILL
after `stop_timeout_s`); on Linux the services are also told to stop (SIGTERM) when the launcher itself dies
without that (SIGKILL, the OOM killer), rather than left holding the bus's ports.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ORDER = ("fuse_track", "localize", "detect", "ingest")
PR_SET_PDEATHSIG = 1  # prctl(2): the signal a child gets when its parent dies


def _libc_prctl():
    """libc's prctl, looked up here in the launcher: the child between fork and exec must import nothing (another
    thread of the launcher, Zenoh's in `roadside demo`, may hold the import lock at the fork)."""
    if sys.platform != "linux":
        return None
    import ctypes

    try:
        return ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None


_PRCTL = _libc_prctl()


def _stop_with_parent() -> None:  # runs in the child between fork and exec
    """Linux: this process gets SIGTERM when the launcher dies, however it dies."""
    _PRCTL(PR_SET_PDEATHSIG, int(signal.SIGTERM))


@dataclass
class UpConfig:
    site: Path
    sets: list[str] = field(default_factory=list)  # section.field=value overrides for every service
    restart: bool = True
    restart_delay_s: float = 1.0
    max_restart_delay_s: float = 30.0
    stable_s: float = 10.0  # a service that ran this long before dying is restarted after restart_delay_s again
    drain_s: float = 3.0
    stop_timeout_s: float = 5.0
    log_dir: Path | None = None  # each service's stderr to <log_dir>/<service>.log (else inherited)
    services: tuple[str, ...] = ORDER


class Launcher:
    def __init__(self, cfg: UpConfig) -> None:
        for s in cfg.services:
            if s not in ORDER:
                raise ValueError(f"unknown service {s!r} (services: {', '.join(ORDER)})")
        if not (Path(cfg.site).is_file() or (Path(cfg.site) / "site.yaml").is_file()):
            raise ValueError(f"site file not found: {cfg.site}")
        self.cfg = cfg
        self.procs: dict[str, subprocess.Popen] = {}
        self.restarts: dict[str, int] = dict.fromkeys(cfg.services, 0)
        self.started_at: dict[str, float] = {}
        self.quick_failures: dict[str, int] = dict.fromkeys(cfg.services, 0)  # deaths in a row soon after start
        self.stopping = False
        self.signalled: str | None = None  # the signal that stopped the run (SIGINT, SIGTERM, SIGHUP), if one did
        self.peak_rss_mb: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}  # CPU seconds (user + system) of each service's current process

    def sample_memory(self) -> None:
        """Record each service's peak resident memory (MB) and the CPU time it has used so far."""
        import psutil

        for s, proc in self.procs.items():
            try:
                p = psutil.Process(proc.pid)
                rss = p.memory_info().rss / 2**20
                cpu = p.cpu_times()
            except (psutil.NoSuchProcess, psutil.AccessDenied):
                continue
            self.peak_rss_mb[s] = max(self.peak_rss_mb.get(s, 0.0), round(rss, 1))
            self.cpu_s[s] = round(cpu.user + cpu.system, 2)

    def command(self, service: str) -> list[str]:
        cmd = [sys.executable, "-m", f"services.{service}", "--site", str(self.cfg.site)]
        for s in self.cfg.sets:
            cmd += ["--set", s]
        return cmd

    def start(self, service: str) -> subprocess.Popen:
        err = None
        if self.cfg.log_dir is not None:
            self.cfg.log_dir.mkdir(parents=True, exist_ok=True)
            err = open(self.cfg.log_dir / f"{service}.log", "a")
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        try:
            proc = subprocess.Popen(self.command(service), stdout=err, stderr=err, env=env, start_new_session=True,
                                    preexec_fn=_stop_with_parent if _PRCTL is not None else None)
        finally:
            if err is not None:
                err.close()  # the child has its own copy; the parent would leak one per (re)start
        self.procs[service] = proc
        self.started_at[service] = time.monotonic()
        return proc

    def restart_delay(self, service: str) -> float:
        """Seconds to wait before restarting a service that just died: doubling while it dies soon after start."""
        if time.monotonic() - self.started_at.get(service, 0.0) < self.cfg.stable_s:
            self.quick_failures[service] += 1
        else:
            self.quick_failures[service] = 0
        return min(self.cfg.restart_delay_s * 2 ** max(self.quick_failures[service] - 1, 0),
                   self.cfg.max_restart_delay_s)

    def last_log_line(self, service: str) -> str | None:
        """The last line of the service's log (with `log_dir`): the reason it gave for a configuration error."""
        if self.cfg.log_dir is None:
            return None
        try:
            lines = (self.cfg.log_dir / f"{service}.log").read_text(errors="replace").strip().splitlines()
        except OSError:
            return None
        return lines[-1] if lines else None

    def stop(self, service: str) -> int | None:
        proc = self.procs.get(service)
        if proc is None or proc.poll() is not None:
            return None if proc is None else proc.returncode
        try:
            os.killpg(proc.pid, signal.SIGTERM)
        except ProcessLookupError:
            return proc.poll()
        try:
            return proc.wait(self.cfg.stop_timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            return proc.wait()

    def stop_all(self) -> None:
        self.stopping = True
        for s in reversed(self.cfg.services):  # ingest first, fuse_track last (it writes the tracks file)
            self.stop(s)

    def run(self, log=print) -> int:
        """Run until ingest ends (or forever with a looping/live source), Ctrl-C or SIGTERM."""
        def on_signal(signum, _):
            self.signalled = signal.Signals(signum).name  # a stop asked for: `roadside up` exits 0, a demo is cut short
            self.stopping = True

        # SIGHUP too: a closed terminal or a dropped ssh session must not leave the services (in their own
        # sessions) running and holding the bus ports
        old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
        status = 0
        due: dict[str, float] = {}  # services that died: when each is started again
        try:
            for s in self.cfg.services:
                self.start(s)
                log(f"[up] started {s} (pid {self.procs[s].pid})")
            while not self.stopping:
                time.sleep(0.2)
                self.sample_memory()
                for s in [s for s, t in due.items() if t <= time.monotonic()]:
                    del due[s]
                    self.restarts[s] += 1
                    self.start(s)
                    log(f"[up] restarted {s} (pid {self.procs[s].pid}, restart {self.restarts[s]})")
                for s, proc in list(self.procs.items()):
                    rc = proc.poll()
                    if rc is None or s in due:
                        continue
                    if s == "ingest" and rc == 0:
                        log(f"[up] ingest finished its source; draining {self.cfg.drain_s:g} s")
                        time.sleep(self.cfg.drain_s)
                        self.stopping = True
                        break
                    log(f"[up] {s} exited with status {rc}")
                    if not self.cfg.restart or rc == 2:
                        # status 2: a configuration error (missing model, masks, source); restarting will not help
                        reason = self.last_log_line(s) if rc == 2 else None
                        if reason:
                            log(f"[up] {s}: a configuration error, not restarted: {reason}")
                        status = 128 - rc if rc < 0 else rc or 1  # killed by a signal: 128 + its number, as a shell
                        self.stopping = True
                        break
                    delay = self.restart_delay(s)
                    if delay > self.cfg.restart_delay_s:
                        log(f"[up] {s} keeps dying soon after it starts: next start in {delay:g} s")
                    due[s] = time.monotonic() + delay  # the others are watched meanwhile
        finally:
            self.stop_all()
            for s, h in old.items():
                signal.signal(s, h)
        log("[up] stopped")
        return status
