"""A connected vehicle's listener that needs nothing of this project: only `eclipse-zenoh` and `msgpack`.

    pip install eclipse-zenoh msgpack
    python vehicle_listener.py --site state_ellsworth --connect tcp/192.168.1.10:7447
    python vehicle_listener.py --site state_ellsworth --connect tls/cabinet.example:7448 --ca cabinet-ca.pem
    python vehicle_listener.py ... --ca cabinet-ca.pem --cert vehicle.pem --key vehicle.key   # mutual TLS

It reads the cabinet's tracks as docs/wire-format.md specifies them, and is that document's worked example in
code: a vehicle written in another language (C++, Rust, ...) does the same steps with its own Zenoh and msgpack
libraries. It asks for the newest Tracks message first (a vehicle that joins late gets the current tracks at once),
then prints one JSON line per message: `{"site", "seq", "t_capture_ns", "tracker", "tracks": [{"id", "x", "y",
"lat", "lon", "vx", "vy", "yaw", "length", "width", "height", "type", "score", "age", "hits", "cameras", "xy_cov",
"velocity_cov", "yaw_confirmed", "yaw_std", "err95_m"}, ...]}` (`err95_m`: the longest half-axis of the ellipse that
holds the vehicle's true position with 95 % probability, from `xy_cov`; `yaw_confirmed` false: the vehicle has not
been seen travelling, and its `yaw` may point backwards; `yaw_std`: how far off, 1 sigma in rad, the heading's axis
may be).
With `--ahead-ms MS` each message is moved on MS milliseconds past its capture time first (`move_on`: where the
vehicles are by the time a vehicle with that link delay uses them; docs/wire-format.md, "Where a vehicle is now"),
and says so in `t_ns`.
A message it cannot read is reported on stderr with the reason and skipped. (Inside the project,
`shared.client.TrackClient` and `roadside tracks` do the same with the project's own codec.)
"""

from __future__ import annotations

import argparse
import json
import math
import struct
import sys
import time

import msgpack

SCHEMA_VERSION = 4
VEHICLE_TYPES = ("car", "suv_van", "truck", "bus", "motorcycle")  # vtype indexes this list
# dtype on the wire -> struct format character (all little-endian, "<" below)
STRUCT_FORMATS = {"<f8": "d", "<f4": "f", "<i8": "q", "<i4": "i", "<u4": "I", "<i2": "h", "<u2": "H", "|i1": "b",
                  "|u1": "B", "|b1": "?"}
# the per-track columns of a Tracks message: field -> (dtype, shape of one track's values)
TRACK_COLUMNS = {"id": ("<i8", ()), "xy": ("<f8", (2,)), "latlon": ("<f8", (2,)), "velocity": ("<f4", (2,)),
                 "yaw": ("<f4", ()), "size_lwh": ("<f4", (3,)), "vtype": ("|i1", ()), "score": ("<f4", ()),
                 "age": ("<i4", ()), "hits": ("<i4", ()), "xy_cov": ("<f4", (2, 2)), "velocity_cov": ("<f4", (2, 2)),
                 "yaw_confirmed": ("|b1", ()), "yaw_std": ("<f4", ())}
CHI2_2DOF_95 = 5.991  # a 2D Gaussian's 95 % ellipse: squared Mahalanobis distance within this
ACCEL_STD_MPS2 = 1.5  # moving tracks on: the acceleration their velocities leave unknown (docs/wire-format.md)
WGS84_A, WGS84_E2 = 6378137.0, 0.00669437999014  # the ellipsoid's semi-major axis (m), first eccentricity squared
# a message of the tracker printed last, captured this much before the last one: a recording played again
# (docs/wire-format.md, "Order"; shared.client.TrackClient's rule)
REPLAYED_NS = 5 * 10**9


class BadMessage(ValueError):
    """A payload that is not a Tracks message of this schema version; the text says why."""


