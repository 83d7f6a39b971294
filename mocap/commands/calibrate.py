"""``mocap calibrate wand``: rig extrinsics from a waved wand / single point.

INPUT is a 2D observation CSV (``frame,camera,x,y``) or a recording folder (its detections).
Writes the calibration TOML (``calibration.rig_io.save_rig``) and a report (.txt + .png)
beside it. ``mocap calibrate intrinsics IMAGES --board chessboard:COLSxROWS:SQUARE_MM``
calibrates one camera. ChArUco boards and a ``world`` subcommand are not implemented yet.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from calibration.camera import Camera
from calibration.rig_io import load_rig, save_rig
from calibration.wand import calibrate_wand
from capture.detections import read_detections_csv


def _load_detections(path: Path, names=None):
    if path.is_dir():
        from capture.replay import read_recording_detections
        det = read_recording_detections(path)
        if det is None:
            raise ValueError(f"{path}: recording has no detections file")
        return det
    return read_detections_csv(path, camera_names=names)


def _wand(args) -> int:
    names = None
    rig0 = None
    if args.intrinsics:
        rig0 = load_rig(args.intrinsics)
        names = rig0.names
    det = _load_detections(Path(args.input), names)
    if rig0 is not None:
        init = list(rig0)
    else:
        if args.focal_px is None or args.size is None:
            print("error: give --intrinsics FILE or --focal-px F --size WxH", file=sys.stderr)
            return 2
        w, h = (int(v) for v in args.size.lower().split("x"))
        init = [Camera.from_params(name=n, size=(w, h), fx=args.focal_px)
                for n in det.camera_names]
    wand_mm = tuple(float(v) for v in args.wand_mm.split(","))
    res = calibrate_wand(det, initial_intrinsics=init, wand_mm=wand_mm,
                         single_point=args.single_point, refine_intrinsics=args.refine_intrinsics,
                         rng=args.seed, progress=lambda s: print(s, file=sys.stderr))
    if not res.ok:
        print(f"calibration failed: {res.reason}", file=sys.stderr)
        return 1
    out = Path(args.output)
    save_rig(res.rig, out)
    text = res.report.summary()
    out.with_suffix(".report.txt").write_text(text + "\n")
    res.report.save_figure(out.with_suffix(".report.png"), res.residual_px)
    print(text)
    print(f"wrote {out}")
    return 0


def _parse_board(spec: str):
    parts = spec.split(":")
    if len(parts) != 3 or parts[0] != "chessboard":
        raise ValueError(f"--board {spec!r}: expected chessboard:COLSxROWS:SQUARE_MM "
                         "(inner corners; charuco is not implemented yet)")
    cols, rows = (int(v) for v in parts[1].lower().split("x"))
    return cols, rows, float(parts[2]) / 1000.0


def _intrinsics(args) -> int:
    import cv2

    from calibration.camera import Rig
    from calibration.intrinsics import calibrate_chessboard
    try:
        cols, rows, sq = _parse_board(args.board)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    imgs = []
    for f in args.images:
        im = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        if im is None:
            print(f"error: cannot read image {f}", file=sys.stderr)
            return 2
        imgs.append(im)
    try:
        res = calibrate_chessboard(imgs, cols=cols, rows=rows, square_m=sq, name=args.name)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1
    if not res.ok:
        print(f"calibration failed: {res.reason}", file=sys.stderr)
        return 1
    for f, u, e in zip(args.images, res.used, res.per_view_rms_px):
        print(f"{f}: {'used' if u else 'rejected'} rms {e:.3f} px")
    print(f"overall rms {res.rms_px:.3f} px")
    save_rig(Rig(cameras=(res.camera,)), args.output)
    print(f"wrote {args.output}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser("calibrate", help="calibrate cameras (wand)")
    sub = p.add_subparsers(dest="calibrate_cmd", required=True)
    w = sub.add_parser("wand", help="extrinsics from a waved wand or single point")
    w.add_argument("input", help="2D observation CSV (frame,camera,x,y) or recording folder")
    w.add_argument("--wand-mm", default="0,250,500", help="marker positions along the wand, mm")
    w.add_argument("--single-point", action="store_true", help="one waved marker (no scale)")
    w.add_argument("--intrinsics", help="calibration TOML with the cameras' intrinsics")
    w.add_argument("--focal-px", type=float, help="nominal focal length (px) for all cameras")
    w.add_argument("--size", help="image size WxH (with --focal-px)")
    w.add_argument("--refine-intrinsics", action="store_true")
    w.add_argument("--seed", type=int, default=0)
    w.add_argument("-o", "--output", required=True, help="calibration TOML to write")
    w.set_defaults(func=_wand)
    i = sub.add_parser("intrinsics", help="intrinsics of one camera from chessboard images")
    i.add_argument("images", nargs="+")
    i.add_argument("--board", required=True, help="chessboard:COLSxROWS:SQUARE_MM (inner corners)")
    i.add_argument("--name", default="cam_1", help="camera name in the TOML")
    i.add_argument("-o", "--output", required=True)
    i.set_defaults(func=_intrinsics)
