"""Live sessions on the simulated rig: matching to pulses, statistics and faults."""
import time

import numpy as np
import pytest

from capture.camera import CameraSettings, PixelFormat
from capture.errors import SyncBoxDisconnected, SyncProtocolError
from capture.frame import TimestampSource
from capture.session import CaptureSession
from capture.syncbox import SyncBox, SyncConfig
from capture.v4l2 import V4L2Camera
from hw_sim.sim_camera import SimCamera, ring_of_cameras

from .fake_v4l2 import FakeVideoDevices, TriggeredSensor
from .realtime import assert_missing_frames_are_counted_drops, wait_until

RATE_HZ = 100.0
DURATION_S = 1.0
MIN_SETS_FRACTION = 0.8   # of rate * duration (startup and a loaded 2-core machine)


@pytest.fixture
def rig(rig_factory):
    return rig_factory(3, size=(160, 128), seed=11, rate_hz=RATE_HZ)


@pytest.fixture
def v4l2_rig(rig_factory, tmp_path):
    """The rig's cameras as V4L2 devices: the real ``V4L2Camera`` over fake kernels whose
    sensors expose at the simulated box's trigger line (tests/capture/fake_v4l2.py)."""
    sim, box, _ = rig_factory(0, size=(320, 240), seed=12, rate_hz=RATE_HZ)
    devices = FakeVideoDevices(tmp_path)
    sensors, cams = [], []
    for i, m in enumerate(ring_of_cameras(3, size=(320, 240))):
        path, kernel = devices.add(f"video{i}")
        kernel.size = m.size
        sensors.append(TriggeredSensor(kernel, m, sim, rng=i).start())
        cams.append(V4L2Camera(path, lp=devices, camera_id=m.name))
    yield sim, box, cams, sensors
    for c in cams:
        c.close()
    for s in sensors:
        s.stop()
    devices.close()


def _check_matching(sets, cams):
    """Every frame in a set was exposed at that set's pulse (ground truth)."""
    for fs in sets:
        for cam, f in zip(cams, fs.frames):
            if f is not None:
                assert cam.truth[f.sequence][0] == fs.pulse_index


def test_frame_sets_match_pulses(rig):
    sim, box, cams = rig
    sets, lines = [], []
    t0 = time.monotonic()
    st = CaptureSession(cams, box, on_frame_set=sets.append, on_status=lines.append,
                        status_interval_s=0.2).run(DURATION_S)
    run_s = time.monotonic() - t0       # the box pulsed within this, for at least DURATION_S
    assert len(sets) >= MIN_SETS_FRACTION * RATE_HZ * DURATION_S
    _check_matching(sets, cams)
    assert [s.index for s in sets] == list(range(len(sets)))
    assert np.all(np.diff([s.host_ns for s in sets]) > 0)
    for i, c in enumerate(st.cameras):
        assert c.unmatched == 0 and c.connected
        # exposure -> frame set: at least the camera's readout latency, under one wait
        assert cams[i].latency_ns / 1e6 <= c.latency_ms < 1e3 * (3 / RATE_HZ + 0.1)
        # one frame per pulse: the camera's rate over the time the box was pulsing
        assert MIN_SETS_FRACTION * RATE_HZ * DURATION_S <= c.frames <= RATE_HZ * run_s + 1
        assert c.frames == sum(fs.frames[i] is not None for fs in sets) + c.late
        # the statistics agree with the sets (drops/late only when the host is starved)
        assert c.missing == sum(fs.frames[i] is None for fs in sets)
        assert c.missing <= c.drops + c.late + cams[i].frames_dropped
    assert st.complete_sets == sum(fs.complete for fs in sets)
    assert lines and "cam_1" in lines[-1] and "sync" in lines[-1]