def column(msg: dict, field: str) -> list[tuple]:
    """One per-track column of a decoded Tracks map: a list of N tuples of its values per track."""
    dtype, per_track = TRACK_COLUMNS[field]
    width = math.prod(per_track)
    arr = msg.get(field)
    if not isinstance(arr, dict) or set(arr) != {"dtype", "shape", "data"}:
        raise BadMessage(f"field {field!r}: expected an array map {{dtype, shape, data}}, got {arr!r:.80}")
    if arr["dtype"] != dtype:
        raise BadMessage(f"field {field!r}: dtype {arr['dtype']!r}, this listener reads {dtype!r}")
    shape = arr["shape"]
    expected = list(per_track)
    if not (isinstance(shape, list) and len(shape) == 1 + len(expected) and shape[1:] == expected
            and type(shape[0]) is int and shape[0] >= 0):
        raise BadMessage(f"field {field!r}: shape {shape}, expected [N{''.join(f', {k}' for k in expected)}]")
    data = arr["data"]
    if not isinstance(data, bytes):
        raise BadMessage(f"field {field!r}: data must be bytes (msgpack bin), got {type(data).__name__}")
    fmt = "<" + STRUCT_FORMATS[dtype] * width
    if len(data) != shape[0] * struct.calcsize(fmt):
        raise BadMessage(f"field {field!r}: {len(data)} bytes for shape {shape} of {dtype}")
    return list(struct.iter_unpack(fmt, data))


def decode_tracks(payload: bytes) -> dict:
    """A Tracks payload (msgpack bytes) -> a plain dict with one row per track (module docstring)."""
    try:
        msg = msgpack.unpackb(payload, raw=False)
    except Exception as exc:  # msgpack raises several unrelated types for garbage
        raise BadMessage(f"not msgpack ({type(exc).__name__}: {exc})") from None
    if not isinstance(msg, dict) or msg.get("kind") != "tracks":
        raise BadMessage(f"not a Tracks message (kind {msg.get('kind') if isinstance(msg, dict) else None!r})")
    if msg.get("v") != SCHEMA_VERSION:
        raise BadMessage(f"schema version {msg.get('v')!r}; this listener reads v{SCHEMA_VERSION}")
    missing = [f for f in ("site", "seq", "t_capture_ns", "cameras") if f not in msg]
    if missing:
        raise BadMessage(f"fields missing: {', '.join(missing)}")
    for field in ("seq", "t_capture_ns"):
        if type(msg[field]) is not int or msg[field] < 0:  # bool is not an int here
            raise BadMessage(f"field {field!r}: expected an integer >= 0, got {msg[field]!r:.80}")
    for field in ("site", "tracker"):
        if not isinstance(msg.get(field, ""), str):
            raise BadMessage(f"field {field!r}: expected a string, got {msg[field]!r:.80}")
    cols = {field: column(msg, field) for field in TRACK_COLUMNS}
    for field, (dtype, _) in TRACK_COLUMNS.items():
        if dtype.startswith("<f") and not all(math.isfinite(v) for row in cols[field] for v in row):
            raise BadMessage(f"field {field!r}: NaN or infinite values")
    for field in ("xy_cov", "velocity_cov"):  # the contract's covariances: symmetric, positive definite
        for i, (a, b, c, d) in enumerate(cols[field]):
            if not (a > 0 and a * d > b * c and b == c):
                raise BadMessage(f"field {field!r}: track {i} has {[[a, b], [c, d]]}, not a symmetric positive "
                                 "definite covariance")
    if not all(s > 0 for (s,) in cols["yaw_std"]):
        raise BadMessage("field 'yaw_std': a value not > 0")
    n = len(cols["id"])
    cameras = msg["cameras"]
    if not (isinstance(cameras, list) and all(isinstance(c, list) and all(isinstance(s, str) for s in c)
                                              for c in cameras)):
        raise BadMessage("field 'cameras': expected a list of lists of camera names")
    lengths = {**{f: len(c) for f, c in cols.items()}, "cameras": len(cameras)}
    if any(k != n for k in lengths.values()):
        raise BadMessage(f"fields of different lengths: {lengths}")
    tracks = []
    for i in range(n):
        (x, y), (lat, lon), (vx, vy), (length, width, height) = (
            cols["xy"][i], cols["latlon"][i], cols["velocity"][i], cols["size_lwh"][i])
        vtype = cols["vtype"][i][0]
        see, sen, sne, snn = cols["xy_cov"][i]  # variance east, covariance east-north (twice), variance north, m^2
        largest = (see + snn) / 2 + math.sqrt(((see - snn) / 2) ** 2 + sen * sne)  # the larger eigenvalue
        tracks.append({"id": cols["id"][i][0], "x": x, "y": y, "lat": lat, "lon": lon, "vx": vx, "vy": vy,
                       "yaw": cols["yaw"][i][0], "length": length, "width": width, "height": height,
                       "type": VEHICLE_TYPES[vtype] if 0 <= vtype < len(VEHICLE_TYPES) else "unknown",
                       "score": cols["score"][i][0], "age": cols["age"][i][0], "hits": cols["hits"][i][0],
                       "cameras": cameras[i], "xy_cov": [[see, sen], [sne, snn]],
                       "velocity_cov": [list(cols["velocity_cov"][i][:2]), list(cols["velocity_cov"][i][2:])],
                       "yaw_confirmed": cols["yaw_confirmed"][i][0], "yaw_std": cols["yaw_std"][i][0],
                       "err95_m": math.sqrt(CHI2_2DOF_95 * largest)})
    return {"site": msg["site"], "seq": msg["seq"], "t_capture_ns": msg["t_capture_ns"],
            "tracker": msg.get("tracker", ""), "tracks": tracks}


