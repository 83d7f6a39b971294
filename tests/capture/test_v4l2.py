"""V4L2Camera against a faked linuxpy/ioctl layer; a real-device test behind the marker."""
import os
import time

import cv2
import numpy as np
import pytest

from capture.camera import Camera, CameraSettings, PixelFormat
from capture.errors import CameraDisconnected, CameraError
from capture.frame import TimestampSource
from capture.v4l2 import V4L2Camera, frame_to_image, timestamp_from_flags

from .fake_v4l2 import FakeKernel

READ_SLACK_S = 2.0       # read(timeout) returns within timeout + (loaded host) slack


def _padded(img_bytes_rows, stride):
    return b"".join(r + bytes(stride - len(r)) for r in img_bytes_rows)


def _camera(k, **kw):
    return V4L2Camera("/dev/video7", lp=k, opener=k.opener, camera_id="left", **kw)


def test_configure_reads_back_what_the_driver_applied():
    k = FakeKernel()
    cam = _camera(k)
    assert isinstance(cam, Camera)
    got = cam.configure(CameraSettings(width=600, height=500, pixel_format=PixelFormat.GREY,
                                       rate_hz=120, exposure_us=2049, gain=100))
    assert (got.width, got.height, got.pixel_format) == (640, 480, PixelFormat.GREY)
    assert got.rate_hz == 125.0                    # nearest supported interval
    assert got.exposure_us == 2000.0               # 100 us units
    assert got.gain == 63.0                        # clamped by the driver, read back
    assert (k.raw.ControlID.EXPOSURE_AUTO, 1) in k.set_calls   # manual exposure first
    assert cam.settings == got                     # what the recording metadata stores
    cam.close()


def test_driver_without_frame_rate_ioctls_reports_rate_unknown():
    k = FakeKernel(has_parm=False)
    cam = _camera(k)
    got = cam.configure(CameraSettings(width=320, height=240, pixel_format=PixelFormat.Y16,
                                       rate_hz=120, gain=5))
    assert got.rate_hz is None                       # not silently echoed as 120
    assert (got.width, got.pixel_format, got.gain) == (320, PixelFormat.Y16, 5.0)
    k.gone = True
    with pytest.raises(CameraDisconnected):          # a vanished device still raises
        cam.configure(CameraSettings(rate_hz=60))


def test_exposure_without_absolute_control_needs_units():
    k = FakeKernel(controls={FakeKernel.raw.ControlID.EXPOSURE: 10,
                             FakeKernel.raw.ControlID.GAIN: 0})
    cam = _camera(k)
    with pytest.raises(CameraError, match="exposure_us_per_unit"):
        cam.configure(CameraSettings(exposure_us=500))
    cam2 = _camera(k, exposure_us_per_unit=25.0)
    assert cam2.configure(CameraSettings(exposure_us=500)).exposure_us == 500.0


@pytest.mark.parametrize("fmt", ["GREY", "Y10 ", "Y16 ", "YUYV"])
def test_stream_frames_with_kernel_sequence_and_timestamps(fmt):
    rng = np.random.default_rng(0)
    k = FakeKernel()
    cam = _camera(k, n_buffers=2)
    s = cam.configure(CameraSettings(width=320, height=240, pixel_format=PixelFormat(fmt)))
    w, h = s.width, s.height
    stride = k.get_raw_format(k.rfd, None).fmt.pix.bytesperline
    top = {"GREY": 255, "Y10 ": 1023, "Y16 ": 65535, "YUYV": 255}[fmt]
    truth = rng.integers(0, top + 1, size=(h, w)).astype(np.uint8 if top == 255 else np.uint16)
    if fmt == "YUYV":
        packed = np.zeros((h, 2 * w), np.uint8)
        packed[:, 0::2], packed[:, 1::2] = truth, 128
        rows = [r.tobytes() for r in packed]
    else:
        rows = [r.astype("<u2").tobytes() if top > 255 else r.tobytes() for r in truth]
    payload = _padded(rows, stride)
    cam.start()
    t0 = 5_000_000_123_000
    assert cam.read(0.05) is None
    assert k.expose(payload, t0) and k.expose(payload, t0 + 8_000_000)
    assert not k.expose(payload, t0 + 16_000_000)      # both buffers full: driver drops
    f1, f2 = cam.read(1.0), cam.read(1.0)
    assert k.expose(payload, t0 + 24_000_000)
    f4 = cam.read(1.0)
    assert [f1.sequence, f2.sequence, f4.sequence] == [0, 1, 3]   # the gap shows the drop
    assert f1.timestamp_ns == t0 and f4.timestamp_ns == t0 + 24_000_000
    assert f1.timestamp_source == TimestampSource.KERNEL_START_OF_EXPOSURE
    assert f1.camera_id == "left" and np.array_equal(f1.image, truth)
    assert f1.image.dtype == truth.dtype
    cam.close()


