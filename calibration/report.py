"""The calibration report: residuals per landmark, leave-one-out error, in/out-ROI statistics,
rejected landmarks with the reason, and warnings about what the landmarks leave unconstrained."""

from __future__ import annotations

import numpy as np

from calibration.fit import CalibConfig, Calibration, calibrate
from calibration.landmarks import Landmarks
from calibration.masks import angular_coverage_deg, roi_mask
from calibration.site_ground import refit_on_surface

MIN_IN_ROI = 4  # fewer landmarks inside the ROI leave it mostly extrapolated (warned about)
INNER_SHARE = 0.5  # warn when no in-ROI landmark lies within this share of the ROI radius from its centre
MAX_GAP_DEG = 150.0  # warn when no in-ROI landmark lies in a wedge this wide around the ROI centre (of 360 seen)


def _stats(x: np.ndarray) -> dict:
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0, "mean_m": None, "std_m": None, "max_m": None}
    return {
        "n": int(x.size),
        "mean_m": round(float(x.mean()), 4),
        "std_m": round(float(x.std()), 4),
        "max_m": round(float(x.max()), 4),
    }


def _opt(values: np.ndarray, k: int, digits: int) -> float | None:
    return None if k >= len(values) or not np.isfinite(values[k]) else round(float(values[k]), digits)


def seen_gap_deg(cal: Calibration, xy: np.ndarray, centre: np.ndarray, radius_m: float) -> tuple[float, float]:
    """(the widest wedge around `centre` without a landmark of xy (N, 2), the wedges the camera sees), in degrees,
    counting only the directions in which the camera sees some of the ROI (a disc of `radius_m`): a pinhole camera's
    ROI is a disc around its foot, most of it behind or beside the camera, where no landmark can be."""
    ang = np.radians(np.arange(360) + 0.5)  # one-degree wedges
    ring = np.arange(1, 21) / 20 * radius_m
    pts = centre + ring[None, :, None] * np.stack([np.cos(ang), np.sin(ang)], -1)[:, None, :]
    pts = pts.reshape(-1, 2)
    if cal.ground is not None:
        z = cal.ground.height(pts)
    else:
        a, b, c = cal.planes.mean(axis=0)
        z = a * pts[:, 0] + b * pts[:, 1] + c
    uv, ok = cal.camera.project(np.column_stack([pts, z]))
    seen = (ok & cal.camera.in_image(uv)).reshape(len(ang), len(ring)).any(axis=1)
    if len(xy) == 0:
        return float(seen.sum()), float(seen.sum())
    marks = np.unique(np.floor(np.degrees(np.arctan2(xy[:, 1] - centre[1], xy[:, 0] - centre[0]))).astype(int) % 360)
    before = np.concatenate([[0], np.cumsum(np.concatenate([seen, seen]))])  # seen wedges below each one
    ends = np.append(marks[1:], marks[0] + 360)
    return float(max(before[b] - before[a + 1] for a, b in zip(marks, ends, strict=True))), float(seen.sum())


