"""Recording folders: round trip, torn tails, kill -9, a full disk, and session faults."""
import errno
import os
import signal
import struct
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from capture.camera import Camera, CameraSettings
from capture.detections import Detections2D
from capture.errors import CameraDisconnected, DiskFullError, SyncBoxDisconnected
from capture.frame import Frame, TimestampSource
from capture.recording import (_HDR, CODEC_AUTO, CODEC_RAW, CODEC_SPARSE, CODEC_ZLIB_RLE,
                               FILE_MAGIC, Recorder, RecordedCamera, decode_payload,
                               encode_record)
from capture.replay import (FrameFileReader, ReplayCamera, is_recording, load_metadata,
                            read_recording, replay_cameras,
                            read_recording_detections, recording_frames)
from capture.session import CaptureSession

from .realtime import wait_until

CRASH_LOSS_S = 1.0        # kill -9 may lose at most the last second
REPO = Path(__file__).resolve().parents[2]


def _image(i, c, shape=(48, 64), dtype=np.uint8):
    top = 255 if dtype == np.uint8 else 1023
    return np.random.default_rng(1000 * i + c).integers(0, top + 1, shape).astype(dtype)


def _frame(i, c, **kw):
    return Frame(image=_image(i, c, **kw), camera_id=f"c{c}", sequence=i,
                 timestamp_ns=10**12 + i * 10**7 + c, exposure_us=500.0, gain=2.0,
                 timestamp_source=TimestampSource.KERNEL_START_OF_EXPOSURE)


def _cams(n):
    return [RecordedCamera(camera_id=f"c{c}", device=f"/dev/video{c}",
                           settings=CameraSettings(width=64, height=48, rate_hz=100).to_dict())
            for c in range(n)]


@pytest.mark.parametrize("codec", [CODEC_AUTO, CODEC_SPARSE, CODEC_ZLIB_RLE, CODEC_RAW])
@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_round_trip_bit_exact(tmp_path, codec, dtype):
    with Recorder(tmp_path / "rec", _cams(3), rate_hz=100, codec=codec,
                  sync_config={"rate_hz": 100}, calibration="calib.toml") as rec:
        for i in range(20):
            for c in range(3):
                if (i, c) != (5, 1):            # camera c1 missed frame set 5
                    rec.write_frame(c, _frame(i, c, dtype=dtype), frame_index=i,
                                    pulse_index=100 + i, set_host_ns=1e12 + i * 1e7)
    meta = load_metadata(tmp_path / "rec")
    assert is_recording(tmp_path / "rec") and not is_recording(tmp_path)
    assert meta.complete and meta.camera_ids == ("c0", "c1", "c2")
    assert meta.calibration == "calib.toml" and meta.sync == {"rate_hz": 100}
    assert meta.settings[0].rate_hz == 100 and meta.raw["frames_per_camera"] == [20, 19, 20]
    rows = list(recording_frames(tmp_path / "rec"))
    assert [fi for fi, _ in rows] == list(range(20))
    for fi, imgs in rows:
        for c, img in enumerate(imgs):
            if (fi, c) == (5, 1):
                assert img is None
            else:
                assert img.dtype == dtype and np.array_equal(img, _image(fi, c, dtype=dtype))
    sets = list(read_recording(tmp_path / "rec"))
    assert sets[7].pulse_index == 107 and sets[7].host_ns == 1e12 + 7e7
    f = sets[7].frames[2]
    assert (f.sequence, f.timestamp_ns, f.exposure_us, f.gain, f.camera_id) == \
        (7, 10**12 + 7 * 10**7 + 2, 500.0, 2.0, "c2")


_PAYLOAD_AT = 8 + _HDR.size     # u32 magic, u32 length, header
_CODEC_AT = _PAYLOAD_AT - 1     # the codec is the header's last byte


def _sparse_image(rng, h, w, dtype, fill):
    img = np.zeros((h, w), dtype)
    mask = rng.random((h, w)) < fill
    img[mask] = rng.integers(1, np.iinfo(dtype).max, int(mask.sum()))
    return img


@pytest.mark.parametrize("codec", [CODEC_AUTO, CODEC_SPARSE, CODEC_ZLIB_RLE, CODEC_RAW])
@given(st.integers(1, 40), st.integers(1, 40), st.sampled_from([np.uint8, np.uint16]),
       st.sampled_from([0.0, 0.001, 0.05, 1.0]), st.integers(0, 2**31))
