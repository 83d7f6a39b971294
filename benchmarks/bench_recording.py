"""Sustained recording: 8 simulated 1280x1024 cameras at 120 Hz, our recorder vs plain .npy.

Frames are pre-rendered (rendering is not what is measured) and submitted as frame sets on
a 120 Hz schedule for ``--duration`` seconds. When a writer's bounded queue is full the
producer falls behind; a set more than one period late is dropped (what a live session's
cameras would do), so "rate kept" is the frame-set rate the writer sustained; "on disk
Hz" divides the sets by the time until the last one was on disk (queues drained, fsynced),
which also counts what the queues still held when the schedule ended. Baseline in
the same run: the same threads and queues writing each frame with ``np.save`` (raw).
Two image kinds: 'noisy' (sensor read noise on the dark background, worst case for a
lossless codec) and 'clean' (black level clamped to 0, typical IR mocap frames).

    .venv/bin/python benchmarks/bench_recording.py [--duration 4] [--cameras 8] [--dir /tmp]

``--kill-trials N`` also runs ``mocap capture --sim`` (4 cameras 320x256 at 100 Hz) N times,
kills it with SIGKILL after 3 s of recording and prints what it lost: kill time minus the
last recorded exposure of the worst camera (both on the host monotonic clock).
``--kill-only`` skips the throughput table. ``--clock-s S`` also measures the sync box
clock fit for S seconds (simulated box on a pty, 50 ppm fast, through pyserial): pulse host
times from the fit against the simulator's truth.
"""
from __future__ import annotations

import argparse
import os
import queue
import shutil
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from capture.frame import Frame, TimestampSource
from capture.recording import CODEC_AUTO, RecordedCamera, Recorder
from hw_sim.render import render_frame
from hw_sim.sim_camera import orbiting_markers, ring_of_cameras


def make_frames(n_cams, size, kind, per_cam=3, seed=0):
    rng = np.random.default_rng(seed)
    models = ring_of_cameras(n_cams, size=size)
    scene = orbiting_markers(30)
    out = []
    for m in models:
        imgs = []
        for k in range(per_cam):
            pts, d = scene(0.1 * k)
            img, _ = render_frame(m, pts, d, rng, bit_depth=8)
            if kind == "clean":
                img = np.where(img > 20, img, 0).astype(np.uint8)
            imgs.append(img)
        out.append(imgs)
    return out


class NpyWriter:
    """Baseline: one thread per camera, bounded queue, ``np.save`` appended to one file."""

    def __init__(self, folder, n_cams, qsize=32):
        folder.mkdir(parents=True)
        self.qs = [queue.Queue(maxsize=qsize) for _ in range(n_cams)]
        self.files = [open(folder / f"cam{i:02d}.npy", "wb") for i in range(n_cams)]
        self.bytes = [0] * n_cams
        self.threads = [threading.Thread(target=self._loop, args=(i,), daemon=True)
                        for i in range(n_cams)]
        for t in self.threads:
            t.start()

    def _loop(self, i):
        f, last = self.files[i], time.monotonic()
        while True:
            item = self.qs[i].get()
            if item is None:
                break
            np.save(f, item.image)
            f.flush()
            if time.monotonic() - last > 0.5:
                os.fsync(f.fileno())
                last = time.monotonic()
        f.flush()
        os.fsync(f.fileno())
        self.bytes[i] = f.tell()
        f.close()

    def write_frame(self, i, frame, **kw):
        self.qs[i].put(frame)

    def close(self):
        for q in self.qs:
            q.put(None)
        for t in self.threads:
            t.join()

    def stats(self, n_frames, raw):
        out = sum(self.bytes)
        return {"bytes_per_frame": out / n_frames, "compression_ratio": raw / out}


def run(writer_factory, frames, rate_hz, duration_s):
    n_cams = len(frames)
    w = writer_factory()
    period = 1.0 / rate_hz
    n_sets_target = int(duration_s * rate_hz)
    submitted = dropped = 0
    t0 = time.monotonic()
    cpu0 = time.process_time()
    for k in range(n_sets_target):
        due = t0 + k * period
        now = time.monotonic()
        if now < due:
            time.sleep(due - now)
        elif now - due > period:
            dropped += 1
            continue
        for c in range(n_cams):
            img = frames[c][k % len(frames[c])]
            f = Frame(image=img, camera_id=f"cam_{c + 1}", sequence=k,
                      timestamp_ns=int(due * 1e9), exposure_us=500.0, gain=1.0,
                      timestamp_source=TimestampSource.KERNEL_START_OF_EXPOSURE)
            w.write_frame(c, f, frame_index=k)
        submitted += 1
    t_prod = time.monotonic() - t0
    w.close()
    t_all = time.monotonic() - t0
    cpu = time.process_time() - cpu0
    return w, submitted, dropped, t_prod, t_all, cpu


