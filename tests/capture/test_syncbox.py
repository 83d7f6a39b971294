"""Host sync box driver against the simulated box, through the real pty device path."""
import struct
import time

import numpy as np
import pytest

from capture.errors import SyncBoxDisconnected, SyncBoxNak, SyncBoxTimeout, SyncProtocolError
from capture.sync_protocol import MsgType, NakCode
from capture.syncbox import SyncBox, SyncConfig
from hw_sim.syncbox import SimSyncBox

# a pulse's host time comes from the clock fit; each fit sample is within rtt/2 of truth,
# the line through them (evaluated slightly outside the samples) within twice that.
FIT_BOUND_FACTOR = 2.0
RATE_HZ = 100.0


def _collect(box, seconds):
    out, t_end = [], time.monotonic() + seconds
    while time.monotonic() < t_end:
        p = box.get_pulse(0.05)
        if p is not None:
            out.append(p)
    return out


@pytest.fixture
def sim():
    s = SimSyncBox(drift_ppm=50.0, jitter_us=2.0, rng=7)
    truth = {}
    s.add_trigger_listener(lambda e: truth.__setitem__((e.index, e.device_ticks), e.host_ns))
    s.truth = truth
    yield s
    s.close()


def test_port_is_a_real_pty_device(sim):
    assert sim.port.startswith("/dev/pts/")


def test_version_clock_and_pulses_match_truth(sim):
    with SyncBox(sim.port) as box:
        assert box.info.tick_hz == 1_000_000 and box.info.protocol == (1, 0)
        box.configure(SyncConfig(rate_hz=RATE_HZ, strobe_width_us=300, strobe_delay_us=20))
        box.start()
        pulses = _collect(box, 1.0)
        box.stop()
        fit = box.clock.fit
        assert fit.ok
        idx = [p.index for p in pulses]
        assert idx == list(range(len(idx))) and len(idx) >= 0.8 * RATE_HZ
        err = np.array([box.host_time(p) - sim.truth[(p.index, p.device_ticks)]
                        for p in pulses])
        assert np.max(np.abs(err)) <= FIT_BOUND_FACTOR * fit.bound_ns, (err, fit)
        # device period in ticks is exact: 1e6 / rate
        ticks = np.array([p.device_ticks for p in pulses])
        assert np.all(np.abs(np.diff(ticks) - 1e6 / RATE_HZ) <= 1)
        assert box.stats().bad_frames == 0


def test_naks_are_raised_with_code(sim):
    with SyncBox(sim.port) as box:
        with pytest.raises(SyncBoxNak) as e:
            box.start()
        assert e.value.code == NakCode.NOT_CONFIGURED and sim.port in str(e.value)
        box.configure(SyncConfig(rate_hz=50))
        box.start()
        with pytest.raises(SyncBoxNak) as e:
            box.configure(SyncConfig(rate_hz=60))
        assert e.value.code == NakCode.BUSY


def _raw_frame(body: bytes) -> bytes:
    from capture.sync_protocol import cobs_encode, crc16_ccitt_false
    return cobs_encode(body + struct.pack("<H", crc16_ccitt_false(body))) + b"\x00"


def _raw_replies(port, wire, n, timeout_s=1.0):
    """Write raw bytes to the box's device path, return the next ``n`` non-PULSE replies."""
    import serial
    from capture.sync_protocol import FrameSplitter, decode_frame
    out, sp = [], FrameSplitter()
    with serial.Serial(port, 115200, timeout=0.05) as ser:
        ser.write(b"\x00" + wire)
        t_end = time.monotonic() + timeout_s
        while len(out) < n and time.monotonic() < t_end:
            for fr in sp.feed(ser.read(256)):
                m = decode_frame(fr)
                if m.type not in (MsgType.PULSE, MsgType.BOOT):
                    out.append(m)
    return out


def test_box_naks_well_formed_frames_it_cannot_parse(sim):
    """Spec 2: good CRC + unknown type -> NAK UNKNOWN_TYPE; known command with a wrong body
    length -> NAK BAD_LENGTH; bad CRC -> silence. Raw bytes through the pty."""
    wire = (_raw_frame(bytes([0x7F, 0x09, 0x00]))                        # unknown type
            + _raw_frame(bytes([0x02, 0x0A, 0x00, 0x01]))                # SET_RATE, short
            + _raw_frame(bytes([0x06, 0x0B, 0x00]))[:-3] + b"\x55\x00"   # bad CRC
            + _raw_frame(bytes([0x06, 0x0C, 0x00])))                     # TIME_QUERY seq 12
    got = sorted(_raw_replies(sim.port, wire, 3), key=lambda m: m.seq)  # latencies vary
    assert [(m.type, m.seq) for m in got] == [(MsgType.NAK, 9), (MsgType.NAK, 10),
                                              (MsgType.TIME_REPLY, 12)]
    assert (got[0].cmd, got[0].code) == (0x7F, NakCode.UNKNOWN_TYPE)
    assert (got[1].cmd, got[1].code) == (0x02, NakCode.BAD_LENGTH)


