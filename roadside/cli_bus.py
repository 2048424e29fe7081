"""`roadside tracks | status | health | metrics | play | check`: what a running pipeline says on the bus (a vehicle's,
an operator's view), a recording played as one, and a site checked before its pipeline starts."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

from roadside.argtypes import (
    endpoint,
    non_negative_float,
    port_base,
    port_number,
    positive_float,
    positive_int,
    site_path,
)
from shared.jsonio import dumps
from shared.messages import MAX_PREDICT_S, SERVICES


def add_bus_jobs(sub) -> dict:
    """Add the jobs' parsers; returns {job: runner}."""
    _add_tracks(sub)
    _add_status(sub)
    _add_health(sub)
    _add_metrics(sub)
    _add_play(sub)
    _add_check(sub)
    return {"tracks": _run_tracks, "status": _run_status, "health": _run_health, "metrics": _run_metrics,
            "play": _run_play, "check": _run_check}


DEFAULT_SITE = "state_ellsworth"
DEFAULT_PORT_BASE = 7451  # BusSettings' own


def _add_endpoint_flags(p: argparse.ArgumentParser, default_to: str) -> None:
    p.add_argument("--site", default=DEFAULT_SITE,
                   help="site name; or a site folder or its site.yaml: the site's name and bus as the services "
                   "take them, ROADSIDE_BUS__* environment overrides included (a cabinet's compose service, "
                   f"`roadside demo`'s out/demo/site) (default: {DEFAULT_SITE})")
    p.add_argument("--connect", action="append", default=[], type=endpoint,
                   help=f"Zenoh endpoint: the cabinet's router tcp/HOST:7447 (default: {default_to})")
    p.add_argument("--port-base", type=port_base,
                   help=f"embedded default's first service port (default: {DEFAULT_PORT_BASE}, or the --site file's)")
    p.add_argument("--ca", type=Path, metavar="PEM",
                   help="with a tls/HOST:PORT endpoint: the cabinet's CA certificate, which its certificate must "
                   "chain to (deploy/sites/README.md)")
    p.add_argument("--cert", type=Path, metavar="PEM",
                   help="with --key, for a cabinet that lets only enrolled vehicles in (mutual TLS): this "
                   "vehicle's certificate, signed by the operator's CA")
    p.add_argument("--key", type=Path, metavar="PEM", help="the private key of --cert")


def _site(args) -> None:
    """--site as given: a name stays one; an existing site folder or site.yaml gives its name to `args.site` and its bus
    settings (listening nowhere: this process only asks) to `args.site_bus`. ValueError for a site file that does not
    load (named by load_settings)."""
    from shared.messages import check_name
    from shared.settings import load_settings

    args.site_bus = None
    given = Path(args.site)
    if given.exists():
        settings = load_settings(site_path(given))
        args.site, args.site_bus = settings.site, settings.bus
    elif len(given.parts) > 1 or given.suffix in (".yaml", ".yml"):
        raise ValueError(f"site not found: {args.site}")
    check_name("site", args.site)


def _bus(args):
    """The bus settings of the endpoint flags over the --site file's bus (or the embedded default's)."""
    tls = {k: v for k, v in (("tls_root_ca", args.ca), ("tls_certificate", args.cert), ("tls_private_key", args.key))
           if v is not None}
    return asking_bus(getattr(args, "site_bus", None), args.connect, args.port_base, tls)


def asking_bus(base=None, connect: list[str] | None = None, port_base: int | None = None, tls: dict | None = None):
    """The bus of a process that only asks (listening nowhere): `base` (a site's bus; default the embedded
    default's) in client mode to `connect` if given, or in peer mode on `port_base`'s embedded ports; the `tls`
    files over the base's."""
    from pydantic import ValidationError

    from shared.settings import BusSettings

    flags: dict = {"listen": [], **(tls or {})}
    if connect:
        flags.update(mode="client", connect=list(connect))
    elif port_base is not None:
        flags.update(mode="peer", port_base=port_base, connect=[])
    try:
        return BusSettings.model_validate({**(base or BusSettings()).model_dump(), **flags})
    except ValidationError as exc:  # e.g. --cert without --key: the rule's own words, not pydantic's report
        raise ValueError(exc.errors()[0]["msg"].removeprefix("Value error, ")) from None


