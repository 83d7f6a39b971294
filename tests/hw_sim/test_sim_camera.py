"""SimCamera follows the Camera protocol and exposes at the simulated box's pulses."""
import select
import time

import numpy as np
import pytest
import serial

from capture.camera import Camera, CameraSettings, PixelFormat
from capture.errors import CameraDisconnected
from capture.frame import TimestampSource
from capture.sync_protocol import (DecodeError, FrameSplitter, Message, MsgType,
                                   decode_frame, encode_message)
from hw_sim.sim_camera import SimCamera, orbiting_markers, ring_of_cameras
from hw_sim.syncbox import SimSyncBox

from ..capture.realtime import WAIT_TIMEOUT_S, wait_until

JITTER_US = 20.0
TS_SIGMAS = 6.0          # timestamp noise is N(0, JITTER_US): 6 sigma never trips
PEAK_PX = 1.5            # brightest pixel of a blob vs its projected centre
READ_SLACK_S = 2.0       # read(timeout) returns within timeout + (loaded host) slack
RATE_MHZ = 100_000       # 100 Hz


def _read(cam, n):
    """The next ``n`` frames (fails after WAIT_TIMEOUT_S instead of hanging)."""
    frames, t_end = [], time.monotonic() + WAIT_TIMEOUT_S
    while len(frames) < n:
        assert time.monotonic() < t_end, f"{len(frames)} of {n} frames"
        f = cam.read(0.05)
        if f is not None:
            frames.append(f)
    return frames


class _Host:
    """The host end of the simulated box's pty (pyserial), sending protocol commands."""

    def __init__(self, port):
        self.ser = serial.Serial(port, timeout=0.02)
        self.seq = 0
        self.pulses = {}      # index -> device ticks, from the PULSE messages seen
        self._split = FrameSplitter()

    def command(self, mtype, **fields):
        self.seq += 1
        self.ser.write(encode_message(Message.make(mtype, seq=self.seq, **fields)))
        reply, t_end = None, time.monotonic() + WAIT_TIMEOUT_S
        while reply is None:
            assert time.monotonic() < t_end, f"no reply to {mtype.name}"
            for fr in self._split.feed(self.ser.read(4096)):
                try:
                    m = decode_frame(fr)
                except DecodeError:          # bytes the box dropped while nobody read
                    continue
                if m.type == MsgType.PULSE:
                    self.pulses[m.index] = m.ticks
                elif m.type in (MsgType.ACK, MsgType.NAK) and m.seq == self.seq:
                    reply = m
        assert reply.type == MsgType.ACK, reply
        return reply


@pytest.fixture
def box():
    with SimSyncBox(rng=3) as b:
        host = _Host(b.port)
        host.command(MsgType.SET_RATE, rate_mhz=RATE_MHZ)
        b.host = host
        yield b
        host.ser.close()


def _start_box(b):
    b.host.command(MsgType.START)


def _stop_box(b):
    b.host.command(MsgType.STOP)


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
    frames = _read(cam, 30)
    _stop_box(box)                       # reads the PULSE messages the box sent meanwhile
    cam.close()
    seq = np.array([f.sequence for f in frames])
    missing = set(range(int(seq[-1]) + 1)) - set(seq.tolist())
    assert missing == {d for d in cam.dropped_sequences if d <= seq[-1]}  # none unless starved
    ticks = box.host.pulses
    assert list(ticks) == list(range(len(ticks)))
    assert np.all(np.diff(list(ticks.values())) == box.tick_hz * 1000 // RATE_MHZ)
    for f in frames:
        index, pulse_ns = cam.truth[f.sequence]
        assert f.timestamp_source == TimestampSource.KERNEL_START_OF_EXPOSURE
        assert abs(f.timestamp_ns - pulse_ns) < TS_SIGMAS * JITTER_US * 1e3
        # exposed at the pulse the box announced with that index
        assert pulse_ns == pytest.approx(float(box.true_host_ns(ticks[index])), abs=1)
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
    assert not select.select([cam.fileno()], [], [], 0)[0]
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
    frames = _read(cam, 40)
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
    wait_until(lambda: cam.frames_dropped > 10, what="drops while nobody reads")
    _stop_box(box)
    frames = []
    while (f := cam.read(0)) is not None:
        frames.append(f)
    cam.close()
    # the three buffers kept the first three frames; every later one was dropped
    assert [f.sequence for f in frames] == [0, 1, 2]
    assert set(cam.dropped_sequences) == set(range(3, cam.frames_exposed))


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
