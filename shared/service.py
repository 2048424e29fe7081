"""What every service's `__main__` shares: flags -> one Settings object, logging, a clean exit.

`python -m services.<name> --site deploy/sites/<site>/site.yaml [--set section.field=value ...]`.
A configuration or start-up problem (missing model, masks or source file, bad site file) stops the
service with one clear error line and exit status 2; `main(settings, stopper)` never sees argparse.
"""

from __future__ import annotations

import argparse
import logging
import sys
import zipfile
from collections.abc import Callable

import yaml
import zenoh

from shared.bus import Stopper
from shared.settings import Settings, load_settings


def parse_sets(items: list[str]) -> dict:
    """`section.field=value` pairs -> nested overrides (values parsed as YAML scalars/lists)."""
    out: dict = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--set expects section.field=value, got {item!r}")
        parts = key.split(".")
        node = out
        for p in parts[:-1]:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise ValueError(f"--set {item!r}: {p} is already set to a value, not a section")
        try:
            node[parts[-1]] = yaml.safe_load(value)
        except yaml.YAMLError:
            raise ValueError(f"--set {item!r}: the value {value!r} is not valid YAML") from None
    return out


def service_settings(argv: list[str] | None, service: str) -> Settings:
    ap = argparse.ArgumentParser(prog=f"python -m services.{service}")
    ap.add_argument("--site", required=True, help="site file (site.yaml) or site folder")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.FIELD=VALUE",
                    help="override one setting, e.g. ingest.pace=max (repeatable)")
    args = ap.parse_args(argv)
    return load_settings(args.site, **parse_sets(args.set))


def setup_logging(level: str, service: str) -> None:
    logging.basicConfig(level=getattr(logging, level.upper(), logging.INFO), stream=sys.stderr,
                        format=f"%(asctime)s {service} %(levelname)s %(message)s")


def run(service: str, main: Callable[[Settings, Stopper], int], argv: list[str] | None = None) -> int:
    try:
        settings = service_settings(argv, service)
    except ValueError as exc:
        print(f"{service}: error: {exc}", file=sys.stderr)
        return 2
    setup_logging(settings.log_level, service)
    stopper = Stopper()
    try:
        return main(settings, stopper)
    except ValueError as exc:
        print(f"{service}: error: {exc}", file=sys.stderr)
        return 2
    except zipfile.BadZipFile as exc:
        print(f"{service}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 2
    except (OSError, zenoh.ZError) as exc:  # a router not up yet, a full disk: may pass, so 1 (restarted), not 2
        print(f"{service}: error: {type(exc).__name__}: {exc}", file=sys.stderr)
        return 1