def build_report(cal: Calibration, lm: Landmarks, cfg: CalibConfig, roi: dict, leave_one_out: bool = True) -> dict:
    xy = lm.to_local(cal.geo)
    got, ok = cal.pixel_to_xy(lm.uv)
    res = np.where(ok, np.linalg.norm(got - xy, axis=1), np.nan)
    proj, pok = cal.camera.project(np.column_stack([xy, cal.ground_z(xy, lm.uv)]))  # on the fitted ground
    res_px = np.where(pok, np.linalg.norm(proj - lm.uv, axis=1), np.nan)
    in_roi = roi_mask(xy, roi)
    loo = np.full(len(lm), np.nan)
    loo_note: list[str | None] = [None] * len(lm)  # why a landmark has no leave-one-out figure
    if leave_one_out:
        for i in np.nonzero(~cal.inliers)[0]:
            loo_note[i] = "rejected by the fit: none (the refits leave the rejected landmarks out)"
        for i in np.nonzero(cal.inliers)[0]:
            # the other inliers only: a rejected landmark would be rejected again in every refit, or drag it
            keep = cal.inliers.copy()
            keep[i] = False
            try:
                if cal.ground is None:
                    sub = calibrate(lm.subset(np.nonzero(keep)[0]), cfg, cal.geo, cal.segment_polygons)
                else:  # on the site's surface: this camera refitted on it without the landmark (the surface keeps it)
                    sub = refit_on_surface(cal, lm, cfg, cal.ground, keep)
            except ValueError as exc:
                loo_note[i] = f"the refit without it failed: {exc}"
                continue
            p, pok_i = sub.pixel_to_xy(lm.uv[i : i + 1])
            if pok_i[0]:
                loo[i] = float(np.linalg.norm(p[0] - xy[i]))
            else:
                loo_note[i] = "its pixel is off the ground of the refit without it"
    inl = cal.inliers
    warnings = list(cal.warnings)
    if (lm.segment >= 0).any() and cal.ground is not None:
        warnings.append("the landmarks' segment column is not used: the site's ground surface (--shared-ground) "
                        "replaces this camera's planes")
    centre = np.asarray(roi.get("center_m", xy[inl].mean(0)))
    if cfg.kind == "pinhole" and "radius_m" in roi:  # only the part of the ROI the camera sees can hold landmarks
        gap, seen = seen_gap_deg(cal, xy[inl & in_roi], centre, float(roi["radius_m"]))
        if seen > 0 and gap > MAX_GAP_DEG * seen / 360.0:
            warnings.append(
                f"landmarks leave part of the ROI unconstrained: no in-ROI landmark in a {gap:.0f} degree wedge "
                f"around the ROI centre, of the {seen:.0f} degrees the camera sees; add landmarks on that side"
            )
    else:
        gap = angular_coverage_deg(xy[inl & in_roi], centre)
        if "radius_m" in roi and gap > MAX_GAP_DEG:
            warnings.append(
                f"landmarks leave part of the ROI unconstrained: no in-ROI landmark in a {gap:.0f} degree "
                "wedge around the ROI centre; add landmarks on that side"
            )
    n_roi = int((inl & in_roi).sum())
    if n_roi < MIN_IN_ROI:
        # `roadside bench calibration`'s simulated landmarks: fisheye fits from 10-20 landmarks with fewer than 4
        # inside the 25 m ROI were 0.33 m off there on average, those with 4 or more 0.18 m (seeds 0-3)
        warnings.append(
            f"only {n_roi} landmarks inside the ROI: its ground is extrapolated from landmarks outside it, and its "
            f"error is not measured; add at least {MIN_IN_ROI - n_roi} inside it"
        )
    elif "radius_m" in roi:
        centre = np.asarray(roi["center_m"], float)
        nearest = float(np.linalg.norm(xy[inl & in_roi] - centre, axis=1).min())
        if nearest > INNER_SHARE * float(roi["radius_m"]):
            warnings.append(
                f"no landmark within {nearest:.0f} m of the ROI centre (under a fisheye camera, its nadir): the ground "
                "there is extrapolated from landmarks further out; add landmarks near the centre"
            )
    return {
        "camera_kind": cfg.kind,
        "landmarks_used": int(inl.sum()),
        "landmarks_total": len(lm),
        "segments": len(cal.planes),
        # the segments the user named (the segment column, --segment-polygons), or null for automatic ones
        "segment_labels": list(cal.labelled.labels) if cal.labelled is not None else None,
        "roi": roi,
        "residual_in_roi": _stats(res[inl & in_roi]),
        "residual_out_roi": _stats(res[inl & ~in_roi]),
        "leave_one_out_in_roi": _stats(loo[inl & in_roi]),
        "leave_one_out_out_roi": _stats(loo[inl & ~in_roi]),
        "rejected": [{"id": i, "reason": r} for i, r in cal.rejected],
        "warnings": warnings,
        "landmarks": [
            {
                "id": lid,
                "inlier": bool(inl[k]),
                "segment": int(cal.labelled.of_landmark[k]) if cal.labelled is not None else None,
                "in_roi": bool(in_roi[k]),
                "residual_m": None if np.isnan(res[k]) else round(float(res[k]), 4),
                "reprojection_px": None if np.isnan(res_px[k]) else round(float(res_px[k]), 2),
                "leave_one_out_m": None if np.isnan(loo[k]) else round(float(loo[k]), 4),
                "leave_one_out_note": loo_note[k],  # why leave_one_out_m is null (rejected, refit failed)
                "outlier_test_sigma": _opt(cal.test_sigma, k, 2),
                "detectable_map_mistake_m": _opt(cal.detectable_map_m, k, 2),
                "detectable_pixel_mistake_px": _opt(cal.detectable_pixel_px, k, 1),
            }
            for k, lid in enumerate(lm.ids)
        ],
    }


