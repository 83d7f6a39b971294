"""Every command checks its paths and numbers before any work: an output never overwrites an
input, a recording is never written over, impossible settings are named in one line."""
from __future__ import annotations

import json

import numpy as np
import pytest

from calibration.rig_io import save_rig
from capture.camera import CameraSettings
from capture.detections import write_detections_csv
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import wand
from mocap.cli import main


@pytest.fixture(scope="module")
def wand_csv(tmp_path_factory):
    d = tmp_path_factory.mktemp("wand")
    rig = make_rig(3, rng=1)
    ob = observe(rig, wand(120, rng=2), rng=3, noise_px=0.0)
    return rig, write_detections_csv(ob.detections, d / "wand.csv"), save_rig(rig, d / "rig.toml")


def _err(capsys):
    return capsys.readouterr().err


def test_outputs_never_overwrite_inputs(tmp_path, wand_csv, capsys):
    rig, csv, toml = wand_csv
    before = csv.read_bytes(), toml.read_bytes()
    f = str(rig[0].K[0, 0])
    cases = [
        (["reconstruct", str(csv), "--calibration", str(toml), "-o", str(csv)],
         "same file as the input"),
        (["reconstruct", str(csv), "--calibration", str(toml), "-o", str(tmp_path)],
         "is a folder"),
        (["calibrate", "wand", str(csv), "--focal-px", f, "--size", "1280x1024", "-o", str(csv)],
         "ends in .toml"),
        (["calibrate", "wand", str(csv), "--intrinsics", str(toml), "-o", str(toml)],
         "same file as --intrinsics"),
        (["calibrate", "world", str(toml), str(csv), "--floor", "-o", str(toml)],
         "same file as the calibration"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        assert msg in _err(capsys), argv
    assert (csv.read_bytes(), toml.read_bytes()) == before


def test_unwritable_outputs_are_refused_before_the_work(tmp_path, wand_csv, capsys):
    """An output below a file, or in a folder that takes no file (procfs refuses new files
    even to root, for whom permission bits do not count), is refused before any work, and
    the check leaves nothing behind in a folder it could write."""
    rig, csv, toml = wand_csv
    cases = [
        (["reconstruct", str(csv), "--calibration", str(toml), "-o", str(csv / "m.c3d")],
         f"{csv} is a file, not a folder"),
        (["reconstruct", str(csv), "--calibration", str(toml), "-o", "/proc/m.c3d"],
         "cannot write in /proc"),
        (["calibrate", "world", str(toml), str(csv), "--floor", "-o", "/proc/rig.toml"],
         "cannot write in /proc"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        err = _err(capsys)
        assert msg in err and "frames" not in err, (argv, err)
    out = tmp_path / "new" / "deeper" / "m.c3d"
    assert main(["reconstruct", str(csv), "--calibration", str(toml), "-o", str(out)]) == 0
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["deeper", "m.c3d", "new"]


def test_impossible_numbers_are_named(tmp_path, wand_csv, capsys):
    rig, csv, toml = wand_csv
    out = str(tmp_path / "c.toml")
    cases = [
        (["calibrate", "wand", str(csv), "--focal-px", "nan", "--size", "1280x1024", "-o", out],
         "--focal-px nan"),
        (["calibrate", "wand", str(csv), "--focal-px", "1200", "--size", "1280", "-o", out],
         "--size '1280'"),
        (["calibrate", "world", str(toml), str(csv), "--floor", "--gate-px", "0", "-o", out],
         "--gate-px 0"),
        (["calibrate", "intrinsics", str(csv), "--board", "chessboard:9x6:nan", "-o", out],
         "--board"),
        (["calibrate", "intrinsics", str(csv), "--board", "chessboard:100000x100000:25",
          "-o", out], "--board"),
        (["capture", "--sim", "--sync", "/dev/ttyACM0", "--out", str(tmp_path / "r")],
         "--sync is for real cameras"),
        (["capture", "--sim", "--duration", "inf", "--out", str(tmp_path / "r")],
         "finite duration"),
        (["capture", "--sim", "--size", "100000", "100000", "--out", str(tmp_path / "r")],
         "--size 100000 100000"),
        (["capture", "--sim", "--calibration", str(tmp_path / "none.toml"),
          "--out", str(tmp_path / "r")], "file not found"),
        (["demo", "--out", str(tmp_path / "d"), "--workers", "0"], "workers=0"),
    ]
    for argv, msg in cases:
        assert main(argv) == 2, argv
        assert msg in _err(capsys), argv
    assert not (tmp_path / "r").exists() and not (tmp_path / "c.toml").exists()
    with pytest.raises(ValueError, match="does not fit in a frame period of 10000 us"):
        CameraSettings(rate_hz=100.0, exposure_us=20000.0)


def test_an_existing_recording_is_left_untouched(tmp_path, capsys):
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "metadata.json").write_text('{"format": "openmocap-recording"}')
    (rec / "sim_rig.toml").write_text("mine")
    assert main(["capture", "--sim", "--out", str(rec)]) == 2
    assert "already holds a recording" in _err(capsys)
    assert (rec / "sim_rig.toml").read_text() == "mine"


@pytest.mark.parametrize("meta,msg", [
    ([], "format=None"),
    ({"format": "openmocap-recording"}, "malformed metadata"),
    ({"format": "openmocap-recording", "rate_hz": 100,
      "cameras": [{"id": "a", "file": "../../elsewhere.frames"}]}, "outside the recording"),
])
def test_malformed_recording_metadata_is_one_line(tmp_path, wand_csv, capsys, meta, msg):
    _, _, toml = wand_csv
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "metadata.json").write_text(json.dumps(meta))
    assert main(["reconstruct", str(rec), "--calibration", str(toml),
                 "-o", str(tmp_path / "m.c3d")]) == 2
    err = _err(capsys)
    assert msg in err and "Traceback" not in err


def test_bad_frame_numbers_in_a_csv(tmp_path, wand_csv, capsys):
    _, csv, toml = wand_csv
    rows = csv.read_text().splitlines()
    h = next(i for i, r in enumerate(rows) if r.startswith("frame"))
    head, first = rows[h], rows[h + 1].split(",")
    for frame, msg in ((-5, "frame -5 < 0"), (10 ** 6, "a frame number is wrong")):
        bad = tmp_path / f"bad{frame}.csv"
        bad.write_text("\n".join(rows + [",".join([str(frame)] + first[1:])]) + "\n")
        assert main(["reconstruct", str(bad), "--calibration", str(toml),
                     "-o", str(tmp_path / "m.c3d")]) == 2
        assert msg in _err(capsys), frame
    assert head.startswith("frame")


def test_runtime_failures_are_one_line(monkeypatch, tmp_path, capsys):
    """A hardware or pipeline fault (a RuntimeError such as CaptureError) ends the command
    with one line and exit 1; MOCAP_DEBUG=1 keeps the traceback."""
    from capture.errors import RecordingError
    from mocap.commands import reconstruct

    def boom(args):
        raise RecordingError("cam01.frames", "bad magic")
    monkeypatch.setattr(reconstruct, "run", boom)
    argv = ["reconstruct", "x.csv", "-o", str(tmp_path / "m.c3d")]
    assert main(argv) == 1
    err = _err(capsys)
    assert "RecordingError" in err and "bad magic" in err and "Traceback" not in err
    monkeypatch.setenv("MOCAP_DEBUG", "1")
    with pytest.raises(RecordingError):
        main(argv)


def test_a_camera_left_without_observations_fails_the_calibration(tmp_path, wand_csv, capsys):
    """A focal length 1e9 times too long puts every wand view of the other cameras outside
    their images: the bundle keeps none, and the calibration says so instead of writing a
    rig whose cameras were never fitted."""
    _, csv, _ = wand_csv
    out = tmp_path / "c.toml"
    assert main(["calibrate", "wand", str(csv), "--focal-px", "1e12", "--size", "1280x1024",
                 "-o", str(out)]) == 1
    assert "wand observations" in _err(capsys) and not out.exists()


def test_binary_files_are_named(tmp_path, wand_csv, capsys):
    _, csv, toml = wand_csv
    junk = bytes([0xff, 0xfe, 0x00, 0x81]) * 20
    (tmp_path / "b.csv").write_bytes(junk)
    (tmp_path / "b.toml").write_bytes(junk)
    assert main(["reconstruct", str(csv), "--calibration", str(tmp_path / "b.toml"),
                 "-o", str(tmp_path / "m.c3d")]) == 2
    assert "b.toml: malformed TOML" in _err(capsys)
    assert main(["reconstruct", str(tmp_path / "b.csv"), "--calibration", str(toml),
                 "-o", str(tmp_path / "m.c3d")]) == 2
    assert "b.csv: not a text CSV" in _err(capsys)


def test_late_checks_come_before_the_work(tmp_path, wand_csv, capsys):
    """A low-pass cutoff above Nyquist is refused before the reconstruction, a wand spacing
    that is not 2-3 distinct finite positions before the detection; a capture whose camera
    is missing says no recording was made, and leaves no folder behind."""
    _, csv, toml = wand_csv
    assert main(["reconstruct", str(csv), "--calibration", str(toml), "--rate", "100",
                 "--cutoff-hz", "60", "-o", str(tmp_path / "m.c3d")]) == 2
    err = _err(capsys)
    assert "below 50 Hz (Nyquist)" in err and "reconstruction" not in err
    assert main(["calibrate", "wand", str(csv), "--focal-px", "1000", "--size", "1280x1024",
                 "--wand-mm", "0,nan,500", "-o", str(tmp_path / "c.toml")]) == 2
    assert "--wand-mm '0,nan,500'" in _err(capsys)
    out = tmp_path / "s"
    assert main(["capture", "--camera", str(tmp_path / "video99"), "--out", str(out)]) == 1
    assert "no recording was made" in _err(capsys) and not out.exists()
