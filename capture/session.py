"""Live capture session: N cameras + a sync box -> frame sets matched to pulses.

Threads: one reader per camera (``camera.read`` -> a bounded per-camera queue; when the
queue is full the reader blocks, the driver's buffers fill and the driver drops frames,
which shows as sequence gaps: back-pressure), and one matcher. The matcher maps each
pulse to host time through the sync box's clock fit, and assigns each frame to the nearest
pulse within half a period (frame time minus the camera's timestamp offset). A frame set
is emitted when every live camera has delivered, or ``max_wait_s`` after its pulse; a frame
arriving after its set left counts as late; a frame with no pulse within half a period
counts as unmatched (once a later pulse has arrived: pulses come in order, so a frame whose
pulse is only delayed - a stalled serial line or reader on a loaded host - waits for it, up
to ``max_wait_cap_s``). Without a sync box, pulses are a virtual train at ``rate_hz``.

Faults: a camera that disappears is reported and the session goes on with the others; a
sync box fault (disconnected, garbage) stops the session and is re-raised by ``run``/``stop``
after the frame-set consumer has been closed by the caller's ``with`` block.
Conventions: docs/conventions.md [time], [camera-order], [errors].
"""
from __future__ import annotations

import bisect
import queue
import statistics
import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from .camera import Camera
from .errors import CameraDisconnected, CaptureError
from .frame import Frame, TimestampSource
from .syncbox import SyncBox, SyncBoxStats

__all__ = ["FrameSet", "CameraStats", "SessionStats", "CaptureSession"]


@dataclass(frozen=True, kw_only=True)
class FrameSet:
    """Frames of one pulse, one entry per camera in session order (None = missing)."""

    index: int
    pulse_index: int
    epoch: int
    host_ns: float
    camera_ids: tuple[str, ...]
    frames: tuple[Frame | None, ...]

    def __post_init__(self):
        if len(self.frames) != len(self.camera_ids):
            raise ValueError(f"{len(self.frames)} frames for {len(self.camera_ids)} cameras")

    @property
    def complete(self) -> bool:
        return all(f is not None for f in self.frames)


@dataclass(frozen=True, kw_only=True)
class CameraStats:
    camera_id: str
    frames: int
    fps: float
    drops: int            # from driver sequence gaps
    late: int             # arrived after their frame set was emitted
    unmatched: int        # no pulse within half a period
    missing: int          # frame sets emitted without this camera
    latency_ms: float     # median pulse (exposure) -> frame set emitted
    connected: bool
    error: str | None


@dataclass(frozen=True, kw_only=True)
class SessionStats:
    elapsed_s: float
    frame_sets: int
    complete_sets: int
    cameras: tuple[CameraStats, ...]
    sync: SyncBoxStats | None

    def status_line(self) -> str:
        parts = [f"{self.elapsed_s:6.1f}s sets {self.frame_sets} ({self.complete_sets} full)"]
        for c in self.cameras:
            if not c.connected:
                parts.append(f"{c.camera_id} LOST")
                continue
            parts.append(f"{c.camera_id} {c.fps:5.1f}fps drop {c.drops} late {c.late} "
                         f"nopulse {c.unmatched} {c.latency_ms:4.1f}ms")
        if self.sync is not None:
            fit = self.sync.fit
            b = f"±{fit.bound_ns / 1e6:.2f}ms" if fit.ok else "unfitted"
            parts.append(f"sync {self.sync.pulses} bad {self.sync.bad_frames} "
                         f"resets {self.sync.resets} clock {b}")
        return " | ".join(parts)


class _Cam:
    def __init__(self, cam: Camera, qsize: int, offset_ns: float | None):
        self.cam = cam
        self.id = cam.camera_id
        self.q: queue.Queue[Frame] = queue.Queue(maxsize=qsize)
        self.connected = True
        self.error: str | None = None
        self.frames = self.drops = self.late = self.unmatched = self.missing = 0
        self.last_seq: int | None = None
        self.last_t = float("-inf")   # frame time of the latest frame placed in a set
        self.arrivals: deque[int] = deque(maxlen=512)
        self.latency: deque[float] = deque(maxlen=256)
        self.offset_ns = offset_ns
        self.offset_samples: list[float] = []
        self.held: list[Frame] = []   # frames waiting for their pulse to arrive
        self.thread: threading.Thread | None = None


