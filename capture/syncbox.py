"""Host driver of the strobe/trigger sync box over a serial port (pyserial).

Protocol: docs/sync-protocol.md. A reader thread splits the byte stream into COBS frames,
answers waiting requests, timestamps pulses and feeds time-query samples to a
``ClockModel``; a maintenance thread keeps querying the device clock and re-applies the
configuration after a box reset. Faults surface as ``capture.errors.SyncBoxError``
subclasses naming the port: garbage and partial frames are survived (counted); sustained
garbage raises ``SyncProtocolError``; a vanished port raises ``SyncBoxDisconnected``.

Conventions: docs/conventions.md [time] (host ``time.monotonic_ns()``), [errors].
"""
from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass
from typing import Callable

import serial

from .clock_model import ClockFit, ClockModel, ClockSample
from .errors import (SyncBoxDisconnected, SyncBoxError, SyncBoxNak, SyncBoxTimeout,
                     SyncProtocolError)
from .sync_protocol import (DecodeError, FrameSplitter, Message, MsgType, NakCode,
                            decode_frame, encode_message)

__all__ = ["Pulse", "SyncConfig", "SyncBoxInfo", "SyncBoxStats", "SyncBox"]


@dataclass(frozen=True, kw_only=True)
class Pulse:
    """One trigger pulse: index since START within ``epoch`` (increments at each box
    reset), the device counter latched at the edge and the host time the clock fit gave
    when it arrived (NaN before the fit was usable; use ``SyncBox.host_time`` for the
    current fit)."""

    index: int
    device_ticks: int
    epoch: int
    host_ns: float
    arrival_ns: int


@dataclass(frozen=True, kw_only=True)
class SyncConfig:
    """Pulse rate and strobe timing ([units]: Hz, microseconds)."""

    rate_hz: float
    strobe_width_us: int = 500
    strobe_delay_us: int = 0

    def __post_init__(self):
        if not 1.0 <= self.rate_hz <= 1000.0:
            raise ValueError(f"rate_hz={self.rate_hz}, expected in [1, 1000]")
        if not 1 <= self.strobe_width_us <= 100_000:
            raise ValueError(f"strobe_width_us={self.strobe_width_us}, expected 1..100000")
        if self.strobe_delay_us < 0:
            raise ValueError(f"strobe_delay_us={self.strobe_delay_us}, expected >= 0")
        if (self.strobe_width_us + self.strobe_delay_us) * 1e-6 >= 1.0 / self.rate_hz:
            raise ValueError(f"strobe width + delay = "
                             f"{self.strobe_width_us + self.strobe_delay_us} us does not fit "
                             f"the {1e6 / self.rate_hz:.0f} us period")

    def to_dict(self) -> dict:
        return {"rate_hz": self.rate_hz, "strobe_width_us": self.strobe_width_us,
                "strobe_delay_us": self.strobe_delay_us}


@dataclass(frozen=True, kw_only=True)
class SyncBoxInfo:
    name: str
    protocol: tuple[int, int]
    tick_hz: int


@dataclass(frozen=True, kw_only=True)
class SyncBoxStats:
    pulses: int
    pulses_missed: int
    bad_frames: int
    resets: int
    clock_samples: int
    fit: ClockFit


