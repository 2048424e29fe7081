"""Precise landmark picking by eye: zoomed crops with a pixel grid, an orthophoto with its lat/lon mapping.

Commands (`python -m calibration.pick <command> ...`, every one writes a PNG):

    crop   --image IMG --at U,V [--size 120] [--zoom 6] [--landmarks FILE] --out crop.png
    ortho  --basemap DIR (--at LAT,LON | --px X,Y) [--size 60] [--zoom 10] [--landmarks FILE] --out crop.png
    pair   --image IMG --at U,V --basemap DIR (--latlon LAT,LON | --px X,Y) [--landmarks FILE] --out pair.png
    check  --landmarks FILE --image IMG --basemap DIR [--ortho-zoom 2] --out check.png

A crop is drawn with nearest-neighbour zoom, so every source pixel is a `zoom` x `zoom` block; thin grid
lines run along pixel borders, and stronger labelled lines every 10 pixels (5 in small crops): the
line labelled `k` passes through the centres of the pixels with coordinate k, so a feature on it reads
exactly k, one halfway to the next labelled line k + 5. A red cross marks the requested point;
landmarks of `--landmarks` are drawn as numbered circles (number = 1-based position in the file; the
legend number -> id is printed on stdout).

Pixel convention (camera images and orthophoto alike): the centre of the top-left pixel is (0, 0), so
pixel (i, j) covers [i - 0.5, i + 0.5] x [j - 0.5, j + 0.5] and the image spans [-0.5, W - 0.5].

Orthophoto: a folder with one `*.jpg`/`*.png` image and one `*.json` with its corners
`{"tl": [lat, lon], "tr": ..., "bl": ..., "br": ...}` (north-up). The corners are the *outer* corners
of the corner pixels (as `services.rerun_sink.basemap` reads a world file): `tl` is pixel
(-0.5, -0.5), `br` is (W - 0.5, H - 0.5). Pixel <-> lat/lon is bilinear between the four corners
(`Ortho.to_latlon`, `Ortho.to_px`; the inverse by Newton's method, exact to 1e-9 px).
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from calibration.landmarks import load_landmarks
from shared.files import visible_files

GRID_MINOR = (90, 90, 90)
GRID_MAJOR = (0, 220, 255)
CROSS = (0, 0, 255)
MARK = (255, 0, 255)
LABEL = (255, 255, 255)


@dataclass(frozen=True)
class Ortho:
    """A north-up orthophoto: `image` (H, W, 3) BGR uint8 and `corners` {"tl","tr","bl","br"} -> (lat, lon)."""

    image: np.ndarray
    corners: dict[str, tuple[float, float]]
    path: Path

    @property
    def size(self) -> tuple[int, int]:
        return self.image.shape[1], self.image.shape[0]

    @classmethod
    def load(cls, folder: str | Path) -> Ortho:
        folder = Path(folder)
        if not folder.is_dir():
            raise ValueError(f"--basemap {folder}: not a folder")
        imgs = visible_files(folder, "*.jpg", "*.png")
        metas = visible_files(folder, "*.json")
        if len(imgs) != 1 or len(metas) != 1:
            raise ValueError(f"--basemap {folder}: need exactly one .jpg/.png and one .json, found {imgs + metas}")
        image = cv2.imread(str(imgs[0]), cv2.IMREAD_COLOR)
        if image is None:
            raise ValueError(f"{imgs[0]}: cannot be read as an image")
        try:
            raw = json.loads(metas[0].read_text())
            corners = {k: (float(raw[k][0]), float(raw[k][1])) for k in ("tl", "tr", "bl", "br")}
        except (json.JSONDecodeError, KeyError, TypeError, ValueError, IndexError) as exc:
            raise ValueError(f"{metas[0]}: expected tl, tr, bl, br as [lat, lon]: {exc!r}") from None
        return cls(image, corners, imgs[0])

    def to_latlon(self, px: np.ndarray) -> np.ndarray:
        """(N, 2) pixels (x, y; centre of the top-left pixel = (0, 0)) -> (N, 2) lat, lon degrees."""
        px = np.asarray(px, float).reshape(-1, 2)
        w, h = self.size
        s = (px[:, :1] + 0.5) / w
        t = (px[:, 1:] + 0.5) / h
        c = {k: np.asarray(v) for k, v in self.corners.items()}
        return (1 - s) * (1 - t) * c["tl"] + s * (1 - t) * c["tr"] + (1 - s) * t * c["bl"] + s * t * c["br"]

    def to_px(self, latlon: np.ndarray) -> np.ndarray:
        """(N, 2) lat, lon degrees -> (N, 2) pixels, inverting `to_latlon` by Newton's method."""
        latlon = np.asarray(latlon, float).reshape(-1, 2)
        w, h = self.size
        px = np.tile([(w - 1) / 2, (h - 1) / 2], (len(latlon), 1))
        dx, dy = np.array([1e-3, 0.0]), np.array([0.0, 1e-3])
        for _ in range(20):
            f = self.to_latlon(px) - latlon
            jx = (self.to_latlon(px + dx) - self.to_latlon(px - dx)) / 2e-3
            jy = (self.to_latlon(px + dy) - self.to_latlon(px - dy)) / 2e-3
            jac = np.stack([jx, jy], axis=2)  # (N, 2 latlon, 2 px)
            step = np.linalg.solve(jac, f[..., None])[..., 0]
            px = px - step
            if np.abs(step).max() < 1e-10:
                break
        return px


