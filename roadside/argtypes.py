"""Flag types the `roadside` command line shares between its modules."""

from __future__ import annotations

import argparse
import math
from pathlib import Path


def finite_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return v


def non_negative_float(text: str) -> float:
    v = finite_float(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number >= 0, got {text}")
    return v


def positive_float(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return v


def type_weights(text: str) -> dict[str, float]:
    """'bus=4,truck=3' -> {'bus': 4.0, 'truck': 3.0} (argparse type; the sim checks the types and values)."""
    out = {}
    for part in text.split(","):
        typ, sep, value = part.partition("=")
        typ = typ.strip()
        try:
            weight = float(value)
        except ValueError:
            sep = ""
        if not sep or not typ:
            raise argparse.ArgumentTypeError(f"expected TYPE=WEIGHT[,TYPE=WEIGHT...], got {part!r}")
        if typ in out:
            raise argparse.ArgumentTypeError(f"{typ} is given twice in {text!r}")
        out[typ] = weight
    return out


def score(text: str) -> float:
    """A detection score threshold: a number from 0 to 1."""
    v = finite_float(text)
    if not 0 <= v <= 1:
        raise argparse.ArgumentTypeError(f"must be a score from 0 to 1, got {text}")
    return v


def _whole(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a whole number: {text!r}") from None


def positive_int(text: str) -> int:
    v = _whole(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 1, got {text}")
    return v


def endpoint(text: str) -> str:
    """A Zenoh endpoint flag (tcp/HOST:PORT, ...), checked here rather than by Zenoh's config parser."""
    from shared.settings import check_endpoint

    try:
        return check_endpoint(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def port_number(text: str) -> int:
    """A TCP port to serve on: 1-65535 (0, any free port, is for tests, not a flag)."""
    v = _whole(text)
    if not 1 <= v <= 65535:
        raise argparse.ArgumentTypeError(f"must be a port from 1 to 65535, got {text}")
    return v


def port_base(text: str) -> int:
    """The embedded default's first service port, in the range BusSettings.port_base allows."""
    from shared.settings import BusSettings

    meta = BusSettings.model_fields["port_base"].metadata
    lo, hi = (next(getattr(m, k) for m in meta if hasattr(m, k)) for k in ("ge", "le"))
    v = _whole(text)
    if not lo <= v <= hi:
        raise argparse.ArgumentTypeError(f"must be a port from {lo} to {hi}, got {text}")
    return v


def site_path(site: Path) -> Path:
    """A site argument: a file, a folder, or the name of a folder under deploy/sites/."""
    if site.exists():
        return site
    if len(site.parts) != 1:  # a path, not a name
        raise ValueError(f"site not found: {site}")
    named = Path(__file__).resolve().parent.parent / "deploy" / "sites" / str(site)
    if named.exists():
        return named
    raise ValueError(f"site not found: {site} (nor {named})")