def test_v4l2_cameras_match_pulses(v4l2_rig):
    """The same session over the real V4L2 driver code (kernel sequence numbers and
    start-of-exposure timestamps from the fake kernel)."""
    sim, box, cams, sensors = v4l2_rig
    for c in cams:
        got = c.configure(CameraSettings(pixel_format=PixelFormat.Y10, exposure_us=500))
        assert (got.width, got.height, got.pixel_format) == (320, 240, PixelFormat.Y10)
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append).run(DURATION_S)
    assert [s.error for s in sensors] == [None] * 3
    assert len(sets) >= MIN_SETS_FRACTION * RATE_HZ * DURATION_S
    _check_matching(sets, sensors)
    assert [s.index for s in sets] == list(range(len(sets)))
    for fs in sets:
        for f in fs.frames:
            if f is not None:
                assert f.image.shape == (240, 320) and f.image.dtype == np.uint16
                assert f.timestamp_source == TimestampSource.KERNEL_START_OF_EXPOSURE
    for c in st.cameras:
        assert c.unmatched == 0 and c.connected
    assert_missing_frames_are_counted_drops(sets, sensors, st)
    assert st.complete_sets == sum(fs.complete for fs in sets)


def test_drops_counted_from_sequence_gaps(rig):
    sim, box, cams = rig
    cams[1].drop_probability = 0.2
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append).run(DURATION_S)
    _check_matching(sets, cams)
    c1 = st.cameras[1]
    seqs = [fs.frames[1].sequence for fs in sets if fs.frames[1] is not None]
    gaps = int(np.sum(np.diff(seqs) - 1))
    assert c1.drops == gaps > 0
    assert c1.missing >= gaps
    seqs0 = [fs.frames[0].sequence for fs in sets if fs.frames[0] is not None]
    assert st.cameras[0].drops == int(np.sum(np.diff(seqs0) - 1)) <= cams[0].frames_dropped


def test_camera_disappearing_mid_session(rig):
    sim, box, cams = rig
    cams[2].disappear_after_frames = 30
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append).run(DURATION_S)
    lost = st.cameras[2]
    assert not lost.connected and "sim:cam_3" in lost.error
    assert "cam_3 LOST" in st.status_line()
    assert all(c.connected for c in st.cameras[:2])
    _check_matching(sets, cams)
    later = sets[40:]
    assert later and all(fs.frames[2] is None for fs in later)
    assert_missing_frames_are_counted_drops(later, cams, st, which=(0, 1))


def test_frames_without_pulses_are_counted(rig):
    sim, box, cams = rig
    sim.pulse_loss = 0.2      # trigger line fires, the serial PULSE message is lost
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append, max_wait_s=0.05).run(DURATION_S)
    _check_matching(sets, cams)
    missed = box.stats().pulses_missed
    assert missed > 0
    unmatched = [c.unmatched for c in st.cameras]
    # each lost pulse leaves one frame per camera without a pulse (+- the run's edges)
    assert all(abs(u - missed) <= 3 for u in unmatched), (unmatched, missed)


def test_late_frames_are_counted(rig):
    sim, box, cams = rig
    cams[0].late_probability = 0.1
    cams[0].late_ms = 100.0
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append, max_wait_s=0.03,
                        adaptive_wait=False).run(DURATION_S)
    _check_matching(sets, cams)
    # every frame the camera delayed past the wait arrives after its set left, except
    # those still in flight at stop (expected rate * late_ms * p = 1; allow 3); the other
    # cameras are late only if the host starves
    assert st.cameras[0].late >= cams[0].frames_delayed - 3 > 0
    assert st.cameras[0].late > st.cameras[1].late


def test_adaptive_wait_keeps_frames_of_a_slow_host(rig):
    sim, box, cams = rig
    latency_s, max_wait_s = 0.08, 0.03
    for c in cams:
        c.latency_ns = int(latency_s * 1e9)   # an overloaded host: frames 80 ms late
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append,
                        max_wait_s=max_wait_s).run(DURATION_S)
    _check_matching(sets, cams)
    # only the pulses that expired before the first frame arrived lose their frames
    bound = int(np.ceil((latency_s - max_wait_s) * RATE_HZ)) + 1
    assert max(c.late for c in st.cameras) <= bound
    # other incomplete sets are explained by drops (a starved host overflows the buffers)
    assert st.complete_sets >= len(sets) - bound - sum(c.drops for c in st.cameras)
    assert st.complete_sets >= MIN_SETS_FRACTION * RATE_HZ * DURATION_S - 2 * bound


