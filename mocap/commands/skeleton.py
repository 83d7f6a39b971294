"""``mocap skeleton MARKERS.c3d|.trc -o skeleton.bvh``: a skeleton from unlabelled markers.

Reads the marker file (``reconstruct.marker_files.read_markers``), runs
``skeleton.app.run_skeleton`` (marker sets, segments, joints, topology, rigid skeleton,
fit back, inverse kinematics) with progress on stderr, writes the BVH (and the skeleton
JSON with ``--report``) and prints the summary and the per-marker deviation tables.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

#: mean fitted-vs-measured marker deviation above which the run warns (mm): rigid segments
#: on skin markers fit within a few mm (the thesis' captured data); hw_sim figures with 1 mm
#: noise fit at ~1.4 mm
POOR_FIT_MM = 10.0


def _run(args) -> int:
    from mocap.paths import check_outputs
    from reconstruct.marker_files import read_markers
    from skeleton.app import run_skeleton, write_outputs
    from skeleton.report import summary_table

    def say(msg):
        print(f"[skeleton] {msg}", file=sys.stderr, flush=True)

    check_outputs({"the input": args.input}, {"-o": args.output, "--report": args.report},
                  existing_folder=True)
    if Path(args.output).suffix.lower() != ".bvh":
        say(f"warning: {args.output} does not end in .bvh (a BVH file is written)")
    with warnings.catch_warnings():
        # libraries' warnings (c3d, NumPy, scikit-learn) become progress lines, once each
        warnings.simplefilter("default")
        shown = set()

        def show(message, category, filename, lineno, file=None, line=None):
            text = f"warning: {str(message).strip()}"
            if text not in shown:
                shown.add(text)
                say(text)
        warnings.showwarning = show
        data = read_markers(Path(args.input))
        say(f"read {args.input}: {data.n_markers} trajectories, {data.n_frames} frames at "
            f"{data.rate_hz:g} Hz")
        run = run_skeleton(data, n_segments=args.segments, rng=args.seed, progress=say,
                           merge=not args.no_merge, min_frames=args.min_frames,
                           ik=not args.closed_form, workers=args.workers)
    dev_mm = 1e3 * run.deviation.overall_mean_m
    if dev_mm > POOR_FIT_MM:
        say(f"warning: mean marker deviation {dev_mm:.1f} mm (> {POOR_FIT_MM:g} mm): the "
            f"markers fit this rigid skeleton poorly (soft tissue, a wrong --segments, "
            f"or markers swapped between segments); see the per-marker table")
    paths = write_outputs(run, args.output, args.report, units=args.units)
    print(summary_table(run.rigid, run.deviation, run.result.junctions))
    print()
    print(run.deviation.format())
    for p in paths:
        print(f"wrote {p}")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "skeleton", help="skeleton (BVH) from unlabelled marker data",
        description="Merge trajectory fragments into markers, cluster them into rigid "
                    "segments, fit the joints, build the tree and a rigid skeleton, fit it "
                    "back to every frame; write a BVH (and the skeleton JSON with --report) "
                    "and print the segment and per-marker deviation tables.",
        epilog="example: mocap skeleton walk.c3d -o walk.bvh --report walk.json",
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("input", help="marker file (.c3d, .trc or .csv)")
    p.add_argument("-o", "--output", required=True, help="BVH file to write")
    p.add_argument("--segments", type=_positive_int, default=None,
                   help="number of segments, 1 to the number of markers (default: chosen "
                        "by the eigengap)")
    p.add_argument("--report", default=None, help="skeleton JSON to write")
    p.add_argument("--units", choices=("m", "cm", "mm"), default="m", help="BVH length unit")
    p.add_argument("--min-frames", type=int, default=10,
                   help="drop trajectory fragments shorter than this")
    p.add_argument("--no-merge", action="store_true",
                   help="trust the file's marker ids (skip merging fragments)")
    p.add_argument("--closed-form", action="store_true",
                   help="keep the thesis' closed-form fit (skip the whole-skeleton IK)")
    p.add_argument("--seed", type=int, default=0,
                   help="seed of the randomised steps (spectral clustering, multi-starts)")
    p.add_argument("--workers", type=_positive_int, default=None,
                   help="processes for the segment-pair joint costs (default: every CPU)")
    p.set_defaults(func=_run)


def _positive_int(text: str) -> int:
    try:
        n = int(text)
    except ValueError:
        n = 0
    if n < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {text!r}")
    return n
