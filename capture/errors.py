"""Hardware faults of the capture layer: one small family, each naming its device.

Conventions: docs/conventions.md [errors] -- bad input raises ValueError/TypeError; hardware
faults raise a ``CaptureError`` subclass whose message starts with the device.
"""
from __future__ import annotations

__all__ = [
    "CaptureError",
    "CameraError",
    "CameraDisconnected",
    "CameraTimeout",
    "SyncBoxError",
    "SyncBoxDisconnected",
    "SyncBoxTimeout",
    "SyncBoxNak",
    "SyncProtocolError",
    "RecordingError",
    "DiskFullError",
]


class CaptureError(RuntimeError):
    """A capture device failed. ``device`` names it (a path, port or camera id)."""

    def __init__(self, device: str, message: str):
        self.device = str(device)
        self.detail = message
        super().__init__(f"{self.device}: {message}")


class CameraError(CaptureError):
    """A camera failed in a way not covered by a more specific class."""


class CameraDisconnected(CameraError):
    """The camera went away (unplugged, driver reset, simulated disappearance)."""


class CameraTimeout(CameraError):
    """The camera produced no frame within a timeout where one was required."""


class SyncBoxError(CaptureError):
    """The sync box failed."""


class SyncBoxDisconnected(SyncBoxError):
    """The serial port of the sync box closed or vanished."""


class SyncBoxTimeout(SyncBoxError):
    """The sync box did not answer a request in time."""


class SyncBoxNak(SyncBoxError):
    """The sync box refused a command; ``code`` is the protocol error code."""

    def __init__(self, device: str, message: str, code: int):
        self.code = int(code)
        super().__init__(device, message)


class SyncProtocolError(SyncBoxError):
    """The byte stream from the sync box stopped making sense (sustained garbage)."""


class RecordingError(CaptureError):
    """Writing or reading a recording failed; ``device`` is the file or folder."""


class DiskFullError(RecordingError):
    """The disk filled up (ENOSPC) while recording."""
