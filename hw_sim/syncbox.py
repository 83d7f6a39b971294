"""A simulated sync box serving docs/sync-protocol.md on a pseudo-terminal.

The host driver (``capture.syncbox.SyncBox``) opens ``SimSyncBox.port`` (``/dev/pts/N``)
with pyserial exactly as it would open ``/dev/ttyACM0``. The box has its own clock: its
counter runs ``drift_ppm`` fast against the host monotonic clock, with Gaussian phase
jitter; replies leave after a random latency. Pulses are emitted at the configured rate and
also delivered, with their true host time, to "trigger line" listeners (the simulated
cameras). Faults on demand: garbage bytes, split (partial) frames, a reset with boot
banner, lost PULSE messages, and disappearing (the pty closes).

Ground truth: ``true_host_ns(ticks)`` maps device ticks back to host time exactly.
Conventions: docs/conventions.md [time].
"""
from __future__ import annotations

import errno
import os
import select
import threading
import time
import tty
from collections import deque
from typing import Callable

import numpy as np

from capture.sync_protocol import (PROTOCOL_VERSION, DecodeError, FrameSplitter, Message,
                                   MsgType, NakCode, checked_body, decode_frame,
                                   encode_message)

__all__ = ["SimSyncBox", "TriggerEvent"]

TriggerListener = Callable[["TriggerEvent"], None]


class TriggerEvent:
    """A pulse on the simulated trigger line: what a camera's FSIN pin would see."""

    __slots__ = ("index", "device_ticks", "host_ns", "strobe_delay_us", "strobe_width_us")

    def __init__(self, index, device_ticks, host_ns, strobe_delay_us, strobe_width_us):
        self.index = index
        self.device_ticks = device_ticks
        self.host_ns = host_ns
        self.strobe_delay_us = strobe_delay_us
        self.strobe_width_us = strobe_width_us


