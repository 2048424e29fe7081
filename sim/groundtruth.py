"""Per-frame ground truth of every vehicle seen by a camera."""

from __future__ import annotations

import numpy as np

from shared.cameras import Camera
from shared.geo import GeoFrame
from shared.ground import Terrain
from sim.geometry import rect
from sim.render import RenderResult, clipped_box_image_points
from sim.traffic import VEHICLE_TYPES, SceneState

_GRID = np.array([[a, b, c] for a in np.linspace(-1, 1, 5) for b in np.linspace(-1, 1, 5) for c in (0.0, 0.5, 1.0)])


def _r(x, nd: int) -> list | float:
    return np.round(np.asarray(x, float), nd).tolist()


def frame_ground_truth(
    camera: Camera, scene: SceneState, result: RenderResult, terrain: Terrain, geo: GeoFrame
) -> list[dict]:
    """One record per vehicle that covers at least one pixel or whose bottom centre is in the image.

    Units: metres and radians in the site ENU frame; pixels in the original image (see
    shared.cameras for the pixel convention); `box` = [x1, y1, x2, y2] of the projected 3D box
    clipped to the image (for a pinhole camera with part of the box behind it, the bounds of the box
    clipped at the camera plane as far as it shows in the image); `box_visible` = bounds of the pixels
    actually showing the vehicle; `corners_uv` = the footprint corners, null for a corner outside the
    lens model's field of view (behind a pinhole camera, say), as `uv` is null for such a bottom centre.
    """
    n = len(scene)
    if n == 0:
        return []
    z = terrain.height(scene.xy[:, 0], scene.xy[:, 1])
    bottom = np.column_stack([scene.xy, z])
    uv, ok = camera.project(bottom)
    in_img = ok & camera.in_image(uv)
    latlon = geo.to_geodetic(bottom)
    ids = result.ids
    ys, xs = np.nonzero(ids >= 0)
    vals = ids[ys, xs]
    vis_px = np.bincount(vals, minlength=n)[:n] if vals.size else np.zeros(n, np.int64)
    order = np.argsort(vals, kind="stable")
    vals_s, xs_s, ys_s = vals[order], xs[order], ys[order]
    starts = np.searchsorted(vals_s, np.arange(n))
    ends = np.searchsorted(vals_s, np.arange(n), side="right")
    out = []
    w_max, h_max = camera.width - 1, camera.height - 1
    for i in range(n):
        if result.hit_px[i] == 0 and not in_img[i]:
            continue
        l, w, h = scene.lwh[i]
        c, s = np.cos(scene.yaw[i]), np.sin(scene.yaw[i])
        rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        local = _GRID * [l / 2, w / 2, 1.0]
        local[:, 2] = _GRID[:, 2] * h
        pts = bottom[i] + local @ rot.T
        puv, pok = camera.project(pts)
        box = None
        if camera.kind == "pinhole" and not pok.all():
            # Part of the box is behind the camera (or beyond the lens model's field of view): the samples in
            # front would give only part of its image, so the box comes from its edges clipped at the camera plane.
            half = np.array([l / 2, w / 2, h / 2])
            p = clipped_box_image_points(camera, bottom[i] + [0.0, 0.0, h / 2], half, scene.yaw[i], *result.border)
        else:
            p = puv[pok]
        if len(p):
            x1, y1 = np.clip(p.min(0), 0, [w_max, h_max])
            x2, y2 = np.clip(p.max(0), 0, [w_max, h_max])
            if x2 > x1 and y2 > y1:
                box = _r([x1, y1, x2, y2], 2)
        corners = np.column_stack([rect(scene.xy[i], l, w, scene.yaw[i]), np.full(4, z[i])])
        cuv, cok = camera.project(corners)
        corners_uv = [_r(c, 2) if good else None for c, good in zip(cuv, cok, strict=True)]
        box_visible = None
        if vis_px[i] > 0:
            sx, sy = xs_s[starts[i] : ends[i]], ys_s[starts[i] : ends[i]]
            box_visible = [int(sx.min()), int(sy.min()), int(sx.max()), int(sy.max())]
        out.append(
            {
                "id": int(scene.ids[i]),
                "type": VEHICLE_TYPES[int(scene.type_idx[i])],
                "lwh": _r(scene.lwh[i], 3),
                "yaw": round(float(scene.yaw[i]), 5),
                "speed": round(float(scene.speed[i]), 3),
                "xyz": _r(bottom[i], 4),
                "latlon": _r(latlon[i, :2], 9),
                "uv": _r(uv[i], 2) if ok[i] else None,
                "in_image": bool(in_img[i]),
                "box": box,
                "box_visible": box_visible,
                "corners_uv": corners_uv,
                "visible_px": int(vis_px[i]),
                "visible_fraction": round(float(vis_px[i] / result.hit_px[i]), 4) if result.hit_px[i] else 0.0,
                "parked": bool(scene.parked[i]),
            }
        )
    return out
