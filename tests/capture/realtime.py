"""Helpers of the real-time tests (tests/capture, tests/hw_sim): waiting on conditions
instead of fixed sleeps, and checking that frames a set lacks are drops the session counted.

A fixed sleep used as synchronisation is a guess about how fast a loaded 2-core machine is;
``wait_until`` waits for the condition itself and fails (does not hang) after a deadline far
beyond any expected time.
"""
from __future__ import annotations

import time
from typing import Callable, TypeVar

T = TypeVar("T")

WAIT_TIMEOUT_S = 10.0


def wait_until(predicate: Callable[[], T], timeout_s: float = WAIT_TIMEOUT_S,
               interval_s: float = 0.01, what: str | None = None) -> T:
    """Poll ``predicate`` until it returns a true value (returned); AssertionError after
    ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while True:
        v = predicate()
        if v:
            return v
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s} s waiting for "
                                 f"{what or getattr(predicate, '__name__', 'condition')}")
        time.sleep(interval_s)


def assert_missing_frames_are_counted_drops(sets, cams, stats, which=None,
                                            since_ns: float = float("-inf")) -> None:
    """Frame sets may lack a camera's frame only where that camera's driver dropped it (the
    documented behaviour of a starved host: the frame is lost and counted as a drop from the
    sequence gap), never because matching lost it. Without drops (normal load) this is
    "every set complete". ``cams`` are simulated cameras (their ground truth is used);
    ``which``: camera indices to check (default all); ``since_ns``: only pulses from this
    host time on (pulse indices restart after a sync box reset)."""
    for i in (range(len(cams)) if which is None else which):
        cam, c = cams[i], stats.cameras[i]
        dropped_seqs = set(cam.dropped_sequences)
        exposed, dropped = set(), set()
        for s, (p, t) in list(cam.truth.items()):
            if t >= since_ns:
                (dropped if s in dropped_seqs else exposed).add(p)
        # a trigger the driver had no room to queue is dropped before it has a truth entry
        n_untracked = len(dropped_seqs - cam.truth.keys())
        lacking = [fs.pulse_index for fs in sets if fs.frames[i] is None]
        delivered = [p for p in lacking if p in exposed]
        untracked = [p for p in lacking if p not in exposed and p not in dropped]
        assert not delivered, (f"{cam.camera_id}: pulses {delivered[:10]} lack a frame the "
                               f"camera delivered", c)
        assert len(untracked) <= n_untracked, (f"{cam.camera_id}: pulses {untracked[:10]} "
                                               f"lack a frame the camera never exposed", c)
        # the session counted every drop between the first and last frame it received
        seqs = sorted(f.sequence for fs in sets if (f := fs.frames[i]) is not None)
        if seqs:
            between = sum(seqs[0] < d < seqs[-1] for d in dropped_seqs)
            assert between <= c.drops <= len(dropped_seqs), (cam.camera_id, between, c)