class _Slot:
    __slots__ = ("key", "host_ns", "frames", "emitted")

    def __init__(self, key, host_ns, n):
        self.key, self.host_ns, self.frames, self.emitted = key, host_ns, [None] * n, False


def _default_offset(frame: Frame) -> float | None:
    if frame.timestamp_source in (TimestampSource.KERNEL_START_OF_EXPOSURE,
                                  TimestampSource.SYNC_PULSE):
        return 0.0
    return None  # end of frame / dequeue: learnt from the first frames


class CaptureSession:
    """Run cameras (and a sync box) and produce ``FrameSet`` s.

    Args:
        cameras: configured cameras, in rig order ([camera-order]).
        sync: host sync box driver (configured; the session starts and stops it) or None.
        rate_hz: pulse rate; taken from ``sync.config`` when a box is given.
        queue_size: per-camera queue length (frames) before back-pressure.
        max_wait_s: how long after its pulse a frame set waits for missing cameras (at
            least; with ``adaptive_wait`` the wait grows to 1.5x the slowest recent frame
            arrival, up to ``max_wait_cap_s``, so an overloaded host delays sets instead of
            losing frames as late).
        offsets_ns: per camera id, frame timestamp minus pulse time; learnt when absent for
            end-of-frame / dequeue timestamps (assumes it is below one period).
        on_frame_set: called from the matcher thread with each set (e.g. a recorder);
            when None, sets go to a bounded queue read with ``get``.
        on_status: called with a one-line status every ``status_interval_s``.
    """

    def __init__(self, cameras: Sequence[Camera], sync: SyncBox | None = None, *,
                 rate_hz: float | None = None, queue_size: int = 8,
                 max_wait_s: float | None = None, adaptive_wait: bool = True,
                 max_wait_cap_s: float = 2.0, offsets_ns: dict | None = None,
                 on_frame_set: Callable[[FrameSet], None] | None = None,
                 on_status: Callable[[str], None] | None = None,
                 status_interval_s: float = 0.5):
        if not cameras:
            raise ValueError("cameras is empty")
        ids = [c.camera_id for c in cameras]
        if len(set(ids)) != len(ids):
            raise ValueError(f"camera ids are not unique: {ids}")
        if sync is not None and sync.config is not None:
            rate_hz = sync.config.rate_hz
        if rate_hz is None or not rate_hz > 0:
            raise ValueError(f"rate_hz={rate_hz}: give a rate or a configured sync box")
        self.sync = sync
        self.rate_hz = float(rate_hz)
        self.period_ns = 1e9 / self.rate_hz
        self.max_wait_ns = (max_wait_s if max_wait_s is not None
                            else 3.0 / self.rate_hz + 0.1) * 1e9
        self.adaptive_wait = bool(adaptive_wait)
        self.max_wait_cap_ns = max(max_wait_cap_s * 1e9, self.max_wait_ns)
        self._arrival_lag: deque[float] = deque(maxlen=256)  # frame arrival - pulse time
        offsets_ns = offsets_ns or {}
        self._cams = [_Cam(c, queue_size, offsets_ns.get(c.camera_id)) for c in cameras]
        self.camera_ids = tuple(ids)
        self.on_frame_set = on_frame_set
        self.on_status = on_status
        self.status_interval_s = status_interval_s
        self._out: queue.Queue[FrameSet | None] = queue.Queue(maxsize=64)
        self._stop = threading.Event()
        self._slots: dict = {}
        self._order: list = []          # slot keys sorted by host time, not yet emitted
        self._order_t: list[float] = []  # their host times (same order, for bisect)
        self._recent: deque = deque(maxlen=4096)  # (host ns, key) of emitted slots, in order
        self._emitted_keys: deque = deque(maxlen=4096)
        self._emitted_set: set = set()
        self._n_sets = self._n_complete = 0
        self._t_start = 0
        self._virtual_t0: float | None = None
        self._last_pulse_ns = -np.inf   # host time of the latest pulse received
        self._matcher: threading.Thread | None = None
        self.error: CaptureError | None = None
        self._draining = False
        self._lock = threading.Lock()

    # -- lifecycle ------------------------------------------------------------------------
    def start(self) -> None:
        self._t_start = time.monotonic_ns()
        for c in self._cams:
            c.cam.start()
            c.thread = threading.Thread(target=self._read_loop, args=(c,), daemon=True,
                                        name=f"session-cam {c.id}")
            c.thread.start()
        if self.sync is not None:
            self.sync.start()
        self._matcher = threading.Thread(target=self._match_loop, daemon=True,
                                         name="session-match")
        self._matcher.start()

    def stop(self) -> SessionStats:
        """Stop the pulses, let frames in flight complete their sets, then stop everything;
        re-raises a fatal sync fault. While draining, a set waits (up to ``max_wait_cap_s``)
        until each live camera has either delivered its frame or a later one (then it
        dropped it): an overloaded host does not lose the frames of the last pulses."""
        if not self._stop.is_set():
            if self.sync is not None:
                # drain from the moment STOP is sent: the box's reply can take a while on a
                # loaded host, and sets completing meanwhile must not time out at the normal
                # wait and drop frames that are still on their way
                self._draining = True
                try:
                    self.sync.stop()
                except CaptureError:
                    pass
            else:
                for c in self._cams:
                    try:
                        c.cam.stop()
                    except CaptureError:
                        pass
            # with a box, cameras still deliver the frames of the last pulses: drain them;
            # free-running cameras were stopped above: only what is queued remains
            self._draining = self.sync is not None
            deadline = time.monotonic_ns() + 20e6 + (
                self.max_wait_cap_ns if self._draining else self._current_wait_ns())
            while (time.monotonic_ns() < deadline and not self._stop.is_set()
                   and (self._order or any(c.held or not c.q.empty() for c in self._cams))):
                time.sleep(0.005)
        self._stop.set()
        if self._matcher is not None:
            self._matcher.join(timeout=5.0)
        for c in self._cams:
            try:
                c.cam.stop()
            except CaptureError:
                pass
            if c.thread is not None:
                c.thread.join(timeout=2.0)
        stats = self.stats()
        if self.error is not None:
            raise self.error
        return stats

    def run(self, duration_s: float) -> SessionStats:
        """Start, run for ``duration_s`` (or until a fatal fault), stop; returns stats."""
        self.start()
        t_end = time.monotonic() + duration_s
        try:
            while time.monotonic() < t_end and not self._stop.is_set():
                time.sleep(0.01)
        except KeyboardInterrupt:    # Ctrl-C: stop the devices and threads, then re-raise
            try:
                self.stop()
            except CaptureError:
                pass
            raise
        return self.stop()

    def __enter__(self):
        self.start()
        return self

    def __exit__(self, *exc):
        try:
            self.stop()
        except CaptureError:
            if exc[0] is None:
                raise

    def get(self, timeout: float) -> FrameSet | None:
        """Next frame set (when no ``on_frame_set`` consumer was given)."""
        try:
            return self._out.get(timeout=timeout)
        except queue.Empty:
            return None

    @property
    def stopped(self) -> bool:
        return self._stop.is_set()

    def stats(self) -> SessionStats:
        now = time.monotonic_ns()
        cams = []
        for c in self._cams:
            arr = [a for a in list(c.arrivals) if now - a <= 1e9]
            fps = len(arr) / min(1.0, max(1e-9, (now - self._t_start) * 1e-9)) if arr else 0.0
            lat = statistics.median(c.latency) / 1e6 if c.latency else float("nan")
            cams.append(CameraStats(camera_id=c.id, frames=c.frames, fps=fps, drops=c.drops,
                                    late=c.late, unmatched=c.unmatched, missing=c.missing,
                                    latency_ms=lat, connected=c.connected, error=c.error))
        return SessionStats(elapsed_s=(now - self._t_start) * 1e-9, frame_sets=self._n_sets,
                            complete_sets=self._n_complete, cameras=tuple(cams),
                            sync=None if self.sync is None else self.sync.stats())

    # -- threads ----------------------------------------------------------------------------
    def _read_loop(self, c: _Cam) -> None:
        while not self._stop.is_set():
            try:
                f = c.cam.read(0.1)
            except CameraDisconnected as e:
                c.connected, c.error = False, str(e)
                return
            except CaptureError as e:
                c.connected, c.error = False, str(e)
                return
            if f is None:
                continue
            while not self._stop.is_set():
                try:
                    c.q.put(f, timeout=0.1)  # blocks when full: back-pressure
                    break
                except queue.Full:
                    continue

    def _fail(self, err: CaptureError) -> None:
        if self.error is None:
            self.error = err
        self._stop.set()

    def _match_loop(self) -> None:
        last_status = time.monotonic()
        try:
            while True:
                stopping = self._stop.is_set()
                busy = self._pull_pulses()
                for i, c in enumerate(self._cams):
                    while True:
                        try:
                            f = c.q.get_nowait()
                        except queue.Empty:
                            break
                        busy = True
                        self._on_frame(i, c, f)
                    self._retry_held(i, c)
                self._emit_ready(flush=stopping)
                if self.on_status and time.monotonic() - last_status >= self.status_interval_s:
                    last_status = time.monotonic()
                    self.on_status(self.stats().status_line())
                if stopping:
                    break
                if not busy:
                    time.sleep(0.002)
        except CaptureError as e:
            self._fail(e)
            try:
                self._emit_ready(flush=True)   # hand over what was matched before the fault
            except CaptureError:
                pass                           # the consumer itself failed (e.g. disk full)
        finally:
            if self.on_frame_set is None:
                try:
                    self._out.put(None, timeout=0.5)
                except queue.Full:
                    pass

    # -- matching ----------------------------------------------------------------------------
    def _pull_pulses(self) -> bool:
        if self.sync is None:
            return False
        got = False
        while True:
            p = self.sync.get_pulse(0)  # raises the box's fault (disconnected, garbage)
            if p is None:
                return got
            got = True
            host = self.sync.host_time(p)
            if not np.isfinite(host):
                continue  # clock not fitted yet (first milliseconds): cannot place it
            self._add_slot((p.epoch, p.index), host)
            self._last_pulse_ns = max(self._last_pulse_ns, host)

    def _add_slot(self, key, host_ns) -> _Slot:
        s = self._slots.get(key)
        if s is None:
            s = _Slot(key, host_ns, len(self._cams))
            self._slots[key] = s
            j = bisect.bisect_right(self._order_t, host_ns)
            self._order.insert(j, key)
            self._order_t.insert(j, host_ns)
        return s

    def _frame_time(self, c: _Cam, f: Frame) -> float | None:
        if c.offset_ns is None:
            c.offset_ns = _default_offset(f)
        if c.offset_ns is None:
            return None
        return f.timestamp_ns - c.offset_ns

    def _on_frame(self, i: int, c: _Cam, f: Frame) -> None:
        c.frames += 1
        c.arrivals.append(time.monotonic_ns())
        if c.last_seq is not None and f.sequence > c.last_seq + 1:
            c.drops += f.sequence - c.last_seq - 1
        c.last_seq = f.sequence
        if not self._place(i, c, f):
            c.held.append(f)

    def _learn_offset(self, c: _Cam, f: Frame) -> bool:
        """For end-of-frame/dequeue stamps: offset = median(ts - latest pulse before ts)."""
        j = bisect.bisect_right(self._order_t, f.timestamp_ns)
        if j == 0:
            return False
        c.offset_samples.append(f.timestamp_ns - self._order_t[j - 1])
        if len(c.offset_samples) >= 8:
            c.offset_ns = float(np.median(c.offset_samples))
        return False

    def _place(self, i: int, c: _Cam, f: Frame) -> bool:
        """Assign ``f`` to its pulse; False when it must wait for pulses to arrive."""
        if self.sync is None and c.offset_ns is None and _default_offset(f) is None:
            c.offset_ns = 0.0  # virtual pulses: a common offset of like cameras cancels
        t = self._frame_time(c, f)
        if t is None:
            self._learn_offset(c, f)
            if c.offset_ns is None:
                return True  # still learning: the frame is used to learn, not placed
            t = f.timestamp_ns - c.offset_ns
        if self.sync is None:
            if self._virtual_t0 is None:
                self._virtual_t0 = t
            k = int(round((t - self._virtual_t0) / self.period_ns))
            key = (0, k)
            if key in self._emitted_set:
                c.late += 1
                return True
            slot = self._slots.get(key) or self._add_slot(key,
                                                          self._virtual_t0 + k * self.period_ns)
        else:
            slot = self._nearest(t)
            if slot is None:
                # Pulses arrive in order: once a later one is in, this frame's pulse was
                # lost. Until then it may only be late (the serial line or its reader
                # stalled: a loaded host), so the frame waits up to the cap for it.
                wait = (self.max_wait_cap_ns if self.adaptive_wait and not self._draining
                        else self.max_wait_ns)
                if (self._last_pulse_ns > t + self.period_ns / 2
                        or time.monotonic_ns() - t > wait):
                    c.unmatched += 1
                    return True
                return False
            self._arrival_lag.append(time.monotonic_ns() - slot.host_ns)
            if slot.emitted:
                c.late += 1
                return True
        if slot.frames[i] is not None:
            c.unmatched += 1  # a second frame for the same pulse
            return True
        slot.frames[i] = f
        c.last_t = max(c.last_t, t)
        return True

    def _nearest(self, t: float) -> _Slot | None:
        half = self.period_ns / 2
        j = bisect.bisect_left(self._order_t, t)
        best, best_d = None, half
        for k in (j - 1, j):
            if 0 <= k < len(self._order_t) and abs(self._order_t[k] - t) <= best_d:
                best, best_d = self._slots[self._order[k]], abs(self._order_t[k] - t)
        if best is None:  # its set may have left already: then the frame is late
            for host_ns, key in reversed(self._recent):
                if host_ns < t - half:
                    break
                if abs(host_ns - t) <= half and key in self._slots:
                    return self._slots[key]
        return best

    def _retry_held(self, i: int, c: _Cam) -> None:
        if c.held:
            c.held = [f for f in c.held if not self._place(i, c, f)]

    def _current_wait_ns(self) -> float:
        wait = self.max_wait_ns
        if self.adaptive_wait and self._arrival_lag:
            wait = min(max(wait, 1.5 * max(self._arrival_lag)), self.max_wait_cap_ns)
        return wait

    def _emit_ready(self, flush: bool = False) -> None:
        now = time.monotonic_ns()
        live = [j for j, c in enumerate(self._cams) if c.connected]
        draining = self._draining
        wait = self.max_wait_cap_ns if draining else self._current_wait_ns()
        half = self.period_ns / 2
        while self._order:
            s = self._slots[self._order[0]]
            complete = all(s.frames[j] is not None
                           or (draining and self._cams[j].last_t > s.host_ns + half)
                           for j in live)
            if not (complete or flush or now - s.host_ns > wait):
                break
            self._order.pop(0)
            self._order_t.pop(0)
            s.emitted = True
            self._recent.append((s.host_ns, s.key))
            self._emitted_keys.append(s.key)
            self._emitted_set.add(s.key)
            if len(self._emitted_keys) == self._emitted_keys.maxlen:
                old = self._emitted_keys[0]
                self._slots.pop(old, None)
                self._emitted_set.discard(old)
            if not any(f is not None for f in s.frames) and self.sync is not None:
                continue  # a pulse no camera saw (e.g. before cameras started): not a set
            self._emit(s, now)

    def _emit(self, s: _Slot, now: int) -> None:
        for j, c in enumerate(self._cams):
            if s.frames[j] is None:
                if c.connected:
                    c.missing += 1
            else:
                c.latency.append(now - s.host_ns)
        fs = FrameSet(index=self._n_sets, pulse_index=s.key[1], epoch=s.key[0],
                      host_ns=float(s.host_ns), camera_ids=self.camera_ids,
                      frames=tuple(s.frames))
        self._n_sets += 1
        self._n_complete += fs.complete
        s.frames = [None] * len(self._cams)  # emitted sets are not kept in memory
        if self.on_frame_set is not None:
            self.on_frame_set(fs)
        else:
            while True:
                try:
                    self._out.put(fs, timeout=0.1)
                    return
                except queue.Full:
                    if self._stop.is_set():
                        return
