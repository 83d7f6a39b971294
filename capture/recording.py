"""Crash-safe session recording: a folder of metadata + one append-only frame file per camera.

Layout of a recording folder::

    metadata.json          cameras (id, device, applied settings), rate, sync config,
                           calibration reference, codec; rewritten (atomically) at close
    cam00.frames, ...      per camera, in rig order ([camera-order])
    detections.csv         optional 2D detections (capture.detections CSV)

A ``.frames`` file is an 8-byte magic ``OMCFRM01`` followed by records::

    u32 magic 0x4D524652 | u32 payload_len | header (struct _HDR) | payload | u32 crc32

``crc32`` (zlib) covers header and payload. The payload is the image compressed
losslessly: codec 1 = deflate level 1 with the RLE strategy (fast on dark mocap frames,
readable with plain ``zlib.decompress``), codec 0 = raw little-endian pixels. Records are
written by one thread per camera and flushed to the kernel after each record (so ``kill -9``
loses only frames still queued), and fsynced every ``fsync_interval_s`` (power loss loses
at most that). A reader stops at the first incomplete or corrupt record at the tail.

A full disk (ENOSPC) truncates the file back to its last complete record, raises
``DiskFullError`` naming the file, and the recording is closed with all earlier frames
readable. Conventions: docs/conventions.md [pixels], [time], [camera-order].
"""
from __future__ import annotations

import errno
import json
import os
import queue
import struct
import threading
import time
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .detections import Detections2D, write_detections_csv
from .errors import DiskFullError, RecordingError
from .frame import Frame, TimestampSource

__all__ = ["Recorder", "RecordedCamera", "FILE_MAGIC", "CODEC_RAW", "CODEC_ZLIB_RLE",
           "encode_record", "frames_file_name"]

FILE_MAGIC = b"OMCFRM01"
REC_MAGIC = 0x4D524652
CODEC_RAW, CODEC_ZLIB_RLE = 0, 1
FORMAT_VERSION = 1
# frame_index, pulse_index, epoch, set_host_ns, sequence, timestamp_ns, source, exposure_us,
# gain, height, width, bits, codec
_HDR = struct.Struct("<qqHqqqBffHHBB")
_SOURCES = list(TimestampSource)


def frames_file_name(i: int) -> str:
    return f"cam{i:02d}.frames"


def _compress(img: np.ndarray, codec: int) -> bytes:
    raw = np.ascontiguousarray(img, dtype=img.dtype.newbyteorder("<")).tobytes()
    if codec == CODEC_RAW:
        return raw
    c = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)
    return c.compress(raw) + c.flush()


def encode_record(frame: Frame, *, frame_index: int, pulse_index: int = -1, epoch: int = 0,
                  set_host_ns: float = float("nan"), codec: int = CODEC_ZLIB_RLE) -> bytes:
    """One framed record (see module docstring)."""
    img = frame.image
    h, w = img.shape
    set_ns = int(set_host_ns) if np.isfinite(set_host_ns) else -1
    hdr = _HDR.pack(int(frame_index), int(pulse_index), int(epoch) & 0xFFFF, set_ns,
                    frame.sequence, frame.timestamp_ns, _SOURCES.index(frame.timestamp_source),
                    frame.exposure_us, frame.gain, h, w, 8 * img.dtype.itemsize, codec)
    payload = _compress(img, codec)
    crc = zlib.crc32(payload, zlib.crc32(hdr))
    return struct.pack("<II", REC_MAGIC, len(payload)) + hdr + payload + struct.pack("<I", crc)


@dataclass(frozen=True, kw_only=True)
class RecordedCamera:
    """What the metadata says about one camera."""

    camera_id: str
    device: str = ""
    settings: dict | None = None   # CameraSettings.to_dict() of the applied settings