def seen(msg: dict, last: tuple[str, int, int] | None) -> bool:
    """Whether a decoded message is one to skip: of the tracker of the message used last (`last`: its tracker, seq,
    t_capture_ns) with a seq not above its seq, a duplicate or stale, unless it was captured more than REPLAYED_NS
    before it: then the same recording is played again (`roadside play`: the tracker's seq starts at 0 again)."""
    return (last is not None and msg["tracker"] == last[0] and msg["seq"] <= last[1]
            and msg["t_capture_ns"] >= last[2] - REPLAYED_NS)


def move_on(msg: dict, dt_s: float) -> dict:
    """A decoded message's tracks moved on `dt_s` seconds at their velocities, their uncertainty grown to match
    and latitude and longitude moved with them (docs/wire-format.md, "Where a vehicle is now"); `t_ns` is the time
    the moved positions hold for."""
    grow, grow_v = (ACCEL_STD_MPS2 * dt_s * dt_s / 2) ** 2, (ACCEL_STD_MPS2 * dt_s) ** 2
    tracks = []
    for t in msg["tracks"]:
        east, north = t["vx"] * dt_s, t["vy"] * dt_s
        sin_lat = math.sin(math.radians(t["lat"]))
        n = WGS84_A / math.sqrt(1 - WGS84_E2 * sin_lat**2)  # radii of curvature: prime vertical, meridian
        m = n * (1 - WGS84_E2) / (1 - WGS84_E2 * sin_lat**2)
        (a, b), (_, c) = t["xy_cov"]
        (va, vb), (_, vc) = t["velocity_cov"]
        cov = [[a + dt_s * dt_s * va + grow, b + dt_s * dt_s * vb], [b + dt_s * dt_s * vb, c + dt_s * dt_s * vc + grow]]
        largest = (cov[0][0] + cov[1][1]) / 2 + math.sqrt(((cov[0][0] - cov[1][1]) / 2) ** 2 + cov[0][1] ** 2)
        tracks.append({**t, "x": t["x"] + east, "y": t["y"] + north, "lat": t["lat"] + math.degrees(north / m),
                       "lon": t["lon"] + math.degrees(east / (n * math.cos(math.radians(t["lat"])))), "xy_cov": cov,
                       "velocity_cov": [[va + grow_v, vb], [vb, vc + grow_v]],
                       "err95_m": math.sqrt(CHI2_2DOF_95 * largest)})
    return {**msg, "t_ns": msg["t_capture_ns"] + round(dt_s * 1e9), "tracks": tracks}