def summary_text(report: dict) -> str:
    def fmt(s: dict) -> str:
        return "n/a" if s["n"] == 0 else f"{s['mean_m']:.3f} ± {s['std_m']:.3f} m (n={s['n']}, max {s['max_m']:.3f})"

    ground = report.get("ground")
    shared = isinstance(ground, dict)
    lines = [
        f"{report['camera_kind']} camera: {report['landmarks_used']}/{report['landmarks_total']} landmarks used, "
        + (f"the site's ground surface (fitted to the landmarks of {len(ground['cameras'])} cameras; leave-one-out: "
           "the camera refitted on it without the landmark)" if shared else f"{report['segments']} ground segment(s)"
           + (f" named {', '.join(map(str, report['segment_labels']))}" if report.get("segment_labels") else "")),
        f"  residual      in-ROI  {fmt(report['residual_in_roi'])}",
        f"  residual      out-ROI {fmt(report['residual_out_roi'])}",
        f"  leave-one-out in-ROI  {fmt(report['leave_one_out_in_roi'])}",
        f"  leave-one-out out-ROI {fmt(report['leave_one_out_out_roi'])}",
    ]
    for r in report["rejected"]:
        lines.append(f"  rejected {r['id']}: {r['reason']}")
    for w in report["warnings"]:
        lines.append(f"  warning: {w}")
    return "\n".join(lines)


def plot_residuals(
    cal: Calibration, lm: Landmarks, image: np.ndarray | None, out_png: str, scale: float = 20.0
) -> None:
    """Residual arrows on the image: from each clicked pixel toward where its map point projects
    (lengths x `scale`); green inliers, red rejected."""
    import cv2

    cfg = cal.config
    if image is not None and image.shape[:2] != (cfg.height, cfg.width):
        raise ValueError(f"the image is {image.shape[1]}x{image.shape[0]}, the landmarks are for a "
                         f"{cfg.width}x{cfg.height} image")
    canvas = np.full((cfg.height, cfg.width, 3), 40, np.uint8) if image is None else image.copy()
    if canvas.ndim == 2:
        canvas = cv2.cvtColor(canvas, cv2.COLOR_GRAY2BGR)
    xy = lm.to_local(cal.geo)
    proj, ok = cal.camera.project(np.column_stack([xy, cal.ground_z(xy, lm.uv)]))
    for k, lid in enumerate(lm.ids):
        a = lm.uv[k]
        colour = (60, 220, 60) if cal.inliers[k] else (40, 40, 255)
        if ok[k]:
            b = a + (proj[k] - a) * scale
            cv2.arrowedLine(
                canvas, tuple(np.round(a).astype(int)), tuple(np.round(b).astype(int)), colour, 2, cv2.LINE_AA
            )
        cv2.circle(canvas, tuple(np.round(a).astype(int)), 4, colour, -1, cv2.LINE_AA)
        cv2.putText(
            canvas,
            lid,
            tuple(np.round(a + np.array([6, -6])).astype(int)),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.45,
            colour,
            1,
            cv2.LINE_AA,
        )
    cv2.putText(
        canvas, f"residual arrows x{scale:g}", (10, 24), cv2.FONT_HERSHEY_SIMPLEX, 0.7, (255, 255, 255), 2, cv2.LINE_AA
    )
    if not cv2.imwrite(out_png, canvas):
        raise ValueError(f"cannot write plot {out_png}")