def kill_trial(base: Path, k: int) -> tuple[float, int, bool]:
    """(seconds lost, frames per camera kept, metadata complete) of one killed capture."""
    import signal
    import subprocess
    import sys

    from capture.replay import FrameFileReader, load_metadata
    out = base / f"killed{k}"
    repo = Path(__file__).resolve().parents[1]
    p = subprocess.Popen([sys.executable, "-m", "mocap", "capture", "--sim", "--cameras", "4",
                          "--size", "320", "256", "--rate", "100", "--duration", "120",
                          "--seed", str(k), "--out", str(out)], cwd=repo,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        f, t_end = out / "cam03.frames", time.monotonic() + 60
        while not (f.exists() and f.stat().st_size > 100_000) and time.monotonic() < t_end:
            time.sleep(0.05)
        time.sleep(3.0)
        t_kill = time.monotonic_ns()
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.wait()
    meta = load_metadata(out)
    lasts, n = [], []
    for fn, cid in zip(meta.files, meta.camera_ids):
        recs = list(FrameFileReader(out / fn, cid))   # every record passes its CRC
        lasts.append(recs[-1].frame.timestamp_ns)
        n.append(len(recs))
    return (t_kill - min(lasts)) * 1e-9, min(n), meta.complete


def clock_fit(seconds: float) -> None:
    from capture.syncbox import SyncBox, SyncConfig
    from hw_sim.syncbox import SimSyncBox

    sim = SimSyncBox(drift_ppm=50.0, jitter_us=2.0, rng=7)
    truth = {}
    sim.add_trigger_listener(lambda e: truth.__setitem__((e.index, e.device_ticks), e.host_ns))
    try:
        with SyncBox(sim.port) as box:
            box.configure(SyncConfig(rate_hz=100))
            box.start()
            pulses, t_end = [], time.monotonic() + seconds
            while time.monotonic() < t_end:
                p = box.get_pulse(0.05)
                if p is not None:
                    pulses.append(p)
            box.stop()
            fit = box.clock.fit
            err = np.array([box.host_time(p) - truth[(p.index, p.device_ticks)]
                            for p in pulses]) / 1e3
            true_ppm = (1 / (1 + sim.drift_ppm * 1e-6) - 1) * 1e6
            print(f"clock fit: {len(pulses)} pulses in {seconds:g} s at 100 Hz; gain-1 "
                  f"{fit.drift_ppm:.1f} ppm (true {true_ppm:.1f}); pulse time error vs truth "
                  f"RMS {np.sqrt(np.mean(err ** 2)):.1f} us, max {np.abs(err).max():.1f} us; "
                  f"bound (largest rtt/2 used) {fit.bound_ns / 1e3:.0f} us; "
                  f"bad frames {box.stats().bad_frames}")
    finally:
        sim.close()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--cameras", type=int, default=8)
    ap.add_argument("--rate", type=float, default=120.0)
    ap.add_argument("--duration", type=float, default=4.0)
    ap.add_argument("--size", type=int, nargs=2, default=(1280, 1024))
    ap.add_argument("--dir", default=None)
    ap.add_argument("--kill-trials", type=int, default=0)
    ap.add_argument("--kill-only", action="store_true")
    ap.add_argument("--clock-s", type=float, default=0.0)
    a = ap.parse_args()
    base = Path(tempfile.mkdtemp(prefix="bench_rec_", dir=a.dir))
    try:
        if not a.kill_only:
            throughput(a, base)
        if a.clock_s > 0:
            clock_fit(a.clock_s)
        for k in range(a.kill_trials):
            lost, n, complete = kill_trial(base, k)
            print(f"kill -9 of mocap capture --sim (4 x 320x256 at 100 Hz) trial {k}: lost "
                  f"{lost * 1e3:.0f} ms, kept {n} frames/camera, metadata complete={complete}")
    finally:
        shutil.rmtree(base, ignore_errors=True)


def throughput(a, base):
    print(f"{a.cameras} cameras {a.size[0]}x{a.size[1]} 8-bit at {a.rate:g} Hz for "
          f"{a.duration:g} s, {os.cpu_count()} CPUs, writing to {base}")
    print(f"{'images':<7} {'writer':<14} {'rate kept Hz':>12} {'on disk Hz':>10} "
          f"{'dropped':>8} {'bytes/frame':>12} {'ratio':>6} {'drain s':>8} {'cpu s':>6}")
    for kind in ("clean", "noisy"):
        frames = make_frames(a.cameras, tuple(a.size), kind)
        raw_frame = frames[0][0].nbytes
        results = {}
        for name in ("recorder", "npy baseline"):
            folder = base / f"{kind}_{name.split()[0]}"
            if name == "recorder":
                cams = [RecordedCamera(camera_id=f"cam_{c + 1}") for c in range(a.cameras)]
                fac = lambda: Recorder(folder, cams, rate_hz=a.rate, codec=CODEC_AUTO)  # noqa: E731
            else:
                fac = lambda: NpyWriter(folder, a.cameras)  # noqa: E731
            w, sub, drop, t_prod, t_all, cpu = run(fac, frames, a.rate, a.duration)
            n = sub * a.cameras
            st = w.stats() if name == "recorder" else w.stats(n, n * raw_frame)
            kept = sub / a.duration
            results[name] = kept
            print(f"{kind:<7} {name:<14} {kept:12.1f} {sub / t_all:10.1f} {drop:8d} "
                  f"{st['bytes_per_frame']:12.0f} {st['compression_ratio']:6.2f} "
                  f"{t_all - t_prod:8.2f} {cpu:6.1f}")
            shutil.rmtree(folder)
        print(f"{kind:<7} rate kept ratio recorder / npy = "
              f"{results['recorder'] / results['npy baseline']:.2f}")


if __name__ == "__main__":
    main()