def _add_tracks(sub) -> None:
    p = sub.add_parser("tracks", help="print live tracks (what a connected vehicle receives)",
                       description="Print live tracks: per track its id, type, position with the longest half-axis "
                       "of its 95 % error ellipse (+- m), heading (rad, counter-clockwise from east; '?' after it: "
                       "the vehicle has not been seen travelling, so front and back may be swapped), speed, how far "
                       "off the heading's axis may be (+- deg, 1 sigma: yaw_std) and the cameras that saw it.")
    _add_endpoint_flags(p, "the local fuse_track")
    p.add_argument("--count", type=positive_int, help="stop after this many messages")
    p.add_argument("--timeout", type=positive_float, help="stop after this many seconds without tracks")
    p.add_argument("--json", action="store_true", help="one JSON line per message")
    p.add_argument("--wait", type=non_negative_float, default=10.0, metavar="SECONDS",
                   help="how long to wait for the first connection (0: until the cabinet answers); a link that "
                   "drops later is reconnected by itself")
    ahead = p.add_mutually_exclusive_group()
    ahead.add_argument("--ahead-ms", type=_ahead_ms, metavar="MS",
                       help="print each message moved on this long after its capture time, at the tracks' "
                       f"velocities, their error ellipses grown to match (Tracks.predicted; at most "
                       f"{MAX_PREDICT_S * 1000:.0f}): where the vehicles are when a vehicle that knows its delay gets "
                       "them")
    ahead.add_argument("--now", action="store_true",
                       help="print each message moved on to this machine's clock (Tracks.predicted): for a live "
                       "cabinet whose clock this machine shares (GNSS, PTP); a recorded minute played back carries "
                       "its own capture times and is refused")


def _ahead_ms(text: str) -> float:
    v = non_negative_float(text)
    if v > MAX_PREDICT_S * 1000:
        raise argparse.ArgumentTypeError(f"must be at most {MAX_PREDICT_S * 1000:.0f} ms, got {text}")
    return v


def _run_tracks(args) -> int:
    from shared.client import TrackClient
    from shared.messages import err95_m

    _site(args)
    n = 0
    with TrackClient(args.site, None, _bus(args), wait_s=args.wait or None) as client:
        current = client.latest()
        if current is None:  # no fuse_track of this site answers: is the bus another site's?
            others = client.sites() - {args.site}
            if others:
                print(f"roadside tracks: no tracks of site {args.site} on this bus; it has site"
                      f"{'s' * (len(others) > 1)} {', '.join(sorted(others))} (--site)", file=sys.stderr, flush=True)
        # printed for a person: the newest when the terminal is slower than the ticks; a JSON line per message is a
        # tracks file (below) and gets every one
        stale = False  # in a run of messages too old (or too new) to move on to now
        for tracks in client.stream(timeout_s=args.timeout, current=current, latest=not args.json):
            if args.now:
                try:
                    tracks = tracks.predicted(time.time_ns())
                except ValueError as exc:
                    if not n:  # the first message says whether this machine shares the cabinet's clock: refused
                        raise
                    if not stale:  # later, a message that waited too long on the way (or in this reader): skipped
                        print(f"roadside tracks: warning: skipping messages that cannot be moved on to now: {exc}",
                              file=sys.stderr, flush=True)
                    stale = True
                    continue
                stale = False
            elif args.ahead_ms:
                tracks = tracks.predicted(tracks.t_capture_ns + round(args.ahead_ms * 1e6))
            rows = tracks.rows()
            if args.json:
                # a tracks-file line (docs/wire-format.md): `roadside viz`, `play` and `counts` read what it prints
                print(dumps({"site": tracks.site, "seq": tracks.seq, "t_ns": tracks.t_capture_ns,
                             "tracker": tracks.tracker, "tracks": rows}), flush=True)
            else:
                print(f"t={tracks.t_capture_ns / 1e9:.2f} s  {len(rows)} tracks", flush=True)
                for r, err in zip(rows, err95_m(tracks.xy_cov).tolist(), strict=True):
                    speed = math.hypot(r["vx"], r["vy"])
                    print(f"  {r['id']:>5} {r['type']:<10} lat {r['lat']:.7f} lon {r['lon']:.7f} +-{err:4.1f} m "
                          f"yaw {r['yaw']:+.2f}{' ' if r['yaw_confirmed'] else '?'} speed {speed:5.1f} m/s  "
                          f"heading +-{math.degrees(r['yaw_std']):2.0f} deg  {','.join(r['cameras'])}")
            n += 1
            if args.count and n >= args.count:
                break
    return 0 if n else 1