class SimSyncBox:
    """Simulated sync box on a pty. Use as a context manager or call ``close()``.

    Args:
        drift_ppm: device oscillator error (counter runs this much fast vs host).
        jitter_us: standard deviation of the counter phase noise.
        reply_latency_us: mean of the exponential extra latency before each reply.
        tick_hz: nominal counter rate.
        rng: Generator or seed.
    """

    def __init__(self, *, drift_ppm: float = 50.0, jitter_us: float = 2.0,
                 reply_latency_us: float = 200.0, tick_hz: int = 1_000_000,
                 name: str = "hw_sim syncbox", rng=None):
        self.rng = np.random.default_rng(rng)
        self.drift_ppm = float(drift_ppm)
        self.jitter_us = float(jitter_us)
        self.reply_latency_us = float(reply_latency_us)
        self.tick_hz = int(tick_hz)
        self.name = name
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self._master, False)
        self.port = os.ttyname(self._slave)
        self._lock = threading.Lock()
        self._listeners: list[TriggerListener] = []
        self._stop = threading.Event()
        self._gone = False
        self._boot_host_ns = time.monotonic_ns() - int(self.rng.integers(1, 10**9))
        self._rate_mhz: int | None = None
        self._width_us = 500
        self._delay_us = 0
        self._running = False
        self._next_index = 0
        self._t0_ticks = 0
        self._period_ticks = 0.0
        self.pulse_loss = 0.0          # probability a PULSE message is not sent
        self._hold_until = 0           # host ns: every outgoing message held back until then
        self.split_writes = False      # deliver frames in random small pieces
        self.pulses_emitted = 0
        self.dropped_bytes = 0
        self.commands: deque[MsgType] = deque(maxlen=1000)  # most recent commands heard
        self._outq: list[tuple[int, bytes]] = []  # (due host ns, bytes)
        self._thread = threading.Thread(target=self._loop, name="sim-syncbox", daemon=True)
        self._send_now(encode_message(Message.make(MsgType.BOOT, reason=0,
                                                   major=PROTOCOL_VERSION[0],
                                                   minor=PROTOCOL_VERSION[1],
                                                   tick_hz=self.tick_hz)))
        self._thread.start()

    # -- the device clock (ground truth) ---------------------------------------------
    @property
    def _scale(self) -> float:
        return (1.0 + self.drift_ppm * 1e-6) * self.tick_hz / 1e9

    def device_ticks(self, host_ns: int | None = None, *, jitter: bool = True) -> int:
        """Counter value at a host time (now by default)."""
        h = time.monotonic_ns() if host_ns is None else host_ns
        t = (h - self._boot_host_ns) * self._scale
        if jitter and self.jitter_us > 0:
            t += self.rng.normal(0.0, self.jitter_us * 1e-6 * self.tick_hz)
        return max(0, int(np.floor(t)))

    def true_host_ns(self, ticks) -> np.ndarray | float:
        """Exact host time at which the counter had value ``ticks``."""
        return self._boot_host_ns + np.asarray(ticks, dtype=np.float64) / self._scale

    # -- trigger line -------------------------------------------------------------------
    def add_trigger_listener(self, callback: TriggerListener) -> None:
        self._listeners.append(callback)

    def remove_trigger_listener(self, callback: TriggerListener) -> None:
        if callback in self._listeners:
            self._listeners.remove(callback)

    @property
    def running(self) -> bool:
        return self._running

    @property
    def rate_hz(self) -> float | None:
        return None if self._rate_mhz is None else self._rate_mhz / 1000.0

    # -- faults ---------------------------------------------------------------------------
    def inject_garbage(self, n_bytes: int = 64, *, with_zeros: bool = True) -> None:
        """Write random bytes (with or without 0x00 delimiters inside)."""
        g = self.rng.integers(0 if with_zeros else 1, 256, size=n_bytes, dtype=np.uint8)
        self._send_now(g.tobytes())

    def reset(self, *, silence_s: float = 0.05, reason: int = 1) -> None:
        """Reboot: stop, forget configuration, counter restarts at 0, BOOT after a silence."""
        with self._lock:
            self._running = False
            self._rate_mhz = None
            self._width_us, self._delay_us = 500, 0
            self._outq.clear()
            self._boot_host_ns = time.monotonic_ns() + int(silence_s * 1e9)
            boot = encode_message(Message.make(MsgType.BOOT, reason=reason,
                                               major=PROTOCOL_VERSION[0],
                                               minor=PROTOCOL_VERSION[1],
                                               tick_hz=self.tick_hz))
            self._outq.append((self._boot_host_ns, boot))

    def stall(self, seconds: float) -> None:
        """The serial line stalls for ``seconds`` (a USB-serial bridge stalling, or a host too
        loaded to read): every message of that time - pulses, replies - leaves in order, in
        one burst, at its end, while the trigger line, and so the cameras, keep running."""
        if not seconds >= 0:
            raise ValueError(f"seconds={seconds!r}, expected >= 0")
        with self._lock:
            self._hold_until = time.monotonic_ns() + int(seconds * 1e9)

    def disappear(self) -> None:
        """The box is unplugged: the pty closes under the host."""
        self._gone = True
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._close_fds()

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and threading.current_thread() is not self._thread:
            self._thread.join(timeout=1.0)
        self._close_fds()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- internals ------------------------------------------------------------------------
    def _close_fds(self):
        for fd in ("_master", "_slave"):
            v = getattr(self, fd)
            if v is not None:
                try:
                    os.close(v)
                except OSError:
                    pass
                setattr(self, fd, None)

    def _send_now(self, data: bytes) -> None:
        if self._master is None:
            return
        if self.split_writes and len(data) > 1:
            cuts = sorted(set(self.rng.integers(1, len(data), size=min(3, len(data) - 1))))
            pieces = [data[a:b] for a, b in zip([0] + cuts, cuts + [len(data)])]
        else:
            pieces = [data]
        for p in pieces:
            try:
                os.write(self._master, p)
            except BlockingIOError:
                self.dropped_bytes += len(p)  # host not reading: a CDC device drops too
            except OSError as e:
                if e.errno not in (errno.EIO, errno.EBADF):
                    raise
            if self.split_writes:
                time.sleep(0.0005)

    def _queue_reply(self, msg: Message) -> None:
        lat = self.rng.exponential(self.reply_latency_us) if self.reply_latency_us > 0 else 0
        self._outq.append((time.monotonic_ns() + int(lat * 1e3), encode_message(msg)))

    def _handle(self, frame: bytes) -> None:
        try:
            msg = decode_frame(frame)
        except DecodeError:
            self._nak_malformed(frame)
            return
        t, seq = msg.type, msg.fields.get("seq", 0)
        self.commands.append(t)

        def ack():
            self._queue_reply(Message.make(MsgType.ACK, seq=seq, cmd=int(t)))

        def nak(code):
            self._queue_reply(Message.make(MsgType.NAK, seq=seq, cmd=int(t), code=int(code)))

        if t == MsgType.TIME_QUERY:
            self._queue_reply(Message.make(MsgType.TIME_REPLY, seq=seq,
                                           ticks=self.device_ticks()))
        elif t == MsgType.GET_VERSION:
            self._queue_reply(Message.make(MsgType.VERSION, seq=seq, major=PROTOCOL_VERSION[0],
                                           minor=PROTOCOL_VERSION[1], tick_hz=self.tick_hz,
                                           name=self.name))
        elif t == MsgType.SET_RATE:
            if self._running:
                nak(NakCode.BUSY)
            elif not 1000 <= msg.rate_mhz <= 1_000_000:
                nak(NakCode.OUT_OF_RANGE)
            else:
                self._rate_mhz = msg.rate_mhz
                ack()
        elif t == MsgType.SET_EXPOSURE:
            period_us = 1e9 / self._rate_mhz if self._rate_mhz else float("inf")
            if self._running:
                nak(NakCode.BUSY)
            elif not (1 <= msg.width_us <= 100_000) or msg.width_us + msg.delay_us >= period_us:
                nak(NakCode.OUT_OF_RANGE)
            else:
                self._width_us, self._delay_us = msg.width_us, msg.delay_us
                ack()
        elif t == MsgType.START:
            if self._rate_mhz is None:
                nak(NakCode.NOT_CONFIGURED)
            elif self._running:
                nak(NakCode.BUSY)
            elif self._width_us + self._delay_us >= 1e9 / self._rate_mhz:
                nak(NakCode.OUT_OF_RANGE)  # strobe set for a slower rate does not fit
            else:
                self._period_ticks = self.tick_hz * 1000.0 / self._rate_mhz
                self._t0_ticks = self.device_ticks(jitter=False) + int(0.002 * self.tick_hz)
                self._next_index = 0
                self._running = True
                ack()
        elif t == MsgType.STOP:
            self._running = False
            ack()
        else:
            nak(NakCode.UNKNOWN_TYPE)

    def _nak_malformed(self, frame: bytes) -> None:
        """Spec 2: a frame with a good CRC but an unknown type or a wrong body length is
        answered with NAK (seq from bytes 1..2 when present); other bad frames are dropped."""
        try:
            body = checked_body(frame)
        except DecodeError:
            return
        seq = int.from_bytes(body[1:3], "little") if len(body) >= 3 else 0
        try:
            MsgType(body[0])
            code = NakCode.BAD_LENGTH
        except ValueError:
            code = NakCode.UNKNOWN_TYPE
        self._queue_reply(Message.make(MsgType.NAK, seq=seq, cmd=body[0], code=int(code)))

    def _emit_pulse(self, index: int, ticks: int) -> None:
        host = float(self.true_host_ns(ticks))
        ev = TriggerEvent(index, ticks, host, self._delay_us, self._width_us)
        for cb in list(self._listeners):
            cb(ev)
        self.pulses_emitted += 1
        if self.pulse_loss > 0 and self.rng.random() < self.pulse_loss:
            return
        msg = encode_message(Message.make(MsgType.PULSE, index=index, ticks=ticks))
        now = time.monotonic_ns()
        if now < self._hold_until or any(q[0] <= now for q in self._outq):
            self._outq.append((now, msg))   # behind what a stall held back, in order
        else:
            self._send_now(msg)

    def _loop(self) -> None:
        splitter = FrameSplitter()
        while not self._stop.is_set():
            now = time.monotonic_ns()
            wake = now + 5_000_000
            with self._lock:
                if self._running:
                    ticks = self._t0_ticks + int(round(self._next_index * self._period_ticks))
                    due = int(np.ceil(self.true_host_ns(ticks)))
                    if due <= now:
                        self._emit_pulse(self._next_index, ticks)
                        self._next_index += 1
                        continue
                    wake = min(wake, due)
                ready = [q for q in self._outq if q[0] <= now] if now >= self._hold_until else []
                if ready:
                    self._outq = [q for q in self._outq if q[0] > now]
                    for _, data in sorted(ready, key=lambda q: q[0]):
                        self._send_now(data)
                if self._outq:
                    wake = min(wake, max(self._hold_until, min(q[0] for q in self._outq)))
            timeout = max(0.0, (wake - time.monotonic_ns()) * 1e-9)
            try:
                r, _, _ = select.select([self._master], [], [], timeout)
            except (OSError, ValueError, TypeError):
                return
            if r:
                try:
                    data = os.read(self._master, 4096)
                except BlockingIOError:
                    continue
                except OSError:
                    data = b""
                if not data:
                    time.sleep(0.001)  # host side closed; keep serving (it may reopen)
                    continue
                with self._lock:
                    frames = splitter.feed(data)
                    if time.monotonic_ns() < self._boot_host_ns:
                        continue  # rebooting: the MCU hears nothing
                    for fr in frames:
                        self._handle(fr)
