"""``SimCamera``: a simulated camera following the ``capture.camera.Camera`` protocol.

Like a sensor with its FSIN/trigger pin wired to the sync box, it exposes a frame at every
pulse of a ``SimSyncBox`` (it listens to the box's trigger line, not to the serial
messages) or, without a box, free-runs at its own rate. Frames carry a driver-like sequence
number and a kernel-like timestamp (start of exposure, or end of frame) on the host
monotonic clock with small jitter, and are delivered after a readout latency. Like V4L2 it
has a fixed number of buffers: when the reader does not keep up, frames are dropped and the
sequence number still advances. Faults: ``disappear()``, random drops, late delivery.

Images come from ``hw_sim.render.render_frame`` (blobs, read and shot noise, bit depth).
Conventions: docs/conventions.md [pixels], [time], [frames].
"""
from __future__ import annotations

import os
import queue
import threading
import time
from collections import deque
from typing import Callable

import numpy as np

from calibration.camera import Camera as CameraModel, look_at
from capture.camera import CameraSettings, PixelFormat, TriggerMode
from capture.errors import CameraDisconnected
from capture.frame import Frame, TimestampSource
from hw_sim.render import render_frame

__all__ = ["SimCamera", "Scene", "orbiting_markers", "ring_of_cameras", "sim_rig"]

Scene = Callable[[float], tuple[np.ndarray, np.ndarray]]  # t_s -> (points (N,3) m, diam (N,) m)

_EXPOSURE_STEP_US = 10.0   # exposure is applied in whole sensor lines (~10 us)
_GAIN_STEP = 1.0 / 16.0
_GAIN_RANGE = (1.0, 16.0)
_READOUT_NS_PER_ROW = 15_000
_FORMATS = {8: PixelFormat.GREY, 10: PixelFormat.Y10, 16: PixelFormat.Y16}  # rolling readout; end-of-frame = start + exposure + rows * this


def orbiting_markers(n: int = 5, *, radius_m: float = 0.5, height_m: float = 1.0,
                     period_s: float = 4.0, diameter_m: float = 0.014) -> Scene:
    """A few markers circling the world z axis (test and demo scene)."""
    phase = 2 * np.pi * np.arange(n) / max(n, 1)
    z = height_m + 0.2 * np.linspace(-1, 1, n) if n > 1 else np.full(n, height_m)

    def scene(t_s: float):
        a = 2 * np.pi * t_s / period_s + phase
        pts = np.stack([radius_m * np.cos(a), radius_m * np.sin(a), z], axis=1)
        return pts, np.full(n, diameter_m)

    return scene


def ring_of_cameras(n: int, *, size=(320, 256), radius_m: float = 3.0, height_m: float = 2.2,
                    hfov_deg: float = 60.0, target=(0.0, 0.0, 1.0)) -> list[CameraModel]:
    """``n`` ideal cameras on a circle looking at ``target`` (ids cam_1..cam_n)."""
    w, h = size
    fx = (w / 2) / np.tan(np.radians(hfov_deg) / 2)
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at((radius_m * np.cos(a), radius_m * np.sin(a), height_m), target)
        cams.append(CameraModel.from_params(name=f"cam_{i + 1}", size=(w, h), fx=fx, R=R, t=t))
    return cams


