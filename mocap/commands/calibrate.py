"""``mocap calibrate wand``: rig extrinsics from a waved wand / single point.

INPUT is a 2D observation CSV (``frame,camera,x,y``) or a recording folder (its detections).
Writes the calibration TOML (``calibration.rig_io.save_rig``) and a report (.txt + .png)
beside it. ``mocap calibrate intrinsics IMAGES --board chessboard:COLSxROWS:SQUARE_MM`` (inner
corners) or ``--board charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT]`` (squares; DICT default
DICT_5X5_100) calibrates one camera. ``mocap calibrate world CALIB.toml INPUT --l-frame
X_MM,Y_MM[,XMID_MM] | --reference-mm "x,y,z;..." | --floor -o out.toml`` moves a calibrated rig
into the world frame (right-handed, z up, floor z = 0) from static markers seen in INPUT.
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


def _parse_board(spec: str) -> dict:
    parts = spec.split(":")
    kind = parts[0].lower()
    try:
        if kind == "chessboard" and len(parts) == 3:
            cols, rows = (int(v) for v in parts[1].lower().split("x"))
            return dict(kind=kind, cols=cols, rows=rows, square_m=float(parts[2]) / 1000.0)
        if kind == "charuco" and len(parts) in (4, 5):
            cols, rows = (int(v) for v in parts[1].lower().split("x"))
            return dict(kind=kind, cols=cols, rows=rows, square_m=float(parts[2]) / 1000.0,
                        marker_m=float(parts[3]) / 1000.0,
                        dictionary=parts[4] if len(parts) == 5 else "DICT_5X5_100")
    except ValueError:
        pass
    raise ValueError(f"--board {spec!r}: expected chessboard:COLSxROWS:SQUARE_MM (inner corners) "
                     "or charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT] (squares)")


def _intrinsics(args) -> int:
    import cv2

    from calibration.camera import Rig
    from calibration.intrinsics import calibrate_charuco, calibrate_chessboard
    try:
        board = _parse_board(args.board)
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
    kind = board.pop("kind")
    try:
        if kind == "chessboard":
            res = calibrate_chessboard(imgs, name=args.name, **board)
        else:
            res = calibrate_charuco(imgs, name=args.name, **board)
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


def _reference(args):
    import numpy as np

    from calibration.world import l_frame_reference
    if args.l_frame:
        v = [float(x) for x in args.l_frame.split(",")]
        if len(v) not in (2, 3):
            raise ValueError(f"--l-frame {args.l_frame!r}: expected X_MM,Y_MM[,XMID_MM]")
        return l_frame_reference(*v)
    rows = [r for r in args.reference_mm.split(";") if r.strip()]
    ref = np.array([[float(x) for x in r.split(",")] for r in rows]) / 1000.0
    if ref.ndim != 2 or ref.shape[1] != 3 or len(ref) < 3:
        raise ValueError(f"--reference-mm {args.reference_mm!r}: expected >= 3 'x,y,z' rows")
    return ref


def _world(args) -> int:
    from calibration.static_markers import static_points
    from calibration.world import align_floor, align_world
    rig = load_rig(args.calibration)
    modes = sum(bool(m) for m in (args.l_frame, args.reference_mm, args.floor))
    if modes != 1:
        print("error: give exactly one of --l-frame, --reference-mm, --floor", file=sys.stderr)
        return 2
    try:
        ref = None if args.floor else _reference(args)
        det = _load_detections(Path(args.input), rig.names)
        sp = static_points(det, rig, gate_px=args.gate_px)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(f"{len(sp.points)} static markers triangulated (reprojection RMS "
          f"{', '.join(f'{e:.3f}' for e in sp.rms_px)} px)")
    res = align_floor(rig, sp.points) if args.floor else align_world(rig, sp.points, ref)
    if not res.ok:
        print(f"world alignment failed: {res.reason}", file=sys.stderr)
        return 1
    what = "floor plane" if args.floor else "reference markers"
    print(f"{what} residual {res.rms_m * 1000:.3f} mm RMS")
    for c in res.rig:
        x, y, z = c.center
        print(f"{c.name:>12} centre ({x:+.3f}, {y:+.3f}, {z:+.3f}) m")
    save_rig(res.rig, args.output)
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
    i = sub.add_parser("intrinsics", help="intrinsics of one camera from board images")
    i.add_argument("images", nargs="+")
    i.add_argument("--board", required=True,
                   help="chessboard:COLSxROWS:SQUARE_MM (inner corners) or "
                        "charuco:COLSxROWS:SQUARE_MM:MARKER_MM[:DICT] (squares)")
    i.add_argument("--name", default="cam_1", help="camera name in the TOML")
    i.add_argument("-o", "--output", required=True)
    i.set_defaults(func=_intrinsics)
    g = sub.add_parser("world", help="set origin, axes and floor from static markers")
    g.add_argument("calibration", help="calibration TOML (e.g. from 'calibrate wand')")
    g.add_argument("input", help="2D observation CSV (frame,camera,x,y) or recording folder "
                                 "of the static markers")
    g.add_argument("--l-frame", help="X_MM,Y_MM[,XMID_MM]: corner at the origin, markers on "
                                     "+x, +y (and on x), lying on the floor")
    g.add_argument("--reference-mm", help="known marker positions 'x,y,z;x,y,z;...' (mm, world)")
    g.add_argument("--floor", action="store_true", help="plane fit to markers on the floor")
    g.add_argument("--gate-px", type=float, default=2.0, help="cross-camera match gate (px)")
    g.add_argument("-o", "--output", required=True, help="calibration TOML to write")
    g.set_defaults(func=_world)