def test_stop_drains_the_frames_of_the_last_pulses(rig):
    """A camera that turns slow just before stop (a host overloaded at the end): its frames
    of the last pulses come 1 s late, beyond the normal wait; stopping waits for them
    (up to max_wait_cap_s) instead of closing the last sets without them."""
    sim, box, cams = rig
    # the normal wait is long enough that the sets of the slow pulses are still open when
    # stop() begins on a loaded host (it drains from the moment it sends STOP)
    late_s, wait_s, cap_s = 1.0, 0.5, 30.0
    sets = []
    session = CaptureSession(cams, box, on_frame_set=sets.append, adaptive_wait=False,
                             max_wait_s=wait_s, max_wait_cap_s=cap_s)
    session.start()
    wait_until(lambda: len(sets) >= 30, what="30 frame sets")
    n0 = sim.pulses_emitted
    cams[0].late_ms, cams[0].late_probability = late_s * 1e3, 1.0
    # a couple of pulses with the slow camera (its first frame is being held back)
    wait_until(lambda: cams[0].frames_delayed >= 1 and sim.pulses_emitted >= n0 + 2,
               interval_s=0.002, what="pulses with the slow camera")
    t0 = time.monotonic()
    st = session.stop()
    assert time.monotonic() - t0 < late_s + 5.0    # waited for the late frames, not the cap
    _check_matching(sets, cams)
    tail = [fs for fs in sets if fs.frames[1] is not None][-3:]
    assert_missing_frames_are_counted_drops(tail, cams, st)
    assert st.cameras[0].late == 0
    assert st.cameras[0].missing <= cams[0].frames_dropped


def test_back_pressure_from_a_slow_consumer_shows_as_drops(rig):
    sim, box, cams = rig

    def slow(fs):
        time.sleep(0.02)      # consumer handles 50 sets/s of 100

    st = CaptureSession(cams, box, on_frame_set=slow, queue_size=2).run(DURATION_S)
    assert all(c.drops > 0 for c in st.cameras)
    assert st.frame_sets <= st.elapsed_s / 0.02 + 1      # the consumer's pace


def test_sync_box_disappearing_stops_with_clear_error(rig):
    sim, box, cams = rig
    sets = []
    session = CaptureSession(cams, box, on_frame_set=sets.append)
    session.start()
    wait_until(lambda: len(sets) > 10, what="frame sets before the fault")
    sim.disappear()
    wait_until(lambda: session.stopped, what="the session to stop")
    with pytest.raises(SyncBoxDisconnected, match="/dev/pts/"):
        session.stop()
    assert len(sets) > 10
    _check_matching(sets, cams)


def test_sync_box_sending_garbage_stops_with_clear_error(rig):
    sim, first, cams = rig
    first.close()
    box = SyncBox(sim.port, garbage_timeout_s=0.3)
    box.configure(SyncConfig(rate_hz=RATE_HZ))
    session = CaptureSession(cams, box, on_frame_set=lambda fs: None)
    session.start()

    def garbage_until_stopped():
        sim.inject_garbage(200, with_zeros=False)
        return session.stopped

    wait_until(garbage_until_stopped, interval_s=0.005, what="the session to stop")
    with pytest.raises(SyncProtocolError):
        session.stop()
    box.close()


def test_free_running_cameras_without_sync_box():
    models = ring_of_cameras(2, size=(160, 128))
    cams = [SimCamera(m, rate_hz=50.0, rng=i,
                      timestamp_source=TimestampSource.KERNEL_END_OF_FRAME)
            for i, m in enumerate(models)]
    sets = []
    st = CaptureSession(cams, None, rate_hz=50.0, on_frame_set=sets.append).run(DURATION_S)
    for c in cams:
        c.close()
    assert st.frame_sets >= 0.6 * 50 * DURATION_S
    seq_pairs = [(fs.frames[0].sequence, fs.frames[1].sequence) for fs in sets if fs.complete]
    assert len(seq_pairs) >= 0.5 * len(sets)
    # each camera appears at most once per set and in order
    for j in range(2):
        seqs = [fs.frames[j].sequence for fs in sets if fs.frames[j] is not None]
        assert np.all(np.diff(seqs) > 0)


