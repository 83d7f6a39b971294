"""``mocap capture``: record cameras + sync box to a session folder (or a simulated rig)."""
from __future__ import annotations

import math
import shutil
import sys
from pathlib import Path

from capture.camera import CameraSettings, PixelFormat
from capture.errors import CaptureError
from capture.live import record_live
from capture.syncbox import SyncBox, SyncConfig


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "capture", help="record a capture session to a folder",
        description="Record synchronised cameras to DIR (metadata.json + one frames file per "
                    "camera). --sim runs a simulated rig (pty sync box + rendered cameras).")
    p.add_argument("--sim", action="store_true", help="use the simulated rig")
    p.add_argument("--cameras", type=int, default=4, help="number of simulated cameras")
    p.add_argument("--size", type=int, nargs=2, default=(320, 256), metavar=("W", "H"),
                   help="simulated image size in px")
    p.add_argument("--camera", action="append", default=[], metavar="/dev/videoN",
                   help="a real camera (repeat for each, in rig order)")
    p.add_argument("--backend", choices=("v4l2", "opencv"), default="v4l2")
    p.add_argument("--sync", metavar="PORT", help="sync box serial port, e.g. /dev/ttyACM0")
    p.add_argument("--rate", type=float, default=100.0, help="frame rate in Hz")
    p.add_argument("--exposure-us", type=float, default=None)
    p.add_argument("--strobe-us", type=int, default=500, help="strobe width in us")
    p.add_argument("--gain", type=float, default=None)
    p.add_argument("--pixel-format", choices=[f.name for f in PixelFormat], default=None)
    p.add_argument("--duration", type=float, default=5.0, help="seconds to record")
    p.add_argument("--calibration", default=None,
                   help="calibration TOML this session uses (--sim: the true rig is saved "
                        "as DIR/sim_rig.toml)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated rig")
    p.add_argument("--out", required=True, metavar="DIR", help="session folder to create")
    p.set_defaults(func=run)


def _status(line: str) -> None:
    width = max(40, shutil.get_terminal_size((160, 20)).columns - 1)
    sys.stderr.write("\r" + line[:width].ljust(width))
    sys.stderr.flush()


def run(args) -> int:
    if args.sim == bool(args.camera):
        raise ValueError("give either --sim or one or more --camera /dev/videoN")
    if args.sim and args.sync:
        raise ValueError("--sync is for real cameras; --sim runs its own simulated sync box")
    if not (args.duration > 0 and math.isfinite(args.duration)):
        raise ValueError(f"--duration {args.duration}: expected a finite duration > 0 (s)")
    if (Path(args.out) / "metadata.json").exists():       # before anything is written there
        raise ValueError(f"{args.out} already holds a recording")
    if args.sim and not all(16 <= v <= 8192 for v in args.size):
        raise ValueError(f"--size {args.size[0]} {args.size[1]}: expected 16..8192 px each")
    if args.calibration is not None:
        # the recording names it for later reprocessing: an absolute path, that exists now
        cal = Path(args.calibration).resolve()
        if not cal.is_file():
            raise FileNotFoundError(f"--calibration {args.calibration}: file not found")
        args.calibration = str(cal)
    settings = CameraSettings(rate_hz=args.rate, exposure_us=args.exposure_us, gain=args.gain,
                              pixel_format=PixelFormat[args.pixel_format]
                              if args.pixel_format else None)
    sim_box, cameras, box = None, [], None
    made = []                      # what this run created before its recording started
    try:
        if args.sim:
            from calibration.rig_io import save_rig
            from hw_sim.sim_camera import sim_rig
            sim_box, cameras, rig = sim_rig(args.cameras, size=tuple(args.size), rng=args.seed)
            port = sim_box.port
            if args.calibration is None:  # the simulated rig's true calibration, inside
                out = Path(args.out)
                if not out.exists():
                    made.append(out)
                out.mkdir(parents=True, exist_ok=True)
                made.append(save_rig(rig, out / "sim_rig.toml"))
                args.calibration = "sim_rig.toml"
        else:
            cameras = [_open_camera(path, args.backend) for path in args.camera]
            port = args.sync
        for c in cameras:
            c.configure(settings)
        if port:
            box = SyncBox(port)
            box.configure(SyncConfig(rate_hz=args.rate, strobe_width_us=args.strobe_us))
        result = record_live(cameras, box, args.out, duration_s=args.duration,
                             rate_hz=args.rate, calibration=args.calibration, on_status=_status)
    except CaptureError as e:
        if (Path(args.out) / "metadata.json").exists():
            kept = f"recording in {args.out} closed; frames before the fault are kept"
        else:                      # the fault came before the recording: leave nothing behind
            for path in reversed(made):
                if path.is_dir():
                    if not any(path.iterdir()):
                        path.rmdir()
                else:
                    path.unlink(missing_ok=True)
            kept = "no recording was made"
        sys.stderr.write(f"\nmocap capture: {type(e).__name__}: {e}\n({kept})\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write(f"\nmocap capture: interrupted (recording in {args.out} closed)\n")
        return 130
    finally:
        for c in cameras:
            try:
                c.close()
            except CaptureError:
                pass
        if box is not None:
            box.close()
        if sim_box is not None:
            sim_box.close()
    s, r = result.session, result.recording
    sys.stderr.write("\n")
    if s.frame_sets == 0:
        lost = "; ".join(f"{c.camera_id}: {c.error}" for c in s.cameras if not c.connected)
        sys.stderr.write(f"mocap capture: no frame set was recorded to {result.folder}"
                         + (f" ({lost})" if lost else "") + "\n")
        return 1
    print(f"recorded {s.frame_sets} frame sets ({s.complete_sets} complete) in "
          f"{s.elapsed_s:.1f} s to {result.folder}")
    print(f"{'camera':<10} {'frames':>7} {'drops':>6} {'late':>5} {'nopulse':>8} "
          f"{'missing':>8} {'latency_ms':>10}  state")
    for c in s.cameras:
        state = "ok" if c.connected else f"LOST ({c.error})"
        print(f"{c.camera_id:<10} {c.frames:>7} {c.drops:>6} {c.late:>5} {c.unmatched:>8} "
              f"{c.missing:>8} {c.latency_ms:>10.1f}  {state}")
    print(f"bytes/frame {r['bytes_per_frame']:.0f}, compression {r['compression_ratio']:.2f}x")
    return 0


def _open_camera(path: str, backend: str):
    if backend == "opencv":
        from capture.opencv_camera import OpenCVCamera
        return OpenCVCamera(path)
    from capture.v4l2 import V4L2Camera
    return V4L2Camera(path)
