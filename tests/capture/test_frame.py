"""Frame and CameraSettings validation."""
import numpy as np
import pytest

from capture.camera import CameraSettings, PixelFormat, TriggerMode
from capture.errors import CameraDisconnected, CaptureError, DiskFullError, SyncBoxNak
from capture.frame import Frame, TimestampSource


def _frame(**kw):
    args = dict(image=np.zeros((4, 5), np.uint8), camera_id="c", sequence=0, timestamp_ns=1,
                timestamp_source=TimestampSource.HOST_DEQUEUE, exposure_us=100.0, gain=1.0)
    args.update(kw)
    return Frame(**args)


def test_frame_is_read_only_and_checked():
    img = np.zeros((4, 5), np.uint16)
    f = _frame(image=img)
    assert f.shape == (4, 5) and not f.image.flags.writeable
    img[0, 0] = 7                                     # the caller's array stays writable
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        _frame(image=np.zeros((4, 5, 3), np.uint8))
    with pytest.raises(TypeError, match="float32"):
        _frame(image=np.zeros((4, 5), np.float32))
    with pytest.raises(TypeError, match="TimestampSource"):
        _frame(timestamp_source="kernel")
    with pytest.raises(ValueError, match="sequence"):
        _frame(sequence=-1)


def test_settings_round_trip_and_validation():
    s = CameraSettings(width=640, height=480, pixel_format="Y10 ", rate_hz=120,
                       exposure_us=500, gain=2, trigger="external")
    assert s.pixel_format == PixelFormat.Y10 and s.trigger == TriggerMode.EXTERNAL
    assert CameraSettings.from_dict(s.to_dict()) == s
    for bad in (dict(width=0), dict(rate_hz=-1), dict(exposure_us=0), dict(gain=-1)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            CameraSettings(**bad)
    with pytest.raises(ValueError):
        CameraSettings(pixel_format="RGB3")


def test_errors_name_the_device():
    e = CameraDisconnected("/dev/video3", "gone")
    assert isinstance(e, CaptureError) and e.device == "/dev/video3"
    assert str(e) == "/dev/video3: gone"
    assert SyncBoxNak("/dev/ttyACM0", "refused", 5).code == 5
    assert isinstance(DiskFullError("/x/cam00.frames", "full"), CaptureError)
