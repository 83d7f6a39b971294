"""Read recordings back: frames per camera, frame sets, and cameras that replay them.

``recording_frames(path)`` yields ``(frame_index, [image or None per camera])`` for offline
reprocessing (``mocap reconstruct`` / ``mocap calibrate`` take a recording folder);
``read_recording(path)`` yields ``FrameSet`` s; ``ReplayCamera`` follows the ``Camera``
protocol. Readers tolerate a torn tail (crash during a write): they stop at the first
incomplete or corrupt record and report it in ``FrameFileReader.truncated``.
Format: capture/recording.py. Conventions: docs/conventions.md [camera-order], [time].
"""
from __future__ import annotations

import dataclasses
import heapq
import json
import os
import struct
import time
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np

from .camera import CameraSettings
from .detections import Detections2D, read_detections_csv
from .errors import CameraDisconnected, RecordingError
from .frame import Frame, TimestampSource
from .recording import _HDR, FILE_MAGIC, REC_MAGIC, decode_payload
from .session import FrameSet

__all__ = ["RecordingMetadata", "RecordedFrame", "FrameFileReader", "is_recording",
           "load_metadata",
           "recording_frames", "read_recording", "read_recording_detections", "ReplayCamera",
           "ReplayClock", "replay_cameras"]

_SOURCES = list(TimestampSource)


@dataclass(frozen=True, kw_only=True)
class RecordingMetadata:
    path: Path
    camera_ids: tuple[str, ...]
    devices: tuple[str, ...]
    settings: tuple[CameraSettings | None, ...]
    files: tuple[str, ...]
    rate_hz: float
    sync: dict | None
    calibration: str | None
    complete: bool
    detections: str | None
    raw: dict

    @property
    def calibration_path(self) -> Path | None:
        """The calibration file, resolved against the folder when relative."""
        if not self.calibration:
            return None
        p = Path(self.calibration)
        return p if p.is_absolute() else self.path / p


@dataclass(frozen=True, kw_only=True)
class RecordedFrame:
    frame: Frame
    frame_index: int
    pulse_index: int
    epoch: int
    set_host_ns: float


def is_recording(path) -> bool:
    """True when ``path`` is a recording folder (CLIs accept folders or other inputs)."""
    p = Path(path)
    return p.is_dir() and (p / "metadata.json").is_file()