def test_bad_arguments():
    cam = SimCamera(ring_of_cameras(1)[0])
    with pytest.raises(ValueError, match="rate_hz"):
        CaptureSession([cam], None)
    with pytest.raises(ValueError, match="empty"):
        CaptureSession([], None, rate_hz=10)
    with pytest.raises(ValueError, match="unique"):
        CaptureSession([cam, cam], None, rate_hz=10)


def test_end_of_frame_timestamps_learn_their_offset(rig):
    sim, box, _ = rig
    models = ring_of_cameras(2, size=(160, 128))
    cams = [SimCamera(m, sync=sim, rng=5 + i,
                      timestamp_source=TimestampSource.KERNEL_END_OF_FRAME)
            for i, m in enumerate(models)]
    sets = []
    st = CaptureSession(cams, box, on_frame_set=sets.append).run(DURATION_S)
    for c in cams:
        c.close()
    _check_matching(sets, cams)
    assert st.complete_sets >= MIN_SETS_FRACTION * RATE_HZ * DURATION_S - 10


def test_session_survives_a_sync_box_reset(rig):
    sim, box, cams = rig
    sets = []
    session = CaptureSession(cams, box, on_frame_set=sets.append)
    session.start()
    wait_until(lambda: len(sets) >= 20, what="frame sets before the reset")
    t_reset = time.monotonic_ns()
    sim.reset()
    wait_until(lambda: sum(fs.epoch == 1 for fs in sets) >= 20, what="sets after the reset")
    st = session.stop()
    assert box.stats().resets == 1
    _check_matching(sets, cams)
    after = [fs for fs in sets if fs.epoch == 1]
    assert len(after) >= 20
    assert_missing_frames_are_counted_drops(after[2:], cams, st, since_ns=t_reset)
    assert st.cameras[0].connected


def test_stalled_pulses_still_match_their_frames(rig):
    """The serial line stalls 0.3 s (beyond the default 0.13 s wait for missing cameras):
    frames whose pulse has not arrived wait for it instead of counting as unmatched."""
    sim, box, cams = rig
    stall_s, stall_at_set = 0.3, 30
    sets, pulse_ns, arrival_ns, window = [], {}, {}, []
    sim.add_trigger_listener(lambda e: pulse_ns.__setitem__(e.index, e.host_ns))
    box.add_listener(lambda p: arrival_ns.__setitem__(p.index, p.arrival_ns))

    def on_set(fs):
        sets.append(fs)
        if fs.index == stall_at_set:             # the stall starts at a known point
            t0 = time.monotonic_ns()
            sim.stall(stall_s)
            window[:] = [time.monotonic_ns(), t0 + stall_s * 1e9]

    session = CaptureSession(cams, box, on_frame_set=on_set)
    session.start()
    # run until the sets of pulses well after the stall are out
    wait_until(lambda: window and sets and sets[-1].host_ns > window[1] + 0.1e9,
               what="frame sets after the stall")
    st = session.stop()
    _check_matching(sets, cams)
    assert [s.index for s in sets] == list(range(len(sets)))
    assert np.all(np.diff([s.host_ns for s in sets]) > 0)
    for i, c in enumerate(st.cameras):
        assert c.unmatched == 0, (i, c)
        assert c.frames == sum(fs.frames[i] is not None for fs in sets) + c.late
    # pulses of the stall: the trigger fired after it began and before it ended; their
    # messages reached the host only at its end (the stall really happened) ...
    stalled_idx = sorted(i for i, t in pulse_ns.items() if window[0] <= t < window[1])
    assert len(stalled_idx) >= 0.9 * stall_s * RATE_HZ - 1
    assert all(arrival_ns[i] >= window[1] for i in stalled_idx), \
        [(i, (window[1] - arrival_ns[i]) / 1e6) for i in stalled_idx if arrival_ns[i] < window[1]]
    # ... and their sets are there, with their frames (unless a starved driver dropped one)
    stalled = [fs for fs in sets if fs.pulse_index in set(stalled_idx)]
    assert [fs.pulse_index for fs in stalled] == stalled_idx
    assert_missing_frames_are_counted_drops(stalled, cams, st)
