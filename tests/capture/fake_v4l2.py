"""A fake of the linuxpy ``video.device`` functions V4L2Camera calls, with a tiny kernel.

It uses linuxpy's real ctypes structures (``raw.v4l2_buffer``, ``raw.v4l2_format``) so the
driver's field handling is exercised; readiness is a real pipe so ``select`` works.
"""
from __future__ import annotations

import errno
import fractions
import os

import numpy as np
from linuxpy.video import raw

SUPPORTED_SIZES = [(320, 240), (640, 480)]
SUPPORTED_FPS = [30, 60, 75, 125, 187]
SUPPORTED_FORMATS = ["GREY", "Y10 ", "Y16 ", "YUYV", "MJPG"]


def fourcc(s):
    return raw.v4l2_fourcc(*s)


class FakeKernel:
    raw = raw

    def __init__(self, *, controls=None, timestamp_flags=0x2000 | 0x10000, has_parm=True):
        self.rfd, self.wfd = os.pipe()
        os.set_blocking(self.rfd, False)
        self.size = (640, 480)
        self.fmt = "YUYV"
        self.fps = fractions.Fraction(30)
        self.controls = dict(controls if controls is not None else {
            raw.ControlID.EXPOSURE_AUTO: 3, raw.ControlID.EXPOSURE_ABSOLUTE: 100,
            raw.ControlID.GAIN: 10})
        self.ts_flags = timestamp_flags
        self.maps = []
        self.streaming = False
        self.ready = []
        self.seq = 0
        self.gone = False
        self.set_calls = []
        self.has_parm = has_parm        # False: the driver has no G_PARM/S_PARM ioctls

    def opener(self, path, flags):
        if self.gone:
            raise FileNotFoundError(errno.ENOENT, "No such device", path)
        return self.rfd

    def _check(self, fd):
        if self.gone:
            raise OSError(errno.ENODEV, "No such device")
        assert fd == self.rfd

    # -- formats, rate, controls --------------------------------------------------------
    def set_format(self, fd, bt, w, h, pixel_format):
        self._check(fd)
        self.size = min(SUPPORTED_SIZES, key=lambda s: abs(s[0] - w) + abs(s[1] - h))
        if pixel_format in SUPPORTED_FORMATS:
            self.fmt = pixel_format

    def get_raw_format(self, fd, bt):
        self._check(fd)
        f = raw.v4l2_format()
        f.type = raw.BufType.VIDEO_CAPTURE if bt is None else bt
        f.fmt.pix.width, f.fmt.pix.height = self.size
        f.fmt.pix.pixelformat = fourcc(self.fmt)
        bpp = 1 if self.fmt == "GREY" else 2
        f.fmt.pix.bytesperline = 0 if self.fmt == "MJPG" else self.size[0] * bpp + 64  # padded
        return f

    def set_fps(self, fd, bt, fps):
        self._check(fd)
        if not self.has_parm:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")
        self.fps = fractions.Fraction(min(SUPPORTED_FPS, key=lambda f: abs(f - fps)))

    def get_fps(self, fd, bt):
        self._check(fd)
        if not self.has_parm:
            raise OSError(errno.ENOTTY, "Inappropriate ioctl for device")
        return self.fps

    def get_control(self, fd, cid):
        self._check(fd)
        if cid not in self.controls:
            raise OSError(errno.EINVAL, "Invalid argument")
        return self.controls[cid]

    def set_control(self, fd, cid, value):
        self._check(fd)
        if cid not in self.controls:
            raise OSError(errno.EINVAL, "Invalid argument")
        self.set_calls.append((cid, value))
        if cid == raw.ControlID.GAIN:
            value = int(np.clip(value, 0, 63))        # the driver clamps silently
        self.controls[cid] = value

    # -- streaming ------------------------------------------------------------------------
    def create_mmap_buffers(self, fd, bt, mem, count):
        self._check(fd)
        w, h = self.size
        self.maps = [bytearray((w * 2 + 64) * h + 4096) for _ in range(count)]
        return self.maps

    def enqueue_buffers(self, fd, bt, mem, count):
        self._check(fd)
        self.free = list(range(count))

    def stream_on(self, fd, bt):
        self._check(fd)
        self.streaming = True

    def stream_off(self, fd, bt):
        self._check(fd)
        self.streaming = False

    def free_buffers(self, fd, bt, mem):
        self.maps = []

    def expose(self, payload: bytes, ts_ns: int, *, error=False):
        """The sensor delivers one frame; dropped (sequence consumed) if no buffer is free."""
        seq = self.seq
        self.seq += 1
        if not self.free:
            return False
        i = self.free.pop(0)
        self.maps[i][:len(payload)] = payload
        b = raw.v4l2_buffer()
        b.index, b.bytesused, b.sequence = i, len(payload), seq
        b.flags = self.ts_flags | (0x40 if error else 0)
        b.timestamp.secs, b.timestamp.usecs = divmod(ts_ns // 1000, 1_000_000)
        self.ready.append(b)
        os.write(self.wfd, b"x")
        return True

    def dequeue_buffer(self, fd, bt, mem):
        self._check(fd)
        if not self.ready:
            raise BlockingIOError(errno.EAGAIN, "Resource temporarily unavailable")
        os.read(self.rfd, 1)
        return self.ready.pop(0)

    def enqueue_buffer_raw(self, fd, buf):
        self._check(fd)
        self.free.append(buf.index)