def parse_pair(text: str, name: str) -> tuple[float, float]:
    """'A,B' -> (A, B); a ValueError names the argument."""
    try:
        a, b = (float(x) for x in text.split(","))
    except ValueError:
        raise ValueError(f"{name} expects two numbers 'A,B', got {text!r}") from None
    return a, b


def read_image(path: str | Path) -> np.ndarray:
    """A camera frame as (H, W, 3) BGR uint8; a ValueError names a missing or unreadable file."""
    img = cv2.imread(str(path), cv2.IMREAD_COLOR) if Path(path).is_file() else None
    if img is None:
        raise ValueError(f"--image {path}: missing or not an image")
    return img


def zoom_crop(
    img: np.ndarray,
    center: tuple[float, float],
    size_px: int,
    zoom: int,
    marks: list[tuple[str, float, float]] = (),
    where: str = "image",
) -> np.ndarray:
    """A (size*zoom)^2 BGR crop of `img` centred on `center` (x, y pixels), with a labelled pixel grid,
    a red cross at `center` and numbered circles at `marks` [(label, x, y)]. Raises ValueError when
    the centre lies outside the image."""
    h, w = img.shape[:2]
    cx, cy = center
    if not (-0.5 <= cx <= w - 0.5 and -0.5 <= cy <= h - 0.5):
        raise ValueError(f"{where}: point ({cx:.1f}, {cy:.1f}) is outside the {w}x{h} image")
    if size_px < 4 or zoom < 1:
        raise ValueError(f"--size must be >= 4 and --zoom >= 1, got {size_px}, {zoom}")
    x0, y0 = int(round(cx)) - size_px // 2, int(round(cy)) - size_px // 2
    pad = np.zeros((size_px, size_px, 3), np.uint8)
    xa, ya, xb, yb = max(x0, 0), max(y0, 0), min(x0 + size_px, w), min(y0 + size_px, h)
    pad[ya - y0 : yb - y0, xa - x0 : xb - x0] = img[ya:yb, xa:xb]
    out = cv2.resize(pad, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
    _grid(out, x0, y0, size_px, zoom)

    def to_out(x: float, y: float) -> tuple[int, int]:
        return int(round((x - x0 + 0.5) * zoom)), int(round((y - y0 + 0.5) * zoom))

    for label, x, y in marks:
        p = to_out(x, y)
        if -50 < p[0] < out.shape[1] + 50 and -50 < p[1] < out.shape[0] + 50:
            cv2.circle(out, p, max(4, zoom), MARK, 1, cv2.LINE_AA)
            _text(out, label, (p[0] + zoom + 2, p[1] - zoom - 2), MARK)
    p = to_out(cx, cy)
    arm = 3 * zoom
    cv2.line(out, (p[0] - arm, p[1]), (p[0] - zoom, p[1]), CROSS, 1)
    cv2.line(out, (p[0] + zoom, p[1]), (p[0] + arm, p[1]), CROSS, 1)
    cv2.line(out, (p[0], p[1] - arm), (p[0], p[1] - zoom), CROSS, 1)
    cv2.line(out, (p[0], p[1] + zoom), (p[0], p[1] + arm), CROSS, 1)
    return out


def _grid(out: np.ndarray, x0: int, y0: int, size_px: int, zoom: int) -> None:
    """Minor lines on pixel borders (zoom >= 4); major lines through the centres of pixels whose
    coordinate is a multiple of 10 (5 when the crop is small), labelled with that coordinate."""
    step = 10 if size_px > 40 else 5
    if zoom >= 4:  # faint: blended at 30 % so the pixels stay readable
        border = np.arange(0, out.shape[0], zoom)
        faint = (0.7 * out[border] + 0.3 * np.array(GRID_MINOR)).astype(np.uint8)
        out[border] = faint
        border = np.arange(0, out.shape[1], zoom)
        out[:, border] = (0.7 * out[:, border] + 0.3 * np.array(GRID_MINOR)).astype(np.uint8)
    for k in range(size_px):
        c = int((k + 0.5) * zoom)
        if (x0 + k) % step == 0:
            cv2.line(out, (c, 0), (c, out.shape[0]), GRID_MAJOR, 1)
            _text(out, str(x0 + k), (c + 2, 12), GRID_MAJOR)
        if (y0 + k) % step == 0:
            cv2.line(out, (0, c), (out.shape[1], c), GRID_MAJOR, 1)
            _text(out, str(y0 + k), (2, c - 3), GRID_MAJOR)


def _text(img: np.ndarray, text: str, org: tuple[int, int], color: tuple[int, int, int]) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, 0.4, color, 1, cv2.LINE_AA)


