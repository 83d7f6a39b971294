"""``mocap calibrate wand`` on a simulated wand CSV writes a rig close to truth."""
import numpy as np

from calibration.rig_io import load_rig
from capture.detections import write_detections_csv
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import wand
from mocap.cli import main

CENTRE_TOL_M = 1e-8  # noise-free input: camera centres (camera-0 frame) to solver precision


def test_cli_wand_csv(tmp_path):
    rig = make_rig(4, rng=1)
    ob = observe(rig, wand(120, rng=2), rng=3, noise_px=0.0)
    csv = write_detections_csv(ob.detections, tmp_path / "wand.csv")
    out = tmp_path / "cal.toml"
    rc = main(["calibrate", "wand", str(csv), "--focal-px", repr(float(rig[0].K[0, 0])),
               "--size", "1280x1024", "-o", str(out)])
    assert rc == 0
    est = load_rig(out)
    assert (tmp_path / "cal.report.txt").is_file() and (tmp_path / "cal.report.png").is_file()
    R0, t0 = rig[0].R, rig[0].t
    for ce, ct in zip(est, rig):
        Rw, tw = ce.R @ R0, ce.R @ t0 + ce.t
        assert np.linalg.norm(-Rw.T @ tw - ct.center) < CENTRE_TOL_M


def test_cli_wand_needs_intrinsics(tmp_path):
    rig = make_rig(3, rng=1)
    ob = observe(rig, wand(20, rng=2), rng=3, noise_px=0.0)
    csv = write_detections_csv(ob.detections, tmp_path / "wand.csv")
    assert main(["calibrate", "wand", str(csv), "-o", str(tmp_path / "c.toml")]) == 2


def test_cli_intrinsics_chessboard(tmp_path):
    import cv2

    from tests.calibration.test_intrinsics import COLS, ROWS, SQUARE_M, _views
    files = []
    for k, im in enumerate(_views()):
        f = tmp_path / f"v{k}.png"
        cv2.imwrite(str(f), im)
        files.append(str(f))
    out = tmp_path / "intr.toml"
    board = f"chessboard:{COLS}x{ROWS}:{SQUARE_M * 1000}"
    assert main(["calibrate", "intrinsics", *files, "--board", board, "-o", str(out)]) == 0
    cam = load_rig(out)[0]
    assert abs(cam.K[0, 0] / 600.0 - 1) < 0.01
    assert main(["calibrate", "intrinsics", *files, "--board", "chessboard:10x6:30",
                 "-o", str(out)]) == 1
