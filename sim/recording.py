"""The recording format that playback, training and evaluation read (see docs/recording-format.md).

```
DIR/recording.json           metadata: site, geo origin, terrain, cameras (model + pose), clip
DIR/frames/<camera>/<t_ns>.jpg  frames, named by capture time (ns since the Unix epoch)
DIR/gt/<camera>.jsonl        one JSON line per frame: {"t_ns", "file", "vehicles": [...]}
DIR/landmarks/<camera>.json  ground landmarks (pixel <-> lat/lon) with truth and the noise model
```
"""

from __future__ import annotations

import json
from functools import cached_property
from pathlib import Path

import cv2
import numpy as np

from shared.cameras import Camera
from shared.geo import GeoFrame
from shared.ground import Terrain, ground_lookup

FORMAT = "roadside-recording"
VERSION = 1
META_FILE = "recording.json"


class Recording:
    """Read access to a recording folder. Raises ValueError naming the file that is wrong."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        meta_path = self.path / META_FILE
        if not meta_path.is_file():
            raise ValueError(f"not a recording: {meta_path} is missing")
        try:
            self.meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{meta_path} is not valid JSON: {exc}") from None
        if self.meta.get("format") != FORMAT:
            raise ValueError(f"{meta_path}: format is {self.meta.get('format')!r}, expected {FORMAT!r}")
        if self.meta.get("version") != VERSION:
            raise ValueError(f"{meta_path}: version {self.meta.get('version')!r} is not supported (expected {VERSION})")

    @cached_property
    def cameras(self) -> dict[str, Camera]:
        return {c["name"]: Camera.from_dict(c) for c in self.meta["cameras"]}

    @property
    def camera_names(self) -> list[str]:
        return [c["name"] for c in self.meta["cameras"]]

    @cached_property
    def geo(self) -> GeoFrame:
        return GeoFrame.from_dict(self.meta["site"]["origin"])

    @cached_property
    def terrain(self) -> Terrain:
        return Terrain.from_dict(self.meta["terrain"])

    def _camera_entry(self, camera: str) -> dict:
        for c in self.meta["cameras"]:
            if c["name"] == camera:
                return c
        raise ValueError(f"recording {self.path} has no camera {camera!r} (has: {', '.join(self.camera_names)})")

    def frames(self, camera: str) -> list[tuple[int, Path]]:
        """(capture time ns, image path) of every frame of a camera, in time order."""
        entry = self._camera_entry(camera)
        folder = self.path / entry["frame_dir"]
        if not folder.is_dir():
            raise ValueError(f"recording frame folder missing: {folder}")
        out = []
        for p in folder.iterdir():
            if p.suffix == ".jpg" and p.stem.isdigit():
                out.append((int(p.stem), p))
        return sorted(out)

    def ground_truth(self, camera: str) -> list[dict]:
        entry = self._camera_entry(camera)
        path = self.path / entry["gt"]
        if not path.is_file():
            raise ValueError(f"recording ground truth missing: {path}")
        out = []
        with path.open() as f:
            for n, line in enumerate(f, 1):
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError as exc:
                    raise ValueError(f"{path}:{n}: not valid JSON: {exc}") from None
        return out

    def landmarks(self, camera: str) -> dict:
        entry = self._camera_entry(camera)
        path = self.path / entry["landmarks"]
        if not path.is_file():
            raise ValueError(f"recording landmarks missing: {path}")
        return json.loads(path.read_text())

    def image(self, path: Path) -> np.ndarray:
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise ValueError(f"cannot decode image {path}")
        return img

    def ground_lookup(self, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """The exact pixel -> ground lookup of a camera: ((H, W, 3) site metres, (H, W) valid)."""
        return ground_lookup(self.cameras[camera], self.terrain)