@settings(max_examples=20, deadline=None)
def test_property_codecs_are_lossless(codec, h, w, dtype, fill, seed):
    img = _sparse_image(np.random.default_rng(seed), h, w, dtype, fill)
    f = Frame(image=img, camera_id="c0", sequence=0, timestamp_ns=0, exposure_us=1.0,
              gain=0.0, timestamp_source=TimestampSource.HOST_DEQUEUE)
    rec = encode_record(f, frame_index=0, codec=codec)
    used = rec[_CODEC_AT]
    if codec == CODEC_AUTO:
        assert used in (CODEC_SPARSE, CODEC_ZLIB_RLE)
    else:
        assert used == codec
    back = decode_payload(rec[_PAYLOAD_AT:-4], used, (h, w), dtype)
    assert back.dtype == dtype and np.array_equal(back, img)


def test_auto_codec_picks_sparse_for_dark_frames():
    rng = np.random.default_rng(0)
    dark = _sparse_image(rng, 256, 320, np.uint8, 0.0005)
    noisy = rng.integers(0, 8, (256, 320)).astype(np.uint8)
    for img, want in ((dark, CODEC_SPARSE), (noisy, CODEC_ZLIB_RLE)):
        f = Frame(image=img, camera_id="c0", sequence=0, timestamp_ns=0, exposure_us=1.0,
                  gain=0.0, timestamp_source=TimestampSource.HOST_DEQUEUE)
        rec = encode_record(f, frame_index=0)
        assert rec[_CODEC_AT] == want
    assert len(encode_record(Frame(image=dark, camera_id="c", sequence=0, timestamp_ns=0,
                                   exposure_us=1.0, gain=0.0,
                                   timestamp_source=TimestampSource.HOST_DEQUEUE),
                             frame_index=0)) < dark.nbytes / 50


@given(st.integers(1, 40), st.integers(1, 40), st.sampled_from([np.uint8, np.uint16]),
       st.integers(0, 2**31))
@settings(max_examples=25, deadline=None)
def test_property_write_read(tmp_path_factory, h, w, dtype, seed):
    folder = tmp_path_factory.mktemp("p") / "rec"
    img = np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, (h, w)).astype(dtype)
    f = Frame(image=img, camera_id="c0", sequence=seed, timestamp_ns=seed, exposure_us=1.0,
              gain=0.0, timestamp_source=TimestampSource.HOST_DEQUEUE)
    with Recorder(folder, _cams(1), rate_hz=1) as rec:
        rec.write_frame(0, f, frame_index=3)
    (fi, [back]), = list(recording_frames(folder))
    assert fi == 3 and back.dtype == dtype and np.array_equal(back, img)


def _record_ends(data: bytes) -> list[int]:
    """Byte offset where each record of a frames file ends (from the records' own length
    fields: u32 magic, u32 payload length, header, payload, u32 crc)."""
    ends, at = [], len(FILE_MAGIC)
    while at < len(data):
        _, n = struct.unpack_from("<II", data, at)
        at += 8 + _HDR.size + n + 4
        ends.append(at)
    return ends


def test_torn_or_corrupt_tail_keeps_everything_before(tmp_path):
    with Recorder(tmp_path / "rec", _cams(1), rate_hz=100) as rec:
        for i in range(10):
            rec.write_frame(0, _frame(i, 0), frame_index=i)
    p = tmp_path / "rec" / "cam00.frames"
    data = p.read_bytes()
    r = FrameFileReader(p, "c0")
    assert len(list(r)) == 10 and not r.truncated
    ends = _record_ends(data)
    assert len(ends) == 10 and ends[-1] == len(data)
    # torn inside the last record (1, 300, 2000 bytes short) or inside the 8th
    for cut in (len(data) - 1, len(data) - 300, len(data) - 2000, ends[6] + 10):
        assert cut > ends[6]
        keep = sum(e <= cut for e in ends)          # the records wholly before the cut
        p.write_bytes(data[:cut])
        r = FrameFileReader(p, "c0")
        got = list(r)
        assert r.truncated and [g.frame_index for g in got] == list(range(keep)), (cut, keep)
    bad = bytearray(data)
    bad[-10] ^= 0xFF                                     # corrupt the last record
    p.write_bytes(bytes(bad))
    r = FrameFileReader(p, "c0")
    assert len(list(r)) == 9 and r.truncated


