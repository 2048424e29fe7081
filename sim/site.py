"""Site description files (`sim/sites/<name>.yaml`): the data that the road-network code builds from.

A site is a roundabout or a signalised intersection with approaches (legs) at given bearings,
its terrain, parking rows, buildings, tree and pedestrian counts, and its cameras.
"""

from __future__ import annotations

import math
from datetime import datetime
from pathlib import Path
from typing import Literal

import numpy as np
import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from shared.cameras import Camera, Pose
from shared.geo import GeoFrame
from shared.ground import Terrain
from shared.messages import check_name

SITES_DIR = Path(__file__).resolve().parent / "sites"
# The ground is painted at 4 cm per pixel over the +-extent_m square, so a world's memory grows with the area:
# about 2 GB at 120 m and 5.7 GB at 200 m (measured); 240 m needs about 8 GB.
MAX_EXTENT_M = 240.0


class _Model(BaseModel):
    # NaN and infinity are refused where they are read, so the error names the field.
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Origin(_Model):
    lat_deg: float = Field(ge=-90, le=90)
    lon_deg: float = Field(ge=-180, le=180)
    alt_m: float = 0.0


class ApproachSpec(_Model):
    """One leg of the junction. `bearing_deg` points from the centre along the leg (0 = north)."""

    name: str
    bearing_deg: float
    lanes_in: int = Field(2, ge=1, le=4)
    lanes_out: int = Field(2, ge=1, le=4)
    lane_width_m: float = Field(3.6, gt=2.5, lt=5.0)
    median_m: float = Field(1.0, ge=0.0, le=12.0)
    splitter_length_m: float = Field(0.0, ge=0.0)
    left_turn_lane: bool = False
    crosswalk_m: float = Field(0.0, ge=0.0)
    demand_veh_h: float = Field(600.0, ge=0.0)
    speed_limit_mps: float = Field(13.4, gt=0.0, le=40.0)

    @property
    def unit_out(self) -> np.ndarray:
        b = math.radians(self.bearing_deg)
        return np.array([math.sin(b), math.cos(b)])

    @property
    def unit_right(self) -> np.ndarray:
        """Right of the outward direction: outbound lanes lie on this side of the leg axis."""
        b = math.radians(self.bearing_deg)
        return np.array([math.cos(b), -math.sin(b)])

    @property
    def half_width_m(self) -> float:
        return 0.5 * self.median_m + max(self.lanes_in, self.lanes_out) * self.lane_width_m


class RoundaboutSpec(_Model):
    island_radius_m: float = Field(gt=2.0)
    apron_width_m: float = Field(ge=0.0)
    lanes: int = Field(2, ge=1, le=3)
    lane_width_m: float = Field(4.4, gt=3.0, lt=6.0)
    entry_angle_deg: float = Field(30.0, gt=5.0, lt=80.0)

    @property
    def inner_radius_m(self) -> float:
        return self.island_radius_m + self.apron_width_m

    @property
    def outer_radius_m(self) -> float:
        return self.inner_radius_m + self.lanes * self.lane_width_m


class IntersectionSpec(_Model):
    corner_radius_m: float = Field(8.0, gt=0.0)
    stop_line_gap_m: float = Field(5.0, ge=0.0)
    green_s: float = Field(18.0, gt=0.0)
    left_green_s: float = Field(7.0, gt=0.0)
    yellow_s: float = Field(3.0, ge=0.0)
    all_red_s: float = Field(1.5, ge=0.0)


class CameraSpec(_Model):
    name: str
    kind: Literal["pinhole", "fisheye"]
    modality: Literal["visible", "thermal"] = "visible"
    position_m: tuple[float, float, float]
    yaw_deg: float
    pitch_deg: float
    roll_deg: float = 0.0
    width: int = Field(gt=0)
    height: int = Field(gt=0)
    hfov_deg: float | None = Field(None, gt=1.0, lt=179.0)
    focal_px: float | None = Field(None, gt=0.0)
    dist: tuple[float, ...] = ()
    max_angle_deg: float | None = None
    pole_offset_m: tuple[float, float] | None = None

    @model_validator(mode="after")
    def _focal(self) -> CameraSpec:
        if (self.hfov_deg is None) == (self.focal_px is None):
            raise ValueError(f"camera {self.name}: give exactly one of hfov_deg or focal_px")
        return self

    def build(self) -> Camera:
        f = self.focal_px
        if f is None:
            f = 0.5 * self.width / math.tan(math.radians(self.hfov_deg) / 2)
        max_angle = self.max_angle_deg
        if max_angle is None:
            max_angle = 89.0 if self.kind == "pinhole" else 95.0
        if self.kind == "pinhole":
            max_angle = min(max_angle, 89.0)
        return Camera(
            name=self.name,
            kind=self.kind,
            width=self.width,
            height=self.height,
            fx=f,
            fy=f,
            cx=(self.width - 1) / 2,
            cy=(self.height - 1) / 2,
            dist=self.dist,
            pose=Pose.from_angles(self.position_m, self.yaw_deg, self.pitch_deg, self.roll_deg),
            max_angle_deg=max_angle,
            modality=self.modality,
        )


