"""Fixtures shared by several test files."""

from __future__ import annotations

from pathlib import Path

import pytest

from sim.clip import ClipConfig, simulate_clip


@pytest.fixture(scope="session")
def small_recording(tmp_path_factory) -> Path:
    """Two frames from one fisheye (NE) and one thermal pinhole (T_SW) camera (~30 s to build)."""
    out = tmp_path_factory.mktemp("rec") / "clip"
    simulate_clip(
        ClipConfig(
            site="state_ellsworth", out=out, seconds=1.0, hz=2.0, seed=3, cameras="NE,T_SW", workers=1, weather="clear"
        )
    )
    return out
