"""A fake of the linuxpy ``video.device`` functions V4L2Camera calls, with a tiny kernel.

It uses linuxpy's real ctypes structures (``raw.v4l2_buffer``, ``raw.v4l2_format``) so the
driver's field handling is exercised; readiness is a real pipe so ``select`` works.

``FakeVideoDevices`` serves several such kernels behind device nodes (FIFOs the driver opens
with plain ``os.open``, as it opens ``/dev/videoN``) and ``TriggeredSensor`` is the sensor
behind one: exposures started by a ``hw_sim`` sync box's trigger line, images rendered by
``hw_sim.render``. Together they let sessions and ``mocap capture`` run the real
``V4L2Camera`` on the simulated rig; the only thing faked is the kernel.
"""
from __future__ import annotations

import errno
import fractions
import os
import queue
import threading
import time
from collections import deque
from pathlib import Path

import cv2
import numpy as np
from linuxpy.video import raw

from hw_sim.render import render_frame
from hw_sim.sim_camera import orbiting_markers

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
        self.node_ino = None            # inode of the device node, when behind one
        self.lock = threading.RLock()   # the ioctls and the sensor's deliveries

    def opener(self, path, flags):
        if self.gone:
            raise FileNotFoundError(errno.ENOENT, "No such device", path)
        return self.rfd

    def attach(self, node) -> None:
        """Serve the device node ``node`` (a FIFO): any fd the driver opens on it is this
        device, and readiness is signalled through it instead of the private pipe."""
        os.close(self.rfd)
        os.close(self.wfd)
        self.rfd = self.wfd = os.open(node, os.O_RDWR | os.O_NONBLOCK)
        self.node_ino = os.fstat(self.rfd).st_ino

    def _check(self, fd):
        if self.gone:
            raise OSError(errno.ENODEV, "No such device")
        assert fd == self.rfd or (self.node_ino is not None
                                  and os.fstat(fd).st_ino == self.node_ino)

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


class FakeVideoDevices:
    """Stands for the linuxpy ``video.device`` module (``V4L2Camera(lp=...)``, or what
    ``capture.v4l2._linuxpy`` returns): each call goes to the FakeKernel behind the fd's
    device node. Nodes are FIFOs in ``folder``, opened by the driver with ``os.open``."""

    raw = raw
    _CALLS = {"set_format", "get_raw_format", "set_fps", "get_fps", "get_control",
              "set_control", "create_mmap_buffers", "enqueue_buffers", "stream_on",
              "stream_off", "free_buffers", "dequeue_buffer", "enqueue_buffer_raw"}

    def __init__(self, folder):
        self.folder = Path(folder)
        self.kernels: dict[str, FakeKernel] = {}
        self._by_ino: dict[int, FakeKernel] = {}

    def add(self, name: str, kernel: FakeKernel | None = None) -> tuple[str, FakeKernel]:
        """A new device node ``folder/name``; returns its path and its kernel."""
        path = self.folder / name
        os.mkfifo(path)
        k = kernel if kernel is not None else FakeKernel()
        k.attach(path)
        self.kernels[str(path)] = k
        self._by_ino[k.node_ino] = k
        return str(path), k

    def __getattr__(self, name):
        if name not in self._CALLS:
            raise AttributeError(name)

        def call(fd, *args):
            try:
                k = self._by_ino[os.fstat(fd).st_ino]
            except (KeyError, OSError):
                raise OSError(errno.ENOTTY, "Inappropriate ioctl for device") from None
            with k.lock:
                return getattr(k, name)(fd, *args)
        return call

    def close(self) -> None:
        for k in self.kernels.values():
            try:
                os.close(k.rfd)
            except OSError:
                pass


def pack_image(img: np.ndarray, fmt: str, stride: int) -> bytes:
    """A (H, W) image as the bytes of one buffer in V4L2 format ``fmt`` (rows ``stride``
    bytes apart; MJPG: a JPEG)."""
    if fmt == "MJPG":
        ok, jpg = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, 95])
        return jpg.tobytes()
    if fmt == "YUYV":
        row = np.full((img.shape[0], 2 * img.shape[1]), 128, np.uint8)
        row[:, 0::2] = img
    elif fmt == "GREY":
        row = img.astype(np.uint8)
    else:                                           # Y10 (right-aligned), Y16: little endian
        row = img.astype("<u2").view(np.uint8).reshape(img.shape[0], -1)
    out = np.zeros((img.shape[0], stride), np.uint8)
    out[:, :row.shape[1]] = row
    return out.tobytes()