def load_metadata(path) -> RecordingMetadata:
    path = Path(path)
    mp = path / "metadata.json"
    if not mp.exists():
        raise FileNotFoundError(f"not a recording folder (no metadata.json): {path}")
    try:
        m = json.loads(mp.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise ValueError(f"{mp}: not a JSON metadata file ({e})") from e
    if not isinstance(m, dict) or m.get("format") != "openmocap-recording":
        fmt = m.get("format") if isinstance(m, dict) else None
        raise ValueError(f"{mp}: format={fmt!r}, expected 'openmocap-recording'")
    try:
        cams = m["cameras"]
        meta = RecordingMetadata(
            path=path, camera_ids=tuple(c["id"] for c in cams),
            devices=tuple(c.get("device", "") for c in cams),
            settings=tuple(None if not c.get("settings")
                           else CameraSettings.from_dict(c["settings"]) for c in cams),
            files=tuple(c["file"] for c in cams), rate_hz=float(m["rate_hz"]),
            sync=m.get("sync"), calibration=m.get("calibration"),
            complete=bool(m.get("complete")), detections=m.get("detections"), raw=m)
    except (KeyError, TypeError, AttributeError, ValueError) as e:
        raise ValueError(f"{mp}: malformed metadata ({type(e).__name__}: {e})") from e
    root = path.resolve()
    for f in meta.files:
        if root not in (path / f).resolve().parents:
            raise ValueError(f"{mp}: camera file {f!r} lies outside the recording folder")
    return meta


class FrameFileReader:
    """Iterate the records of one ``.frames`` file."""

    def __init__(self, path, camera_id: str):
        self.path = Path(path)
        self.camera_id = camera_id
        self.truncated = False
        self.n_read = 0

    def __iter__(self) -> Iterator[RecordedFrame]:
        with open(self.path, "rb") as f:
            if f.read(len(FILE_MAGIC)) != FILE_MAGIC:
                raise RecordingError(str(self.path), "not a frames file (bad magic)")
            pre = struct.Struct("<II")
            while True:
                head = f.read(pre.size)
                if not head:
                    return
                if len(head) < pre.size:
                    self.truncated = True
                    return
                magic, n = pre.unpack(head)
                if magic != REC_MAGIC:
                    self.truncated = True
                    return
                body = f.read(_HDR.size + n + 4)
                if len(body) < _HDR.size + n + 4:
                    self.truncated = True
                    return
                hdr, payload = body[:_HDR.size], body[_HDR.size:-4]
                (crc,) = struct.unpack("<I", body[-4:])
                if zlib.crc32(payload, zlib.crc32(hdr)) != crc:
                    self.truncated = True
                    return
                yield self._decode(hdr, payload)
                self.n_read += 1

    def _decode(self, hdr: bytes, payload: bytes) -> RecordedFrame:
        (fi, pi, ep, set_ns, seq, ts, src, exp, gain, h, w, bits, codec) = _HDR.unpack(hdr)
        try:
            img = decode_payload(payload, codec, (h, w), np.uint8 if bits == 8 else np.uint16)
        except (ValueError, zlib.error) as e:
            raise RecordingError(str(self.path), f"record {self.n_read}: {e}") from e
        fr = Frame(image=img, camera_id=self.camera_id, sequence=seq, timestamp_ns=ts,
                   timestamp_source=_SOURCES[src], exposure_us=exp, gain=gain)
        return RecordedFrame(frame=fr, frame_index=fi, pulse_index=pi, epoch=ep,
                             set_host_ns=float(set_ns) if set_ns >= 0 else float("nan"))


def _readers(meta: RecordingMetadata) -> list[FrameFileReader]:
    return [FrameFileReader(meta.path / f, cid) for f, cid in zip(meta.files, meta.camera_ids)]


def _merged(meta: RecordingMetadata) -> Iterator[tuple[int, list[RecordedFrame | None]]]:
    readers = _readers(meta)
    yield from _merge_readers(readers)
    for r in readers:       # a torn tail (a crash while writing) is kept up to its last record
        if r.truncated:
            warnings.warn(f"{r.path}: truncated after {r.n_read} frames (the recording was "
                          f"cut short; the frames before the cut are used)", stacklevel=2)


def _merge_readers(readers) -> Iterator[tuple[int, list[RecordedFrame | None]]]:
    its = [iter(r) for r in readers]
    heap = []
    for i, it in enumerate(its):
        rf = next(it, None)
        if rf is not None:
            heap.append((rf.frame_index, i, rf))
    heapq.heapify(heap)
    while heap:
        fi = heap[0][0]
        row: list[RecordedFrame | None] = [None] * len(its)
        while heap and heap[0][0] == fi:
            _, i, rf = heapq.heappop(heap)
            row[i] = rf
            nxt = next(its[i], None)
            if nxt is not None:
                heapq.heappush(heap, (nxt.frame_index, i, nxt))
        yield fi, row


def recording_frames(path) -> Iterator[tuple[int, list[np.ndarray | None]]]:
    """``(frame_index, [image (H, W) or None per camera])`` in frame order."""
    meta = load_metadata(path)
    for fi, row in _merged(meta):
        yield fi, [None if r is None else r.frame.image for r in row]


def read_recording(path) -> Iterator[FrameSet]:
    """The recorded frame sets, in order."""
    meta = load_metadata(path)
    for fi, row in _merged(meta):
        first = next(r for r in row if r is not None)
        yield FrameSet(index=fi, pulse_index=first.pulse_index, epoch=first.epoch,
                       host_ns=first.set_host_ns, camera_ids=meta.camera_ids,
                       frames=tuple(None if r is None else r.frame for r in row))


def read_recording_detections(path) -> Detections2D | None:
    meta = load_metadata(path)
    if not meta.detections:
        return None
    return read_detections_csv(meta.path / meta.detections, camera_names=meta.camera_ids,
                               rate_hz=meta.rate_hz)


class ReplayClock:
    """Shared time origin of the cameras of one replay: recorded time ``rec_t0_ns`` is
    played at the host time of the first ``start()`` of any of them."""

    def __init__(self, rec_t0_ns: int):
        self.rec_t0_ns = int(rec_t0_ns)
        self.wall_t0_ns: int | None = None

    def start(self) -> None:
        if self.wall_t0_ns is None:
            self.wall_t0_ns = time.monotonic_ns()

    def wall_of(self, rec_ns: int) -> int:
        return rec_ns - self.rec_t0_ns + self.wall_t0_ns


def replay_cameras(path, *, realtime: bool = True) -> list["ReplayCamera"]:
    """All cameras of a recording, in rig order, on one ``ReplayClock``: with
    ``realtime`` they deliver frames at their recorded pace with timestamps moved to the
    host clock of now, so a ``CaptureSession`` (no sync box, ``rate_hz`` of the
    recording) re-forms the frame sets as it would live. (Offline, ``read_recording``
    gives the recorded sets directly.)"""
    meta = load_metadata(path)
    firsts = []
    for f, cid in zip(meta.files, meta.camera_ids):
        rf = next(iter(FrameFileReader(meta.path / f, cid)), None)
        if rf is not None:
            firsts.append(rf.frame.timestamp_ns)
    if not firsts:
        raise RecordingError(str(meta.path), "recording holds no frames")
    clock = ReplayClock(min(firsts))
    return [ReplayCamera(path, i, realtime=realtime, clock=clock, rebase_time=realtime)
            for i in range(len(meta.camera_ids))]


class ReplayCamera:
    """A recorded camera played back through the ``Camera`` protocol.

    ``realtime=True`` paces frames by their recorded timestamps (relative to ``clock``,
    shared by the cameras of one replay; by default this camera's first frame);
    otherwise as fast as read. ``rebase_time`` moves the timestamps to the host clock of
    the replay (needs ``realtime``), as a live camera would stamp them. At the end of the
    recording ``read`` raises ``CameraDisconnected`` (the stream ended).
    """

    def __init__(self, path, camera: str | int, *, realtime: bool = False,
                 clock: ReplayClock | None = None, rebase_time: bool = False):
        if rebase_time and not realtime:
            raise ValueError("rebase_time=True needs realtime=True")
        self._clock = clock
        self.rebase_time = rebase_time
        self.meta = load_metadata(path)
        idx = camera if isinstance(camera, int) else self.meta.camera_ids.index(camera)
        self._idx = idx
        self._reader = FrameFileReader(self.meta.path / self.meta.files[idx],
                                       self.meta.camera_ids[idx])
        self._it: Iterator[RecordedFrame] | None = None
        self.realtime = realtime
        self._rfd, self._wfd = os.pipe()
        os.write(self._wfd, b"\x01")  # readable while frames remain
        self._next: RecordedFrame | None = None
        self._done = False

    @property
    def camera_id(self) -> str:
        return self.meta.camera_ids[self._idx]

    @property
    def settings(self) -> CameraSettings:
        """The settings recorded for this camera."""
        return self.meta.settings[self._idx] or CameraSettings()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Recorded settings are fixed; returns them whatever was asked."""
        return self.settings

    def start(self) -> None:
        if self._it is None:
            self._it = iter(self._reader)
        if self.realtime and self._clock is not None:
            self._clock.start()

    def stop(self) -> None:
        pass

    def read(self, timeout: float) -> Frame | None:
        if self._it is None:
            time.sleep(max(0.0, timeout))
            return None
        if self._done:
            raise CameraDisconnected(f"replay:{self.camera_id}", "end of recording")
        rf, self._next = (self._next, None) if self._next is not None else \
            (next(self._it, None), None)
        if rf is None:
            self._done = True
            try:
                os.read(self._rfd, 1)
            except OSError:
                pass
            raise CameraDisconnected(f"replay:{self.camera_id}", "end of recording")
        if self.realtime:
            now = time.monotonic_ns()
            if self._clock is None:
                self._clock = ReplayClock(rf.frame.timestamp_ns)
                self._clock.start()
            wait = (self._clock.wall_of(rf.frame.timestamp_ns) - now) * 1e-9
            if wait > timeout:
                time.sleep(max(0.0, timeout))
                self._next = rf  # not due yet: keep it for the next call
                return None
            if wait > 0:
                time.sleep(wait)
            if self.rebase_time:
                return dataclasses.replace(
                    rf.frame, timestamp_ns=self._clock.wall_of(rf.frame.timestamp_ns))
        return rf.frame

    def fileno(self) -> int:
        return self._rfd

    def close(self) -> None:
        for fd in (self._rfd, self._wfd):
            try:
                os.close(fd)
            except OSError:
                pass
