"""Calibration quality report: reprojection RMS per camera, wand length statistics, coverage.

The wand length is measured on points triangulated freely (maximum likelihood in px,
``calibration.points.refine_points``) from the inlier observations, so its SD holds both the
calibration error and the triangulation noise of the two ends. ``wand_sd_floor_mm`` is the SD
the noise alone gives (first-order propagation of the estimated pixel noise through the
calibrated cameras, ``calibration.points.point_covariance``): an SD at that floor means the
calibration adds no measurable length error; well above it means calibration error or outliers.
Units: px, mm (docs/conventions.md [units]).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calibration.points import point_covariance
from capture.atomic import atomic_file

NOISE_LIMITED_RATIO = 1.2   # SD / floor below this: the SD is triangulation noise


@dataclass(frozen=True, kw_only=True)
class CalibrationReport:
    """Per-camera figures (index = camera, [camera-order]) and wand statistics.

    rms_px: (C,) reprojection RMS (2D norm) of inlier observations; n_obs: (C,) int;
    coverage: (C,) fraction of a grid of image cells holding an observation;
    mean_error_px: mean 2D reprojection error; noise_px: estimated pixel noise per coordinate;
    wand_mean_mm, wand_sd_mm, wand_score (100*SD/mean), wand_sd_floor_mm (SD expected from
    noise_px alone): NaN in single-point mode;
    mean_ray_error_mm: mean distance of the inlier rays to their 3D points;
    wand_lengths_mm: (K,) the per-frame lengths (empty in single-point mode).
    """

    camera_names: tuple
    rms_px: np.ndarray
    n_obs: np.ndarray
    coverage: np.ndarray
    mean_error_px: float
    wand_mean_mm: float
    wand_sd_mm: float
    wand_score: float
    mean_ray_error_mm: float
    noise_px: float = np.nan
    wand_sd_floor_mm: float = np.nan
    wand_lengths_mm: np.ndarray = field(default_factory=lambda: np.zeros(0))
    coverage_maps: np.ndarray | None = None

    def __post_init__(self):
        C = len(self.camera_names)
        for n in ("rms_px", "n_obs", "coverage"):
            if np.shape(getattr(self, n)) != (C,):
                raise ValueError(f"{n}.shape={np.shape(getattr(self, n))}, expected ({C},)")
        if self.coverage_maps is not None and np.shape(self.coverage_maps)[0] != C:
            raise ValueError(f"coverage_maps.shape={np.shape(self.coverage_maps)}, "
                             f"expected ({C}, gy, gx)")

    def summary(self) -> str:
        lines = [f"{'camera':>12} {'obs':>8} {'rms_px':>8} {'coverage':>9}"]
        for n, k, r, cv in zip(self.camera_names, self.n_obs, self.rms_px, self.coverage):
            lines.append(f"{n:>12} {int(k):8d} {r:8.3f} {cv:9.2f}")
        unit = "mm" if np.isfinite(self.wand_mean_mm) else \
            "mm if the camera 0-1 baseline were 1 m (single point: no metric scale)"
        lines.append(f"mean reprojection error {self.mean_error_px:.3f} px "
                     f"(noise estimate {self.noise_px:.3f} px per coordinate), "
                     f"mean ray error {self.mean_ray_error_mm:.3f} {unit}")
        if np.isfinite(self.wand_mean_mm):
            lines.append(f"wand length {self.wand_mean_mm:.3f} mm, SD {self.wand_sd_mm:.3f} mm, "
                         f"score {self.wand_score:.4f}")
            if np.isfinite(self.wand_sd_floor_mm):
                ratio = self.wand_sd_mm / self.wand_sd_floor_mm
                verdict = ("at the triangulation-noise floor: the calibration adds no measurable "
                           "length error" if ratio < NOISE_LIMITED_RATIO else
                           "above the noise floor: calibration error or outliers")
                lines.append(f"wand SD expected from {self.noise_px:.3f} px noise alone "
                             f"{self.wand_sd_floor_mm:.3f} mm (SD/floor {ratio:.2f}: {verdict})")
        return "\n".join(lines)

    def save_figure(self, path, residual_px=None) -> None:
        """PNG: residual histograms per camera (if given), RMS and observation counts per
        camera, wand lengths, and image coverage maps (matplotlib Agg)."""
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        C = len(self.camera_names)
        maps = self.coverage_maps
        ncov = C if maps is not None else 0
        cols = 4
        rows = 1 + int(np.ceil(ncov / cols))
        fig = plt.figure(figsize=(12, 3.2 * rows))
        gs = fig.add_gridspec(rows, cols)
        ax = fig.add_subplot(gs[0, 0])
        if residual_px is not None:
            for c, n in enumerate(self.camera_names):
                e = np.linalg.norm(residual_px[c].reshape(-1, 2), axis=1)
                e = e[np.isfinite(e)]
                if e.size:
                    ax.hist(e, bins=50, range=_padded(e), histtype="step", label=n)
            ax.legend(fontsize=5)
        ax.set_xlabel("reprojection error (px)")
        ax = fig.add_subplot(gs[0, 1])
        x = np.arange(C)
        ax.bar(x, self.rms_px)
        ax.set_xticks(x, self.camera_names, rotation=90, fontsize=6)
        ax.set_ylabel("RMS (px)")
        ax2 = ax.twinx()
        ax2.plot(x, self.n_obs, "k.")
        ax2.set_ylabel("observations")
        ax = fig.add_subplot(gs[0, 2])
        if len(self.wand_lengths_mm):
            ax.hist(self.wand_lengths_mm, bins=60, range=_padded(self.wand_lengths_mm))
            ax.set_title(f"wand {self.wand_mean_mm:.2f} mm SD {self.wand_sd_mm:.3f} "
                         f"(floor {self.wand_sd_floor_mm:.3f})", fontsize=8)
        ax.set_xlabel("wand length (mm)")
        ax = fig.add_subplot(gs[0, 3])
        ax.bar(x, self.coverage)
        ax.set_xticks(x, self.camera_names, rotation=90, fontsize=6)
        ax.set_ylabel("image coverage")
        ax.set_ylim(0, 1)
        for c in range(ncov):
            a = fig.add_subplot(gs[1 + c // cols, c % cols])
            a.imshow(maps[c], cmap="viridis", interpolation="nearest")
            a.set_title(f"{self.camera_names[c]} observations per cell", fontsize=7)
            a.set_xticks([])
            a.set_yticks([])
        fig.tight_layout()
        try:
            with atomic_file(path, "wb") as f:
                fig.savefig(f, dpi=80, format="png")
        finally:
            plt.close(fig)


def _padded(v, min_width=1e-3):
    """Histogram range of v at least min_width wide (exact data has a ~1e-13 spread)."""
    lo, hi = float(np.min(v)), float(np.max(v))
    pad = max(0.0, min_width - (hi - lo)) / 2
    return lo - pad, hi + pad


def make_report(cameras, xy, residual_px, inlier, X, spacing_m=None, grid=(8, 8),
                noise_px=None) -> CalibrationReport:
    """Figures from the bundle output: xy/residual_px (C,T,M,2), inlier (C,T,M), X (T,M,3) m
    (free triangulation). noise_px: pixel noise per coordinate for the wand SD floor (default:
    the per-coordinate RMS of the inlier residuals)."""
    C = len(cameras)
    e2 = np.sum(residual_px ** 2, axis=3)
    rms = np.array([np.sqrt(np.nanmean(e2[c][inlier[c]])) if inlier[c].any() else np.nan
                    for c in range(C)])
    n_obs = inlier.reshape(C, -1).sum(axis=1)
    cov = np.zeros(C)
    maps = np.zeros((C, grid[1], grid[0]), np.int64)
    rays = []
    for c, cam in enumerate(cameras):
        p = xy[c][inlier[c]]
        if len(p) == 0:
            continue
        w, h = cam.size
        gx = np.clip((p[:, 0] / w * grid[0]).astype(int), 0, grid[0] - 1)
        gy = np.clip((p[:, 1] / h * grid[1]).astype(int), 0, grid[1] - 1)
        np.add.at(maps[c], (gy, gx), 1)
        cov[c] = np.count_nonzero(maps[c]) / (grid[0] * grid[1])
        o, d = cam.unproject(p)
        v = X[inlier[c]] - o
        rays.append(np.linalg.norm(v - (v * d).sum(1, keepdims=True) * d, axis=1))
    ray = float(np.nanmean(np.concatenate(rays)) * 1000) if rays else np.nan
    mean_err = float(np.nanmean(np.sqrt(e2[inlier])))
    if noise_px is None:
        noise_px = float(np.sqrt(np.nanmean(e2[inlier]) / 2))
    wm = wsd = ws = floor = np.nan
    L = np.zeros(0)
    if spacing_m is not None:
        L = np.linalg.norm(X[:, -1] - X[:, 0], axis=1) * 1000
        ok = np.isfinite(L)
        L = L[ok]
        if L.size:
            wm, wsd = float(L.mean()), float(L.std(ddof=1)) if L.size > 1 else 0.0
            ws = 100 * wsd / wm
            ends = []
            for m in (0, -1):
                ends.append(point_covariance(cameras, inlier[:, ok, m], X[ok, m], noise_px))
            u = X[ok, -1] - X[ok, 0]
            u /= np.linalg.norm(u, axis=1, keepdims=True)
            var = np.einsum("ni,nij,nj->n", u, ends[0] + ends[1], u)
            floor = float(np.sqrt(np.nanmean(var)) * 1000)
    return CalibrationReport(camera_names=tuple(c.name for c in cameras), rms_px=rms,
                             n_obs=n_obs, coverage=cov, mean_error_px=mean_err,
                             wand_mean_mm=wm, wand_sd_mm=wsd, wand_score=ws,
                             mean_ray_error_mm=ray, noise_px=noise_px, wand_sd_floor_mm=floor,
                             wand_lengths_mm=L, coverage_maps=maps)