def test_mjpg_decodes_to_grey():
    k = FakeKernel()
    cam = _camera(k)
    cam.configure(CameraSettings(width=320, height=240, pixel_format=PixelFormat.MJPG))
    img = np.zeros((240, 320), np.uint8)
    img[100:120, 50:90] = 200
    ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 100])
    cam.start()
    k.expose(jpg.tobytes(), 10**9)
    f = cam.read(1.0)
    assert f.image.shape == (240, 320) and np.abs(f.image.astype(int) - img).max() <= 8


def test_timestamp_flags():
    assert timestamp_from_flags(0x2000, 3, 7) == (3_000_007_000,
                                                   TimestampSource.KERNEL_END_OF_FRAME)
    assert timestamp_from_flags(0x2000 | 0x10000, 1, 0)[1] == \
        TimestampSource.KERNEL_START_OF_EXPOSURE
    assert timestamp_from_flags(0x4000, 1, 0) is None        # COPY: not a kernel clock


def test_non_monotonic_timestamp_falls_back_to_host_dequeue():
    k = FakeKernel(timestamp_flags=0x4000)
    cam = _camera(k)
    cam.configure(CameraSettings(width=320, height=240, pixel_format=PixelFormat.GREY))
    cam.start()
    before = time.monotonic_ns()
    k.expose(bytes(k.get_raw_format(k.rfd, None).fmt.pix.bytesperline * 240), 42)
    f = cam.read(1.0)
    assert f.timestamp_source == TimestampSource.HOST_DEQUEUE
    assert before <= f.timestamp_ns <= time.monotonic_ns()


def test_read_times_out_and_unplug_raises_disconnected():
    k = FakeKernel()
    cam = _camera(k)
    cam.start()
    t0 = time.monotonic()
    assert cam.read(0.1) is None
    assert time.monotonic() - t0 < 0.1 + READ_SLACK_S
    k.gone = True
    os.write(k.wfd, b"x")                              # the fd reports readable (POLLERR)
    with pytest.raises(CameraDisconnected, match="/dev/video7"):
        cam.read(1.0)
    with pytest.raises(CameraDisconnected, match="/dev/video7"):
        _camera(k)


def test_short_buffer_is_rejected():
    with pytest.raises(ValueError, match="short"):
        frame_to_image(bytes(100), PixelFormat.GREY, 320, 240)


@pytest.mark.hardware
def test_real_v4l2_device_streams():
    """Needs a camera at $MOCAP_TEST_VIDEO (default /dev/video0): pytest --run-hardware."""
    path = os.environ.get("MOCAP_TEST_VIDEO", "/dev/video0")
    cam = V4L2Camera(path)
    s = cam.configure(CameraSettings(rate_hz=60))
    cam.start()
    frames = [cam.read(1.0) for _ in range(30)]
    cam.close()
    frames = [f for f in frames if f is not None]
    assert len(frames) >= 20 and frames[0].image.shape == (s.height, s.width)
    assert all(b.sequence > a.sequence for a, b in zip(frames, frames[1:]))
    assert all(b.timestamp_ns > a.timestamp_ns for a, b in zip(frames, frames[1:]))


def test_buffer_with_error_flag_is_skipped_and_counts_as_a_drop():
    k = FakeKernel()
    cam = _camera(k)
    cam.configure(CameraSettings(width=320, height=240, pixel_format=PixelFormat.GREY))
    cam.start()
    payload = bytes(k.get_raw_format(k.rfd, None).fmt.pix.bytesperline * 240)
    k.expose(payload, 10**9, error=True)
    k.expose(payload, 2 * 10**9)
    assert cam.read(1.0) is None                     # corrupted buffer, requeued
    f = cam.read(1.0)
    assert f.sequence == 1 and len(k.free) == cam.n_buffers
