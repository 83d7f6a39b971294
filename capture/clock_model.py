"""Device-to-host clock model of the sync box: ``t_host = gain * t_device + offset``.

Each time query gives ``(host_send_ns, device_ticks, host_recv_ns)``: the device read its
counter somewhere inside ``[send, recv]``, so the round-trip midpoint is an estimate of the
host time of the tick with error at most ``rtt / 2``. The model keeps a sliding window of
samples, fits only the shortest round trips (the ones queueing did not delay) by weighted
least squares (weight 1/(rtt/2)^2) with a prior pulling the gain to 1 while the samples span
too little time to measure drift, rejects residual outliers (MAD), and detects a device reset when the counter runs backwards.

Conventions: docs/conventions.md [time] (host ``time.monotonic_ns()``).
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

__all__ = ["ClockSample", "ClockFit", "ClockModel"]


@dataclass(frozen=True, kw_only=True)
class ClockSample:
    host_send_ns: int
    device_ticks: int
    host_recv_ns: int

    def __post_init__(self):
        if self.host_recv_ns < self.host_send_ns:
            raise ValueError(f"host_recv_ns={self.host_recv_ns} before "
                             f"host_send_ns={self.host_send_ns}")

    @property
    def rtt_ns(self) -> int:
        return self.host_recv_ns - self.host_send_ns

    @property
    def host_mid_ns(self) -> float:
        return self.host_send_ns + 0.5 * self.rtt_ns


@dataclass(frozen=True, kw_only=True)
class ClockFit:
    """A fitted map; ``ok=False`` with a ``reason`` when there is not enough data.

    ``gain`` is dimensionless (host ns per nominal device ns, i.e. 1 + drift); ``offset`` is
    applied around reference points to keep precision with 64-bit counters.
    ``bound_ns`` is the largest half round trip among the samples used (the worst-case error
    of any one of them).
    """

    ok: bool
    reason: str = ""
    gain: float = float("nan")
    device_ref_ticks: int = 0
    host_ref_ns: float = float("nan")
    tick_hz: float = 1e6
    n_used: int = 0
    bound_ns: float = float("nan")
    residual_rms_ns: float = float("nan")

    def __bool__(self) -> bool:
        return self.ok

    def to_host_ns(self, device_ticks) -> np.ndarray | float:
        """Host monotonic time (ns, float) of device counter value(s)."""
        if not self.ok:
            raise ValueError(f"clock fit is not usable: {self.reason}")
        d = (np.asarray(device_ticks, dtype=np.int64) - self.device_ref_ticks).astype(np.float64)
        return self.host_ref_ns + self.gain * d * (1e9 / self.tick_hz)

    @property
    def drift_ppm(self) -> float:
        return (self.gain - 1.0) * 1e6


class ClockModel:
    """Sliding-window, min-round-trip, outlier-robust linear clock fit.

    Args:
        tick_hz: nominal device counter rate.
        window: number of most recent samples kept.
        keep_fraction: fraction of the window with the shortest round trips used for the fit.
        min_samples: samples needed before a fit is ``ok``.
        prior_ppm: spread of oscillator errors expected (crystals: tens of ppm); the gain
            is pulled towards 1 with this standard deviation.
    """

    def __init__(self, tick_hz: float = 1e6, *, window: int = 64, keep_fraction: float = 0.5,
                 min_samples: int = 4, prior_ppm: float = 200.0):
        if not tick_hz > 0:
            raise ValueError(f"tick_hz={tick_hz}, expected > 0")
        if window < 2:
            raise ValueError(f"window={window}, expected >= 2")
        if not 0 < keep_fraction <= 1:
            raise ValueError(f"keep_fraction={keep_fraction}, expected in (0, 1]")
        self.tick_hz = float(tick_hz)
        self.min_samples = int(min_samples)
        self.keep_fraction = float(keep_fraction)
        if not prior_ppm > 0:
            raise ValueError(f"prior_ppm={prior_ppm}, expected > 0")
        self.prior_ppm = float(prior_ppm)
        self._samples: deque[ClockSample] = deque(maxlen=int(window))
        self.resets = 0
        self._fit = ClockFit(ok=False, reason="no samples", tick_hz=self.tick_hz)

    def reset(self, tick_hz: float | None = None) -> None:
        """Forget all samples (after a device reset / reboot)."""
        if tick_hz is not None:
            self.tick_hz = float(tick_hz)
        self._samples.clear()
        self._fit = ClockFit(ok=False, reason="reset", tick_hz=self.tick_hz)

    def add(self, sample: ClockSample) -> bool:
        """Add a sample; returns True when it revealed a device reset (counter went back)."""
        reset = bool(self._samples) and sample.device_ticks < self._samples[-1].device_ticks
        if reset:
            self.resets += 1
            self.reset()
        self._samples.append(sample)
        self._fit = self._refit()
        return reset

    @property
    def fit(self) -> ClockFit:
        return self._fit

    @property
    def n_samples(self) -> int:
        return len(self._samples)

    def _solve(self, x, y, w) -> tuple[float, float]:
        """Weighted least squares of y = gain * x + off with a Gaussian prior on the gain
        around 1 (std ``prior_ppm``): a burst of queries spanning milliseconds cannot
        fix the drift, so the nominal rate holds until the samples span enough time."""
        lam = 1.0 / (self.prior_ppm * 1e-6) ** 2
        sw = w.sum()
        xm, ym = (w * x).sum() / sw, (w * y).sum() / sw
        dx, dy = x - xm, y - ym
        gain = ((w * dx * dy).sum() + lam) / ((w * dx * dx).sum() + lam)
        return float(gain), float(ym - gain * xm)

    def _refit(self) -> ClockFit:
        s = list(self._samples)
        if len(s) < self.min_samples:
            return ClockFit(ok=False, reason=f"{len(s)} samples, need {self.min_samples}",
                            tick_hz=self.tick_hz)
        rtt = np.array([x.rtt_ns for x in s], dtype=np.float64)
        k = max(self.min_samples, int(np.ceil(self.keep_fraction * len(s))))
        idx = np.argsort(rtt, kind="stable")[:k]
        dev = np.array([s[i].device_ticks for i in idx], dtype=np.int64)
        host = np.array([s[i].host_mid_ns for i in idx], dtype=np.float64)
        dev_ref = int(dev.min())
        host_ref = float(host.min())
        x = (dev - dev_ref).astype(np.float64) * (1e9 / self.tick_hz)
        y = host - host_ref
        sigma = np.maximum(0.5 * rtt[idx], 1e3)   # each sample is within rtt/2 (floor 1 us)
        w = 1.0 / sigma ** 2
        keep = np.ones(len(x), bool)
        for _ in range(3):
            gain, off = self._solve(x[keep], y[keep], w[keep])
            r = y - (gain * x + off)
            mad = np.median(np.abs(r[keep] - np.median(r[keep]))) * 1.4826
            new = np.abs(r) <= max(4.0 * mad, 0.5 * rtt[idx].min() + 1e3)
            if new.sum() < self.min_samples or np.array_equal(new, keep):
                break
            keep = new
        gain, off = self._solve(x[keep], y[keep], w[keep])
        r = y[keep] - (gain * x[keep] + off)
        return ClockFit(ok=True, gain=float(gain), device_ref_ticks=dev_ref,
                        host_ref_ns=host_ref + float(off), tick_hz=self.tick_hz,
                        n_used=int(keep.sum()), bound_ns=float(0.5 * rtt[idx][keep].max()),
                        residual_rms_ns=float(np.sqrt(np.mean(r ** 2))))
