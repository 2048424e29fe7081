"""The cabinet deployment: compose.yaml, deploy/Dockerfile, the Zenoh router config and the example site.

No Docker engine is needed: the files are parsed and checked against each other, the Compose
Specification schema (when shared/ has it) and the code they start (services, settings, bus).
"""

from __future__ import annotations

import json
import os
import re
import tomllib
from pathlib import Path

import pytest
import yaml

from shared.keys import SERVICES
from shared.settings import BusSettings, load_settings

ROOT = Path(__file__).resolve().parents[1]
COMPOSE = ROOT / "compose.yaml"
DOCKERFILE = ROOT / "deploy" / "Dockerfile"
ROUTER_CONFIG = ROOT / "deploy" / "zenoh" / "router.json5"
EXAMPLE_SITE = ROOT / "deploy" / "sites" / "example" / "site.yaml"
COMPOSE_SCHEMA = ROOT.parent / "shared" / "schemas" / "compose-spec.json"
ROUTER = "zenoh"
ROUTER_PORT = 7447
SERVICE_ENDPOINT = "unixsock-stream//run/zenoh/cabinet.sock"  # the services' way in: a socket on a shared volume
SITE_FILE = "/site/site.yaml"
METRICS = "metrics"  # the services' Prometheus metrics (`roadside metrics`)
COUNTS = "counts"  # the junction's turning-movement counts (`roadside counts --live`), under its profile
METRICS_PORT = 9464


# --- helpers -------------------------------------------------------------------------------------


def _compose() -> dict:
    return yaml.safe_load(COMPOSE.read_text())


def _interpolate(value: str, env: dict[str, str] | None = None) -> str:
    """Compose variable interpolation (`${VAR}`, `${VAR:-default}`, `${VAR-default}`, `$$`)."""
    env = {} if env is None else env

    def sub(m: re.Match) -> str:
        name, op, default = m.group(1), m.group(2), m.group(3) or ""
        if op == ":-":
            return env.get(name) or default
        if op == "-":
            return env.get(name, default)
        return env.get(name, "")

    value = re.sub(r"(?<!\$)\$\{([A-Za-z_][A-Za-z0-9_]*)(?:(:-|-)([^}]*))?\}", sub, value)
    return value.replace("$$", "$")


def _service_env(service: dict) -> dict[str, str]:
    env = service.get("environment", {})
    if isinstance(env, list):  # the list form KEY=VALUE
        env = dict(item.split("=", 1) for item in env)
    return {k: _interpolate(str(v)) for k, v in env.items()}


def _json5_loads(text: str):
    """The JSON5 subset config files use: comments, unquoted keys, single quotes, trailing commas."""
    try:
        import json5  # optional; the fallback below covers what the router config uses

        return json5.loads(text)
    except ImportError:
        pass
    parts: list[str] = []
    code: list[str] = []  # the current stretch outside strings, comments dropped

    def flush() -> None:
        seg = "".join(code)
        seg = re.sub(r"([A-Za-z_$][\w$]*)(\s*):", r'"\1"\2:', seg)  # bare keys
        seg = re.sub(r",(\s*[}\]])", r"\1", seg)  # trailing commas
        parts.append(seg)
        code.clear()

    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c in "\"'":
            j = i + 1
            while text[j] != c:
                j += 2 if text[j] == "\\" else 1
            flush()
            parts.append(text[i : j + 1] if c == '"' else json.dumps(text[i + 1 : j]))
            i = j + 1
        elif text.startswith("//", i):
            end = text.find("\n", i)
            i = n if end < 0 else end
        elif text.startswith("/*", i):
            i = text.index("*/", i) + 2
        else:
            code.append(c)
            i += 1
    flush()
    return json.loads("".join(parts))


