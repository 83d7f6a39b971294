"""Find V4L2 cameras and the USB devices behind them (sysfs), and reset a wedged one (pyusb).

``/sys/class/video4linux/videoN/device`` links to the USB interface; its parent directory
is the USB device with ``idVendor``, ``idProduct``, ``serial``, ``busnum``, ``devnum``; the
directory name (``1-1.2``) is the port path, stable across reboots for a given socket.
Roots are injectable so tests build a fake sysfs tree.
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .errors import CameraError

__all__ = ["VideoDevice", "discover_cameras", "find_by_serial", "reset_usb_device"]

_PORT_RE = re.compile(r"^\d+-\d+(\.\d+)*$")


@dataclass(frozen=True, kw_only=True)
class VideoDevice:
    """A /dev/videoN node and (when on USB) its USB identity."""

    path: str
    name: str
    index: int
    vid: int | None = None
    pid: int | None = None
    serial: str | None = None
    port_path: str | None = None
    busnum: int | None = None
    devnum: int | None = None

    @property
    def usb_id(self) -> str | None:
        return None if self.vid is None else f"{self.vid:04x}:{self.pid:04x}"


def _read(p: Path) -> str | None:
    try:
        return p.read_text().strip()
    except OSError:
        return None


def _usb_device_dir(dev_link: Path) -> Path | None:
    try:
        d = dev_link.resolve()
    except OSError:
        return None
    for cand in (d, *d.parents):
        if (cand / "idVendor").exists() and _PORT_RE.match(cand.name):
            return cand
    return None


def discover_cameras(*, sysfs_root="/sys", dev_root="/dev",
                     capture_nodes_only: bool = True) -> list[VideoDevice]:
    """All video nodes, sorted by number; with USB identity when the device is on USB.

    ``capture_nodes_only`` keeps nodes with ``index`` 0 (UVC creates a second, metadata
    node per camera with index 1).
    """
    base = Path(sysfs_root) / "class" / "video4linux"
    if not base.is_dir():
        return []
    out = []
    for node in sorted(base.iterdir(),
                       key=lambda p: int(re.sub(r"\D", "", p.name) or -1)):
        if not node.name.startswith("video"):
            continue
        idx = int(_read(node / "index") or 0)
        if capture_nodes_only and idx != 0:
            continue
        usb = _usb_device_dir(node / "device")
        kw = {}
        if usb is not None:
            vid, pid = _read(usb / "idVendor"), _read(usb / "idProduct")
            kw = dict(vid=int(vid, 16) if vid else None, pid=int(pid, 16) if pid else None,
                      serial=_read(usb / "serial"), port_path=usb.name,
                      busnum=int(_read(usb / "busnum") or 0) or None,
                      devnum=int(_read(usb / "devnum") or 0) or None)
        out.append(VideoDevice(path=str(Path(dev_root) / node.name),
                               name=_read(node / "name") or node.name, index=idx, **kw))
    return out


def find_by_serial(serial: str, **kw) -> VideoDevice:
    """The capture node of the USB camera with this serial number."""
    hits = [d for d in discover_cameras(**kw) if d.serial == serial]
    if not hits:
        raise CameraError(f"serial {serial}", "no video device with this USB serial number")
    return hits[0]


def reset_usb_device(device: VideoDevice, *, find: Callable | None = None) -> None:
    """USB port reset of a wedged camera (pyusb ``Device.reset``); needs write access to
    ``/dev/bus/usb``. ``find`` is ``usb.core.find`` (injectable for tests)."""
    if device.vid is None:
        raise CameraError(device.path, "not a USB device; cannot reset")
    if find is None:
        import usb.core
        find = usb.core.find

    def match(d):
        if device.busnum is not None and getattr(d, "bus", None) != device.busnum:
            return False
        return device.devnum is None or getattr(d, "address", None) == device.devnum

    try:
        dev = find(idVendor=device.vid, idProduct=device.pid, custom_match=match)
    except Exception as e:  # noqa: BLE001 - pyusb raises NoBackendError and friends
        raise CameraError(device.path, f"USB lookup failed: {e}") from e
    if dev is None:
        raise CameraError(device.path, f"USB device {device.usb_id} at bus {device.busnum} "
                                       f"address {device.devnum} not found")
    try:
        dev.reset()
    except Exception as e:  # noqa: BLE001 - usb.core.USBError
        raise CameraError(device.path, f"USB reset failed: {e}") from e
