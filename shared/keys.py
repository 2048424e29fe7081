"""Key expressions on the bus (chunks separated by `/`, the most variable last)."""

from __future__ import annotations

from shared.messages import SERVICES, check_name

STAGES = ("frame", "detections", "objects")


def camera_key(site: str, camera: str, stage: str) -> str:
    """`roadside/<site>/cam/<camera>/<frame|detections|objects>`."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return f"roadside/{check_name('site', site)}/cam/{check_name('camera', camera)}/{stage}"


def all_cameras_key(site: str, stage: str) -> str:
    """`roadside/<site>/cam/*/<stage>`: one stage of every camera."""
    if stage not in STAGES:
        raise ValueError(f"stage must be one of {STAGES}, got {stage!r}")
    return f"roadside/{check_name('site', site)}/cam/*/{stage}"


def tracks_key(site: str) -> str:
    return f"roadside/{check_name('site', site)}/tracks"


def latest_tracks_key(site: str) -> str:
    """Queryable answering with the newest Tracks message, for a subscriber that joins late (when it is current: sent
    within the last 2 s, docs/wire-format.md; whatever its age to a query with the parameter LATEST_ANY_AGE)."""
    return f"roadside/{check_name('site', site)}/tracks/latest"


LATEST_ANY_AGE = "any_age"  # `roadside/<site>/tracks/latest?any_age`: the newest Tracks however old (ingest's resume)


def alive_key(site: str, service: str, instance: str) -> str:
    """Liveliness token `roadside/<site>/alive/<service>/<camera or instance>`."""
    if service not in SERVICES:
        raise ValueError(f"service must be one of {SERVICES}, got {service!r}")
    return f"roadside/{check_name('site', site)}/alive/{service}/{check_name('instance', instance)}"


def status_key(site: str, service: str, instance: str) -> str:
    """`roadside/<site>/status/<service>/<instance>`: a service's Status reports (shared/status.py)."""
    if service not in SERVICES:
        raise ValueError(f"service must be one of {SERVICES}, got {service!r}")
    return f"roadside/{check_name('site', site)}/status/{service}/{check_name('instance', instance)}"


def all_status_key(site: str) -> str:
    return f"roadside/{check_name('site', site)}/status/**"


def observer_alive_key(site: str, name: str) -> str:
    """Liveliness token `roadside/<site>/alive/observer/<name>` of a process that is not one of the services but that
    ingest may be told to wait for (`ingest.wait_extra_peers`), e.g. a recorder that must see the first frame."""
    return f"roadside/{check_name('site', site)}/alive/observer/{check_name('name', name)}"


def all_alive_key(site: str) -> str:
    return f"roadside/{check_name('site', site)}/alive/**"


def camera_of(key: str) -> str:
    """The camera chunk of a `roadside/<site>/cam/<camera>/<stage>` key."""
    parts = str(key).split("/")
    if len(parts) != 5 or parts[0] != "roadside" or parts[2] != "cam":
        raise ValueError(f"not a camera key: {key!r}")
    return parts[3]