def _dockerfile_stages() -> dict[str, dict]:
    """Stage name -> {"base": image or stage, "lines": [(INSTRUCTION, args)]}; comments and line
    continuations resolved, global ARG defaults substituted into FROM."""
    logical: list[str] = []
    buf = ""
    for raw in DOCKERFILE.read_text().splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        if line.endswith("\\"):
            buf += line[:-1] + " "
            continue
        logical.append(buf + line)
        buf = ""
    if buf:
        logical.append(buf)
    global_args: dict[str, str] = {}
    stages: dict[str, dict] = {}
    current = None
    for line in logical:
        instr, _, args = line.partition(" ")
        instr, args = instr.upper(), args.strip()
        if instr == "FROM":
            m = re.match(r"(?:--platform=\S+\s+)?(\S+)(?:\s+AS\s+(\S+))?$", args, re.I)
            assert m, f"cannot parse FROM {args!r}"
            base = re.sub(r"\$\{?(\w+)\}?", lambda a: global_args.get(a.group(1), a.group(0)), m.group(1))
            name = m.group(2) or f"stage{len(stages)}"
            current = stages[name] = {"base": base, "lines": []}
        elif current is None:
            if instr == "ARG" and "=" in args:
                key, _, value = args.partition("=")
                global_args[key.strip()] = value.strip()
        else:
            current["lines"].append((instr, args))
    return stages


def _stage_chain(stages: dict[str, dict], name: str) -> list[str]:
    """A stage and every stage it builds on or copies from."""
    seen: list[str] = []
    todo = [name]
    while todo:
        s = todo.pop()
        if s in seen or s not in stages:
            continue
        seen.append(s)
        todo.append(stages[s]["base"])
        for instr, args in stages[s]["lines"]:
            m = re.search(r"--from=(\S+)", args)
            if instr == "COPY" and m:
                todo.append(m.group(1))
    return seen


def _app_services(doc: dict) -> dict[str, dict]:
    return {name: svc for name, svc in doc["services"].items() if name != ROUTER}


# --- the Compose Specification -------------------------------------------------------------------


def test_compose_file_matches_the_compose_specification():
    if not COMPOSE_SCHEMA.is_file():
        pytest.skip(f"Compose Specification schema not found at {COMPOSE_SCHEMA} (a clean clone has no ../shared)")
    jsonschema = pytest.importorskip("jsonschema", reason="jsonschema is not installed (pip install jsonschema)")
    schema = json.loads(COMPOSE_SCHEMA.read_text())
    validator = jsonschema.Draft7Validator(schema)
    doc = _compose()
    errors = [f"{'/'.join(map(str, e.absolute_path))}: {e.message}" for e in validator.iter_errors(doc)]
    assert not errors, "\n".join(errors)
    # The schema does catch a mistake (it is not silently accepting everything).
    doc["services"]["ingest"]["restart_policy"] = "always"
    assert not validator.is_valid(doc)


# --- compose.yaml --------------------------------------------------------------------------------


def test_compose_has_the_router_the_four_services_their_metrics_and_the_counts():
    services = _compose()["services"]
    assert set(services) == {ROUTER, *SERVICES, METRICS, COUNTS}
    assert [name for name, svc in services.items() if "profiles" in svc] == [COUNTS]  # opt-in: it needs movements:


@pytest.mark.parametrize("name", SERVICES)
def test_each_service_runs_its_module_on_the_mounted_site_file(name):
    svc = _compose()["services"][name]
    assert svc["command"] == ["python", "-m", f"services.{name}", "--site", SITE_FILE]


def test_detect_reserves_an_nvidia_gpu_and_the_others_do_not():
    doc = _compose()
    devices = doc["services"]["detect"]["deploy"]["resources"]["reservations"]["devices"]
    assert devices == [{"driver": "nvidia", "count": 1, "capabilities": ["gpu"]}]
    for name, svc in doc["services"].items():
        if name != "detect":
            assert "deploy" not in svc, f"{name} reserves devices"


def test_every_service_restarts_and_has_a_healthcheck():
    doc = _compose()
    for name, svc in doc["services"].items():
        assert svc.get("restart") == "unless-stopped", name
        hc = svc.get("healthcheck")
        assert hc and hc.get("test") and not hc.get("disable"), f"{name} has no healthcheck"
        for key in ("interval", "timeout", "retries"):
            assert key in hc, f"{name} healthcheck has no {key}"
    for name in SERVICES:
        assert doc["services"][name]["healthcheck"]["test"] == [
            "CMD", "roadside", "health", "--site", SITE_FILE, "--service", name]
    router_test = " ".join(doc["services"][ROUTER]["healthcheck"]["test"])
    assert str(ROUTER_PORT) in router_test