class _Writer:
    """One camera's append-only file, written by its own thread from a bounded queue."""

    def __init__(self, path: Path, codec: int, qsize: int, fsync_interval_s: float,
                 file_factory: Callable, on_error: Callable):
        self.path = path
        self.codec = codec
        self.fsync_interval_s = fsync_interval_s
        self.q: queue.Queue = queue.Queue(maxsize=qsize)
        self.f = file_factory(path)
        self.f.write(FILE_MAGIC)
        self.f.flush()
        self.good_end = len(FILE_MAGIC)
        self.n_records = 0
        self.bytes_raw = 0
        self.bytes_written = 0
        self.on_error = on_error
        self._last_sync = time.monotonic()
        self.thread = threading.Thread(target=self._loop, daemon=True, name=f"rec {path.name}")
        self.thread.start()

    def _sync(self):
        self.f.flush()
        os.fsync(self.f.fileno())
        self._last_sync = time.monotonic()

    def _loop(self):
        try:
            while True:
                try:
                    item = self.q.get(timeout=self.fsync_interval_s)
                except queue.Empty:
                    item = ()
                if item is None:
                    self._sync()
                    return
                if item:
                    frame, kw = item
                    rec = encode_record(frame, codec=self.codec, **kw)
                    self.f.write(rec)
                    self.f.flush()   # in the kernel: survives kill -9
                    self.good_end += len(rec)
                    self.n_records += 1
                    self.bytes_raw += frame.image.nbytes
                    self.bytes_written += len(rec)
                if time.monotonic() - self._last_sync >= self.fsync_interval_s:
                    self._sync()
        except OSError as e:
            self._recover(e)

    def _recover(self, e: OSError):
        try:
            self.f.truncate(self.good_end)   # drop a partial record
            self.f.flush()
        except (OSError, ValueError):
            pass
        if e.errno == errno.ENOSPC:
            err = DiskFullError(str(self.path), f"disk full after {self.n_records} frames "
                                                f"({self.good_end} bytes); recording closed")
        else:
            err = RecordingError(str(self.path), f"write failed: {e}")
        self.on_error(err)
        while True:  # unblock producers
            try:
                self.q.get_nowait()
            except queue.Empty:
                break

    def close(self, timeout: float = 30.0):
        if self.thread.is_alive():
            while self.thread.is_alive():
                try:
                    self.q.put(None, timeout=0.1)
                    break
                except queue.Full:
                    continue
            self.thread.join(timeout)
        try:
            self.f.close()
        except OSError:
            pass