def _add_status(sub) -> None:
    p = sub.add_parser("status", help="what each running service has done: messages in and out and their rates, "
                       "bad input by reason, CPU, memory (shared/status.py)")
    _add_endpoint_flags(p, "the four local services")
    p.add_argument("--timeout", type=positive_float, default=2.0, help="seconds to wait for the services' answers")
    p.add_argument("--watch", type=positive_float, metavar="SECONDS",
                   help="ask again every SECONDS until Ctrl-C (default: once)")
    p.add_argument("--require", action="append", default=[], choices=SERVICES,
                   help="exit 1 unless this service answers (repeatable)")
    p.add_argument("--json", action="store_true", help="one JSON document per answer: the Status messages")


def _watcher_session(args):
    """A Zenoh session that asks the site's services (`--site`, `--connect` or `--port-base`, `_bus`), listening
    nowhere."""

    from shared.bus import zenoh_config

    _site(args)
    return _open(zenoh_config(_bus(args), None, 0))


def _open(config):
    """zenoh.open, its failure to reach the bus a ValueError (a message, not a traceback)."""
    import zenoh

    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        raise ValueError(f"cannot reach the bus: {exc}") from None


def _run_status(args) -> int:
    from shared.status import collect_status, status_table

    session = _watcher_session(args)
    try:
        while True:
            reports, errors = collect_status(session, args.site, args.timeout)
            if args.json:
                print(dumps({"t_ns": time.time_ns(), "services": [r.model_dump() for r in reports],
                             "errors": errors}), flush=True)
            else:
                print(status_table(reports) if reports else _nobody(session, args.site, args.timeout), flush=True)
                for e in errors:
                    print(f"  not a status report: {e}", flush=True)
            missing = sorted(set(args.require) - {r.service for r in reports})
            if args.watch is None:
                break
            time.sleep(args.watch)
    finally:
        session.close()
    if missing:
        print(f"not answering: {', '.join(missing)}", file=sys.stderr if args.json else sys.stdout)
        return 1
    return 0 if reports else 1


def _nobody(session, site: str, timeout_s: float) -> str:
    """What `roadside status` says when no service of `site` answered: the sites whose services are on the bus, if any
    (a --connect or --port-base without --site asks for the default site)."""
    from shared.bus import bus_sites

    others = bus_sites(session, timeout_s) - {site}
    told = f"; this bus has site{'s' * (len(others) > 1)} {', '.join(sorted(others))} (--site)" if others else ""
    return f"no service of site {site} answered{told}"


def _add_metrics(sub) -> None:
    p = sub.add_parser("metrics", help="serve the services' status reports as Prometheus metrics on GET /metrics "
                       "(shared/metrics.py), asking the bus at each scrape")
    _add_endpoint_flags(p, "the four local services")
    p.add_argument("--host", default="127.0.0.1", help="address to serve on (0.0.0.0: every interface)")
    p.add_argument("--port", type=port_number, default=9464, help="port to serve on (default 9464)")
    p.add_argument("--timeout", type=positive_float, default=1.5, help="seconds a scrape waits for the reports")


def _run_metrics(args) -> int:
    from shared.metrics import serve
    from shared.status import collect_status

    session = _watcher_session(args)
    try:
        serve(args.host, args.port, lambda: collect_status(session, args.site, args.timeout)[0],
              ready=lambda port: print(f"metrics of site {args.site} on http://{args.host}:{port}/metrics", flush=True))
    except KeyboardInterrupt:
        pass
    except OSError as exc:  # the port is taken, or the address is not this machine's
        raise ValueError(f"cannot serve on {args.host}:{args.port}: {exc.strerror or exc}") from None
    finally:
        session.close()
    return 0


def _add_health(sub) -> None:
    p = sub.add_parser("health", help="exit 0 when a service's liveliness token is on the bus and, where the site's "
                       "services report their status, its status says it works")
    p.add_argument("--site", required=True, type=Path)
    p.add_argument("--service", required=True, choices=SERVICES)
    p.add_argument("--timeout", type=positive_float, default=3.0, help="seconds to wait for the liveliness token")
    p.add_argument("--stalled-after", type=non_negative_float, default=15.0, metavar="SECONDS",
                   help="unhealthy when fed but silent this long, or its newest status report is this old "
                   "(shared/status.py stall_reasons; 0: the liveliness token alone)")


STATUS_ANSWER_S = 1.5  # how long `roadside health` waits for the status reports (a compose check has 5 s in all)