def _bytes(size: str) -> int:
    """A Compose byte value ("512m", "4g", "256k", or a plain number of bytes) in bytes."""
    m = re.fullmatch(r"(\d+)([bkmg]?)", str(size).lower())
    assert m, f"not a Compose byte value: {size!r}"
    return int(m.group(1)) * 1024 ** "bkmg".index(m.group(2) or "b")


def test_every_service_has_a_memory_limit_well_above_its_budget():
    """A leaking service is killed and restarted at its limit, not let starve the cabinet; the limit leaves room above
    the issue's budget (150 MB resident for each service, 600 MB for detect): twice it at least."""
    doc = _compose()
    for name, svc in doc["services"].items():
        assert "mem_limit" in svc, f"{name} has no mem_limit"
    for name in SERVICES:
        assert _bytes(doc["services"][name]["mem_limit"]) >= 2 * (600 if name == "detect" else 150) * 2**20, name
    assert _bytes("512m") == 512 * 2**20 and _bytes(1024) == 1024


def test_every_service_waits_for_a_healthy_router():
    doc = _compose()
    for name, svc in _app_services(doc).items():
        deps = svc.get("depends_on")
        assert isinstance(deps, dict) and ROUTER in deps, f"{name} does not depend on {ROUTER}"
        assert deps[ROUTER]["condition"] == "service_healthy", name


def test_router_is_a_pinned_zenoh_1x_image_with_the_config_mounted_and_port_published():
    router = _compose()["services"][ROUTER]
    assert re.fullmatch(r"eclipse/zenoh:1\.\d+\.\d+", router["image"]), router["image"]
    mounts = {}
    for v in router["volumes"]:
        src, dst, *mode = v.split(":")
        mounts[dst] = (src, mode)
    command = router["command"]
    config_path = command[command.index("--config") + 1]
    assert config_path in mounts, f"{config_path} is not mounted"
    src, mode = mounts[config_path]
    assert (ROOT / src).resolve() == ROUTER_CONFIG.resolve() and mode == ["ro"]
    published = [str(p) for p in router["ports"]]
    assert f"{ROUTER_PORT}:{ROUTER_PORT}" in published


def test_services_reach_the_router_in_client_mode():
    doc = _compose()
    for name, svc in _app_services(doc).items():
        env = _service_env(svc)
        assert env["ROADSIDE_BUS__MODE"] == "client", name
        assert json.loads(env["ROADSIDE_BUS__CONNECT"]) == [SERVICE_ENDPOINT], name


def test_the_services_socket_is_on_a_volume_of_the_router_and_every_service_and_the_router_listens_on_it():
    doc = _compose()
    folder = SERVICE_ENDPOINT.removeprefix("unixsock-stream/").rsplit("/", 1)[0]
    volumes = set()
    for name, svc in doc["services"].items():
        mounted = [v.split(":")[0] for v in svc["volumes"] if v.split(":")[1] == folder]
        assert len(mounted) == 1, f"{name} does not mount {folder}"
        volumes.add(mounted[0])
    assert len(volumes) == 1 and volumes <= set(doc["volumes"]), volumes  # one named volume, shared
    assert SERVICE_ENDPOINT in _json5_loads(ROUTER_CONFIG.read_text())["listen"]["endpoints"]


