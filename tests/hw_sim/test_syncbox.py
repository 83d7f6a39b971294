"""The simulated sync box: its clock, its protocol answers and its faults, over the pty."""
import time

import numpy as np
import pytest
import serial

from capture.sync_protocol import (Message, MsgType, NakCode, decode_frame,
                                   encode_message)
from hw_sim.syncbox import SimSyncBox


def _frames(ser, seconds):
    """Whole frames read one delimiter at a time (nothing is consumed past a frame)."""
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        raw = ser.read_until(b"\x00")
        if raw.endswith(b"\x00") and len(raw) > 1:
            yield decode_frame(raw[:-1])


def _exchange(ser, msg, want, timeout=1.0):
    ser.write(encode_message(msg))
    for m in _frames(ser, timeout):
        if m.type in want:
            return m
    raise AssertionError(f"no {want} reply")


@pytest.fixture
def pair():
    with SimSyncBox(drift_ppm=50.0, jitter_us=0.0, rng=1) as sim:
        with serial.Serial(sim.port, timeout=0.05) as ser:
            yield sim, ser


def test_clock_truth_is_exact_inverse_and_drifts(pair):
    sim, _ = pair
    h = time.monotonic_ns()
    t = sim.device_ticks(h, jitter=False)
    assert abs(sim.true_host_ns(t) - h) <= 1e9 / sim.tick_hz      # floor to one tick
    t2 = sim.device_ticks(h + 10**9, jitter=False)
    assert t2 - t == pytest.approx(1e6 * (1 + 50e-6), abs=1)


def test_version_and_time(pair):
    sim, ser = pair
    v = _exchange(ser, Message.make(MsgType.GET_VERSION, seq=3), {MsgType.VERSION})
    assert v.seq == 3 and v.tick_hz == 1_000_000 and v.name == sim.name
    before = sim.device_ticks(jitter=False)
    r = _exchange(ser, Message.make(MsgType.TIME_QUERY, seq=4), {MsgType.TIME_REPLY})
    assert r.seq == 4 and before <= r.ticks <= sim.device_ticks(jitter=False)


def test_rate_pulses_and_naks(pair):
    sim, ser = pair
    n = _exchange(ser, Message.make(MsgType.START, seq=1), {MsgType.NAK})
    assert n.code == NakCode.NOT_CONFIGURED
    n = _exchange(ser, Message.make(MsgType.SET_RATE, seq=2, rate_mhz=5), {MsgType.NAK})
    assert n.code == NakCode.OUT_OF_RANGE
    _exchange(ser, Message.make(MsgType.SET_RATE, seq=3, rate_mhz=200_000), {MsgType.ACK})
    n = _exchange(ser, Message.make(MsgType.SET_EXPOSURE, seq=4, width_us=4000, delay_us=1500),
                  {MsgType.NAK})
    assert n.code == NakCode.OUT_OF_RANGE      # 5.5 ms does not fit a 5 ms period
    _exchange(ser, Message.make(MsgType.START, seq=5), {MsgType.ACK})
    pulses = [m for m in _frames(ser, 0.3) if m.type == MsgType.PULSE]
    ticks = np.array([p.ticks for p in pulses])
    assert [p.index for p in pulses] == list(range(len(pulses))) and len(pulses) > 20
    assert np.all(np.diff(ticks) == 5000)
    _exchange(ser, Message.make(MsgType.STOP, seq=6), {MsgType.ACK})
    assert not sim.running


def test_reset_restarts_counter_and_sends_boot(pair):
    sim, ser = pair
    _exchange(ser, Message.make(MsgType.SET_RATE, seq=1, rate_mhz=100_000), {MsgType.ACK})
    _exchange(ser, Message.make(MsgType.START, seq=2), {MsgType.ACK})
    before = _exchange(ser, Message.make(MsgType.TIME_QUERY, seq=3), {MsgType.TIME_REPLY})
    sim.reset(silence_s=0.02)
    b = _exchange(ser, Message.make(MsgType.TIME_QUERY, seq=9), {MsgType.BOOT})
    assert b.reason == 1 and not sim.running and sim.rate_hz is None
    r = _exchange(ser, Message.make(MsgType.TIME_QUERY, seq=10), {MsgType.TIME_REPLY})
    assert r.ticks < before.ticks, (r.ticks, before.ticks)     # the counter went back


def test_disappear_closes_pty(pair):
    sim, ser = pair
    sim.disappear()
    with pytest.raises(serial.SerialException):
        for _ in range(20):
            ser.read(1)
