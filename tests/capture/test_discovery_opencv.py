"""Device discovery on a fake sysfs tree, USB reset through a fake pyusb, OpenCV fallback."""
import time

import cv2
import numpy as np
import pytest

from capture.camera import CameraSettings, PixelFormat
from capture.discovery import discover_cameras, find_by_serial, reset_usb_device
from capture.errors import CameraDisconnected, CameraError
from capture.frame import TimestampSource
from capture.opencv_camera import OpenCVCamera


def _fake_sysfs(root):
    usb = root / "devices/pci0000:00/0000:00:14.0/usb1"
    cams = [("video0", "1-1.2", "1415", "2000", "EYE-A", 0, "USB Camera-B4.09.24.1"),
            ("video1", "1-1.2", "1415", "2000", "EYE-A", 1, "USB Camera-B4.09.24.1"),
            ("video2", "1-1.3", "046d", "0825", None, 0, "UVC Camera (046d:0825)")]
    for node, port, vid, pid, serial, index, name in cams:
        dev = usb / "1-1" / port
        intf = dev / f"{port}:1.0"
        intf.mkdir(parents=True, exist_ok=True)
        (dev / "idVendor").write_text(vid + "\n")
        (dev / "idProduct").write_text(pid + "\n")
        (dev / "busnum").write_text("1\n")
        (dev / "devnum").write_text(str(5 + int(port[-1])) + "\n")
        if serial:
            (dev / "serial").write_text(serial + "\n")
        cls = root / "class/video4linux" / node
        cls.mkdir(parents=True)
        (cls / "device").symlink_to(intf)
        (cls / "index").write_text(f"{index}\n")
        (cls / "name").write_text(name + "\n")
    plat = root / "class/video4linux/video10"
    plat.mkdir()
    (plat / "name").write_text("bcm2835-isp\n")
    return root


def test_discovery_maps_nodes_to_usb_identity(tmp_path):
    root = _fake_sysfs(tmp_path / "sys")
    devs = discover_cameras(sysfs_root=root, dev_root="/dev")
    assert [d.path for d in devs] == ["/dev/video0", "/dev/video2", "/dev/video10"]
    eye = devs[0]
    assert (eye.usb_id, eye.serial, eye.port_path, eye.busnum, eye.devnum) == \
        ("1415:2000", "EYE-A", "1-1.2", 1, 7)
    assert devs[1].serial is None and devs[1].usb_id == "046d:0825"
    assert devs[2].vid is None and devs[2].name == "bcm2835-isp"
    assert len(discover_cameras(sysfs_root=root, capture_nodes_only=False)) == 4
    assert find_by_serial("EYE-A", sysfs_root=root).path == "/dev/video0"
    with pytest.raises(CameraError, match="NOPE"):
        find_by_serial("NOPE", sysfs_root=root)
    assert discover_cameras(sysfs_root=tmp_path / "empty") == []


class _UsbDev:
    def __init__(self, bus, address):
        self.bus, self.address, self.resets = bus, address, 0

    def reset(self):
        self.resets += 1


def test_usb_reset_finds_the_right_device(tmp_path):
    eye = discover_cameras(sysfs_root=_fake_sysfs(tmp_path / "sys"))[0]
    devices = [_UsbDev(1, 8), _UsbDev(1, 7), _UsbDev(2, 7)]

    def find(idVendor, idProduct, custom_match):
        assert (idVendor, idProduct) == (0x1415, 0x2000)
        return next((d for d in devices if custom_match(d)), None)

    reset_usb_device(eye, find=find)
    assert [d.resets for d in devices] == [0, 1, 0]
    devices.pop(1)
    with pytest.raises(CameraError, match="not found"):
        reset_usb_device(eye, find=find)


class FakeCapture:
    """cv2.VideoCapture look-alike: set() silently ignores what the 'driver' refuses."""

    def __init__(self, n_frames=5, fail_after=None):
        self.props = {cv2.CAP_PROP_FRAME_WIDTH: 640, cv2.CAP_PROP_FRAME_HEIGHT: 480,
                      cv2.CAP_PROP_FPS: 30.0, cv2.CAP_PROP_EXPOSURE: 100.0,
                      cv2.CAP_PROP_GAIN: 0.0,
                      cv2.CAP_PROP_FOURCC: cv2.VideoWriter_fourcc(*"YUYV")}
        self.n, self.fail_after = 0, fail_after

    def isOpened(self):
        return True

    def set(self, prop, value):
        if prop == cv2.CAP_PROP_FPS:
            return False                       # silently refused
        if prop in self.props:
            self.props[prop] = value
        return True

    def get(self, prop):
        if prop == cv2.CAP_PROP_POS_MSEC:
            return time.monotonic_ns() / 1e6
        return self.props.get(prop, 0.0)

    def read(self):
        time.sleep(0.01)
        self.n += 1
        if self.fail_after is not None and self.n > self.fail_after:
            return False, None
        img = np.full((480, 640, 3), self.n % 256, np.uint8)
        return True, img

    def release(self):
        pass


def test_opencv_fallback_reads_back_and_marks_dequeue_time():
    cap = FakeCapture()
    cam = OpenCVCamera("/dev/video0", capture_factory=lambda s: cap)
    got = cam.configure(CameraSettings(rate_hz=120, exposure_us=2000, gain=4,
                                       pixel_format=PixelFormat.GREY))
    assert got.rate_hz == 30.0                 # the refused set() is visible in read-back
    assert got.exposure_us == 2000.0 and got.gain == 4.0
    assert got.pixel_format == PixelFormat.GREY and cam.settings == got
    assert cam.read(0.05) is None                  # not started: bounded, nothing
    cam.start()
    before = time.monotonic_ns()
    import select
    assert select.select([cam.fileno()], [], [], 1.0)[0]   # pollable handle
    f = cam.read(0)
    assert f is not None and f.image.shape == (480, 640)
    assert f.timestamp_source == TimestampSource.HOST_DEQUEUE
    assert abs(f.timestamp_ns - before) < 200e6
    g = cam.read(1.0)
    assert g.sequence == f.sequence + 1
    cam.close()


def test_opencv_fallback_reports_unplug():
    cam = OpenCVCamera(0, capture_factory=lambda s: FakeCapture(fail_after=2))
    cam.start()
    with pytest.raises(CameraDisconnected, match="failed reads"):
        for _ in range(200):
            cam.read(0.05)
    cam.close()