_BITS = {"GREY": 8, "YUYV": 8, "MJPG": 8, "Y10 ": 10, "Y16 ": 16}


class TriggeredSensor:
    """The sensor behind a FakeKernel, its trigger input wired to a ``SimSyncBox``.

    At each pulse of the box's trigger line it exposes a frame of ``model`` (a hw_sim camera
    model, size = the kernel's) showing ``scene`` at the pulse time, rendered by
    ``hw_sim.render``; after ``latency_ms`` the frame goes into the kernel's next free buffer
    (packed in the format the driver configured) with the pulse time (+ jitter) as its
    start-of-exposure timestamp. With no free buffer, or while the trigger queue is full,
    the frame is dropped and its sequence number consumed, as a V4L2 driver does. Frames are
    delivered only while streaming.

    Ground truth, like ``SimCamera``: ``truth[sequence] = (pulse index, pulse host ns)`` and
    ``dropped_sequences``; ``camera_id`` is the model name.
    """

    def __init__(self, kernel: FakeKernel, model, sync, *, scene=None, latency_ms=3.0,
                 timestamp_jitter_us=20.0, time_origin_ns=0, rng=None):
        if tuple(kernel.size) != tuple(model.size):
            raise ValueError(f"model size {model.size} != sensor size {kernel.size}")
        self.kernel, self.model, self.sync = kernel, model, sync
        self.scene = scene if scene is not None else orbiting_markers()
        self.latency_ns = int(latency_ms * 1e6)
        self.jitter_ns = timestamp_jitter_us * 1e3
        self.time_origin_ns = int(time_origin_ns)
        self.rng = np.random.default_rng(rng)
        self.truth: dict[int, tuple[int, float]] = {}
        self.dropped_sequences: deque[int] = deque(maxlen=100_000)
        self.error: BaseException | None = None
        self._triggers: queue.Queue = queue.Queue(maxsize=64)
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None

    @property
    def camera_id(self) -> str:
        return self.model.name

    def start(self) -> "TriggeredSensor":
        self._stop.clear()
        self._worker = threading.Thread(target=self._work, daemon=True,
                                        name=f"sensor {self.camera_id}")
        self._worker.start()
        self.sync.add_trigger_listener(self._on_trigger)
        return self

    def stop(self) -> None:
        self.sync.remove_trigger_listener(self._on_trigger)
        self._stop.set()
        if self._worker is not None:
            self._worker.join(timeout=2.0)

    def _on_trigger(self, ev) -> None:
        try:
            self._triggers.put_nowait((ev.index, ev.host_ns))
        except queue.Full:                 # exposed, nowhere to put it: a consumed sequence
            k = self.kernel
            with k.lock:
                if k.streaming:
                    self.dropped_sequences.append(k.seq)
                    k.seq += 1

    def _work(self) -> None:
        k = self.kernel
        try:
            while not self._stop.is_set():
                try:
                    index, pulse_ns = self._triggers.get(timeout=0.05)
                except queue.Empty:
                    continue
                with k.lock:
                    fmt = k.fmt
                    stride = k.get_raw_format(k.rfd, None).fmt.pix.bytesperline
                pts, diam = self.scene((pulse_ns - self.time_origin_ns) * 1e-9)
                img, _ = render_frame(self.model, pts, diam, self.rng, bit_depth=_BITS[fmt])
                payload = pack_image(img, fmt, stride)
                ts = int(round(pulse_ns + self.rng.normal(0.0, self.jitter_ns)))
                wait = (pulse_ns + self.latency_ns - time.monotonic_ns()) * 1e-9
                if wait > 0 and self._stop.wait(wait):
                    return
                with k.lock:
                    if not k.streaming:
                        continue
                    seq = k.seq
                    self.truth[seq] = (index, pulse_ns)
                    if not k.expose(payload, ts):
                        self.dropped_sequences.append(seq)
        except BaseException as e:  # noqa: BLE001 - reported to the test through .error
            self.error = e
            raise