def test_start_refuses_a_strobe_that_does_not_fit_the_period(sim):
    with SyncBox(sim.port) as box:
        box.configure(SyncConfig(rate_hz=10, strobe_width_us=60_000))
        # a faster rate alone is accepted (rate and strobe may be set in either order) ...
        box._request(MsgType.SET_RATE, rate_mhz=100_000)
        with pytest.raises(SyncBoxNak) as e:                 # ... but START checks the fit
            box.start()
        assert e.value.code == NakCode.OUT_OF_RANGE and not sim.running
        box.configure(SyncConfig(rate_hz=100, strobe_width_us=500))
        box.start()
        assert sim.running


def test_survives_garbage_and_partial_frames(sim):
    with SyncBox(sim.port) as box:
        box.configure(SyncConfig(rate_hz=RATE_HZ))
        box.start()
        sim.split_writes = True
        n_bursts = 10
        for _ in range(n_bursts // 2):
            sim.inject_garbage(40)
            sim.inject_garbage(300, with_zeros=False)
            time.sleep(0.05)
        pulses = _collect(box, 0.6)
        assert box.error is None
        assert box.stats().bad_frames > 0
        idx = [p.index for p in pulses]
        assert len(idx) > 0.3 * RATE_HZ
        # a burst corrupts at most the frame it lands in and the one it runs into
        assert np.all(np.diff(idx) > 0)
        assert box.stats().pulses_missed <= 2 * n_bursts
        assert box.time_query().rtt_ns > 0


def test_survives_box_reset(sim):
    with SyncBox(sim.port, query_interval_s=0.05) as box:
        box.configure(SyncConfig(rate_hz=RATE_HZ))
        box.start()
        _collect(box, 0.3)
        sim.reset()
        deadline = time.monotonic() + 3.0
        while not (sim.running and box.epoch == 1) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert box.stats().resets == 1 and sim.running  # reconfigured and restarted
        while box.get_pulse(0) is not None:
            pass
        after = [p for p in _collect(box, 0.5) if p.epoch == 1]
        assert len(after) > 10
        fit = box.clock.fit
        assert fit.ok
        err = [box.host_time(p) - sim.truth[(p.index, p.device_ticks)] for p in after]
        assert np.max(np.abs(err)) <= FIT_BOUND_FACTOR * fit.bound_ns


def test_disappearing_box_raises_disconnected(sim):
    box = SyncBox(sim.port)
    box.configure(SyncConfig(rate_hz=RATE_HZ))
    box.start()
    sim.disappear()
    deadline = time.monotonic() + 10.0             # fails (DID NOT RAISE), never hangs
    with pytest.raises(SyncBoxDisconnected, match="/dev/pts/"):
        while time.monotonic() < deadline:
            box.get_pulse(0.1)
    assert isinstance(box.error, SyncBoxDisconnected)
    box.close()


def test_sustained_garbage_is_a_protocol_error(sim):
    box = SyncBox(sim.port, garbage_timeout_s=0.3, query_interval_s=10)
    sim.split_writes = False
    t_end = time.monotonic() + 2.0
    with pytest.raises(SyncProtocolError, match="no valid frame"):
        while time.monotonic() < t_end:
            sim.inject_garbage(64, with_zeros=False)
            sim.inject_garbage(8)
            time.sleep(0.01)
            box.get_pulse(0)
    box.close()


def test_missing_port_is_clear_error(tmp_path):
    with pytest.raises(SyncBoxDisconnected, match="nothing-here"):
        SyncBox(str(tmp_path / "nothing-here"))


def test_silent_device_times_out_and_releases_the_port():
    import os
    import tty
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        with pytest.raises(SyncBoxTimeout) as e:
            SyncBox(os.ttyname(slave), request_timeout_s=0.1)
        assert "GET_VERSION" in str(e.value) and os.ttyname(slave) in str(e.value)
    finally:
        os.close(master)
        os.close(slave)


@pytest.mark.hardware
def test_real_sync_box():
    """A box on $MOCAP_TEST_SYNC (default /dev/ttyACM0): pytest --run-hardware."""
    import os
    with SyncBox(os.environ.get("MOCAP_TEST_SYNC", "/dev/ttyACM0")) as box:
        box.configure(SyncConfig(rate_hz=100))
        box.start()
        pulses = _collect(box, 1.0)
        box.stop()
        assert len(pulses) >= 90 and box.clock.fit.ok
        assert abs(box.clock.fit.drift_ppm) < 500
