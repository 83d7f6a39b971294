"""Linux V4L2 camera driver (linuxpy functional API over the device file descriptor).

Uses what only the kernel knows: the per-buffer ``sequence`` (gaps are drops) and the buffer
timestamp on CLOCK_MONOTONIC (the clock of ``time.monotonic_ns()``), with its flags saying
whether it marks start of exposure or end of frame. Formats GREY, Y10, Y16, YUYV and MJPG
become (H, W) images. Every setting is read back after setting it.

The ``lp`` argument is the linuxpy ``video.device`` module (or a fake with the same
functions, as the unit tests use); the file is opened with ``opener`` (``os.open``).
Conventions: docs/conventions.md [pixels], [time], [errors].
"""
from __future__ import annotations

import errno
import os
import select
import time
from typing import Callable

import cv2
import numpy as np

from .camera import CameraSettings, PixelFormat, TriggerMode
from .errors import CameraDisconnected, CameraError
from .frame import Frame, TimestampSource

__all__ = ["V4L2Camera", "frame_to_image", "fourcc_code", "timestamp_from_flags"]

_BUF_TIMESTAMP_MASK = 0xE000
_BUF_TIMESTAMP_MONOTONIC = 0x2000
_BUF_TSTAMP_SRC_MASK = 0x70000
_BUF_TSTAMP_SRC_SOE = 0x10000
_BUF_ERROR = 0x40
_EXPOSURE_MANUAL = 1
_GONE = {errno.ENODEV, errno.EIO, errno.ENXIO, errno.ENOENT, errno.EBADF}


def fourcc_code(fmt: PixelFormat) -> int:
    s = fmt.value
    return ord(s[0]) | (ord(s[1]) << 8) | (ord(s[2]) << 16) | (ord(s[3]) << 24)


def _fourcc_format(code: int) -> PixelFormat:
    s = "".join(chr((code >> (8 * i)) & 0xFF) for i in range(4))
    try:
        return PixelFormat(s)
    except ValueError:
        raise CameraError("v4l2", f"unsupported pixel format {s!r}") from None


def frame_to_image(data: bytes, fmt: PixelFormat, width: int, height: int,
                   bytes_per_line: int = 0) -> np.ndarray:
    """Decode one buffer into an (H, W) uint8/uint16 image ([pixels]).

    Y10 keeps 0..1023 in uint16 (right-aligned); Y16 keeps 16 bits; YUYV keeps luminance;
    MJPG is decoded to grey.
    """
    buf = np.frombuffer(data, dtype=np.uint8)
    if fmt == PixelFormat.MJPG:
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE)
        if img is None or img.shape != (height, width):
            raise ValueError(f"MJPG buffer of {len(data)} bytes does not decode to "
                             f"({height}, {width})")
        return img
    bpp = {PixelFormat.GREY: 1, PixelFormat.Y10: 2, PixelFormat.Y16: 2, PixelFormat.YUYV: 2}[fmt]
    stride = bytes_per_line or width * bpp
    if buf.size < stride * (height - 1) + width * bpp:
        raise ValueError(f"buffer of {buf.size} bytes is short for {fmt.name} "
                         f"{width}x{height} (stride {stride})")
    rows = np.lib.stride_tricks.as_strided(buf, shape=(height, width * bpp),
                                           strides=(stride, 1))
    if fmt == PixelFormat.GREY:
        return rows.copy()
    if fmt == PixelFormat.YUYV:
        return rows[:, 0::2].copy()
    words = np.ascontiguousarray(rows).view("<u2").astype(np.uint16)
    return words & 0x3FF if fmt == PixelFormat.Y10 else words


def timestamp_from_flags(flags: int, secs: int, usecs: int) -> tuple[int, TimestampSource] | None:
    """Kernel buffer time in ns and its source, or None when not on CLOCK_MONOTONIC."""
    if flags & _BUF_TIMESTAMP_MASK != _BUF_TIMESTAMP_MONOTONIC:
        return None
    src = (TimestampSource.KERNEL_START_OF_EXPOSURE
           if flags & _BUF_TSTAMP_SRC_MASK == _BUF_TSTAMP_SRC_SOE
           else TimestampSource.KERNEL_END_OF_FRAME)
    return int(secs) * 1_000_000_000 + int(usecs) * 1000, src


