"""Benchmarks; each prints one JSON document."""

from __future__ import annotations

import argparse


def first_paragraph(doc: str | None) -> str:
    """A docstring's whole first paragraph (up to the first blank line), its lines joined."""
    return " ".join(line.strip() for line in (doc or "").strip().split("\n\n")[0].splitlines())


def bench_parser(name: str, doc: str | None, argv: list[str] | None, *, module: str | None = None,
                 epilog: str | None = None) -> argparse.ArgumentParser:
    """The flag parser of benchmark `name`: `roadside bench NAME` when the CLI hands it `argv` (a list), `python -m
    bench.MODULE` when run as a module (`argv` None: read from the command line); the docstring's first paragraph as
    the description."""
    prog = f"python -m bench.{module or name}" if argv is None else f"roadside bench {name}"
    return argparse.ArgumentParser(prog=prog, description=first_paragraph(doc), epilog=epilog)
