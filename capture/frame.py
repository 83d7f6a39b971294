"""One captured image with where and when it came from.

Conventions: docs/conventions.md [pixels] (images (H, W) uint8/uint16), [time] (host
``time.monotonic_ns()`` nanoseconds), [units] (``exposure_us``).
"""
from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

__all__ = ["Frame", "TimestampSource"]


class TimestampSource(enum.Enum):
    """Which event ``Frame.timestamp_ns`` marks, and who measured it."""

    KERNEL_START_OF_EXPOSURE = "kernel_start_of_exposure"  # V4L2_BUF_FLAG_TSTAMP_SRC_SOE
    KERNEL_END_OF_FRAME = "kernel_end_of_frame"            # V4L2_BUF_FLAG_TSTAMP_SRC_EOF
    HOST_DEQUEUE = "host_dequeue"                          # user space saw the buffer
    SYNC_PULSE = "sync_pulse"                              # the sync box pulse (clock model)


@dataclass(frozen=True, kw_only=True)
class Frame:
    """A single image from one camera.

    Attributes:
        image: (H, W) uint8 or uint16 array (10/12-bit data right-aligned), read-only.
        camera_id: stable camera id ([camera-order]).
        sequence: driver frame counter; a gap of k means k frames were dropped.
        timestamp_ns: capture time on the host monotonic clock ([time]).
        timestamp_source: the event that time marks.
        exposure_us: exposure time actually applied, in microseconds.
        gain: analogue gain actually applied (driver units; 1.0 = unity when known).
    """

    image: np.ndarray
    camera_id: str
    sequence: int
    timestamp_ns: int
    timestamp_source: TimestampSource
    exposure_us: float
    gain: float

    def __post_init__(self):
        img = np.asarray(self.image)
        if img.ndim != 2:
            raise ValueError(f"image.shape={img.shape}, expected (H, W)")
        if img.dtype not in (np.uint8, np.uint16):
            raise TypeError(f"image.dtype={img.dtype}, expected uint8 or uint16")
        if not isinstance(self.timestamp_source, TimestampSource):
            raise TypeError(f"timestamp_source={self.timestamp_source!r}, expected TimestampSource")
        if int(self.sequence) < 0:
            raise ValueError(f"sequence={self.sequence}, expected >= 0")
        if not self.exposure_us >= 0:
            raise ValueError(f"exposure_us={self.exposure_us}, expected >= 0")
        if img.flags.writeable:
            img = img.view()
            img.setflags(write=False)
        object.__setattr__(self, "image", img)
        object.__setattr__(self, "camera_id", str(self.camera_id))
        object.__setattr__(self, "sequence", int(self.sequence))
        object.__setattr__(self, "timestamp_ns", int(self.timestamp_ns))
        object.__setattr__(self, "exposure_us", float(self.exposure_us))
        object.__setattr__(self, "gain", float(self.gain))

    @property
    def shape(self) -> tuple[int, int]:
        return tuple(self.image.shape)  # type: ignore[return-value]
