"""Sub-pixel marker blob detection in IR frames.

Threshold -> connected components (``cv2.connectedComponentsWithStats``) -> per component, a
background-subtracted intensity-weighted centroid over a small window around it (background =
median of the window's border ring). Pixel convention: docs/conventions.md [pixels] (centre of
the top-left pixel is (0, 0), x = column, y = row); images as [pixels] (uint8 / uint16,
right-aligned bit depth).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import erf

from capture.detections import Detections2D

__all__ = ["Refine", "ThresholdMode", "BlobConfig", "Blobs", "auto_threshold", "detect_blobs",
           "detect_frames", "detections_from_frames"]

BIT_DEPTHS = (8, 10, 12, 16)
MAD_TO_SIGMA = 1.4826


class Refine(str, Enum):
    """Centroid method: ``MOMENTS`` (background-subtracted intensity-weighted centroid) or
    ``GAUSSIAN`` (moments, then least-squares fit of a pixel-integrated 2D Gaussian + constant
    background over the same window; ~2x lower noise on Gaussian-like blobs, ~10x slower)."""

    MOMENTS = "moments"
    GAUSSIAN = "gaussian"


class ThresholdMode(str, Enum):
    """``FIXED``: ``BlobConfig.threshold`` is a grey level; ``AUTO``: median + k * MAD."""

    FIXED = "fixed"
    AUTO = "auto"


@dataclass(frozen=True, kw_only=True)
class BlobConfig:
    """Blob detection settings.

    Attributes:
        threshold: grey level (FIXED mode) in the image's units, or the string ``"auto"``.
        bit_depth: 8, 10, 12 or 16 ([pixels]).
        auto_k: AUTO mode threshold = median + auto_k * 1.4826 * MAD of the image.
        auto_min_fraction: AUTO threshold is at least this fraction of full scale above the
            median (a noise-free image has MAD = 0).
        min_area_px, max_area_px: accepted component area (thresholded pixels).
        min_roundness: minor/major axis ratio (sqrt of second-moment eigenvalue ratio), 0..1.
        window_pad_px: pixels added around each component's bounding box for the centroid.
        mask: optional (H, W) bool, True = ignore the pixel (static reflections).
        refine: ``Refine.MOMENTS`` (default) or ``Refine.GAUSSIAN``.
    """

    threshold: float | str = "auto"
    bit_depth: int = 8
    auto_k: float = 8.0
    auto_min_fraction: float = 0.05
    min_area_px: int = 2
    max_area_px: int = 400
    min_roundness: float = 0.5
    window_pad_px: int = 2
    mask: np.ndarray | None = field(default=None, repr=False)
    refine: Refine = Refine.MOMENTS

    def __post_init__(self):
        object.__setattr__(self, "refine", Refine(self.refine))
        if self.bit_depth not in BIT_DEPTHS:
            raise ValueError(f"bit_depth={self.bit_depth!r}, expected one of {BIT_DEPTHS}")
        if isinstance(self.threshold, str):
            if self.threshold != ThresholdMode.AUTO.value:
                raise ValueError(f"threshold={self.threshold!r}, expected a number or 'auto'")
        elif not 0 <= float(self.threshold) < 2 ** self.bit_depth:
            raise ValueError(f"threshold={self.threshold!r} outside 0..{2 ** self.bit_depth - 1}")
        if not 0 < self.min_area_px <= self.max_area_px:
            raise ValueError(f"min_area_px={self.min_area_px}, max_area_px={self.max_area_px}")
        if not 0 <= self.min_roundness <= 1:
            raise ValueError(f"min_roundness={self.min_roundness}, expected 0..1")
        if self.window_pad_px < 1:
            raise ValueError(f"window_pad_px={self.window_pad_px}, expected >= 1")
        if self.mask is not None:
            m = np.asarray(self.mask)
            if m.ndim != 2:
                raise ValueError(f"mask.shape={m.shape}, expected (H, W)")

    @property
    def mode(self) -> ThresholdMode:
        return ThresholdMode.AUTO if isinstance(self.threshold, str) else ThresholdMode.FIXED


@dataclass(frozen=True, kw_only=True)
class Blobs:
    """Blobs of one image (N of them).

    Attributes:
        xy: (N, 2) float64 sub-pixel centres, px [pixels].
        area_px: (N,) thresholded area.
        peak: (N,) maximum grey level in the component.
        roundness: (N,) minor/major axis ratio (1 = circle).
        threshold: grey level used.
    """

    xy: np.ndarray
    area_px: np.ndarray
    peak: np.ndarray
    roundness: np.ndarray
    threshold: float = float("nan")

    def __post_init__(self):
        xy = np.asarray(self.xy, dtype=np.float64).reshape(-1, 2) if np.size(self.xy) == 0 \
            else np.asarray(self.xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"xy.shape={xy.shape}, expected (N, 2)")
        n = len(xy)
        object.__setattr__(self, "xy", xy)
        for name in ("area_px", "peak", "roundness"):
            a = np.asarray(getattr(self, name), dtype=np.float64).reshape(-1)
            if a.shape != (n,):
                raise ValueError(f"{name}.shape={a.shape}, expected ({n},)")
            object.__setattr__(self, name, a)

    def __len__(self) -> int:
        return len(self.xy)


def _check_image(image, bit_depth: int) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 2:
        raise ValueError(f"image.shape={img.shape}, expected (H, W)")
    if img.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"image.dtype={img.dtype}, expected uint8 or uint16")
    if bit_depth == 8 and img.dtype != np.uint8:
        raise ValueError(f"bit_depth=8 but image.dtype={img.dtype}")
    return img


def auto_threshold(image, config: BlobConfig) -> float:
    """Background median + k * robust sigma (1.4826 * MAD), from a subsample of the image;
    at least ``auto_min_fraction`` of full scale above the median."""
    img = np.asarray(image)
    sub = img[::4, ::4].ravel()
    if config.mask is not None:
        sub = sub[~np.asarray(config.mask, bool)[::4, ::4].ravel()]
    if sub.size == 0:
        raise ValueError("auto threshold: every pixel is masked")
    med = float(np.median(sub))
    mad = float(np.median(np.abs(sub.astype(np.float64) - med)))
    full = 2 ** config.bit_depth - 1
    return med + max(config.auto_k * MAD_TO_SIGMA * mad, config.auto_min_fraction * full)


TILE_PX = 16


def detect_blobs(image, config: BlobConfig) -> Blobs:
    """Detect marker blobs in one (H, W) uint8/uint16 image; see the module docstring.

    Thresholded pixels are grouped into occupied TILE_PX tiles; connected components run only
    in the windows of connected tile groups (sparse IR frames are mostly empty)."""
    img = _check_image(image, config.bit_depth)
    H, W = img.shape
    thr = auto_threshold(img, config) if config.mode is ThresholdMode.AUTO \
        else float(config.threshold)
    binary = (img > thr).view(np.uint8)
    m = None
    if config.mask is not None:
        m = np.asarray(config.mask, bool)
        if m.shape != img.shape:
            raise ValueError(f"mask.shape={m.shape}, image.shape={img.shape}")
        binary = binary.copy()
        binary[m] = 0
    th, tw = -(-H // TILE_PX), -(-W // TILE_PX)
    # tile occupancy: area-average of a 0/255 image is > 0 iff any pixel of the tile is set
    occ = cv2.threshold(binary, 0, 255, cv2.THRESH_BINARY)[1]
    if (th * TILE_PX, tw * TILE_PX) != (H, W):
        occ = cv2.copyMakeBorder(occ, 0, th * TILE_PX - H, 0, tw * TILE_PX - W,
                                 cv2.BORDER_CONSTANT, value=0)
    occ = (cv2.resize(occ, (tw, th), interpolation=cv2.INTER_AREA) > 0).view(np.uint8)
    nt, tlab, tstats, _ = cv2.connectedComponentsWithStats(occ, connectivity=8,
                                                           ltype=cv2.CV_32S)
    pad = config.window_pad_px
    res = ([], [], [], [])
    for g in range(1, nt):
        tx, ty, tww, thh = tstats[g, :4]
        r0, c0 = max(ty * TILE_PX - pad, 0), max(tx * TILE_PX - pad, 0)
        r1, c1 = min((ty + thh) * TILE_PX + pad, H), min((tx + tww) * TILE_PX + pad, W)
        own_tiles = np.repeat(np.repeat(tlab[ty:ty + thh, tx:tx + tww] == g, TILE_PX, 0),
                              TILE_PX, 1)
        sub = np.zeros((r1 - r0, c1 - c0), np.uint8)
        ir0, ic0 = ty * TILE_PX - r0, tx * TILE_PX - c0
        ir1, ic1 = min(ir0 + own_tiles.shape[0], r1 - r0), min(ic0 + own_tiles.shape[1], c1 - c0)
        sub[ir0:ir1, ic0:ic1] = binary[r0 + ir0:r0 + ir1, c0 + ic0:c0 + ic1] \
            & own_tiles[:ir1 - ir0, :ic1 - ic0]
        _components(img[r0:r1, c0:c1], sub, None if m is None else m[r0:r1, c0:c1],
                    (c0, r0), config, res)
    xs, areas, peaks, rounds = res
    return Blobs(xy=np.array(xs, dtype=np.float64).reshape(-1, 2), area_px=np.array(areas),
                 peak=np.array(peaks), roundness=np.array(rounds), threshold=thr)


def _median(v: np.ndarray) -> float:
    """Upper median (no interpolation), cheaper than np.median on small arrays."""
    k = len(v) // 2
    return float(np.partition(v, k)[k])


def _gauss_refine(win, keep_px, c0, r0, cx, cy, total, bg):
    """Least-squares fit of amplitude * pixel-integrated Gaussian + background over the
    window pixels ``keep_px``; falls back to (cx, cy) when the fit fails or moves > 1 px."""
    h, w = win.shape
    ex = np.arange(c0, c0 + w + 1) - 0.5
    ey = np.arange(r0, r0 + h + 1) - 0.5
    obs = win[keep_px]

    def resid(p):
        a, x, y, sg, b = p
        k = 1.0 / (np.sqrt(2.0) * sg)
        gx = np.diff(0.5 * erf((ex - x) * k))
        gy = np.diff(0.5 * erf((ey - y) * k))
        return (a * np.outer(gy, gx) + b)[keep_px] - obs

    sg0 = max(np.sqrt(total / max(win.max() - bg, 1e-9) / (2 * np.pi)), 0.3)
    try:
        sol = least_squares(resid, [total, cx, cy, sg0, bg], x_scale="jac",
                            bounds=([0, cx - 2, cy - 2, 0.2, -np.inf],
                                    [np.inf, cx + 2, cy + 2, 20.0, np.inf]))
    except ValueError:
        return cx, cy
    x, y = sol.x[1], sol.x[2]
    if not sol.success or np.hypot(x - cx, y - cy) > 1.0:
        return cx, cy
    return float(x), float(y)


def _components(img, binary, m, offset, config: BlobConfig, res) -> None:
    """Connected components of ``binary`` in the window ``img`` at ``offset`` (x0, y0);
    appends (xy, area, peak, roundness) of accepted blobs to ``res``."""
    H, W = img.shape
    n, labels, stats, _ = cv2.connectedComponentsWithStats(binary, connectivity=8,
                                                           ltype=cv2.CV_32S)
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = np.nonzero((area >= config.min_area_px) & (area <= config.max_area_px))[0] + 1
    pad = config.window_pad_px
    xs, areas, peaks, rounds = res
    for k in keep:
        x0, y0, w, h = stats[k, :4]
        c0, r0 = max(x0 - pad, 0), max(y0 - pad, 0)
        c1, r1 = min(x0 + w + pad, W), min(y0 + h + pad, H)
        win = img[r0:r1, c0:c1].astype(np.float64)
        lab = labels[r0:r1, c0:c1]
        own = lab == k
        # roundness from the component's binary second moments (+ 1/12: pixel extent)
        yy, xx = np.nonzero(own)
        dx, dy = xx - xx.sum() / len(xx), yy - yy.sum() / len(yy)
        sxx, syy, sxy = dx @ dx / len(xx) + 1 / 12, dy @ dy / len(xx) + 1 / 12, dx @ dy / len(xx)
        tr2, det = 0.5 * (sxx + syy), sxx * syy - sxy * sxy
        disc = np.sqrt(max(tr2 * tr2 - det, 0.0))
        rnd = float(np.sqrt(max(tr2 - disc, 0.0) / (tr2 + disc)))
        if rnd < config.min_roundness:
            continue
        ring = np.ones_like(own)
        ring[1:-1, 1:-1] = False
        ring &= lab == 0
        bg = _median(win[ring]) if ring.any() else _median(win[~own])
        wgt = win - bg
        wgt[(lab != 0) & ~own] = 0.0  # other blobs in the window
        if m is not None:
            wgt[m[r0:r1, c0:c1]] = 0.0
        np.maximum(wgt, 0.0, out=wgt)
        s = wgt.sum()
        if not s > 0:
            continue
        cx = (wgt.sum(axis=0) @ np.arange(c0, c1)) / s
        cy = (wgt.sum(axis=1) @ np.arange(r0, r1)) / s
        if config.refine is Refine.GAUSSIAN:
            keep_px = ((lab == 0) | own) if m is None else (((lab == 0) | own) & ~m[r0:r1, c0:c1])
            cx, cy = _gauss_refine(win, keep_px, c0, r0, cx, cy, s, bg)
        xs.append((cx + offset[0], cy + offset[1]))
        areas.append(area[k - 1])
        peaks.append(win[own].max())
        rounds.append(rnd)


def detect_frames(images, config: BlobConfig, masks=None) -> list[Blobs]:
    """Detect blobs in one frame of C cameras; ``masks``: optional list of C masks (or None)
    overriding ``config.mask`` per camera."""
    images = list(images)
    if masks is not None and len(masks) != len(images):
        raise ValueError(f"len(masks)={len(masks)} != len(images)={len(images)}")
    out = []
    for i, img in enumerate(images):
        cfg = config
        if masks is not None and masks[i] is not None:
            from dataclasses import replace
            cfg = replace(config, mask=masks[i])
        out.append(detect_blobs(img, cfg))
    return out


def detections_from_frames(frames, camera_names, config: BlobConfig, rate_hz=None,
                           masks=None) -> Detections2D:
    """Detect over ``frames`` = iterable of ``(frame_index, [image per camera])`` and return
    the flat ``Detections2D`` table (with ``area_px``)."""
    names = tuple(camera_names)
    fi, ci, pts, ar = [], [], [], []
    for t, images in frames:
        images = list(images)
        if len(images) != len(names):
            raise ValueError(f"frame {t}: {len(images)} images for {len(names)} cameras")
        for c, b in enumerate(detect_frames(images, config, masks)):
            fi.append(np.full(len(b), int(t), np.int64))
            ci.append(np.full(len(b), c, np.int64))
            pts.append(b.xy)
            ar.append(b.area_px)
    if not pts:
        return Detections2D(frame=np.zeros(0, np.int64), camera=np.zeros(0, np.int64),
                            xy=np.zeros((0, 2)), camera_names=names, rate_hz=rate_hz,
                            area_px=np.zeros(0))
    return Detections2D(frame=np.concatenate(fi), camera=np.concatenate(ci),
                        xy=np.concatenate(pts), camera_names=names, rate_hz=rate_hz,
                        area_px=np.concatenate(ar).astype(np.float64))