class Recorder:
    """Write a recording folder incrementally.

    Args:
        folder: created (must not hold a recording already).
        cameras: cameras in rig order.
        rate_hz: frame-set rate.
        sync_config: dict describing the sync box configuration (or None).
        calibration: path of the calibration file this recording belongs to (or None).
        codec: ``CODEC_ZLIB_RLE`` (default) or ``CODEC_RAW``.
        queue_frames: per-camera queue; a full queue blocks the producer (back-pressure).
        fsync_interval_s: at most this much is lost on power failure.
        file_factory: ``path -> binary file`` (tests inject a disk that fills up).
    """

    def __init__(self, folder, cameras: Sequence[RecordedCamera], *, rate_hz: float,
                 sync_config: dict | None = None, calibration: str | None = None,
                 codec: int = CODEC_ZLIB_RLE, queue_frames: int = 32,
                 fsync_interval_s: float = 0.5, file_factory: Callable | None = None,
                 extra: dict | None = None):
        self.folder = Path(folder)
        if not cameras:
            raise ValueError("cameras is empty")
        if codec not in (CODEC_RAW, CODEC_ZLIB_RLE):
            raise ValueError(f"codec={codec}, expected CODEC_RAW or CODEC_ZLIB_RLE")
        if (self.folder / "metadata.json").exists():
            raise ValueError(f"{self.folder} already holds a recording")
        self.folder.mkdir(parents=True, exist_ok=True)
        self.cameras = list(cameras)
        self.rate_hz = float(rate_hz)
        self.error: RecordingError | None = None
        self._closed = False
        self._t0 = time.time()
        self._meta = {
            "format": "openmocap-recording", "version": FORMAT_VERSION,
            "created_unix_s": self._t0, "rate_hz": self.rate_hz,
            "cameras": [{"id": c.camera_id, "device": c.device, "settings": c.settings,
                         "file": frames_file_name(i)} for i, c in enumerate(self.cameras)],
            "sync": sync_config, "calibration": calibration,
            "codec": {CODEC_RAW: "raw", CODEC_ZLIB_RLE: "zlib-rle"}[codec],
            "complete": False, "frame_sets": None, "frames_per_camera": None,
            "detections": None, "error": None, **(extra or {}),
        }
        self._write_metadata()
        factory = file_factory or (lambda p: open(p, "xb"))
        self._writers = [_Writer(self.folder / frames_file_name(i), codec, queue_frames,
                                 fsync_interval_s, factory, self._on_error)
                         for i in range(len(self.cameras))]
        self.n_frame_sets = 0

    def _on_error(self, err: RecordingError):
        if self.error is None:
            self.error = err

    def _write_metadata(self):
        tmp = self.folder / "metadata.json.tmp"
        tmp.write_text(json.dumps(self._meta, indent=2))
        with open(tmp, "rb") as f:
            os.fsync(f.fileno())
        os.replace(tmp, self.folder / "metadata.json")

    def _raise_if_failed(self):
        if self.error is not None:
            self._shutdown()
            raise self.error

    def write_frame(self, camera_index: int, frame: Frame, *, frame_index: int,
                    pulse_index: int = -1, epoch: int = 0,
                    set_host_ns: float = float("nan")) -> None:
        """Queue one frame (blocks while the camera's queue is full)."""
        self._raise_if_failed()
        if self._closed:
            raise RecordingError(str(self.folder), "recording is closed")
        w = self._writers[camera_index]
        item = (frame, dict(frame_index=frame_index, pulse_index=pulse_index, epoch=epoch,
                            set_host_ns=set_host_ns))
        while True:
            try:
                w.q.put(item, timeout=0.1)
                return
            except queue.Full:
                self._raise_if_failed()

    def write_frame_set(self, fs) -> None:
        """Queue every frame of a ``capture.session.FrameSet`` (usable as ``on_frame_set``)."""
        if len(fs.frames) != len(self._writers):
            raise ValueError(f"frame set has {len(fs.frames)} cameras, recording has "
                             f"{len(self._writers)}")
        for i, f in enumerate(fs.frames):
            if f is not None:
                self.write_frame(i, f, frame_index=fs.index, pulse_index=fs.pulse_index,
                                 epoch=fs.epoch, set_host_ns=fs.host_ns)
        self.n_frame_sets += 1

    def write_detections(self, det: Detections2D) -> Path:
        names = tuple(c.camera_id for c in self.cameras)
        if det.camera_names != names:
            raise ValueError(f"detections cameras {det.camera_names} != recording {names}")
        p = write_detections_csv(det, self.folder / "detections.csv")
        self._meta["detections"] = p.name
        return p

    def stats(self) -> dict:
        raw = sum(w.bytes_raw for w in self._writers)
        out = sum(w.bytes_written for w in self._writers)
        n = sum(w.n_records for w in self._writers)
        return {"frames": n, "bytes_raw": raw, "bytes_written": out,
                "bytes_per_frame": out / n if n else float("nan"),
                "compression_ratio": raw / out if out else float("nan"),
                "queued": sum(w.q.qsize() for w in self._writers)}

    def _shutdown(self):
        if self._closed:
            return
        self._closed = True
        for w in self._writers:
            w.close()
        self._meta.update(complete=self.error is None, frame_sets=self.n_frame_sets,
                          frames_per_camera=[w.n_records for w in self._writers],
                          error=None if self.error is None else str(self.error),
                          closed_unix_s=time.time())
        try:
            self._write_metadata()
        except OSError:
            pass  # disk full: the metadata written at open still describes the folder

    def close(self) -> None:
        """Flush and fsync everything, finalise metadata; raises the writer error if any."""
        self._shutdown()
        if self.error is not None:
            raise self.error

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._shutdown()
        if self.error is not None and exc[0] is None:
            raise self.error
