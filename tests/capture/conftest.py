"""Fixtures of the capture tests: the simulated rig (sync box on a pty + cameras)."""
from __future__ import annotations

import pytest

from capture.syncbox import SyncBox, SyncConfig
from hw_sim.sim_camera import SimCamera, ring_of_cameras
from hw_sim.syncbox import SimSyncBox


@pytest.fixture
def rig_factory():
    """``rig_factory(n_cameras, size=(w, h), seed=..., rate_hz=100, drift_ppm=50, **box_kw)``
    -> ``(sim, box, cams)``: a simulated sync box on its pty, the host driver ``SyncBox``
    opened on that device path (``box_kw``) and configured at ``rate_hz``, and
    ``n_cameras`` SimCameras of a ring wired to the box's trigger line. Everything is closed
    at teardown (also what a test closed itself)."""
    made = []

    def make(n_cameras, *, size, seed, rate_hz=100.0, drift_ppm=50.0, **box_kw):
        sim = SimSyncBox(drift_ppm=drift_ppm, rng=seed)
        made.append(sim)
        box = SyncBox(sim.port, **box_kw)
        made.append(box)
        box.configure(SyncConfig(rate_hz=rate_hz))
        cams = [SimCamera(m, sync=sim, rng=i)
                for i, m in enumerate(ring_of_cameras(n_cameras, size=size))]
        made.extend(cams)
        return sim, box, cams

    yield make
    for x in reversed(made):      # cameras, then the host driver, then the box
        x.close()