def test_the_router_lets_the_socket_do_everything_and_the_network_read_tracks_liveliness_and_status():
    acl = _json5_loads(ROUTER_CONFIG.read_text())["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    protocols = {s["id"]: s["link_protocols"] for s in acl["subjects"]}
    rules = {r["id"]: r for r in acl["rules"]}
    allowed = {}
    for policy in acl["policies"]:
        for subject in policy["subjects"]:
            for rule in policy["rules"]:
                assert rules[rule]["permission"] == "allow"
                for proto in protocols[subject]:
                    allowed.setdefault(proto, []).append(rules[rule])
    assert set(allowed) == {"unixsock-stream", "tcp", "tls"}
    assert all(k == "roadside/**" for r in allowed["unixsock-stream"] for k in r["key_exprs"])
    assert allowed["tls"] == allowed["tcp"]  # a vehicle over TLS may read what one over TCP may, no more
    network_keys = {k for r in allowed["tcp"] for k in r["key_exprs"]}
    assert network_keys == {"roadside/*/tracks", "roadside/*/tracks/latest", "roadside/*/alive/**",
                            "roadside/*/status/**"}
    ingress = {m for r in allowed["tcp"] if "ingress" in r["flows"] for m in r["messages"]}
    assert not ingress & {"put", "delete", "declare_queryable", "reply", "liveliness_token"}, ingress


def test_site_folder_is_chosen_by_SITE_and_mounted_read_only():
    doc = _compose()
    for name, svc in _app_services(doc).items():
        site_mounts = [v for v in svc["volumes"] if v.endswith(":/site:ro")]
        assert len(site_mounts) == 1, f"{name}: no read-only /site mount"
        src = site_mounts[0].removesuffix(":/site:ro")
        assert "${SITE" in src, f"{name}: the site folder is not taken from $SITE"
        assert (ROOT / _interpolate(src) / "site.yaml").is_file(), "the default site folder has no site.yaml"
        assert _interpolate(src, {"SITE": "/srv/sites/elm"}) == "/srv/sites/elm"


def test_fuse_track_records_tracks_to_a_writable_volume():
    doc = _compose()
    svc = doc["services"]["fuse_track"]
    data = [v for v in svc["volumes"] if v.split(":")[1:2] == ["/data"]]
    assert data and not data[0].endswith(":ro")
    volume = data[0].split(":")[0]
    assert volume in doc.get("volumes", {}), f"named volume {volume!r} is not declared"
    assert _service_env(svc)["ROADSIDE_FUSE_TRACK__RECORD"] == "/data/tracks.jsonl"
    assert float(_service_env(svc)["ROADSIDE_FUSE_TRACK__RECORD_ROTATE_MB"]) > 0, "a volume that fills for ever"


def test_common_parts_come_from_an_extension_anchor():
    text = COMPOSE.read_text()
    doc = _compose()
    anchors = [k for k in doc if k.startswith("x-")]
    assert anchors, "no x- extension field"
    assert len(re.findall(r"<<: \*roadside-service", text)) == len(SERVICES) + 2  # and the metrics and counts


def _parsed_in_its_environment(svc: dict, add_jobs, monkeypatch):
    """A `roadside` service's command line parsed (the example site for /site) with its compose environment set
    and nothing else of ROADSIDE_'s."""
    import argparse

    for key in [k for k in os.environ if k.startswith("ROADSIDE_")]:
        monkeypatch.delenv(key)
    for key, value in _service_env(svc).items():
        monkeypatch.setenv(key, value)
    parser = argparse.ArgumentParser()
    add_jobs(parser.add_subparsers(dest="job"))
    return parser.parse_args([str(EXAMPLE_SITE) if a == SITE_FILE else a for a in svc["command"][1:]])


def test_the_metrics_serve_the_sites_services_through_the_router_on_a_published_port(monkeypatch):
    """The metrics service asks the site of the mounted site.yaml through the router's socket (its compose
    environment, as the four services'), serves every interface inside its container on the published port, and its
    healthcheck scrapes that port."""

    from roadside.cli_bus import _bus, _site, add_bus_jobs

    svc = _compose()["services"][METRICS]
    assert svc["command"][:2] == ["roadside", "metrics"]
    args = _parsed_in_its_environment(svc, add_bus_jobs, monkeypatch)
    assert (args.host, args.port) == ("0.0.0.0", METRICS_PORT)
    _site(args)
    bus = _bus(args)
    assert args.site == load_settings(EXAMPLE_SITE).site
    assert bus.mode == "client" and bus.connect == [SERVICE_ENDPOINT] and bus.listen == []
    published = [_interpolate(str(p)) for p in svc["ports"]]
    assert published == [f"{METRICS_PORT}:{METRICS_PORT}"]
    assert _interpolate(str(svc["ports"][0]), {"METRICS_PORT": "127.0.0.1:9999"}) == f"127.0.0.1:9999:{METRICS_PORT}"
    assert f"http://127.0.0.1:{METRICS_PORT}/metrics" in " ".join(svc["healthcheck"]["test"])


def test_the_counts_append_the_example_sites_junction_to_a_volume_through_the_router(monkeypatch, tmp_path):
    """The counts service counts the live tracks of the mounted site's junction through the router's socket and
    appends its CSV to a named volume of its own; its healthcheck reads the age of the file it touches as tracks
    arrive."""

    from roadside.cli import _add_counts
    from roadside.cli_bus import asking_bus

    doc = _compose()
    svc = doc["services"][COUNTS]
    assert svc["profiles"] == [COUNTS] and svc["command"][:3] == ["roadside", "counts", "--live"]
    args = _parsed_in_its_environment(svc, _add_counts, monkeypatch)
    settings = load_settings(args.site)
    assert settings.movements is not None and len(settings.movements.junction().names) >= 3
    bus = asking_bus(settings.bus)
    assert bus.mode == "client" and bus.connect == [SERVICE_ENDPOINT]
    data = {v.split(":")[1]: v.split(":")[0] for v in svc["volumes"]}
    assert args.out.parent.as_posix() in data and data[args.out.parent.as_posix()] in doc["volumes"]
    assert data[args.out.parent.as_posix()] != "tracks"  # its own volume: fuse_track's rotation never touches it
    assert args.heartbeat.as_posix() in " ".join(svc["healthcheck"]["test"])  # counting: tracks arrive


@pytest.mark.parametrize("name", SERVICES)
def test_compose_environment_gives_valid_settings_for_the_example_site(name, monkeypatch):
    """Each service's compose environment on top of the example site builds its settings and its
    Zenoh configuration (client mode, connected to the router)."""
    from shared.bus import zenoh_config

    for key in [k for k in os.environ if k.startswith("ROADSIDE_")]:
        monkeypatch.delenv(key)
    for key, value in _service_env(_compose()["services"][name]).items():
        monkeypatch.setenv(key, value)
    s = load_settings(EXAMPLE_SITE)
    assert s.bus.mode == "client"
    assert s.bus.connect == [SERVICE_ENDPOINT]
    zenoh_config(s.bus, name)
    if name == "detect":
        assert s.detect.model.is_absolute() and s.detect.providers
    if name == "fuse_track":
        assert s.fuse_track.record == Path("/data/tracks.jsonl")
        assert (s.fuse_track.record_rotate_mb, s.fuse_track.record_keep) == (256, 40)


# --- deploy/Dockerfile ---------------------------------------------------------------------------


def _targets(doc: dict) -> dict[str, str]:
    out = {}
    for name, svc in _app_services(doc).items():
        build = svc["build"]
        assert (ROOT / build.get("context", ".") / build["dockerfile"]).resolve() == DOCKERFILE.resolve(), name
        out[name] = build["target"]
    return out


def test_dockerfile_has_the_stages_compose_targets():
    stages = _dockerfile_stages()
    targets = _targets(_compose())
    assert set(targets) == {*SERVICES, METRICS, COUNTS}
    missing = {name: t for name, t in targets.items() if t not in stages}
    assert not missing, f"stages not in deploy/Dockerfile: {missing}"
    assert targets["detect"] != targets["ingest"], "detect should use the GPU stage"
    assert len({targets[s] for s in (*SERVICES, METRICS) if s != "detect"}) == 1, "the CPU services share one stage"


def test_runtime_images_never_install_torch_or_the_train_extra():
    deps = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["dependencies"]
    assert not [d for d in deps if d.lower().startswith("torch")], "torch is a core dependency"
    stages = _dockerfile_stages()
    for target in set(_targets(_compose()).values()):
        for stage in _stage_chain(stages, target):
            for instr, args in stages[stage]["lines"]:
                line = f"{instr} {args}"
                assert not re.search(r"torch", line, re.I), f"{stage}: {line}"
                assert not re.search(r"\btrain\b", line), f"{stage}: {line}"
                assert not re.search(r"pip install[^&;]*\s\.\[", line), f"{stage} installs extras: {line}"


def test_cpu_stage_is_python_slim_and_gpu_stage_is_cuda_with_onnxruntime_gpu():
    stages = _dockerfile_stages()
    targets = _targets(_compose())

    def chain_text(target: str) -> str:
        return "\n".join(f"{i} {a}" for s in _stage_chain(stages, target) for i, a in stages[s]["lines"])

    def base_image(target: str) -> str:
        base = stages[target]["base"]
        while base in stages:
            base = stages[base]["base"]
        return base

    assert base_image(targets["ingest"]) == "python:3.11-slim"
    assert re.fullmatch(r"nvidia/cuda:[\d.]+-cudnn\d*-runtime-ubuntu[\d.]+", base_image(targets["detect"]))
    gpu = chain_text(targets["detect"])
    assert "onnxruntime-gpu" in gpu
    # The package goes in with --no-deps: its own dependencies would bring the CPU onnxruntime back.
    installs = [c.strip() for c in re.split(r"&&|;|\n", gpu) if re.match(r"\s*(RUN\s+)?pip install", c)]
    package_installs = [c for c in installs if re.search(r"\s\.(\s|$)", c)]
    assert package_installs and all("--no-deps" in c for c in package_installs), package_installs
    assert "onnxruntime-gpu" not in chain_text(targets["ingest"])


@pytest.mark.parametrize("kind", ["cpu", "gpu"])
def test_images_run_as_an_unprivileged_user_with_the_models(kind):
    stages = _dockerfile_stages()
    targets = _targets(_compose())
    target = targets["detect"] if kind == "gpu" else targets["ingest"]
    lines = stages[target]["lines"]
    users = [a for i, a in lines if i == "USER"]
    assert users and users[-1].split(":")[0] not in ("root", "0"), f"{target} runs as root"
    assert any(i == "COPY" and a.split()[0].rstrip("/") == "models" for i, a in lines), f"{target}: no models/"


def test_dockerfile_copies_every_package_the_project_installs():
    includes = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    packages = {p.rstrip("*").rstrip(".") for p in includes}
    stages = _dockerfile_stages()
    for target in set(_targets(_compose()).values()):
        copied = {
            a.split()[0].rstrip("/")
            for s in _stage_chain(stages, target)
            for i, a in stages[s]["lines"]
            if i == "COPY" and not a.startswith("--")
        }
        assert packages <= copied, f"{target}: not copied: {sorted(packages - copied)}"


# --- deploy/zenoh/router.json5 -------------------------------------------------------------------


def test_json5_helper_reads_comments_bare_keys_and_trailing_commas():
    text = "// c\n{a: 'x//y', /* c */ b: [1, 2,], \"c\": {d: true,}, // d\n}"
    assert _json5_loads(text) == {"a": "x//y", "b": [1, 2], "c": {"d": True}}


def test_router_config_is_a_router_listening_on_7447_without_multicast():
    conf = _json5_loads(ROUTER_CONFIG.read_text())
    assert conf["mode"] == "router"
    endpoints = conf["listen"]["endpoints"]
    assert any(re.fullmatch(rf"tcp/.+:{ROUTER_PORT}", e) for e in endpoints), endpoints
    assert conf["scouting"]["multicast"]["enabled"] is False
    assert "rest" not in conf.get("plugins", {})


def test_router_config_is_accepted_by_zenoh():
    import zenoh

    conf = zenoh.Config.from_file(str(ROUTER_CONFIG))  # unknown keys or bad values raise
    assert json.loads(conf.get_json("mode")) == "router"


def test_router_queues_as_many_data_batches_as_the_services():
    # the router forwards every frame: a shorter send queue there would drop what the services' queues keep
    conf = _json5_loads(ROUTER_CONFIG.read_text())
    assert conf["transport"]["link"]["tx"]["queue"]["size"]["data"] == BusSettings().tx_queue_batches


# --- the example site ----------------------------------------------------------------------------


def _clean_env(monkeypatch) -> None:
    for key in [k for k in os.environ if k.startswith("ROADSIDE_")]:
        monkeypatch.delenv(key)


def test_example_site_loads(monkeypatch):
    _clean_env(monkeypatch)
    s = load_settings(EXAMPLE_SITE)
    assert s.site == "example"
    assert len(s.cameras) == 2
    assert {c.kind for c in s.cameras} == {"fisheye", "pinhole"}
    assert all(c.masks is not None for c in s.cameras)
    assert s.path(s.cameras[0].masks) == EXAMPLE_SITE.parent / "masks" / "NE.npz"
    assert s.bus.mode == "peer"


def test_env_overrides_nested_bus_fields_and_keeps_the_rest(monkeypatch, tmp_path):
    _clean_env(monkeypatch)
    data = yaml.safe_load(EXAMPLE_SITE.read_text())
    data["bus"] = {"host": "10.1.2.3", "port_base": 7600, "listen": ["tcp/10.1.2.3:7700"]}
    site = tmp_path / "site.yaml"
    site.write_text(yaml.safe_dump(data))
    for path in (EXAMPLE_SITE, site):
        before = load_settings(path)
        monkeypatch.setenv("ROADSIDE_BUS__MODE", "client")
        monkeypatch.setenv("ROADSIDE_BUS__CONNECT", '["tcp/zenoh:7447"]')
        after = load_settings(path)
        monkeypatch.delenv("ROADSIDE_BUS__MODE")
        monkeypatch.delenv("ROADSIDE_BUS__CONNECT")
        assert before.bus.mode == "peer" and before.bus.connect == []
        assert after.bus.mode == "client"
        assert after.bus.connect == ["tcp/zenoh:7447"]
        keep = ("host", "port_base", "listen", "multicast_scouting")
        assert {k: getattr(after.bus, k) for k in keep} == {k: getattr(before.bus, k) for k in keep}
        assert after.model_dump(exclude={"bus"}) == before.model_dump(exclude={"bus"})
    assert after.bus.host == "10.1.2.3" and after.bus.port_base == 7600 and after.bus.listen == ["tcp/10.1.2.3:7700"]


# --- what compose starts exists ------------------------------------------------------------------


@pytest.mark.parametrize("name", SERVICES)
def test_service_module_exists(name):
    main = ROOT / "services" / name / "__main__.py"
    assert main.is_file(), f"compose runs python -m services.{name}, but {main} is missing"
    assert main.stat().st_size > 0


def test_roadside_health_command_exists(capsys):
    from roadside.cli import main

    with pytest.raises(SystemExit) as exc:
        main(["health", "--help"])
    assert exc.value.code == 0, "`roadside health` must exist: the compose healthchecks run it"
    out = capsys.readouterr().out
    assert "--site" in out and "--service" in out


def test_image_models_exist():
    """compose.yaml points detect at /app/models/detector_fp{32,16}.onnx, copied from models/."""
    missing = [p for p in ("detector_fp32.onnx", "detector_fp16.onnx") if not (ROOT / "models" / p).is_file()]
    assert not missing, f"models/ lacks {missing}: the images cannot be built without them"


def test_make_example_site_makes_what_the_example_site_names():
    """`docker compose up` on the example site needs its recording and masks, which `make example-site` makes (not
    shipped): the files the Makefile writes are the ones site.yaml names."""
    makefile = (ROOT / "Makefile").read_text()
    body = makefile.split("\nexample-site:", 1)[1].split("\n\n", 1)[0]
    example = re.search(r"^EXAMPLE := (\S+)$", makefile, re.M).group(1)
    made = {(ROOT / out.replace("$(EXAMPLE)", example)).resolve() for out in re.findall(r"--out (\S+)", body)}
    settings = load_settings(EXAMPLE_SITE)
    named = {settings.path(c.masks).resolve() for c in settings.cameras} | {settings.path(settings.ingest.source)
                                                                           .resolve()}
    assert named == made, (named, made)
