"""``mocap reconstruct INPUT --calibration FILE -o OUT``: 2D detections -> marker file.

INPUT is a recording folder (its recorded 2D detections, or blob detection over its frames)
or a ``frame,camera,x,y`` CSV (raw pixels; camera = name or index in the calibration file).
OUT ends in .c3d, .trc or .csv. The work is ``reconstruct.app.run_reconstruct``.
"""
from __future__ import annotations

import argparse
import shutil
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("reconstruct", help="reconstruct 3D marker trajectories from 2D "
                       "detections (recording folder or CSV) to C3D/TRC/CSV",
                       description=__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", metavar="INPUT", help="recording folder or frame,camera,x,y CSV")
    p.add_argument("--calibration", metavar="FILE", default=None,
                   help="calibration TOML (default: the recording's own, if it names one)")
    p.add_argument("-o", "--out", required=True, metavar="OUT",
                   help="output marker file: .c3d, .trc or .csv")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes (default: all cores)")
    p.add_argument("--fill-max-gap", type=int, default=0, metavar="F",
                   help="spline-fill interior gaps of at most F frames (default 0: off)")
    p.add_argument("--cutoff-hz", type=float, default=None, metavar="HZ",
                   help="zero-phase Butterworth low-pass cutoff (default: no filtering)")
    p.add_argument("--rate", type=float, default=None, metavar="HZ",
                   help="frame rate when the input does not carry one")
    p.set_defaults(func=run)


class _Status:
    def __init__(self):
        self.width = max(40, shutil.get_terminal_size((100, 20)).columns - 1)
        self.shown = False

    def __call__(self, stage: str, done: int, total: int) -> None:
        msg = f"{stage}: {done}/{total} frames" if total else f"{stage}: {done} frames"
        if total:
            msg += f" ({100 * done / total:.0f}%)"
        sys.stderr.write("\r" + msg[:self.width].ljust(self.width))
        sys.stderr.flush()
        self.shown = True


def run(args) -> int:
    from mocap.paths import check_outputs
    from reconstruct.app import ReconstructJob, run_reconstruct
    from reconstruct.pipeline import ReconstructionConfig

    check_outputs({"the input": args.input, "--calibration": args.calibration},
                  {"-o": args.out})
    cfg = ReconstructionConfig(fill_max_gap=args.fill_max_gap, filter_cutoff_hz=args.cutoff_hz)
    job = ReconstructJob(input=args.input, calibration=args.calibration, output=args.out,
                         config=cfg, rate_hz=args.rate, workers=args.workers)
    status = _Status()
    summary = run_reconstruct(job, progress=status)
    if status.shown:
        sys.stderr.write("\n")
    print(summary.table())
    return 0