class SimCamera:
    """Simulated camera (see module docstring).

    Args:
        model: calibrated camera model (pose, intrinsics, size); ``model.name`` is the id.
        scene: ``t_s -> (points (N,3), diameters (N,))``; time since ``time_origin_ns``.
        sync: simulated sync box whose trigger line starts each exposure, or None.
        bit_depth: 8 (GREY), 10 (Y10) or 16 (Y16).
        render_options: extra keyword arguments of ``hw_sim.render.render_frame``.
        n_buffers: driver buffers; when all hold undelivered frames, new frames are dropped.
        latency_ms: exposure start -> frame available (readout + USB + driver).
        timestamp_jitter_us: std of the kernel timestamp noise.
        rng: Generator or seed.
    """

    def __init__(self, model: CameraModel, *, scene: Scene | None = None, sync=None,
                 bit_depth: int = 8, exposure_us: float = 500.0, gain: float = 1.0,
                 rate_hz: float = 100.0,
                 timestamp_source: TimestampSource = TimestampSource.KERNEL_START_OF_EXPOSURE,
                 n_buffers: int = 4, latency_ms: float = 3.0, timestamp_jitter_us: float = 20.0,
                 time_origin_ns: int = 0, render_options: dict | None = None, rng=None):
        if bit_depth not in _FORMATS:
            raise ValueError(f"bit_depth={bit_depth}, expected one of {sorted(_FORMATS)}")
        if timestamp_source not in (TimestampSource.KERNEL_START_OF_EXPOSURE,
                                    TimestampSource.KERNEL_END_OF_FRAME):
            raise ValueError(f"timestamp_source={timestamp_source}, expected a kernel source")
        if n_buffers < 1:
            raise ValueError(f"n_buffers={n_buffers}, expected >= 1")
        self.model = model
        self.scene = scene if scene is not None else orbiting_markers()
        self.sync = sync
        self.bit_depth = bit_depth
        self.timestamp_source = timestamp_source
        self.latency_ns = int(latency_ms * 1e6)
        self.timestamp_jitter_ns = timestamp_jitter_us * 1e3
        self.time_origin_ns = int(time_origin_ns)
        self.rng = np.random.default_rng(rng)
        self.render_options = dict(render_options or {})
        self.device = f"sim:{model.name}"
        w, h = model.size
        self._settings = CameraSettings(
            width=w, height=h, pixel_format=_FORMATS[bit_depth],
            rate_hz=float(rate_hz), exposure_us=self._quant_exposure(exposure_us),
            gain=self._quant_gain(gain),
            trigger=TriggerMode.EXTERNAL if sync is not None else TriggerMode.FREE_RUN)
        self._n_buffers = n_buffers
        self._out: queue.Queue[Frame] = queue.Queue()
        self._triggers: queue.Queue = queue.Queue(maxsize=64)
        self._rfd, self._wfd = os.pipe()
        os.set_blocking(self._rfd, False)
        self._seq = -1
        self._running = False
        self._gone = False
        self._stop = threading.Event()
        self._worker: threading.Thread | None = None
        self._free_run: threading.Thread | None = None
        self._pending = 0
        self._plock = threading.Lock()
        # faults and truth
        self.drop_probability = 0.0
        self.late_probability = 0.0
        self.late_ms = 30.0
        self.disappear_after_frames: int | None = None
        self.frames_exposed = 0
        self.frames_dropped = 0
        self.frames_delayed = 0
        self.dropped_sequences: deque[int] = deque(maxlen=100_000)  # truth of the gaps
        # ground truth of the most recent frames: sequence -> (pulse index, pulse host ns)
        self.truth: dict[int, tuple[int, float]] = {}
        self.truth_capacity = 100_000

    # -- Camera protocol ------------------------------------------------------------------
    @property
    def camera_id(self) -> str:
        return self.model.name

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply what the simulated sensor supports; returns the settings read back."""
        self._check_alive()
        cur = self._settings
        w, h = self.model.size  # fixed-size sensor: a size request is not honoured
        fmt = cur.pixel_format
        if settings.pixel_format in _FORMATS.values():
            fmt = settings.pixel_format
            self.bit_depth = {v: k for k, v in _FORMATS.items()}[fmt]
        self._settings = CameraSettings(
            width=w, height=h, pixel_format=fmt,
            rate_hz=cur.rate_hz if settings.rate_hz is None else float(settings.rate_hz),
            exposure_us=cur.exposure_us if settings.exposure_us is None
            else self._quant_exposure(settings.exposure_us),
            gain=cur.gain if settings.gain is None else self._quant_gain(settings.gain),
            trigger=TriggerMode.EXTERNAL if self.sync is not None else TriggerMode.FREE_RUN)
        return self._settings

    @property
    def settings(self) -> CameraSettings:
        return self._settings

    def start(self) -> None:
        self._check_alive()
        if self._running:
            return
        self._running = True
        self._stop.clear()
        self._worker = threading.Thread(target=self._work, name=f"simcam {self.camera_id}",
                                        daemon=True)
        self._worker.start()
        if self.sync is not None:
            self.sync.add_trigger_listener(self._on_trigger)
        else:
            self._free_run = threading.Thread(target=self._free_run_loop, daemon=True,
                                              name=f"simcam-clock {self.camera_id}")
            self._free_run.start()

    def stop(self) -> None:
        self._running = False
        if self.sync is not None:
            self.sync.remove_trigger_listener(self._on_trigger)
        self._stop.set()
        for t in (self._worker, self._free_run):
            if t is not None and t is not threading.current_thread():
                t.join(timeout=1.0)
        self._worker = self._free_run = None

    def read(self, timeout: float) -> Frame | None:
        try:
            f = self._out.get(timeout=max(0.0, timeout)) if timeout > 0 else \
                self._out.get_nowait()
        except queue.Empty:
            self._check_alive()
            return None
        with self._plock:
            self._pending -= 1
        try:
            os.read(self._rfd, 1)
        except (BlockingIOError, OSError):
            pass
        return f

    def fileno(self) -> int:
        return self._rfd

    def close(self) -> None:
        self.stop()
        for fd in (self._rfd, self._wfd):
            try:
                os.close(fd)
            except OSError:
                pass

    # -- faults -----------------------------------------------------------------------------
    def disappear(self) -> None:
        """Unplug: no more frames; ``read`` raises ``CameraDisconnected`` once drained."""
        self._gone = True
        self._running = False
        if self.sync is not None:
            self.sync.remove_trigger_listener(self._on_trigger)
        self._stop.set()

    # -- internals ------------------------------------------------------------------------
    @staticmethod
    def _quant_exposure(us: float) -> float:
        return max(_EXPOSURE_STEP_US, round(float(us) / _EXPOSURE_STEP_US) * _EXPOSURE_STEP_US)

    @staticmethod
    def _quant_gain(g: float) -> float:
        g = min(max(float(g), _GAIN_RANGE[0]), _GAIN_RANGE[1])
        return round(g / _GAIN_STEP) * _GAIN_STEP

    def _dropped(self, seq: int) -> None:
        self.frames_dropped += 1
        self.dropped_sequences.append(seq)

    def _check_alive(self):
        if self._gone:
            raise CameraDisconnected(self.device, "camera disappeared (simulated unplug)")

    def _on_trigger(self, ev) -> None:
        try:
            self._triggers.put_nowait((ev.index, ev.host_ns))
        except queue.Full:
            self._seq += 1  # sensor exposed, driver had nowhere to put it
            self._dropped(self._seq)

    def _free_run_loop(self) -> None:
        period = 1e9 / self._settings.rate_hz
        t0 = time.monotonic_ns() + 1_000_000
        k = 0
        while not self._stop.is_set():
            due = t0 + k * period
            dt = (due - time.monotonic_ns()) * 1e-9
            if dt > 0 and self._stop.wait(dt):
                return
            try:
                self._triggers.put_nowait((k, float(due)))
            except queue.Full:
                self._seq += 1
                self._dropped(self._seq)
            k += 1

    def _work(self) -> None:
        while not self._stop.is_set():
            try:
                index, pulse_ns = self._triggers.get(timeout=0.05)
            except queue.Empty:
                continue
            self._seq += 1
            seq = self._seq
            self.frames_exposed += 1
            if self.disappear_after_frames is not None and \
                    self.frames_exposed > self.disappear_after_frames:
                self.disappear()
                return
            s = self._settings
            t_s = (pulse_ns - self.time_origin_ns) * 1e-9
            pts, diam = self.scene(t_s)
            img, _ = render_frame(self.model, pts, diam, self.rng, bit_depth=self.bit_depth,
                                  **self.render_options)
            ts = pulse_ns + self.rng.normal(0.0, self.timestamp_jitter_ns)
            if self.timestamp_source == TimestampSource.KERNEL_END_OF_FRAME:
                ts += s.exposure_us * 1e3 + self.model.size[1] * _READOUT_NS_PER_ROW
            frame = Frame(image=img, camera_id=self.camera_id, sequence=seq,
                          timestamp_ns=int(round(ts)), timestamp_source=self.timestamp_source,
                          exposure_us=s.exposure_us, gain=s.gain)
            self.truth[seq] = (index, pulse_ns)
            if len(self.truth) > self.truth_capacity:
                del self.truth[next(iter(self.truth))]
            if self.drop_probability and self.rng.random() < self.drop_probability:
                self._dropped(seq)
                continue
            due = pulse_ns + self.latency_ns
            if self.late_probability and self.rng.random() < self.late_probability:
                due += self.late_ms * 1e6
                self.frames_delayed += 1
            wait = (due - time.monotonic_ns()) * 1e-9
            if wait > 0 and self._stop.wait(wait):
                return
            with self._plock:
                if self._pending >= self._n_buffers:
                    self._dropped(seq)  # all buffers full: the driver drops
                    continue
                self._pending += 1
            self._out.put(frame)
            try:
                os.write(self._wfd, b"\x01")
            except OSError:
                pass


def sim_rig(n_cameras: int | None = None, *, rig=None, size=(320, 256),
            scene: Scene | None = None, drift_ppm: float = 50.0, rng=None):
    """A simulated sync box and SimCameras wired to its trigger line.

    Cameras come from ``rig`` (a ``calibration.camera.Rig``) or from
    ``hw_sim.rig.make_rig(n_cameras, size=size)``; ``scene`` is ``t_s -> (points, diameters)``
    (e.g. ``MarkerScene.at_time``; default: markers circling the volume centre).
    Returns ``(box, cameras, rig)``; the caller opens ``box.port`` with the host driver and
    closes everything. Cameras share one scene clock (origin: now).
    """
    from hw_sim.syncbox import SimSyncBox

    rng = np.random.default_rng(rng)
    if rig is None:
        if n_cameras is None or n_cameras < 1:
            raise ValueError(f"n_cameras={n_cameras}, expected >= 1 (or give a rig)")
        from hw_sim.rig import make_rig
        rig = make_rig(n_cameras, size=tuple(size), rng=rng)
    if scene is None:
        scene = orbiting_markers(8, height_m=1.25)
    box = SimSyncBox(drift_ppm=drift_ppm, rng=rng)
    origin = time.monotonic_ns()
    cams = [SimCamera(m, scene=scene, sync=box, time_origin_ns=origin, rng=rng)
            for m in rig.cameras]
    return box, cams, rig
