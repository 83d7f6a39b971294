"""The ``Camera`` protocol every capture device (V4L2, OpenCV, simulated, replayed) follows.

Conventions: docs/conventions.md [units], [time], [pixels].
"""
from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

from .frame import Frame

__all__ = ["Camera", "CameraSettings", "PixelFormat", "TriggerMode"]


class PixelFormat(enum.Enum):
    """Sensor pixel formats we accept; all become (H, W) images ([pixels])."""

    GREY = "GREY"   # 8-bit luminance
    Y10 = "Y10 "    # 10-bit in 16-bit little-endian words
    Y16 = "Y16 "    # 16-bit luminance
    YUYV = "YUYV"   # 4:2:2, luminance taken
    MJPG = "MJPG"   # motion JPEG, decoded to grey


class TriggerMode(enum.Enum):
    FREE_RUN = "free_run"
    EXTERNAL = "external"   # exposure started by the sync box line (FSIN / trigger input)


@dataclass(frozen=True, kw_only=True)
class CameraSettings:
    """Requested or applied camera settings. ``None`` means 'leave as is' when requesting.

    Attributes:
        width, height: image size in px.
        pixel_format: sensor format.
        rate_hz: frame rate (free-run) or expected trigger rate.
        exposure_us: exposure time in microseconds.
        gain: analogue gain in driver units.
        trigger: free-run or external trigger.
    """

    width: int | None = None
    height: int | None = None
    pixel_format: PixelFormat | None = None
    rate_hz: float | None = None
    exposure_us: float | None = None
    gain: float | None = None
    trigger: TriggerMode | None = None

    def __post_init__(self):
        for name in ("width", "height"):
            v = getattr(self, name)
            if v is not None and int(v) <= 0:
                raise ValueError(f"{name}={v}, expected > 0")
        if self.rate_hz is not None and not self.rate_hz > 0:
            raise ValueError(f"rate_hz={self.rate_hz}, expected > 0")
        if self.exposure_us is not None and not self.exposure_us > 0:
            raise ValueError(f"exposure_us={self.exposure_us}, expected > 0")
        if (self.exposure_us is not None and self.rate_hz is not None
                and self.exposure_us >= 1e6 / self.rate_hz):
            raise ValueError(f"exposure_us={self.exposure_us:g} does not fit in a frame period "
                             f"of {1e6 / self.rate_hz:g} us at rate_hz={self.rate_hz:g}")
        if self.gain is not None and not self.gain >= 0:
            raise ValueError(f"gain={self.gain}, expected >= 0")
        if self.pixel_format is not None and not isinstance(self.pixel_format, PixelFormat):
            object.__setattr__(self, "pixel_format", PixelFormat(self.pixel_format))
        if self.trigger is not None and not isinstance(self.trigger, TriggerMode):
            object.__setattr__(self, "trigger", TriggerMode(self.trigger))

    def to_dict(self) -> dict:
        return {
            "width": self.width, "height": self.height,
            "pixel_format": None if self.pixel_format is None else self.pixel_format.value,
            "rate_hz": self.rate_hz, "exposure_us": self.exposure_us, "gain": self.gain,
            "trigger": None if self.trigger is None else self.trigger.value,
        }

    @classmethod
    def from_dict(cls, d: dict) -> "CameraSettings":
        return cls(**{k: d.get(k) for k in ("width", "height", "pixel_format", "rate_hz",
                                            "exposure_us", "gain", "trigger")})


@runtime_checkable
class Camera(Protocol):
    """A frame source.

    ``configure`` returns the settings the device actually applied (read back, never the
    request echoed); ``settings`` gives them again later. ``read(timeout)`` returns the next ``Frame`` or ``None`` when none
    arrived within ``timeout`` seconds; it never blocks forever, and raises
    ``CameraDisconnected`` once the device is gone. ``fileno()`` is a handle that becomes
    readable (``select``/``poll``) when a frame is waiting.
    """

    @property
    def camera_id(self) -> str: ...

    @property
    def settings(self) -> CameraSettings:
        """The settings in effect (as read back from the device), recorded as metadata."""
        ...

    def configure(self, settings: CameraSettings) -> CameraSettings: ...

    def start(self) -> None: ...

    def stop(self) -> None: ...

    def read(self, timeout: float) -> Frame | None: ...

    def fileno(self) -> int: ...

    def close(self) -> None: ...