def _linuxpy():
    from linuxpy.video import device as lp  # Linux only; imported on use
    return lp


class V4L2Camera:
    """A V4L2 capture device, e.g. ``V4L2Camera("/dev/video0")``.

    Args:
        path: device node.
        camera_id: stable id (defaults to the path).
        n_buffers: mmap buffers queued to the driver.
        exposure_us_per_unit: for drivers without ``exposure_time_absolute`` whose plain
            ``exposure`` control is in lines/driver units; None when unknown (then the
            applied exposure is reported in those units * 1.0 and flagged by name).
        lp, opener: injectable linuxpy module and ``open`` for tests.
    """

    def __init__(self, path: str, *, camera_id: str | None = None, n_buffers: int = 4,
                 exposure_us_per_unit: float | None = None, lp=None,
                 opener: Callable[[str, int], int] = os.open):
        self.path = str(path)
        self._id = camera_id or self.path
        self.n_buffers = int(n_buffers)
        self.exposure_us_per_unit = exposure_us_per_unit
        self._lp = lp if lp is not None else _linuxpy()
        raw = self._lp.raw
        self._bt = raw.BufType.VIDEO_CAPTURE
        self._mem = raw.Memory.MMAP
        self._cid = raw.ControlID
        try:
            self._fd = opener(self.path, os.O_RDWR | os.O_NONBLOCK)
        except OSError as e:
            raise CameraDisconnected(self.path, f"cannot open: {e}") from e
        self._maps: list = []
        self._streaming = False
        self._settings = self._read_back()

    # -- Camera protocol ------------------------------------------------------------------
    @property
    def camera_id(self) -> str:
        return self._id

    @property
    def settings(self) -> CameraSettings:
        """Settings in effect, as last read back from the driver."""
        return self._settings

    def configure(self, settings: CameraSettings) -> CameraSettings:
        if self._streaming:
            raise CameraError(self.path, "configure while streaming; stop() first")
        lp = self._lp
        try:
            cur = self._settings
            if settings.width or settings.height or settings.pixel_format:
                lp.set_format(self._fd, self._bt, int(settings.width or cur.width),
                              int(settings.height or cur.height),
                              (settings.pixel_format or cur.pixel_format).value)
            if settings.rate_hz:
                try:
                    lp.set_fps(self._fd, self._bt, settings.rate_hz)
                except OSError as e:  # no S_PARM (externally triggered sensors): read back
                    if e.errno in _GONE:
                        raise
            if settings.exposure_us is not None:
                self._set_exposure(settings.exposure_us)
            if settings.gain is not None:
                self._try_set((self._cid.GAIN, self._cid.ANALOGUE_GAIN), int(round(settings.gain)))
        except OSError as e:
            self._raise_os(e, "configure")
        self._settings = self._read_back()
        return self._settings

    def start(self) -> None:
        if self._streaming:
            return
        lp = self._lp
        try:
            self._maps = lp.create_mmap_buffers(self._fd, self._bt, self._mem, self.n_buffers)
            lp.enqueue_buffers(self._fd, self._bt, self._mem, self.n_buffers)
            lp.stream_on(self._fd, self._bt)
        except OSError as e:
            self._raise_os(e, "start streaming")
        self._streaming = True

    def stop(self) -> None:
        if not self._streaming:
            return
        self._streaming = False
        try:
            self._lp.stream_off(self._fd, self._bt)
            for m in self._maps:
                if hasattr(m, "close"):
                    m.close()
            self._maps = []
            self._lp.free_buffers(self._fd, self._bt, self._mem)
        except OSError as e:
            if e.errno not in _GONE:
                raise CameraError(self.path, f"stop streaming: {e}") from e

    def read(self, timeout: float) -> Frame | None:
        if not self._streaming:
            raise CameraError(self.path, "read() before start()")
        try:
            r, _, _ = select.select([self._fd], [], [], max(0.0, timeout))
        except (OSError, ValueError) as e:
            raise CameraDisconnected(self.path, f"select failed: {e}") from e
        if not r:
            return None
        try:
            buf = self._lp.dequeue_buffer(self._fd, self._bt, self._mem)
        except BlockingIOError:
            return None
        except OSError as e:
            self._raise_os(e, "dequeue")
        t_host = time.monotonic_ns()
        try:
            s = self._settings
            if buf.flags & _BUF_ERROR:
                image = None
            else:
                data = bytes(self._maps[buf.index][:buf.bytesused])
                image = frame_to_image(data, s.pixel_format, s.width, s.height,
                                       self._bytes_per_line)
        finally:
            try:
                self._lp.enqueue_buffer_raw(self._fd, buf)
            except OSError as e:
                self._raise_os(e, "requeue")
        if image is None:
            return None  # corrupted buffer: its sequence number is consumed -> counted drop
        ts = timestamp_from_flags(buf.flags, buf.timestamp.secs, buf.timestamp.usecs)
        ts_ns, src = ts if ts is not None else (t_host, TimestampSource.HOST_DEQUEUE)
        return Frame(image=image, camera_id=self._id, sequence=buf.sequence, timestamp_ns=ts_ns,
                     timestamp_source=src, exposure_us=s.exposure_us or 0.0, gain=s.gain or 0.0)

    def fileno(self) -> int:
        return self._fd

    def close(self) -> None:
        self.stop()
        try:
            os.close(self._fd)
        except OSError:
            pass

    # -- internals ------------------------------------------------------------------------
    def _raise_os(self, e: OSError, what: str):
        if e.errno in _GONE:
            raise CameraDisconnected(self.path, f"{what}: device gone ({e})") from e
        raise CameraError(self.path, f"{what}: {e}") from e

    def _try_set(self, ids, value) -> bool:
        for cid in ids:
            try:
                self._lp.set_control(self._fd, cid, value)
                return True
            except OSError as e:
                if e.errno in _GONE:
                    raise
        return False

    def _try_get(self, ids):
        for cid in ids:
            try:
                return cid, self._lp.get_control(self._fd, cid)
            except OSError as e:
                if e.errno in _GONE:
                    raise
        return None, None

    def _set_exposure(self, us: float) -> None:
        self._try_set((self._cid.EXPOSURE_AUTO,), _EXPOSURE_MANUAL)
        if self._try_set((self._cid.EXPOSURE_ABSOLUTE,), max(1, int(round(us / 100.0)))):
            return
        unit = self.exposure_us_per_unit
        if unit is None:
            raise CameraError(self.path, "driver has no exposure_time_absolute; pass "
                                         "exposure_us_per_unit to use its 'exposure' control")
        if not self._try_set((self._cid.EXPOSURE,), max(1, int(round(us / unit)))):
            raise CameraError(self.path, "driver refuses exposure controls")

    def _read_back(self) -> CameraSettings:
        lp = self._lp
        try:
            f = lp.get_raw_format(self._fd, self._bt)
            try:
                fps = lp.get_fps(self._fd, self._bt)
            except ZeroDivisionError:   # driver reports a 0/0 frame interval
                fps = None
            except OSError as e:        # driver without G_PARM: rate unknown
                if e.errno in _GONE:
                    raise
                fps = None
            _, v = self._try_get((self._cid.EXPOSURE_ABSOLUTE,))
            exposure_us = None if v is None else float(v) * 100.0
            if exposure_us is None and self.exposure_us_per_unit is not None:
                _, v = self._try_get((self._cid.EXPOSURE,))
                exposure_us = None if v is None else float(v) * self.exposure_us_per_unit
            _, g = self._try_get((self._cid.GAIN, self._cid.ANALOGUE_GAIN))
        except OSError as e:
            self._raise_os(e, "read back settings")
        pix = f.fmt.pix
        self._bytes_per_line = int(pix.bytesperline)
        return CameraSettings(width=int(pix.width), height=int(pix.height),
                              pixel_format=_fourcc_format(int(pix.pixelformat)),
                              rate_hz=float(fps) if fps else None,
                              exposure_us=exposure_us if exposure_us else None,
                              gain=None if g is None else float(g),
                              trigger=TriggerMode.FREE_RUN)
