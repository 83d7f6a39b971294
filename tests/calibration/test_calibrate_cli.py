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


def test_cli_intrinsics_charuco(tmp_path):
    import cv2

    from tests.calibration.test_charuco import (COLS, DICT, MARKER_M, ROWS, SQUARE_M,
                                                render_views)
    files = []
    for k, im in enumerate(render_views()):
        f = tmp_path / f"c{k}.png"
        cv2.imwrite(str(f), im)
        files.append(str(f))
    out = tmp_path / "intr.toml"
    board = f"charuco:{COLS}x{ROWS}:{SQUARE_M * 1000}:{MARKER_M * 1000}:{DICT}"
    assert main(["calibrate", "intrinsics", *files, "--board", board, "-o", str(out)]) == 0
    assert abs(load_rig(out)[0].K[0, 0] / 600.0 - 1) < 0.01
    wrong = f"charuco:{COLS}x{ROWS}:{SQUARE_M * 1000}:{MARKER_M * 1000}:DICT_4X4_50"
    assert main(["calibrate", "intrinsics", *files, "--board", wrong, "-o", str(out)]) == 1
    assert main(["calibrate", "intrinsics", *files, "--board", "charuco:7x5", "-o",
                 str(out)]) == 2


def test_cli_wand_then_world_recovers_the_world_frame(tmp_path, capsys):
    """Wand CSV -> camera-0 gauge calibration -> L-frame CSV -> world frame == hw_sim truth."""
    from hw_sim.scenes import MarkerScene
    rig = make_rig(5, rng=1)
    ob = observe(rig, wand(120, rng=2), rng=3, noise_px=0.0)
    csv = write_detections_csv(ob.detections, tmp_path / "wand.csv")
    cal = tmp_path / "cal.toml"
    assert main(["calibrate", "wand", str(csv), "--focal-px", repr(float(rig[0].K[0, 0])),
                 "--size", "1280x1024", "-o", str(cal)]) == 0
    L = np.array([[0, 0, 0], [0.6, 0, 0], [0, 0.4, 0], [0.25, 0, 0]])
    P = np.broadcast_to(L, (10, 4, 3)).copy()
    scene = MarkerScene(positions=P, marker_diameter_m=np.full(4, 0.014), rate_hz=100.0,
                        labels=("o", "x", "y", "xm"))
    lcsv = write_detections_csv(observe(rig, scene, rng=4, noise_px=0.0).detections,
                                tmp_path / "lframe.csv")
    out = tmp_path / "world.toml"
    capsys.readouterr()
    assert main(["calibrate", "world", str(cal), str(lcsv), "--l-frame", "600,400,250",
                 "-o", str(out)]) == 0
    assert "4 static markers" in capsys.readouterr().out
    est = load_rig(out)
    for ce, ct in zip(est, rig):
        assert np.linalg.norm(ce.center - ct.center) < 1e-6   # solver precision, world frame
        assert np.abs(ce.R - ct.R).max() < 1e-8
    assert main(["calibrate", "world", str(cal), str(lcsv), "--floor", "-o", str(out)]) == 0
    assert all(abs(a.center[2] - b.center[2]) < 1e-6 for a, b in zip(load_rig(out), rig))
    assert main(["calibrate", "world", str(cal), str(lcsv), "-o", str(out)]) == 2
