"""``mocap capture --sim`` end to end, and record_live with a camera lost mid-session."""
import numpy as np
import pytest

from capture.live import record_live
from capture.replay import load_metadata, read_recording, recording_frames
from capture.syncbox import SyncBox, SyncConfig
from hw_sim.sim_camera import sim_rig
from mocap.cli import main

MIN_SETS_FRACTION = 0.7


def test_capture_sim_cli_records_a_readable_folder(tmp_path, capsys):
    out = tmp_path / "session"
    rc = main(["capture", "--sim", "--cameras", "2", "--size", "96", "64", "--duration", "0.8",
               "--rate", "50", "--out", str(out)])
    assert rc == 0
    text = capsys.readouterr()
    assert "frame sets" in text.out and "cam_2" in text.out
    assert "sets" in text.err                          # the live status line
    meta = load_metadata(out)
    assert meta.complete and meta.camera_ids == ("cam_1", "cam_2")
    assert meta.sync["rate_hz"] == 50 and meta.sync["port"].startswith("/dev/pts/")
    assert meta.settings[0].width == 96
    from calibration.rig_io import load_rig
    rig = load_rig(meta.calibration_path)         # the simulated rig's true calibration
    assert list(rig.names) == ["cam_1", "cam_2"]
    rows = list(recording_frames(out))
    assert len(rows) >= MIN_SETS_FRACTION * 50 * 0.8
    assert rows[0][1][0].shape == (64, 96)


def test_capture_cli_rejects_ambiguous_sources(tmp_path, capsys):
    assert main(["capture", "--out", str(tmp_path / "x")]) == 2
    assert "--sim" in capsys.readouterr().err


def test_record_live_goes_on_when_a_camera_is_lost(tmp_path):
    sim, cams, _ = sim_rig(3, size=(96, 64), rng=4)
    cams[1].disappear_after_frames = 20
    box = SyncBox(sim.port)
    box.configure(SyncConfig(rate_hz=100))
    try:
        res = record_live(cams, box, tmp_path / "rec", duration_s=0.8)
    finally:
        for c in cams:
            c.close()
        box.close()
        sim.close()
    lost = res.session.cameras[1]
    assert not lost.connected and "cam_2" in lost.error
    sets = list(read_recording(tmp_path / "rec"))
    assert len(sets) == res.session.frame_sets
    assert sum(fs.frames[1] is not None for fs in sets) <= 20
    assert all(fs.frames[0] is not None for fs in sets[30:])
    assert np.isfinite(res.recording["compression_ratio"])
    with pytest.raises(ValueError, match="duration"):
        record_live(cams, None, tmp_path / "r2", duration_s=0, rate_hz=10)


def test_capture_cli_real_form_reports_a_missing_device(tmp_path, capsys):
    rc = main(["capture", "--camera", str(tmp_path / "video99"), "--sync",
               str(tmp_path / "ttyACM9"), "--out", str(tmp_path / "s")])
    assert rc == 1
    err = capsys.readouterr().err
    assert "CameraDisconnected" in err and "video99" in err