def listen(site: str, connect: str, count: int, timeout_s: float, wait_s: float, ca: str | None = None,
           ahead_ms: float = 0.0, cert: str | None = None, key: str | None = None) -> int:
    """Print the newest tracks, then every new message, as JSON lines; returns how many were printed."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", '"client"')
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("connect/timeout_ms", json.dumps(max(1, round(wait_s * 1000))))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if ca:  # a tls/ endpoint: the cabinet's certificate must chain to this CA
        conf.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(ca))
    if cert:  # a cabinet that lets only enrolled vehicles in (mutual TLS): this vehicle's certificate and key
        conf.insert_json5("transport/link/tls/enable_mtls", "true")
        conf.insert_json5("transport/link/tls/connect_certificate", json.dumps(cert))
        conf.insert_json5("transport/link/tls/connect_private_key", json.dumps(key))
    printed, last = 0, None  # last: (tracker, seq, t_capture_ns) of the newest message printed

    def show(payload: bytes) -> bool:
        nonlocal printed, last
        try:
            msg = decode_tracks(payload)
        except BadMessage as exc:
            print(f"skipped a message: {exc}", file=sys.stderr, flush=True)
            return False
        if seen(msg, last):
            return False  # already printed (the answer to the query may also arrive on the subscription)
        last = (msg["tracker"], msg["seq"], msg["t_capture_ns"])
        print(json.dumps(move_on(msg, ahead_ms / 1000) if ahead_ms else msg), flush=True)
        printed += 1
        return True

    with zenoh.open(conf) as session:
        subscriber = session.declare_subscriber(f"roadside/{site}/tracks")  # before the query: nothing is missed
        for reply in session.get(f"roadside/{site}/tracks/latest", timeout=2.0):
            if reply.ok is not None:
                show(reply.ok.payload.to_bytes())
        if not printed:  # no tracks of this site: which sites are on the bus? (their services' liveliness tokens)
            sites = {str(r.ok.key_expr).split("/")[1] for r in session.liveliness().get("roadside/*/alive/**",
                                                                                         timeout=1.0) if r.ok}
            if sites - {site}:
                print(f"no tracks of site {site} on this bus; it has {', '.join(sorted(sites - {site}))} (--site)",
                      file=sys.stderr, flush=True)
        quiet_since = time.monotonic()
        while not (count and printed >= count):
            sample = subscriber.try_recv()
            if sample is None:
                if time.monotonic() - quiet_since > timeout_s:
                    break
                time.sleep(0.02)
                continue
            if show(sample.payload.to_bytes()):
                quiet_since = time.monotonic()
    return printed


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--site", required=True, help="the site's name (site.yaml's `site`)")
    p.add_argument("--connect", required=True, help="the cabinet's Zenoh router, e.g. tcp/192.168.1.10:7447")
    p.add_argument("--count", type=int, default=0, help="stop after this many messages (default: never)")
    p.add_argument("--timeout", type=float, default=math.inf, help="stop after this many seconds without tracks")
    p.add_argument("--wait", type=float, default=10.0, help="seconds to wait for the first connection")
    p.add_argument("--ca", help="with --connect tls/HOST:7448: the cabinet's CA certificate (PEM)")
    p.add_argument("--ahead-ms", type=float, default=0.0,
                   help="move each message's tracks on this long past their capture time (your link's delay)")
    p.add_argument("--cert", help="with --key, for a cabinet that lets only enrolled vehicles in (mutual TLS): "
                   "this vehicle's certificate (PEM)")
    p.add_argument("--key", help="the private key of --cert (PEM)")
    args = p.parse_args(argv)
    if not 0 <= args.ahead_ms <= 2000:
        p.error(f"--ahead-ms must be from 0 to 2000, got {args.ahead_ms}")
    if (args.cert is None) != (args.key is None):
        p.error("--cert and --key go together")
    try:
        printed = listen(args.site, args.connect, args.count, args.timeout, args.wait, args.ca, args.ahead_ms,
                         args.cert, args.key)
    except KeyboardInterrupt:  # Ctrl-C: the way to stop a listener without --count or --timeout
        return 0
    except Exception as exc:  # no router in reach, a malformed endpoint: one line, not a traceback
        print(f"vehicle_listener: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    return 0 if printed else 1


if __name__ == "__main__":
    sys.exit(main())