def _run_health(args) -> int:

    from shared.bus import wait_for_peers, zenoh_config
    from shared.keys import alive_key
    from shared.settings import load_settings
    from shared.status import collect_status, stall_reasons

    settings = load_settings(site_path(args.site))
    session = _open(zenoh_config(settings.bus.model_copy(update={"listen": []}), None, 0))
    reasons: list[str] = []
    try:
        key = alive_key(settings.site, args.service, "x").rsplit("/", 1)[0] + "/*"
        n = wait_for_peers(session, key, 1, args.timeout)
        checked = n and args.stalled_after > 0 and settings.bus.status_period_s > 0
        if checked:
            reports, _ = collect_status(session, settings.site, STATUS_ANSWER_S)
            if not any(r.service == args.service for r in reports):
                reasons = [f"{args.service}: alive but its status does not answer within {STATUS_ANSWER_S} s"]
            else:
                reasons = stall_reasons(args.service, reports, time.time_ns(), args.stalled_after,
                                         settings.bus.status_period_s)
    finally:
        session.close()
    if not n:
        print(f"{args.service}: not seen (0 tokens)")
        return 1
    for line in reasons:
        print(line)
    state = "not working" if reasons else "working" if checked else "alive"
    print(f"{args.service}: {state} ({n} tokens)")
    return 1 if reasons else 0


def _add_check(sub) -> None:
    p = sub.add_parser("check", help="a site's pre-flight: every service's start-up checks at once (masks, detector, "
                       "sources, fusion, the files written, the bus's ports), before roadside up or docker compose up",
                       description="Run what each service checks at start and report every problem at once (roadside/"
                       "check.py). Exit 0 when all pass, 2 otherwise.")
    p.add_argument("--site", required=True, type=Path,
                   help="site folder or site.yaml (a name such as state_ellsworth means deploy/sites/NAME)")
    p.add_argument("--source", help="recording, image folders, video file or stream URL (overrides ingest.source)")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                   help="override a setting, as roadside up --set (repeatable)")
    p.add_argument("--no-live", action="store_true", help="do not read live streams (RTSP, HTTP)")
    p.add_argument("--json", action="store_true", help="one JSON document instead of a table")


def _run_check(args) -> int:
    import json

    from roadside.check import as_json, check_site
    from shared.service import parse_sets
    from shared.settings import load_settings

    sets = list(args.set)
    if args.source:
        source = args.source if "://" in args.source else str(Path(args.source).resolve())
        sets.append(f"ingest.source={json.dumps(source)}")
    try:
        settings = load_settings(site_path(args.site), **parse_sets(sets))
    except ValueError as exc:
        if not args.json:
            raise  # one error line, exit 2
        print(dumps({"site": str(args.site), "ok": False, "error": str(exc), "checks": []}, indent=1))
        return 2
    checks = check_site(settings, live=not args.no_live)
    if args.json:
        print(dumps(as_json(settings.site, checks), indent=1))
    else:
        width = max(len(c.name) for c in checks)
        for c in checks:
            print(f"{'FAIL' if not c.ok else 'WARN' if c.warning else 'ok  '}  {c.name:<{width}}  {c.detail}")
        failed, warned = sum(not c.ok for c in checks), sum(c.ok and c.warning for c in checks)
        print(f"site {settings.site}: " + (f"{failed} of {len(checks)} checks failed" if failed
                                           else f"all {len(checks)} checks passed") +
              (f", {warned} with a warning" if warned else ""))
    return 0 if all(c.ok for c in checks) else 2


def _pace(text: str) -> float | None:
    if text == "max":
        return None
    v = positive_float(text)
    if v > 1000:
        raise argparse.ArgumentTypeError(f"must be at most 1000 (x real time) or max, got {text}")
    return v


