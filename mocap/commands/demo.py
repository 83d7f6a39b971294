"""``mocap demo [--out DIR]``: the whole pipeline on the simulated rig (see mocap.demo)."""
from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="run the simulated rig end to end: wand calibration, "
                       "IR frames, blobs, reconstruction, C3D/TRC, skeleton BVH",
                       description=__doc__)
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--cameras", type=int, default=8, help="number of cameras (default 8)")
    p.add_argument("--frames", type=int, default=240,
                   help="frames of the moving figure (default 240 = 2 s at 120 Hz)")
    p.add_argument("--wand-frames", type=int, default=1500, help="wand frames (default 1500)")
    p.add_argument("--workers", type=int, default=None, help="worker processes")
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.set_defaults(func=_run)


def _run(args) -> int:
    from mocap.demo import DemoConfig, run_demo

    cfg = DemoConfig(n_cameras=args.cameras, figure_frames=args.frames,
                     wand_frames=args.wand_frames, seed=args.seed, workers=args.workers)
    res = run_demo(args.out, cfg, progress=lambda s: print(s, file=sys.stderr, flush=True))
    print(res.table())
    return 0