class ParkingRow(_Model):
    start_m: tuple[float, float]
    bearing_deg: float
    count: int = Field(ge=1)
    spacing_m: float = Field(gt=1.0)
    occupancy: float = Field(0.7, ge=0.0, le=1.0)


class Building(_Model):
    center_m: tuple[float, float]
    size_m: tuple[float, float]
    height_m: float = Field(gt=0.0)
    yaw_deg: float = 0.0


class TreeSpec(_Model):
    count: int = Field(40, ge=0)
    min_road_gap_m: float = Field(3.0, ge=0.0)


class SiteSpec(_Model):
    name: str
    description: str = ""
    origin: Origin
    utc_start: str = "2024-01-01T12:00:00Z"
    extent_m: float = Field(120.0, gt=20.0)
    terrain: dict = Field(default_factory=dict)
    layout: Literal["roundabout", "intersection"]
    roundabout: RoundaboutSpec | None = None
    intersection: IntersectionSpec | None = None
    approaches: tuple[ApproachSpec, ...]
    parking: tuple[ParkingRow, ...] = ()
    buildings: tuple[Building, ...] = ()
    trees: TreeSpec = TreeSpec()
    pedestrians: int = Field(10, ge=0)
    cameras: tuple[CameraSpec, ...]

    @model_validator(mode="after")
    def _consistent(self) -> SiteSpec:
        if self.layout == "roundabout" and self.roundabout is None:
            raise ValueError("layout roundabout needs a `roundabout:` section")
        if self.layout == "intersection" and self.intersection is None:
            raise ValueError("layout intersection needs an `intersection:` section")
        if len(self.approaches) < 3:
            raise ValueError(f"a junction needs at least 3 approaches, got {len(self.approaches)}")
        names = [c.name for c in self.cameras]
        if len(set(names)) != len(names):
            raise ValueError(f"camera names must be unique, got {names}")
        for n in names:  # they name folders and files of the recording
            check_name("camera", n)
        try:
            start = datetime.fromisoformat(self.utc_start.replace("Z", "+00:00"))
        except ValueError:
            raise ValueError(f"utc_start must be an ISO date and time, got {self.utc_start!r}") from None
        if start.tzinfo is None:  # else it would be read in the machine's own time zone
            raise ValueError(f"utc_start must give its time zone (Z for UTC), got {self.utc_start!r}")
        if not self.cameras:
            raise ValueError("a site needs at least one camera")
        Terrain.from_dict(self.terrain)
        return self

    @property
    def geo(self) -> GeoFrame:
        return GeoFrame(self.origin.lat_deg, self.origin.lon_deg, self.origin.alt_m)

    @property
    def ground(self) -> Terrain:
        return Terrain.from_dict(self.terrain)

    def build_cameras(self) -> list[Camera]:
        return [c.build() for c in self.cameras]

    def movements(self, outer_radius_m: float = 70.0) -> dict:
        """The junction as a site.yaml's `movements:` section (shared/movements.py): its centre is the site's origin
        and its legs the approaches; a vehicle is in the junction within a metre of the ring's outer edge (a car
        waiting at the yield line, its centre ~2.5 m behind the edge, is still on its leg). Roundabouts only: an
        intersection's box is the site file's to give."""
        if self.roundabout is None:
            raise ValueError(f"site {self.name}: the junction of a {self.layout} is not derived; give `movements:` "
                             "in the site file")
        return {"center": {"lat_deg": self.origin.lat_deg, "lon_deg": self.origin.lon_deg},
                "legs": [{"name": a.name, "bearing_deg": a.bearing_deg} for a in self.approaches],
                "inner_radius_m": round(self.roundabout.outer_radius_m + 1.0, 2), "outer_radius_m": outer_radius_m}

    def camera_spec(self, name: str) -> CameraSpec:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(name)


def known_sites() -> list[str]:
    return sorted(p.stem for p in SITES_DIR.glob("*.yaml"))


def load_site(name_or_path: str | Path) -> SiteSpec:
    """Load a site by name (a file in `sim/sites/`) or by the path of a site YAML file."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = SITES_DIR / f"{name_or_path}.yaml"
        if not path.is_file():
            raise ValueError(f"unknown site {str(name_or_path)!r} (known: {', '.join(known_sites())})")
    if not path.is_file():
        raise ValueError(f"site file not found: {path}")
    try:
        data = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise ValueError(f"site file {path} is not valid YAML: {exc}") from None
    except UnicodeDecodeError as exc:
        raise ValueError(f"site file {path} is not a text file ({exc})") from None
    if not isinstance(data, dict):
        raise ValueError(f"site file {path} must hold a mapping, got {type(data).__name__}")
    try:
        spec = SiteSpec.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(x) for x in first["loc"])  # empty for a check of the whole file
        msg = first["msg"].removeprefix("Value error, ")
        raise ValueError(f"site file {path}: {where + ': ' if where else ''}{msg}") from None
    # checked where a world is to be built from the file, not where a recording's site is read back
    if spec.extent_m > MAX_EXTENT_M:
        raise ValueError(f"site file {path}: extent_m must be at most {MAX_EXTENT_M:g} m, got {spec.extent_m:g}: the "
                         f"ground is painted at 4 cm per pixel and the world's memory grows with its area (about 2 GB "
                         f"at 120 m, 8 GB at {MAX_EXTENT_M:g} m)")
    return spec