def _add_play(sub) -> None:
    p = sub.add_parser("play", help="publish a tracks recording on the bus as fuse_track would (a vehicle's "
                       "subscriber run against a recorded session, without the pipeline)",
                       description="Publish the Tracks messages of fuse_track's recording (JSON lines; rotated files "
                       "in order) on roadside/<site>/tracks at their capture times' pace, answering the latest-tracks "
                       "query as fuse_track does (services/fuse_track/player.py). Bad lines are counted and skipped.")
    p.add_argument("files", nargs="+", type=Path, help="tracks files (fuse_track.record), oldest first")
    p.add_argument("--pace", type=_pace, default=1.0, help="1 (real time, the default), N (N x real time) or max")
    p.add_argument("--loop", action="store_true", help="start again at the end, times and seq going on (Ctrl-C stops)")
    p.add_argument("--site", type=Path,
                   help="site folder or site.yaml (a name such as state_ellsworth means deploy/sites/NAME): play on "
                   "its bus as its fuse_track would (bus.mode, host, port_base, TLS; ROADSIDE_BUS__* environment "
                   "overrides included), where `roadside tracks --site` and a vehicle of that site look; a recording "
                   "of another site is refused (default: the embedded default's bus)")
    p.add_argument("--connect", action="append", default=[], type=endpoint,
                   help="Zenoh endpoint of a router to publish through (default: listen where fuse_track would, "
                   "--port-base + 3); a development router, not a cabinet's: a cabinet's "
                   "router drops what the network publishes (deploy/sites/README.md)")
    p.add_argument("--port-base", type=port_base,
                   help=f"embedded default's first service port, over the --site file's (default: {DEFAULT_PORT_BASE}, "
                   "or the --site file's)")


def _play_bus(args):
    """The bus `roadside play` publishes on, and the --site file's site name (None without --site): the site's bus as
    its fuse_track opens it (or the embedded default's), --connect (a router, client mode) or --port-base (the
    embedded ports, peer mode) over where it plays; the site's TLS files stay."""
    from pydantic import ValidationError

    from shared.settings import BusSettings, load_settings

    name = None
    if args.site is None:
        base = BusSettings()
    else:
        settings = load_settings(site_path(args.site))  # a bad site file: one error line, exit 2
        base, name = settings.bus, settings.site
    flags: dict = {}
    if args.connect:
        flags.update(mode="client", connect=list(args.connect), listen=[])
    elif args.port_base is not None:
        flags.update(mode="peer", port_base=args.port_base, connect=[], listen=[])
    try:
        return BusSettings.model_validate({**base.model_dump(), **flags}), name
    except ValidationError as exc:
        raise ValueError(exc.errors()[0]["msg"].removeprefix("Value error, ")) from None


def _recorded_site(files: list[Path]) -> str | None:
    """The site of the recording's first good line (the one play publishes under); None when none is good (play
    then says so)."""
    from services.fuse_track.player import records

    lines = records(files, lambda reason, where: None)
    try:
        first = next(lines, None)
    finally:
        lines.close()
    return None if first is None else first[1].site


def _run_play(args) -> int:
    import zenoh

    from services.fuse_track.player import TracksPublisher, play
    from shared.bus import BadInput, Stopper, zenoh_config

    missing = [str(f) for f in args.files if not f.exists()]
    if missing:
        raise ValueError(f"tracks file not found: {', '.join(missing)}")
    folders = [str(f) for f in args.files if not f.is_file()]
    if folders:
        raise ValueError(f"not a tracks file (a folder?): {', '.join(folders)}")
    bus, site = _play_bus(args)
    recorded = _recorded_site(args.files) if site is not None else None
    if recorded is not None and recorded != site:
        raise ValueError(f"the recording's tracks are of site {recorded}, not of site {site} (--site {args.site}): a "
                         f"vehicle or `roadside tracks` asking for site {site} would not see them; subscribe with "
                         f"--site {recorded}, or play on another bus without --site (--port-base, --connect)")
    client = bus.mode == "client"
    where = ", ".join(bus.connect) if client else bus.service_endpoint("fuse_track")
    try:
        session = zenoh.open(zenoh_config(bus, None if client else "fuse_track"))
    except zenoh.ZError as exc:
        raise ValueError(f"cannot open the bus at {where} (is fuse_track, or another player, running there?): "
                         f"{exc}") from None
    stopper, bad = Stopper(), BadInput("play")
    publish = TracksPublisher(session, block=args.pace is None, status_period_s=bus.status_period_s)
    pace = "as fast as it goes" if args.pace is None else f"{args.pace:g} x real time"
    print(f"playing {len(args.files)} file(s) on {where}, {pace}{', looping' if args.loop else ''}", flush=True)
    try:
        done = play(args.files, publish, args.pace, args.loop, stopper.wait, bad)
    finally:
        publish.close()
        session.close()
    span = (done.last_ns - done.first_ns) / 1e9 if done.published else 0.0
    print(f"done: {done.published} messages of site {done.site} ({span:.1f} s of capture time, {done.passes} passes), "
          f"{done.bad} bad lines", flush=True)
    return 0
