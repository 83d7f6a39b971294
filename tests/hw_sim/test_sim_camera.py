"""SimCamera follows the Camera protocol and exposes at the simulated box's pulses."""
import select
import time

import numpy as np
import pytest

from capture.camera import Camera, CameraSettings, PixelFormat
from capture.errors import CameraDisconnected
from capture.frame import TimestampSource
from hw_sim.sim_camera import SimCamera, orbiting_markers, ring_of_cameras
from hw_sim.syncbox import SimSyncBox

JITTER_US = 20.0
TS_SIGMAS = 6.0          # timestamp noise is N(0, JITTER_US): 6 sigma never trips
PEAK_PX = 1.5            # brightest pixel of a blob vs its projected centre
READ_SLACK_S = 0.25      # read(timeout) returns within timeout + scheduling slack


def _drain(cam, seconds):
    frames, t_end = [], time.monotonic() + seconds
    while time.monotonic() < t_end:
        f = cam.read(0.05)
        if f is not None:
            frames.append(f)
    return frames


@pytest.fixture
def box():
    with SimSyncBox(rng=3) as b:
        b._rate_mhz = 100_000  # drive the box directly (no host driver needed here)
        yield b


def _start_box(b):
    b._period_ticks = b.tick_hz * 1000.0 / b._rate_mhz
    b._t0_ticks = b.device_ticks(jitter=False) + 2000
    b._next_index = 0
    b._running = True


def test_protocol_and_configure_reads_back_applied_values():
    cam = SimCamera(ring_of_cameras(1)[0], rng=0)
    assert isinstance(cam, Camera)
    applied = cam.configure(CameraSettings(exposure_us=333, gain=2.03, width=640,
                                           pixel_format=PixelFormat.Y10))
    assert applied.exposure_us == 330.0 and applied.gain == 2.0
    assert (applied.width, applied.height) == (320, 256)   # fixed sensor size read back
    assert applied.pixel_format == PixelFormat.Y10
    cam.close()


def test_frames_at_pulses_with_sequence_and_kernel_timestamps(box):
    model = ring_of_cameras(4)[0]
    scene = orbiting_markers(3)
    cam = SimCamera(model, scene=scene, sync=box, rng=1, timestamp_jitter_us=JITTER_US)
    cam.start()
    _start_box(box)
    frames = _drain(cam, 0.5)
    cam.close()
    assert len(frames) >= 30
    seq = np.array([f.sequence for f in frames])
    missing = set(range(int(seq[-1]) + 1)) - set(seq.tolist())
    assert missing == {d for d in cam.dropped_sequences if d <= seq[-1]}  # none unless starved
    for f in frames:
        index, pulse_ns = cam.truth[f.sequence]
        assert f.timestamp_source == TimestampSource.KERNEL_START_OF_EXPOSURE
        assert abs(f.timestamp_ns - pulse_ns) < TS_SIGMAS * JITTER_US * 1e3
        assert pulse_ns == pytest.approx(float(box.true_host_ns(
            box._t0_ticks + round(index * box._period_ticks))), abs=1)
    f = frames[-1]
    pts, _ = scene((cam.truth[f.sequence][1]) * 1e-9)
    uv = model.project(pts)
    img = f.image.astype(float)
    for u, v in uv:
        r, c = int(round(v)), int(round(u))
        win = img[r - 3:r + 4, c - 3:c + 4]
        dr, dc = np.unravel_index(np.argmax(win), win.shape)
        assert np.hypot(dr - 3, dc - 3) <= PEAK_PX


def test_fileno_is_pollable_and_read_never_blocks_forever():
    cam = SimCamera(ring_of_cameras(1)[0], rate_hz=50, rng=2)
    t0 = time.monotonic()
    assert cam.read(0.1) is None                       # not started: times out
    assert time.monotonic() - t0 < 0.1 + READ_SLACK_S
    cam.start()
    r, _, _ = select.select([cam.fileno()], [], [], 1.0)
    assert r == [cam.fileno()]
    assert cam.read(0) is not None
    cam.close()


def test_drops_show_as_sequence_gaps(box):
    cam = SimCamera(ring_of_cameras(1)[0], sync=box, rng=4)
    cam.drop_probability = 0.3
    cam.start()
    _start_box(box)
    frames = _drain(cam, 0.6)
    cam.close()
    seq = np.array([f.sequence for f in frames])
    gaps = int(np.sum(np.diff(seq) - 1)) + int(seq[0])
    assert gaps > 0
    assert gaps == sum(d < seq[-1] for d in cam.dropped_sequences)
    assert not set(cam.dropped_sequences) & set(seq.tolist())


def test_full_buffers_drop_frames_when_reader_stalls(box):
    cam = SimCamera(ring_of_cameras(1)[0], sync=box, n_buffers=3, rng=5)
    cam.start()
    _start_box(box)
    time.sleep(0.3)
    box._running = False
    frames = []
    while (f := cam.read(0)) is not None:
        frames.append(f)
    cam.close()
    assert len(frames) <= 3 and cam.frames_dropped > 10


def test_disappear_raises_disconnected(box):
    cam = SimCamera(ring_of_cameras(1)[0], sync=box, rng=6)
    cam.disappear_after_frames = 5
    cam.start()
    _start_box(box)
    with pytest.raises(CameraDisconnected, match="sim:cam_1"):
        for _ in range(100):
            cam.read(0.05)
    with pytest.raises(CameraDisconnected):
        cam.start()


def test_bad_arguments():
    with pytest.raises(ValueError, match="bit_depth"):
        SimCamera(ring_of_cameras(1)[0], bit_depth=12)  # no V4L2 format for 12-bit here
    with pytest.raises(ValueError, match="timestamp_source"):
        SimCamera(ring_of_cameras(1)[0], timestamp_source=TimestampSource.HOST_DEQUEUE)
