"""Crash-safe session recording: a folder of metadata + one append-only frame file per camera.

Layout of a recording folder::

    metadata.json          cameras (id, device, applied settings), rate, sync config,
                           calibration reference, codec; rewritten (atomically) at close
    cam00.frames, ...      per camera, in rig order ([camera-order])
    detections.csv         optional 2D detections (capture.detections CSV)

A ``.frames`` file is an 8-byte magic ``OMCFRM01`` followed by records::

    u32 magic 0x4D524652 | u32 payload_len | header (struct _HDR) | payload | u32 crc32

``crc32`` (zlib) covers header and payload. The payload is the image, lossless, in
one of three codecs chosen per record: 0 = raw little-endian pixels; 1 = deflate level 1
with the RLE strategy (plain ``zlib.decompress`` reads it); 2 = sparse blocks: the pixel
bytes cut into 64-byte blocks, a bitmap (``np.packbits``) of the non-zero blocks, then those
blocks deflated as in codec 1 (payload ``u32 block, u32 n_blocks, u32 n_nonzero, bitmap,
deflate``). ``CODEC_AUTO`` picks 2 for mostly-black frames, else 1, and writes 0 while the
compression cost exceeds the writer's share of the CPUs at the recording rate, or while its
queue is more than half full -- unless, with a full queue, compressing fits the CPU budget,
at least halves the bytes and saves more write time (measured write + fsync time per byte)
than it costs, i.e. the disk is the bottleneck: a slow CPU costs compression ratio before
frames, a slow disk keeps the compression. Records are
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

from .atomic import write_text_atomic
from .detections import Detections2D, write_detections_csv
from .errors import DiskFullError, RecordingError
from .frame import Frame, TimestampSource

__all__ = ["Recorder", "RecordedCamera", "FILE_MAGIC", "CODEC_RAW", "CODEC_ZLIB_RLE",
           "CODEC_SPARSE", "CODEC_AUTO", "encode_record", "decode_payload", "frames_file_name"]

FILE_MAGIC = b"OMCFRM01"
REC_MAGIC = 0x4D524652
CODEC_RAW, CODEC_ZLIB_RLE, CODEC_SPARSE = 0, 1, 2
CODEC_AUTO = -1
_BLOCK = 64
_SPARSE_MAX_FILL = 0.5   # auto: sparse coding when at most this fraction of blocks is non-zero
FORMAT_VERSION = 1
# frame_index, pulse_index, epoch, set_host_ns, sequence, timestamp_ns, source, exposure_us,
# gain, height, width, bits, codec
_HDR = struct.Struct("<qqHqqqBffHHBB")
_SOURCES = list(TimestampSource)


def frames_file_name(i: int) -> str:
    return f"cam{i:02d}.frames"


def _deflate(b) -> bytes:
    c = zlib.compressobj(1, zlib.DEFLATED, 15, 9, zlib.Z_RLE)
    return c.compress(b) + c.flush()


def _compress(img: np.ndarray, codec: int) -> tuple[int, bytes]:
    """(codec used, payload); CODEC_AUTO resolves to sparse or deflate."""
    a = np.ascontiguousarray(img, dtype=img.dtype.newbyteorder("<"))
    if codec == CODEC_RAW:
        return CODEC_RAW, memoryview(a).cast("B")  # no copy: written straight from the image
    if codec == CODEC_ZLIB_RLE:
        return CODEC_ZLIB_RLE, _deflate(a)
    flat = a.reshape(-1).view(np.uint8)
    pad = (-flat.size) % _BLOCK
    if pad:
        flat = np.concatenate([flat, np.zeros(pad, np.uint8)])
    blocks = flat.reshape(-1, _BLOCK)
    nz = blocks.view(np.uint64).any(axis=1)
    n_nz = int(nz.sum())
    if codec == CODEC_AUTO and n_nz > _SPARSE_MAX_FILL * len(nz):
        return CODEC_ZLIB_RLE, _deflate(a)
    head = struct.pack("<III", _BLOCK, len(nz), n_nz)
    return CODEC_SPARSE, head + np.packbits(nz).tobytes() + _deflate(blocks[nz])


def decode_payload(payload: bytes, codec: int, shape: tuple[int, int], dtype) -> np.ndarray:
    """Inverse of the record codecs: an (H, W) image of ``dtype`` (native byte order)."""
    dt = np.dtype(dtype).newbyteorder("<")
    nbytes = int(np.prod(shape)) * dt.itemsize
    if codec == CODEC_RAW:
        data = payload
    elif codec == CODEC_ZLIB_RLE:
        data = zlib.decompress(payload)
    elif codec == CODEC_SPARSE:
        block, n_blocks, n_nz = struct.unpack_from("<III", payload)
        nb = (n_blocks + 7) // 8
        nz = np.unpackbits(np.frombuffer(payload, np.uint8, nb, 12))[:n_blocks].astype(bool)
        if int(nz.sum()) != n_nz:
            raise ValueError(f"sparse bitmap has {int(nz.sum())} blocks, header says {n_nz}")
        out = np.zeros((n_blocks, block), np.uint8)
        out[nz] = np.frombuffer(zlib.decompress(payload[12 + nb:]), np.uint8).reshape(-1, block)
        data = out.reshape(-1)[:nbytes].tobytes()
    else:
        raise ValueError(f"unknown codec {codec}")
    if len(data) != nbytes:
        raise ValueError(f"payload decodes to {len(data)} bytes, expected {nbytes}")
    return np.frombuffer(data, dtype=dt).reshape(shape).astype(np.dtype(dtype).newbyteorder("="))


def encode_record(frame: Frame, **kw) -> bytes:
    """One framed record as bytes (see module docstring)."""
    return b"".join(encode_record_parts(frame, **kw))


def encode_record_parts(frame: Frame, *, frame_index: int, pulse_index: int = -1, epoch: int = 0,
                  set_host_ns: float = float("nan"), codec: int = CODEC_AUTO) -> list[bytes]:
    """A record as [prefix + header, payload, crc] (written without joining copies)."""
    img = frame.image
    h, w = img.shape
    set_ns = int(set_host_ns) if np.isfinite(set_host_ns) else -1
    used, payload = _compress(img, codec)
    hdr = _HDR.pack(int(frame_index), int(pulse_index), int(epoch) & 0xFFFF, set_ns,
                    frame.sequence, frame.timestamp_ns, _SOURCES.index(frame.timestamp_source),
                    frame.exposure_us, frame.gain, h, w, 8 * img.dtype.itemsize, used)
    crc = zlib.crc32(payload, zlib.crc32(hdr))
    return [struct.pack("<II", REC_MAGIC, len(payload)) + hdr, payload, struct.pack("<I", crc)]


@dataclass(frozen=True, kw_only=True)
class RecordedCamera:
    """What the metadata says about one camera."""

    camera_id: str
    device: str = ""
    settings: dict | None = None   # CameraSettings.to_dict() of the applied settings


class _Writer:
    """One camera's append-only file, written by its own thread from a bounded queue."""

    _PROBE_MIN, _PROBE_MAX = 32, 1024

    def __init__(self, path: Path, codec: int, qsize: int, fsync_interval_s: float,
                 file_factory: Callable, on_error: Callable, budget_s: float = float("inf")):
        self.path = path
        self.codec = codec
        self.budget_s = budget_s      # CPU time per frame this writer may spend compressing
        self._cost_s = 0.0            # running mean compression time per frame
        self._frac = 1.0              # running mean compressed / raw size
        self._w_write = 0.0           # running mean write wall time per byte (s)
        self._w_sync = 0.0            # running mean fsync wall time per byte written (s)
        self._sync_bytes = 0
        self._n_since_probe = 0
        self._probe_every = self._PROBE_MIN
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

    def _compression_pays(self, nbytes: int) -> bool:
        """The writer is behind because of the disk, not the CPU: compressing fits the CPU
        budget, at least halves the bytes and saves more write time than it costs
        (wall-clock write times are noisy on a loaded host: a marginal saving does not
        count)."""
        saved_s = nbytes * (1.0 - self._frac) * (self._w_write + self._w_sync)
        return self._frac < 0.5 and 0 < self._cost_s <= min(self.budget_s, saved_s)

    def _choose_codec(self, nbytes: int = 0) -> int:
        """AUTO: compress while it fits the CPU budget and the queue keeps up, or while it
        saves more write time than it costs; else raw (lossless either way), re-probing
        the compression cost every 32..1024 frames."""
        if self.codec != CODEC_AUTO:
            return self.codec
        if self._cost_s == 0:
            return CODEC_AUTO   # the first frame measures what compression costs
        behind = self.q.qsize() > self.q.maxsize // 2
        over = self._cost_s > self.budget_s
        if (behind or over) and not self._compression_pays(nbytes):
            self._n_since_probe += 1
            if self._n_since_probe < self._probe_every or behind:
                return CODEC_RAW
            # probe again; each probe that is still over budget doubles the interval
            self._probe_every = min(2 * self._probe_every, self._PROBE_MAX) if over \
                else self._PROBE_MIN
        self._n_since_probe = 0
        return CODEC_AUTO

    def _sync(self):
        t0 = time.monotonic()
        self.f.flush()
        os.fsync(self.f.fileno())
        self._last_sync = time.monotonic()
        if self._sync_bytes:   # fsync time is part of the cost of each byte written
            w = (self._last_sync - t0) / self._sync_bytes
            self._w_sync = 0.5 * self._w_sync + 0.5 * w
            self._sync_bytes = 0

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
                    codec = self._choose_codec(frame.image.nbytes)
                    t0 = time.thread_time()
                    parts = encode_record_parts(frame, codec=codec, **kw)
                    n = sum(len(p) for p in parts)
                    if codec != CODEC_RAW:
                        dt = time.thread_time() - t0
                        frac = min(1.0, n / frame.image.nbytes)
                        first = self._cost_s == 0
                        self._cost_s = dt if first else 0.8 * self._cost_s + 0.2 * dt
                        self._frac = frac if first else 0.8 * self._frac + 0.2 * frac
                    tw = time.monotonic()
                    for p in parts:
                        self.f.write(p)
                    self.f.flush()   # in the kernel: survives kill -9
                    w = (time.monotonic() - tw) / n
                    self._w_write = 0.8 * self._w_write + 0.2 * w
                    self._sync_bytes += n
                    self.good_end += n
                    self.n_records += 1
                    self.bytes_raw += frame.image.nbytes
                    self.bytes_written += n
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
        codec: ``CODEC_AUTO`` (default), ``CODEC_SPARSE``, ``CODEC_ZLIB_RLE`` or ``CODEC_RAW``.
        queue_frames: per-camera queue; a full queue blocks the producer (back-pressure).
            Default: half a second of frames (2..32), so a crash loses at most that much
            of what is queued.
        fsync_interval_s: at most this much is lost on power failure.
        file_factory: ``path -> binary file`` (tests inject a disk that fills up).
    """

    def __init__(self, folder, cameras: Sequence[RecordedCamera], *, rate_hz: float,
                 sync_config: dict | None = None, calibration: str | None = None,
                 codec: int = CODEC_AUTO, queue_frames: int | None = None,
                 fsync_interval_s: float = 0.5, file_factory: Callable | None = None,
                 extra: dict | None = None):
        self.folder = Path(folder)
        if not cameras:
            raise ValueError("cameras is empty")
        if codec not in (CODEC_RAW, CODEC_ZLIB_RLE, CODEC_SPARSE, CODEC_AUTO):
            raise ValueError(f"codec={codec}, expected one of CODEC_AUTO, CODEC_SPARSE, "
                             f"CODEC_ZLIB_RLE, CODEC_RAW")
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
            "codec": {CODEC_RAW: "raw", CODEC_ZLIB_RLE: "zlib-rle", CODEC_SPARSE: "sparse",
                      CODEC_AUTO: "auto"}[codec],
            "complete": False, "frame_sets": None, "frames_per_camera": None,
            "detections": None, "error": None, **(extra or {}),
        }
        self._write_metadata()
        if queue_frames is None:
            queue_frames = int(min(32, max(2, round(0.5 * self.rate_hz))))
        if queue_frames < 1:
            raise ValueError(f"queue_frames={queue_frames}, expected >= 1")
        factory = file_factory or (lambda p: open(p, "xb"))
        # each writer may use its share of the CPUs (with margin) for compression
        budget = 0.7 * (os.cpu_count() or 1) / (self.rate_hz * len(self.cameras))
        self._writers = [_Writer(self.folder / frames_file_name(i), codec, queue_frames,
                                 fsync_interval_s, factory, self._on_error, budget)
                         for i in range(len(self.cameras))]
        self.n_frame_sets = 0

    def _on_error(self, err: RecordingError):
        if self.error is None:
            self.error = err

    def _write_metadata(self):
        write_text_atomic(self.folder / "metadata.json", json.dumps(self._meta, indent=2))

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

    def finish(self, session_error: str | None = None) -> None:
        """Close (flush, fsync, finalise metadata) without raising; see ``error``.
        ``session_error`` (why the session ended early, e.g. the sync box vanished) is
        stored in the metadata."""
        if session_error is not None and not self._closed:
            self._meta["session_error"] = str(session_error)
        self._shutdown()

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
