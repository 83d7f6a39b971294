"""Record a live session to a folder: the one call behind ``mocap capture``.

Opens nothing itself: it takes configured cameras and a sync box (real or simulated),
runs a ``CaptureSession`` into a ``Recorder`` and closes the recording cleanly whatever
happens (camera lost: goes on; sync box fault or full disk: stops, re-raises).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

from .camera import Camera
from .recording import CODEC_AUTO, RecordedCamera, Recorder
from .session import CaptureSession, SessionStats
from .syncbox import SyncBox

__all__ = ["LiveResult", "record_live"]


@dataclass(frozen=True, kw_only=True)
class LiveResult:
    session: SessionStats
    recording: dict
    folder: Path


def record_live(cameras: Sequence[Camera], sync: SyncBox | None, out, *, duration_s: float,
                rate_hz: float | None = None, calibration: str | None = None,
                codec: int = CODEC_AUTO,
                on_status: Callable[[str], None] | None = None) -> LiveResult:
    """Run cameras (+ sync box) for ``duration_s`` and record to folder ``out``."""
    if not (duration_s > 0 and math.isfinite(duration_s)):
        raise ValueError(f"duration_s={duration_s}, expected a finite duration > 0")
    rate = sync.config.rate_hz if sync is not None and sync.config is not None else rate_hz
    recorded = []
    for c in cameras:
        s = c.settings   # applied, as read back ([Camera protocol])
        recorded.append(RecordedCamera(camera_id=c.camera_id,
                                       device=str(getattr(c, "device", getattr(c, "path", ""))),
                                       settings=s.to_dict()))
    rec = Recorder(out, recorded, rate_hz=rate,
                   sync_config=None if sync is None or sync.config is None
                   else {**sync.config.to_dict(), "port": sync.port,
                         "device": None if sync.info is None else sync.info.name},
                   calibration=calibration, codec=codec)
    session = CaptureSession(cameras, sync, rate_hz=rate, on_frame_set=rec.write_frame_set,
                             on_status=on_status)
    try:
        stats = session.run(duration_s)
    except BaseException as e:
        rec.finish(session_error=f"{type(e).__name__}: {e}")  # a readable, closed folder
        raise
    rec.finish()
    rec.close()  # raises a recorder error (disk full) the session did not see
    return LiveResult(session=stats, recording=rec.stats(), folder=Path(out))