def test_kill_minus_9_loses_at_most_the_last_second(tmp_path):
    folder = tmp_path / "rec"
    child = textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from tests.capture.test_recording import _frame, _cams
        from capture.recording import Recorder
        rec = Recorder({str(folder)!r}, _cams(2), rate_hz=100, fsync_interval_s=0.2)
        i = 0
        while True:
            for c in range(2):
                rec.write_frame(c, _frame(i, c), frame_index=i)
            print(i, time.monotonic(), flush=True)
            i += 1
            time.sleep(0.005)
    """)
    proc = subprocess.Popen([sys.executable, "-c", child], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    written = []
    t_start = time.monotonic()
    while time.monotonic() - t_start < 30:
        line = proc.stdout.readline()
        if not line:
            break
        i, t = line.split()
        written.append((int(i), float(t)))
        if float(t) - written[0][1] >= 2.5 * CRASH_LOSS_S:
            break
    t_kill = time.monotonic()
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    assert len(written) > 50, proc.stderr.read()
    must_have = max(i for i, t in written if t <= t_kill - CRASH_LOSS_S)
    meta = load_metadata(folder)
    assert not meta.complete                      # never closed
    rows = list(recording_frames(folder))
    assert [fi for fi, _ in rows] == list(range(len(rows)))
    assert len(rows) - 1 >= must_have
    for fi, imgs in rows:
        for c, img in enumerate(imgs):
            if img is not None:
                assert np.array_equal(img, _image(fi, c))
    assert all(all(img is not None for img in imgs) for fi, imgs in rows if fi <= must_have)


class _FillingDisk:
    """A file whose disk fills after ``limit`` bytes: short write, then ENOSPC."""

    def __init__(self, path, limit):
        self.f = open(path, "xb")
        self.left = limit

    def write(self, b):
        if len(b) > self.left:
            self.f.write(b[:self.left])
            self.left = 0
            raise OSError(errno.ENOSPC, "No space left on device")
        self.left -= len(b)
        return self.f.write(b)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_disk_full_closes_cleanly_with_everything_before_readable(tmp_path):
    folder = tmp_path / "rec"
    rec = Recorder(folder, _cams(2), rate_hz=100, codec=CODEC_RAW,
                   file_factory=lambda p: _FillingDisk(p, 8 + 10 * 3200 + 100))
    with pytest.raises(DiskFullError, match="cam0[01].frames"):
        for i in range(100):
            for c in range(2):
                rec.write_frame(c, _frame(i, c), frame_index=i)
        rec.close()
    with pytest.raises(DiskFullError):
        rec.close()                               # stays closed, same error
    meta = load_metadata(folder)
    assert not meta.complete and "disk full" in meta.raw["error"]
    for c in range(2):
        r = FrameFileReader(folder / f"cam{c:02d}.frames", f"c{c}")
        got = list(r)
        assert not r.truncated                    # the partial record was cut off
        assert len(got) == 10                     # 10 records of 3200 bytes fit
        for g in got:
            assert np.array_equal(g.frame.image, _image(g.frame_index, c))


def test_detections_inside_the_folder(tmp_path):
    det = Detections2D(frame=[0, 0, 1], camera=[0, 1, 1], xy=[[1.5, 2.0], [3.0, 4.25], [5, 6]],
                       camera_names=("c0", "c1"), rate_hz=100.0)
    with Recorder(tmp_path / "rec", _cams(2), rate_hz=100) as rec:
        rec.write_detections(det)
        with pytest.raises(ValueError, match="cameras"):
            rec.write_detections(Detections2D(frame=[0], camera=[0], xy=[[0, 0]],
                                              camera_names=("x", "y")))
    back = read_recording_detections(tmp_path / "rec")
    assert np.array_equal(back.xy, det.xy) and back.camera_names == ("c0", "c1")


def test_replay_camera_follows_the_protocol(tmp_path):
    with Recorder(tmp_path / "rec", _cams(2), rate_hz=100) as rec:
        for i in range(5):
            rec.write_frame(1, _frame(i, 1), frame_index=i)
    cam = ReplayCamera(tmp_path / "rec", "c1")
    assert isinstance(cam, Camera)
    assert cam.configure(CameraSettings(rate_hz=5)).rate_hz == 100
    cam.start()
    got = [cam.read(0.1) for _ in range(5)]
    assert [f.sequence for f in got] == list(range(5))
    assert np.array_equal(got[3].image, _image(3, 1))
    with pytest.raises(CameraDisconnected, match="end of recording"):
        cam.read(0.1)
    cam.close()


def test_realtime_replay_paces_frames_and_honours_timeouts(tmp_path):
    with Recorder(tmp_path / "rec", _cams(1), rate_hz=100) as rec:
        for i in (0, 20, 40, 60):
            rec.write_frame(0, _frame(i, 0), frame_index=i)   # 200 ms apart
    cam = ReplayCamera(tmp_path / "rec", 0, realtime=True)
    cam.start()
    t0 = time.monotonic()
    assert cam.read(0.1).sequence == 0
    assert cam.read(0.01) is None                  # the next frame is due 200 ms later
    got = [cam.read(0.5).sequence for _ in range(3)]
    assert got == [20, 40, 60] and time.monotonic() - t0 >= 0.6
    cam.close()


def test_existing_recording_is_not_overwritten(tmp_path):
    Recorder(tmp_path / "rec", _cams(1), rate_hz=1).close()
    with pytest.raises(ValueError, match="already holds"):
        Recorder(tmp_path / "rec", _cams(1), rate_hz=1)


# -- recording live sessions on the simulated rig, with faults ---------------------------
@pytest.fixture
def rig(rig_factory):
    return rig_factory(2, size=(96, 64), seed=21)


def _recorder(folder, cams, box, **kw):
    return Recorder(folder, [RecordedCamera(camera_id=c.camera_id, device=c.device,
                                            settings=c.settings.to_dict()) for c in cams],
                    rate_hz=box.config.rate_hz, sync_config=box.config.to_dict(), **kw)


def test_session_recording_round_trip(tmp_path, rig):
    sim, box, cams = rig
    sets = []
    with _recorder(tmp_path / "rec", cams, box) as rec:
        def sink(fs):
            sets.append(fs)
            rec.write_frame_set(fs)
        CaptureSession(cams, box, on_frame_set=sink).run(0.6)
    back = list(read_recording(tmp_path / "rec"))
    assert len(back) == len(sets) > 30
    for a, b in zip(sets, back):
        assert (a.index, a.pulse_index) == (b.index, b.pulse_index)
        for fa, fb in zip(a.frames, b.frames):
            assert (fa is None) == (fb is None)
            if fa is not None:
                assert np.array_equal(fa.image, fb.image)
                assert (fa.sequence, fa.timestamp_ns) == (fb.sequence, fb.timestamp_ns)


def test_replayed_cameras_reform_the_recorded_sets_in_a_live_session(tmp_path, rig):
    """Replay as cameras: the recording's cameras, played back in real time on one clock,
    go through a CaptureSession (no sync box) and give back the recorded frame sets."""
    import select
    sim, box, cams = rig
    with _recorder(tmp_path / "rec", cams, box) as rec:
        CaptureSession(cams, box, on_frame_set=rec.write_frame_set).run(0.6)
    recorded = {tuple(f.sequence for f in fs.frames)
                for fs in read_recording(tmp_path / "rec") if fs.complete}
    assert len(recorded) > 30
    replay = replay_cameras(tmp_path / "rec")
    assert [c.camera_id for c in replay] == [c.camera_id for c in cams]
    assert all(isinstance(c, Camera) for c in replay)
    assert select.select([replay[0].fileno()], [], [], 0)[0]   # pollable: frames waiting
    t0 = time.monotonic_ns()
    sets = []
    st = CaptureSession(replay, None, rate_hz=100.0, on_frame_set=sets.append).run(1.0)
    for c in replay:
        c.close()
    replayed = [tuple(f.sequence for f in fs.frames) for fs in sets if fs.complete]
    assert set(replayed) <= recorded                      # never mixes two recorded sets
    assert len(replayed) >= 0.9 * len(recorded)
    assert all(not c.connected and "end of recording" in c.error for c in st.cameras)
    ts = [f.timestamp_ns for fs in sets for f in fs.frames if f is not None]
    assert min(ts) >= t0 - 10**7                          # stamped on the replay's clock


def test_sync_box_vanishing_leaves_a_clean_recording(tmp_path, rig):
    sim, box, cams = rig
    rec = _recorder(tmp_path / "rec", cams, box)
    session = CaptureSession(cams, box, on_frame_set=rec.write_frame_set)
    session.start()
    wait_until(lambda: session.stats().frame_sets > 10, what="frame sets before the fault")
    sim.disappear()
    wait_until(lambda: session.stopped, what="the session to stop")
    with pytest.raises(SyncBoxDisconnected):
        session.stop()
    rec.close()
    meta = load_metadata(tmp_path / "rec")
    assert meta.complete and meta.raw["frame_sets"] == rec.n_frame_sets > 10
    assert len(list(read_recording(tmp_path / "rec"))) == rec.n_frame_sets


def test_disk_full_during_session_stops_it_cleanly(tmp_path, rig):
    sim, box, cams = rig
    rec = _recorder(tmp_path / "rec", cams, box, codec=CODEC_RAW,
                    file_factory=lambda p: _FillingDisk(p, 8 + 20 * (96 * 64 + 72)))
    session = CaptureSession(cams, box, on_frame_set=rec.write_frame_set)
    session.start()
    wait_until(lambda: session.stopped, what="the session to stop on a full disk")
    with pytest.raises(DiskFullError):
        session.stop()
    with pytest.raises(DiskFullError):
        rec.close()
    rows = list(recording_frames(tmp_path / "rec"))
    # each camera's file holds 20 frames; the first full one stops the session (a camera
    # that missed a pulse on a loaded host spreads its 20 over one more row)
    per_cam = [sum(imgs[i] is not None for _, imgs in rows) for i in range(len(cams))]
    assert max(per_cam) == 20 and len(rows) >= 20, (per_cam, len(rows))


def test_auto_codec_stores_raw_when_compression_exceeds_the_cpu_budget(tmp_path):
    rng = np.random.default_rng(5)
    imgs = [_sparse_image(rng, 128, 160, np.uint8, 0.02) for _ in range(40)]
    ratios = {}
    for rate in (10.0, 1e7):                      # 1e7 Hz: no time to compress anything
        # a queue longer than the test: raw only because of the CPU budget, never of lag
        with Recorder(tmp_path / f"r{rate:g}", _cams(1), rate_hz=rate, queue_frames=100) as rec:
            for i, img in enumerate(imgs):
                rec.write_frame(0, Frame(image=img, camera_id="c0", sequence=i, timestamp_ns=i,
                                         exposure_us=1.0, gain=0.0,
                                         timestamp_source=TimestampSource.HOST_DEQUEUE),
                                frame_index=i)
        ratios[rate] = rec.stats()["compression_ratio"]
        back = [imgs_[0] for _, imgs_ in recording_frames(tmp_path / f"r{rate:g}")]
        assert all(np.array_equal(a, b) for a, b in zip(back, imgs)) and len(back) == 40
    assert ratios[10.0] > 2.0 and ratios[1e7] < 1.1


class _SlowDisk:
    """A file whose writes take ``s_per_byte`` of wall time (a disk that cannot keep up)."""

    def __init__(self, path, s_per_byte):
        self.f = open(path, "xb")
        self.s_per_byte = s_per_byte

    def write(self, b):
        time.sleep(len(b) * self.s_per_byte)
        return self.f.write(b)

    def __getattr__(self, name):
        return getattr(self.f, name)


def test_auto_codec_keeps_compressing_when_the_disk_is_the_bottleneck(tmp_path):
    """The queue is behind (40 frames pushed at once into 4 places) because the disk is
    slow, not the CPU: compressing saves more write time than it costs and fits the CPU
    budget, so AUTO keeps compressing instead of writing raw (which the slow disk would
    take 8x longer to absorb)."""
    rng = np.random.default_rng(6)
    imgs = [_sparse_image(rng, 128, 160, np.uint8, 0.02) for _ in range(40)]
    with Recorder(tmp_path / "slow", _cams(1), rate_hz=10, queue_frames=4,
                  file_factory=lambda p: _SlowDisk(p, 2e-7)) as rec:   # 20 kB raw: 4 ms
        for i, img in enumerate(imgs):
            rec.write_frame(0, Frame(image=img, camera_id="c0", sequence=i, timestamp_ns=i,
                                     exposure_us=1.0, gain=0.0,
                                     timestamp_source=TimestampSource.HOST_DEQUEUE),
                            frame_index=i)
    assert rec.stats()["compression_ratio"] > 2.0
    back = [im[0] for _, im in recording_frames(tmp_path / "slow")]
    assert len(back) == 40 and all(np.array_equal(a, b) for a, b in zip(back, imgs))