class SyncBox:
    """Sync box on ``port`` (e.g. ``/dev/ttyACM0`` or a pty from ``hw_sim.syncbox``).

    Args:
        port: serial device path.
        request_timeout_s: time to wait for each reply.
        query_interval_s: period of background TIME_QUERYs feeding the clock fit.
        garbage_timeout_s: bytes arriving without a valid frame for this long is fatal.
        serial_factory: ``callable(port) -> serial.Serial``-like object (tests).
    """

    def __init__(self, port: str, *, request_timeout_s: float = 0.5,
                 query_interval_s: float = 0.1, garbage_timeout_s: float = 2.0,
                 clock_window: int = 64, serial_factory: Callable | None = None):
        self.port = str(port)
        self.request_timeout_s = float(request_timeout_s)
        self.query_interval_s = float(query_interval_s)
        self.garbage_timeout_s = float(garbage_timeout_s)
        try:
            if serial_factory is None:
                self._ser = serial.Serial(self.port, 115200, timeout=0.02, write_timeout=1.0)
            else:
                self._ser = serial_factory(self.port)
        except (serial.SerialException, OSError) as e:
            raise SyncBoxDisconnected(self.port, f"cannot open serial port: {e}") from e
        self.clock = ClockModel(1e6, window=clock_window)
        self._lock = threading.Lock()
        self._wlock = threading.Lock()
        self._pending: dict[int, list] = {}
        self._seq = 0
        self._error: SyncBoxError | None = None
        self._closed = threading.Event()
        self._pulses: deque[Pulse] = deque(maxlen=100_000)
        self._pulse_cv = threading.Condition(self._lock)
        self._listeners: list[Callable[[Pulse], None]] = []
        self._config: SyncConfig | None = None
        self._running = False
        self._epoch = 0
        self._last_pulse_ticks = -1
        self._last_query_ticks = -1
        self._last_index: int | None = None
        self._need_reconfigure = threading.Event()
        self.n_pulses = 0
        self.pulses_missed = 0
        self.bad_frames = 0
        self.resets = 0
        self.info: SyncBoxInfo | None = None
        self._reader = threading.Thread(target=self._read_loop, name=f"syncbox-rx {port}",
                                        daemon=True)
        self._reader.start()
        try:
            self._write(b"\x00")
            self.info = self.version()
            self.clock.reset(self.info.tick_hz)
            self.sync_clock(16)
        except SyncBoxError:
            self.close()
            raise
        self._maint = threading.Thread(target=self._maintain_loop,
                                       name=f"syncbox-clock {port}", daemon=True)
        self._maint.start()

    # -- public API --------------------------------------------------------------------
    def version(self) -> SyncBoxInfo:
        r = self._request(MsgType.GET_VERSION, retries=2)
        return SyncBoxInfo(name=r.name, protocol=(r.major, r.minor), tick_hz=r.tick_hz)

    def configure(self, config: SyncConfig) -> SyncConfig:
        """Send rate and strobe timing (box must be stopped); returns the config applied."""
        self._request(MsgType.SET_RATE, rate_mhz=int(round(config.rate_hz * 1000)))
        self._request(MsgType.SET_EXPOSURE, width_us=int(config.strobe_width_us),
                      delay_us=int(config.strobe_delay_us))
        self._config = config
        return config

    @property
    def config(self) -> SyncConfig | None:
        return self._config

    def start(self) -> None:
        self._request(MsgType.START)
        with self._lock:
            self._last_index = None
        self._running = True

    def stop(self) -> None:
        self._running = False
        self._request(MsgType.STOP, retries=2)

    def time_query(self) -> ClockSample:
        """One TIME_QUERY round trip; the sample is also added to ``clock``."""
        box: list = []
        epoch = self._epoch
        r = self._request(MsgType.TIME_QUERY, retries=2, _box=box)
        sample = ClockSample(host_send_ns=box[0], device_ticks=r.ticks, host_recv_ns=box[1])
        with self._lock:
            if epoch == self._epoch:
                self.clock.add(sample)
        return sample

    def sync_clock(self, n: int = 16) -> ClockFit:
        for _ in range(n):
            self.time_query()
        return self.clock.fit

    def host_time(self, pulse: Pulse) -> float:
        """Host monotonic ns of a pulse through the current fit (NaN if stale epoch/no fit)."""
        fit = self.clock.fit
        if pulse.epoch != self._epoch or not fit.ok:
            return pulse.host_ns
        return float(fit.to_host_ns(pulse.device_ticks))

    def add_listener(self, callback: Callable[[Pulse], None]) -> None:
        """Call ``callback(pulse)`` from the reader thread for each pulse (keep it short)."""
        self._listeners.append(callback)

    def get_pulse(self, timeout: float) -> Pulse | None:
        """Next buffered pulse, or None after ``timeout`` s; raises the box's fault if any."""
        deadline = time.monotonic() + timeout
        with self._pulse_cv:
            while not self._pulses:
                self._raise_if_failed()
                rem = deadline - time.monotonic()
                if rem <= 0:
                    return None
                self._pulse_cv.wait(rem)
            return self._pulses.popleft()

    @property
    def epoch(self) -> int:
        return self._epoch

    @property
    def error(self) -> SyncBoxError | None:
        return self._error

    def stats(self) -> SyncBoxStats:
        return SyncBoxStats(pulses=self.n_pulses, pulses_missed=self.pulses_missed,
                            bad_frames=self.bad_frames, resets=self.resets,
                            clock_samples=self.clock.n_samples, fit=self.clock.fit)

    def close(self) -> None:
        if self._closed.is_set():
            return
        if self._error is None and self._running:
            try:
                self.stop()
            except SyncBoxError:
                pass
        self._closed.set()
        self._reader.join(timeout=1.0)
        try:
            self._ser.close()
        except Exception:  # noqa: BLE001 - closing a vanished port may fail any way
            pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- internals ---------------------------------------------------------------------
    def _raise_if_failed(self):
        if self._error is not None:
            raise self._error

    def _write(self, data: bytes) -> None:
        try:
            with self._wlock:
                self._ser.write(data)
                self._ser.flush()
        except (serial.SerialException, OSError) as e:
            self._fail(SyncBoxDisconnected(self.port, f"write failed: {e}"))
            raise self._error from e

    def _request(self, mtype: MsgType, *, retries: int = 0, _box: list | None = None,
                 **fields) -> Message:
        last: Exception | None = None
        for _ in range(retries + 1):
            self._raise_if_failed()
            if self._closed.is_set():
                raise SyncBoxError(self.port, "driver is closed")
            with self._lock:
                self._seq = (self._seq + 1) & 0xFFFF
                seq = self._seq
                slot = [threading.Event(), None, 0]
                self._pending[seq] = slot
            data = encode_message(Message.make(mtype, seq=seq, **fields))
            t_send = time.monotonic_ns()
            self._write(data)
            ok = slot[0].wait(self.request_timeout_s)
            with self._lock:
                self._pending.pop(seq, None)
            self._raise_if_failed()
            if not ok:
                last = SyncBoxTimeout(self.port, f"no reply to {mtype.name} (seq {seq}) "
                                                 f"within {self.request_timeout_s} s")
                continue
            reply: Message | None = slot[1]
            if reply is None:  # the box rebooted while we waited: ask again
                last = SyncBoxTimeout(self.port, f"box reset during {mtype.name}")
                continue
            if reply.type == MsgType.NAK:
                code = reply.code
                name = NakCode(code).name if code in NakCode._value2member_map_ else str(code)
                raise SyncBoxNak(self.port, f"{mtype.name} refused: {name}", code)
            if _box is not None:
                _box[:] = [t_send, slot[2]]
            return reply
        raise last  # type: ignore[misc]

    def _fail(self, err: SyncBoxError) -> None:
        with self._lock:
            if self._error is None:
                self._error = err
            for slot in self._pending.values():
                slot[0].set()
            self._pulse_cv.notify_all()

    def _on_reset(self, reason: str) -> None:
        self.resets += 1
        self._epoch += 1
        self._last_pulse_ticks = -1
        self._last_query_ticks = -1
        self._last_index = None
        self.clock.reset()
        self._need_reconfigure.set()
        for slot in self._pending.values():  # requests the rebooting box never heard
            slot[0].set()

    def _read_loop(self) -> None:
        splitter = FrameSplitter()
        last_valid = time.monotonic_ns()
        garbage_since_valid = 0
        while not self._closed.is_set():
            try:
                n = self._ser.in_waiting
                data = self._ser.read(n if n > 0 else 1)
            except (serial.SerialException, OSError, TypeError) as e:
                if not self._closed.is_set():
                    self._fail(SyncBoxDisconnected(self.port, f"serial port vanished: {e}"))
                return
            t_rx = time.monotonic_ns()
            if not data:
                continue
            overruns = splitter.overruns
            frames = splitter.feed(data)
            got_valid = False
            for fr in frames:
                try:
                    msg = decode_frame(fr)
                except DecodeError:
                    self.bad_frames += 1
                    continue
                got_valid = True
                self._dispatch(msg, t_rx)
            self.bad_frames += splitter.overruns - overruns
            if got_valid:
                last_valid, garbage_since_valid = t_rx, 0
            else:
                garbage_since_valid += len(data)
                if (t_rx - last_valid) * 1e-9 > self.garbage_timeout_s and garbage_since_valid:
                    self._fail(SyncProtocolError(
                        self.port, f"{garbage_since_valid} bytes and no valid frame for "
                                   f"{(t_rx - last_valid) * 1e-9:.1f} s (wrong device or "
                                   f"baud rate?)"))
                    return

    def _dispatch(self, msg: Message, t_rx: int) -> None:
        t = msg.type
        if t == MsgType.PULSE:
            with self._lock:
                if msg.ticks < self._last_pulse_ticks:
                    self._on_reset("pulse counter went back")
                self._last_pulse_ticks = msg.ticks
                if self._last_index is not None and msg.index > self._last_index + 1:
                    self.pulses_missed += msg.index - self._last_index - 1
                self._last_index = msg.index
                fit = self.clock.fit
                host = float(fit.to_host_ns(msg.ticks)) if fit.ok else float("nan")
                p = Pulse(index=msg.index, device_ticks=msg.ticks, epoch=self._epoch,
                          host_ns=host, arrival_ns=t_rx)
                self.n_pulses += 1
                self._pulses.append(p)
                self._pulse_cv.notify_all()
            for cb in list(self._listeners):
                cb(p)
        elif t == MsgType.BOOT:
            with self._lock:
                self._on_reset("boot banner")
                self.clock.reset(msg.tick_hz)
        else:
            with self._lock:
                slot = self._pending.get(msg.seq)
                if slot is None:
                    return  # late reply to a timed-out request
                if t == MsgType.TIME_REPLY:
                    if msg.ticks < self._last_query_ticks:
                        self._on_reset("time counter went back")
                    self._last_query_ticks = msg.ticks
                slot[1], slot[2] = msg, t_rx
                slot[0].set()

    def _maintain_loop(self) -> None:
        while not self._closed.wait(self.query_interval_s):
            if self._error is not None:
                return
            try:
                if self._need_reconfigure.is_set():
                    self._need_reconfigure.clear()
                    self.sync_clock(16)
                    if self._config is not None:
                        self.configure(self._config)
                        if self._running:
                            self._request(MsgType.START)
                else:
                    self.time_query()
            except SyncBoxTimeout:
                continue
            except SyncBoxError:
                return
