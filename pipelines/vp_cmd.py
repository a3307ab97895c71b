"""``octofactor vp``: vanishing points of images, one JSON object per line and image."""
from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

from estimation.errors import OctofactorError
from pipelines.cli_common import add_output

# BGR colours of VP 0, 1, 2 (and grey for segments that support none)
_COLOURS = ((0, 0, 255), (0, 200, 0), (255, 80, 0))
_UNASSIGNED = (150, 150, 150)


class IntrinsicsError(OctofactorError):
    """The --intrinsics argument is not four positive numbers fx,fy,cx,cy."""


def register(add_command) -> None:
    parser = add_command("vp", "vanishing points of images (seed paper method or Manhattan)")
    parser.add_argument("images", nargs="+", metavar="IMAGE", help="image files")
    parser.add_argument("--intrinsics", required=True, metavar="FX,FY,CX,CY",
                        help="pinhole intrinsics in pixels (0-based principal point)")
    parser.add_argument("--method", choices=("seed", "manhattan"), default="manhattan",
                        help="seed: Canny + Hough + least squares (one VP); manhattan: up to "
                             "three orthogonal VPs from LSD segments (default)")
    parser.add_argument("--json", action="store_true",
                        help="print one JSON object per image and line (the default output; "
                             "without it a short text line per image)")
    add_output(parser, "write overlay PNGs (segments coloured by VP, VPs marked) to "
               "OUT_DIR/<image>_vp.png", required=False, metavar="OUT_DIR",
               old_option="--plot")
    parser.set_defaults(func=run)


def parse_intrinsics(text: str):
    """Return the 3x3 camera matrix from ``"fx,fy,cx,cy"``."""
    import numpy as np

    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) != 4 or not all(math.isfinite(v) for v in values) or min(values[:2]) <= 0:
        raise IntrinsicsError(f"--intrinsics: expected four numbers fx,fy,cx,cy with fx, fy > 0, "
                              f"got {text!r}")
    from pipelines.validate import intrinsics

    fx, fy, cx, cy = intrinsics("--intrinsics", values)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _finite_or_none(x: float):
    return float(x) if math.isfinite(x) else None


def result_to_json(image: str, result) -> dict:
    """Return the JSON-ready record of one image's :class:`VPResult` (null for infinity)."""
    vps = []
    for vp in result.vps:
        vps.append({
            "u": None if vp.uv is None else float(vp.uv[0]),
            "v": None if vp.uv is None else float(vp.uv[1]),
            "direction": [float(x) for x in vp.direction],
            "cov": [[_finite_or_none(x) for x in row] for row in vp.cov],
            "inliers": int(len(vp.inliers)),
        })
    return {"image": image, "ms": round(float(result.ms), 3), "vps": vps}


def write_overlay(path: Path, gray, result) -> None:
    """Write a PNG of the image with segments coloured by VP and the VPs marked."""
    import cv2
    import numpy as np

    from estimation.fileio import atomic_write

    canvas = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
    canvas = (canvas * 0.6).astype(np.uint8)
    colour_of = np.full(len(result.segments), -1)
    for k, vp in enumerate(result.vps):
        colour_of[vp.inliers] = k
    for seg, k in zip(np.round(result.segments).astype(int), colour_of, strict=True):
        colour = _COLOURS[k % 3] if k >= 0 else _UNASSIGNED
        cv2.line(canvas, tuple(seg[:2]), tuple(seg[2:]), colour, 2 if k >= 0 else 1, cv2.LINE_AA)
    h, w = gray.shape[:2]
    for k, vp in enumerate(result.vps):
        if vp.uv is None or not np.all(np.abs(vp.uv) < 1e6):
            continue
        centre = tuple(int(round(x)) for x in vp.uv)
        if 0 <= centre[0] < w and 0 <= centre[1] < h:
            cv2.drawMarker(canvas, centre, _COLOURS[k % 3], cv2.MARKER_CROSS, 25, 2)
        else:
            # outside the image: an arrow from the centre towards the VP
            c = np.array([w / 2.0, h / 2.0])
            tip = c + 0.45 * min(w, h) * (vp.uv - c) / max(np.linalg.norm(vp.uv - c), 1e-9)
            cv2.arrowedLine(canvas, tuple(int(x) for x in c), tuple(int(x) for x in tip),
                            _COLOURS[k % 3], 2, cv2.LINE_AA, tipLength=0.15)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:
        raise OctofactorError(f"{path}: PNG encoding failed")
    with atomic_write(path, "wb") as handle:
        handle.write(png.tobytes())


def run(args: argparse.Namespace) -> int:
    from perception.lines import read_image
    from perception.vanishing_points import detect_manhattan, detect_seed

    K = parse_intrinsics(args.intrinsics)
    if args.output is not None:
        from pipelines.validate import output_folder

        output_folder("-o", args.output)
        os.makedirs(args.output, exist_ok=True)
    for image_path in args.images:
        gray = read_image(image_path)
        if args.method == "seed":
            result = detect_seed(gray, K=K)
        else:
            result = detect_manhattan(gray, K)
        record = result_to_json(image_path, result)
        if args.json:
            print(json.dumps(record), flush=True)
        else:
            parts = []
            for vp in record["vps"]:
                where = ("infinity" if vp["u"] is None else f"({vp['u']:.1f}, {vp['v']:.1f})")
                parts.append(f"{where} [{vp['inliers']} segments]")
            print(f"{image_path}: {record['ms']:.1f} ms, "
                  f"{len(parts)} VP(s) {'; '.join(parts)}", flush=True)
        if args.output is not None:
            write_overlay(Path(args.output) / (Path(image_path).stem + "_vp.png"), gray, result)
    return 0


if __name__ == "__main__":  # pragma: no cover
    from pipelines.cli import main

    sys.exit(main(["vp", *sys.argv[1:]]))