def landmark_marks(path: str | Path | None, ortho: Ortho | None = None) -> list[tuple[str, float, float]]:
    """Numbered marks from a landmark file: image pixels, or orthophoto pixels when `ortho` is given."""
    if path is None:
        return []
    lm, _ = load_landmarks(path)
    pts = lm.uv if ortho is None else ortho.to_px(lm.latlon)
    return [(str(i + 1), float(x), float(y)) for i, (x, y) in enumerate(pts)]


def side_by_side(left: np.ndarray, right: np.ndarray) -> np.ndarray:
    h = max(left.shape[0], right.shape[0])

    def fit(a: np.ndarray) -> np.ndarray:
        return np.vstack([a, np.zeros((h - a.shape[0], a.shape[1], 3), np.uint8)])

    return np.hstack([fit(left), np.full((h, 8, 3), 255, np.uint8), fit(right)])


def check_overlay(landmarks: str | Path, image: np.ndarray, ortho: Ortho, ortho_zoom: int = 2) -> np.ndarray:
    """The whole camera frame and the orthophoto (scaled by `ortho_zoom`) side by side, every landmark
    of the file drawn on both with its number."""
    lm, _ = load_landmarks(landmarks)
    cam = image.copy()
    ort = cv2.resize(ortho.image, None, fx=ortho_zoom, fy=ortho_zoom, interpolation=cv2.INTER_CUBIC)
    for i, ((u, v), (x, y)) in enumerate(zip(lm.uv, ortho.to_px(lm.latlon), strict=True)):
        for img, (a, b) in ((cam, (u, v)), (ort, ((x + 0.5) * ortho_zoom - 0.5, (y + 0.5) * ortho_zoom - 0.5))):
            p = (int(round(a)), int(round(b)))
            cv2.circle(img, p, 5, MARK, 2, cv2.LINE_AA)
            _text(img, str(i + 1), (p[0] + 6, p[1] - 6), LABEL)
    return side_by_side(cam, ort)


def _ortho_center(ortho: Ortho, latlon: str | None, px: str | None) -> tuple[float, float]:
    if (latlon is None) == (px is None):
        raise ValueError("give exactly one of --at LAT,LON (or --latlon) and --px X,Y for the orthophoto")
    if px is not None:
        return parse_pair(px, "--px")
    x, y = ortho.to_px(np.array([parse_pair(latlon, "--at/--latlon")]))[0]
    return float(x), float(y)


