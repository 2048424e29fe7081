"""Listing a folder as a person sees it."""

from __future__ import annotations

from pathlib import Path


def visible_files(folder: str | Path, *patterns: str) -> list[Path]:
    """The entries of `folder` matching any of the glob `patterns`, sorted, without hidden ones (a name starting with
    "."): footage, labels or a basemap copied from a Mac carry an AppleDouble `._<name>` beside each file, which is not
    the file it names."""
    folder = Path(folder)
    return sorted({p for pattern in patterns for p in folder.glob(pattern) if not p.name.startswith(".")})
