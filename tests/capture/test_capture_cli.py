"""``mocap capture`` end to end (simulated rig, the real-device form, kill -9), and
record_live with faults."""
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from capture.camera import PixelFormat
from capture.errors import SyncProtocolError
from capture.frame import TimestampSource
from capture.live import record_live
from capture.replay import FrameFileReader, load_metadata, read_recording, recording_frames
from hw_sim.sim_camera import ring_of_cameras
from hw_sim.syncbox import SimSyncBox
from mocap.cli import main

from .fake_v4l2 import FakeVideoDevices, TriggeredSensor
from .realtime import assert_missing_frames_are_counted_drops

MIN_SETS_FRACTION = 0.7
CRASH_LOSS_S = 1.0          # kill -9 may lose at most the last second
REPO = Path(__file__).resolve().parents[2]


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


def test_record_live_goes_on_when_a_camera_is_lost(tmp_path, rig_factory):
    sim, box, cams = rig_factory(3, size=(96, 64), seed=4)
    cams[1].disappear_after_frames = 20
    res = record_live(cams, box, tmp_path / "rec", duration_s=0.8)
    lost = res.session.cameras[1]
    assert not lost.connected and "cam_2" in lost.error
    sets = list(read_recording(tmp_path / "rec"))
    assert len(sets) == res.session.frame_sets
    assert sum(fs.frames[1] is not None for fs in sets) <= 20
    # the others go on: a set lacks their frame only where their driver dropped it
    assert_missing_frames_are_counted_drops(sets[30:], cams, res.session, which=(0, 2))
    assert np.isfinite(res.recording["compression_ratio"])
    with pytest.raises(ValueError, match="duration"):
        record_live(cams, None, tmp_path / "r2", duration_s=0, rate_hz=10)


def test_capture_cli_real_form_reports_a_missing_device(tmp_path, capsys):
    rc = main(["capture", "--camera", str(tmp_path / "video99"), "--sync",
               str(tmp_path / "ttyACM9"), "--out", str(tmp_path / "s")])
    assert rc == 1
    err = capsys.readouterr().err
    assert "CameraDisconnected" in err and "video99" in err


def test_capture_cli_real_device_form(tmp_path, capsys, monkeypatch):
    """``--camera /dev/videoN ... --sync PORT``: the sync box is opened by its device path
    (a simulated box's pty), the cameras by theirs through the real ``V4L2Camera``; only the
    kernel is simulated (fake_v4l2: device nodes whose sensors expose at the box's trigger
    line and render the hw_sim scene)."""
    sim = SimSyncBox(rng=3)
    devices = FakeVideoDevices(tmp_path)
    sensors, paths = [], []
    for name, model in zip(("video4", "video2"), ring_of_cameras(2, size=(320, 240))):
        path, kernel = devices.add(name)
        kernel.size = model.size                  # the sensor's size; format left as YUYV
        sensors.append(TriggeredSensor(kernel, model, sim, rng=len(paths)).start())
        paths.append(path)
    monkeypatch.setattr("capture.v4l2._linuxpy", lambda: devices)   # the kernel interface
    out = tmp_path / "real"
    try:
        rc = main(["capture", "--camera", paths[0], "--camera", paths[1],
                   "--sync", sim.port, "--rate", "50", "--exposure-us", "800",
                   "--pixel-format", "GREY", "--duration", "0.8", "--out", str(out)])
        assert sim.rate_hz == 50.0 and not sim.running       # configured, then stopped
    finally:
        for s in sensors:
            s.stop()
        devices.close()
        sim.close()
    assert rc == 0, capsys.readouterr().err
    assert [s.error for s in sensors] == [None, None]
    assert all(not k.streaming and k.fmt == "GREY" for k in devices.kernels.values())
    meta = load_metadata(out)
    assert meta.complete and meta.devices == tuple(paths)
    assert meta.sync["port"] == sim.port and meta.sync["rate_hz"] == 50
    assert meta.settings[0].exposure_us == 800.0 and meta.calibration is None
    assert meta.settings[0].pixel_format == PixelFormat.GREY
    sets = list(read_recording(out))
    assert len(sets) >= MIN_SETS_FRACTION * 50 * 0.8
    for fs in sets:                                # each frame from its own pulse
        for sensor, f in zip(sensors, fs.frames):
            if f is not None:
                assert sensor.truth[f.sequence][0] == fs.pulse_index
                assert f.image.shape == (240, 320)
                assert f.timestamp_source == TimestampSource.KERNEL_START_OF_EXPOSURE


def test_record_live_closes_the_recording_when_the_box_sends_garbage(tmp_path, rig_factory):
    sim, box, cams = rig_factory(2, size=(96, 64), seed=5, garbage_timeout_s=0.3)
    stop = threading.Event()

    def spew():
        # the fault comes once the host has received 40 pulses (~0.4 s of recording)
        while box.stats().pulses < 40:
            if stop.wait(0.005):
                return
        while not stop.wait(0.005):
            sim.inject_garbage(200, with_zeros=False)

    t = threading.Thread(target=spew, daemon=True)
    t.start()
    try:
        with pytest.raises(SyncProtocolError, match="no valid frame"):
            record_live(cams, box, tmp_path / "rec", duration_s=30.0)
    finally:
        stop.set()
        t.join()
    meta = load_metadata(tmp_path / "rec")
    assert meta.complete                                  # closed cleanly, not torn
    assert "SyncProtocolError" in meta.raw["session_error"] and sim.port in \
        meta.raw["session_error"]
    sets = list(read_recording(tmp_path / "rec"))
    assert len(sets) == meta.raw["frame_sets"] >= 20      # 40 pulses before the fault


def test_kill_minus_9_of_mocap_capture_keeps_all_but_the_last_second(tmp_path):
    """The real command in a subprocess, killed with SIGKILL mid-recording: the folder reads
    back, and the last recorded exposure is within a second of the kill (same monotonic
    clock in both processes)."""
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "mocap", "capture", "--sim", "--cameras",
                             "2", "--size", "96", "64", "--rate", "50", "--duration", "120",
                             "--out", str(out)], cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 60
        first = out / "cam01.frames"
        while not (first.exists() and first.stat().st_size > 50_000):
            assert proc.poll() is None, proc.stderr.read().decode()
            assert time.monotonic() < deadline, "recording never started"
            time.sleep(0.05)
        time.sleep(1.5)
        t_kill = time.monotonic_ns()
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(timeout=10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()
    assert proc.returncode == -signal.SIGKILL
    meta = load_metadata(out)
    assert not meta.complete                               # it never got to close
    last = []
    for f, cid in zip(meta.files, meta.camera_ids):
        r = FrameFileReader(out / f, cid)
        recs = list(r)                                     # every record passes its CRC
        assert len(recs) > 50
        assert [x.frame.sequence for x in recs] == sorted(x.frame.sequence for x in recs)
        last.append(recs[-1].frame.timestamp_ns)
    lost_s = (t_kill - min(last)) * 1e-9
    assert 0 <= lost_s <= CRASH_LOSS_S, lost_s
    rows = list(recording_frames(out))
    assert [fi for fi, _ in rows] == sorted(fi for fi, _ in rows)