def _describe_ortho(ortho: Ortho, x: float, y: float) -> str:
    la, lo = ortho.to_latlon(np.array([[x, y]]))[0]
    return f"orthophoto px ({x:.2f}, {y:.2f}) = lat {la:.8f}, lon {lo:.8f}"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m calibration.pick", description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    p_crop = sub.add_parser("crop", help="zoomed crop of a camera frame")
    p_crop.add_argument("--image", required=True)
    p_crop.add_argument("--at", required=True, help="U,V pixel centre of the crop")
    p_ortho = sub.add_parser("ortho", help="zoomed crop of the orthophoto")
    p_ortho.add_argument("--basemap", required=True)
    p_ortho.add_argument("--at", help="LAT,LON centre of the crop")
    p_ortho.add_argument("--px", help="X,Y orthophoto pixel centre of the crop")
    p_pair = sub.add_parser("pair", help="camera crop and orthophoto crop side by side")
    p_pair.add_argument("--image", required=True)
    p_pair.add_argument("--at", required=True, help="U,V in the camera frame")
    p_pair.add_argument("--basemap", required=True)
    p_pair.add_argument("--latlon", help="LAT,LON on the orthophoto")
    p_pair.add_argument("--px", help="X,Y orthophoto pixel")
    p_pair.add_argument("--ortho-size", type=int, default=40)
    p_pair.add_argument("--ortho-zoom", type=int, default=12)
    p_check = sub.add_parser("check", help="all landmarks of a file on the frame and the orthophoto")
    p_check.add_argument("--image", required=True)
    p_check.add_argument("--basemap", required=True)
    p_check.add_argument("--ortho-zoom", type=int, default=2)
    for p, size, zoom in ((p_crop, 120, 6), (p_ortho, 60, 10), (p_pair, 80, 6)):
        p.add_argument("--size", type=int, default=size, help="crop side in source pixels")
        p.add_argument("--zoom", type=int, default=zoom, help="integer zoom factor")
        p.add_argument("--landmarks", help="landmark file whose points are drawn, numbered")
    p_check.add_argument("--landmarks", required=True)
    for p in (p_crop, p_ortho, p_pair, p_check):
        p.add_argument("--out", required=True, help="PNG to write")
    args = ap.parse_args(argv)
    try:
        out = _run(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not cv2.imwrite(str(args.out), out):
        print(f"error: --out {args.out}: cannot be written", file=sys.stderr)
        return 2
    print(f"wrote {args.out}")
    return 0


def _run(args: argparse.Namespace) -> np.ndarray:
    if args.landmarks is not None:
        lm, _ = load_landmarks(args.landmarks)
        print("landmarks: " + ", ".join(f"{i + 1}={lid}" for i, lid in enumerate(lm.ids)))
    if args.cmd == "crop":
        u, v = parse_pair(args.at, "--at")
        print(f"camera px ({u:.2f}, {v:.2f})")
        return zoom_crop(read_image(args.image), (u, v), args.size, args.zoom, landmark_marks(args.landmarks), "--at")
    ortho = Ortho.load(args.basemap)
    if args.cmd == "check":
        return check_overlay(args.landmarks, read_image(args.image), ortho, args.ortho_zoom)
    if args.cmd == "ortho":
        x, y = _ortho_center(ortho, args.at, args.px)
        print(_describe_ortho(ortho, x, y))
        return zoom_crop(ortho.image, (x, y), args.size, args.zoom, landmark_marks(args.landmarks, ortho), "--at/--px")
    u, v = parse_pair(args.at, "--at")
    x, y = _ortho_center(ortho, args.latlon, args.px)
    print(f"camera px ({u:.2f}, {v:.2f}); {_describe_ortho(ortho, x, y)}")
    cam = zoom_crop(read_image(args.image), (u, v), args.size, args.zoom, landmark_marks(args.landmarks), "--at")
    ort = zoom_crop(
        ortho.image, (x, y), args.ortho_size, args.ortho_zoom, landmark_marks(args.landmarks, ortho), "--latlon/--px"
    )
    return side_by_side(cam, ort)


if __name__ == "__main__":
    sys.exit(main())
