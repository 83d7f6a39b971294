"""OpenCV ``CAP_V4L2`` fallback camera, for when linuxpy cannot drive a device.

What OpenCV gives (FIELD_NOTES 'Hardware layer'): a millisecond timestamp of the dequeued
buffer (``CAP_PROP_POS_MSEC``), no sequence number, no timestamp flags; it discards the
first frame; many ``set()`` calls fail silently. So: every setting is read back with
``get()``; timestamps are marked ``HOST_DEQUEUE``; the sequence is our own counter (drops
cannot be seen from it). A reader thread makes ``read(timeout)`` bounded and ``fileno()``
pollable. Conventions: docs/conventions.md [time], [pixels].
"""
from __future__ import annotations

import os
import queue
import threading
import time
from typing import Callable

import cv2
import numpy as np

from .camera import CameraSettings, PixelFormat, TriggerMode
from .errors import CameraDisconnected
from .frame import Frame, TimestampSource

__all__ = ["OpenCVCamera"]

_MAX_CONSECUTIVE_FAILURES = 20


class OpenCVCamera:
    """``OpenCVCamera("/dev/video0")`` or an index; ``capture_factory`` is injectable."""

    def __init__(self, source: str | int, *, camera_id: str | None = None,
                 capture_factory: Callable | None = None, queue_size: int = 4):
        self.source = source
        self.device = str(source)
        self._id = camera_id or self.device
        factory = capture_factory or (lambda s: cv2.VideoCapture(s, cv2.CAP_V4L2))
        self._cap = factory(source)
        if not self._cap.isOpened():
            raise CameraDisconnected(self.device, "OpenCV could not open the device (CAP_V4L2)")
        self._q: queue.Queue = queue.Queue(maxsize=queue_size)
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seq = 0
        self._error: Exception | None = None
        self.frames_dropped = 0  # frames we had to discard because the reader was slow
        self._settings = self._read_back()

    @property
    def camera_id(self) -> str:
        return self._id

    @property
    def settings(self) -> CameraSettings:
        """Settings in effect, as last read back from the driver."""
        return self._settings

    def configure(self, settings: CameraSettings) -> CameraSettings:
        c = self._cap
        if settings.pixel_format is not None:
            c.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*settings.pixel_format.value))
        if settings.width:
            c.set(cv2.CAP_PROP_FRAME_WIDTH, settings.width)
        if settings.height:
            c.set(cv2.CAP_PROP_FRAME_HEIGHT, settings.height)
        if settings.rate_hz:
            c.set(cv2.CAP_PROP_FPS, settings.rate_hz)
        if settings.exposure_us is not None:
            c.set(cv2.CAP_PROP_AUTO_EXPOSURE, 1)            # V4L2 manual mode
            c.set(cv2.CAP_PROP_EXPOSURE, settings.exposure_us / 100.0)  # 100 us units
        if settings.gain is not None:
            c.set(cv2.CAP_PROP_GAIN, settings.gain)
        self._settings = self._read_back()
        return self._settings

    def _read_back(self) -> CameraSettings:
        c = self._cap
        code = int(c.get(cv2.CAP_PROP_FOURCC))
        s = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
        try:
            fmt = PixelFormat(s)
        except ValueError:
            fmt = None
        exp = c.get(cv2.CAP_PROP_EXPOSURE)
        gain = c.get(cv2.CAP_PROP_GAIN)
        fps = c.get(cv2.CAP_PROP_FPS)
        w, h = int(c.get(cv2.CAP_PROP_FRAME_WIDTH)), int(c.get(cv2.CAP_PROP_FRAME_HEIGHT))
        return CameraSettings(width=w or None, height=h or None, pixel_format=fmt,
                              rate_hz=fps if fps > 0 else None,
                              exposure_us=exp * 100.0 if exp > 0 else None,
                              gain=gain if gain >= 0 else None, trigger=TriggerMode.FREE_RUN)

    def start(self) -> None:
        if self._thread is not None:
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._loop, daemon=True,
                                        name=f"opencv-cam {self.device}")
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None

    def read(self, timeout: float) -> Frame | None:
        try:
            f = self._q.get(timeout=timeout) if timeout > 0 else self._q.get_nowait()
        except queue.Empty:
            if self._error is not None:
                raise self._error
            return None
        try:
            os.read(self._rfd, 1)
        except OSError:
            pass
        return f

    def fileno(self) -> int:
        return self._rfd

    def close(self) -> None:
        self.stop()
        self._cap.release()
        for fd in (self._rfd, self._wfd):
            try:
                os.close(fd)
            except OSError:
                pass

    def _loop(self) -> None:
        failures = 0
        s = self._settings
        while not self._stop.is_set():
            ok, img = self._cap.read()
            t_host = time.monotonic_ns()
            if not ok or img is None:
                failures += 1
                if failures >= _MAX_CONSECUTIVE_FAILURES:
                    self._error = CameraDisconnected(self.device, f"{failures} failed reads "
                                                                  f"in a row (unplugged?)")
                    return
                time.sleep(0.005)
                continue
            failures = 0
            if img.ndim == 3:
                img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY)
            if img.dtype not in (np.uint8, np.uint16):
                img = img.astype(np.uint8)
            ms = self._cap.get(cv2.CAP_PROP_POS_MSEC)
            ts = int(round(ms * 1e6)) if ms > 0 else t_host
            if abs(ts - t_host) > 10**9:
                ts = t_host  # not on CLOCK_MONOTONIC (some builds give stream time)
            frame = Frame(image=img, camera_id=self._id, sequence=self._seq, timestamp_ns=ts,
                          timestamp_source=TimestampSource.HOST_DEQUEUE,
                          exposure_us=s.exposure_us or 0.0, gain=s.gain or 0.0)
            self._seq += 1
            try:
                self._q.put_nowait(frame)
            except queue.Full:
                self.frames_dropped += 1
                continue
            try:
                os.write(self._wfd, b"\x01")
            except OSError:
                pass
