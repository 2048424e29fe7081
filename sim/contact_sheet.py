"""A grid of frames from every camera of a recording with the ground truth drawn on top."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np

from sim.recording import Recording

TILE_W = 480


def _draw(img: np.ndarray, vehicles: list[dict], scale: float) -> None:
    for v in vehicles:
        if v["visible_px"] == 0:
            continue
        colour = (0, 220, 0) if v["visible_fraction"] >= 0.5 else (0, 140, 255)
        if v["box"]:
            x1, y1, x2, y2 = (np.array(v["box"]) * scale).round().astype(int)
            cv2.rectangle(img, (x1, y1), (x2, y2), colour, 1, cv2.LINE_AA)
            cv2.putText(
                img,
                f"{v['id']} {v['type'][:3]} {int(100 * v['visible_fraction'])}%",
                (x1, max(y1 - 2, 8)),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.3,
                colour,
                1,
                cv2.LINE_AA,
            )
        if v["corners_uv"] is not None and all(c is not None for c in v["corners_uv"]):  # none behind the camera
            corners = (np.array(v["corners_uv"]) * scale).round().astype(np.int32)
            cv2.polylines(img, [corners], True, (0, 230, 255), 1, cv2.LINE_AA)
        if v["uv"] is not None and v["in_image"]:
            u, w = (np.array(v["uv"]) * scale).round().astype(int)
            cv2.circle(img, (u, w), 2, (0, 0, 255), -1, cv2.LINE_AA)


def contact_sheet(recording: str | Path, out_png: str | Path, moments: int = 3) -> Path:
    """Rows: `moments` instants spread over the clip; columns: cameras. Returns the PNG path."""
    rec = Recording(recording)
    rows = []
    for m in range(moments):
        tiles = []
        for cam in rec.camera_names:
            gt = rec.ground_truth(cam)
            if not gt:
                continue
            rec_gt = gt[min(len(gt) - 1, int(m * (len(gt) - 1) / max(moments - 1, 1)))]
            img = rec.image(rec.path / rec_gt["file"])
            if img.ndim == 2:
                img = cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
            scale = TILE_W / img.shape[1]
            img = cv2.resize(img, (TILE_W, int(round(img.shape[0] * scale))), interpolation=cv2.INTER_AREA)
            _draw(img, rec_gt["vehicles"], scale)
            t_s = (rec_gt["t_ns"] - rec.meta["t0_ns"]) / 1e9
            cv2.putText(
                img, f"{cam}  t={t_s:.2f}s", (6, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA
            )
            tiles.append(img)
        height = max(t.shape[0] for t in tiles)
        tiles = [cv2.copyMakeBorder(t, 0, height - t.shape[0], 0, 2, cv2.BORDER_CONSTANT) for t in tiles]
        rows.append(np.hstack(tiles))
    width = max(r.shape[1] for r in rows)
    sheet = np.vstack([cv2.copyMakeBorder(r, 0, 2, 0, width - r.shape[1], cv2.BORDER_CONSTANT) for r in rows])
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        written = cv2.imwrite(str(out), sheet)
    except cv2.error as exc:  # an extension OpenCV has no encoder for, among others
        reason = str(exc).strip().splitlines()[-1]
        m = re.search(r"error: \([^)]*\) (.*?)(?: in function .*)?$", reason)  # OpenCV's own message, bare
        raise ValueError(f"cannot write contact sheet {out}: {m.group(1) if m else reason}") from None
    if not written:
        raise ValueError(f"cannot write contact sheet {out}")
    return out
