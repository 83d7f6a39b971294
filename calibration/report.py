"""Calibration quality report: reprojection RMS per camera, wand length statistics, coverage.

Units: px, mm (docs/conventions.md [units]).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, kw_only=True)
class CalibrationReport:
    """Per-camera figures (index = camera, [camera-order]) and wand statistics.

    rms_px: (C,) reprojection RMS (2D norm) of inlier observations; n_obs: (C,) int;
    coverage: (C,) fraction of a grid of image cells holding an observation;
    wand_mean_mm, wand_sd_mm, wand_score (100*SD/mean): NaN in single-point mode;
    mean_ray_error_mm: mean distance of the inlier rays to their 3D points.
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

    def __post_init__(self):
        C = len(self.camera_names)
        for n in ("rms_px", "n_obs", "coverage"):
            if np.shape(getattr(self, n)) != (C,):
                raise ValueError(f"{n}.shape={np.shape(getattr(self, n))}, expected ({C},)")

    def summary(self) -> str:
        lines = [f"{'camera':>12} {'obs':>8} {'rms_px':>8} {'coverage':>9}"]
        for n, k, r, cv in zip(self.camera_names, self.n_obs, self.rms_px, self.coverage):
            lines.append(f"{n:>12} {int(k):8d} {r:8.3f} {cv:9.2f}")
        lines.append(f"mean reprojection error {self.mean_error_px:.3f} px, "
                     f"mean ray error {self.mean_ray_error_mm:.3f} mm")
        if np.isfinite(self.wand_mean_mm):
            lines.append(f"wand length {self.wand_mean_mm:.3f} mm, SD {self.wand_sd_mm:.3f} mm, "
                         f"score {self.wand_score:.4f}")
        return "\n".join(lines)

    def save_figure(self, path, residual_px=None) -> None:
        """PNG: per-camera residual histograms (if given) and coverage bars (matplotlib Agg)."""
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        fig, ax = plt.subplots(1, 2, figsize=(10, 4))
        if residual_px is not None:
            for c, n in enumerate(self.camera_names):
                e = np.linalg.norm(residual_px[c].reshape(-1, 2), axis=1)
                e = e[np.isfinite(e)]
                ax[0].hist(e, bins=50, histtype="step", label=n)
            ax[0].set_xlabel("reprojection error (px)")
            ax[0].legend(fontsize=6)
        ax[1].bar(range(len(self.coverage)), self.coverage)
        ax[1].set_xticks(range(len(self.coverage)), self.camera_names, rotation=90, fontsize=6)
        ax[1].set_ylabel("image coverage")
        fig.tight_layout()
        fig.savefig(path)
        plt.close(fig)


def make_report(cameras, xy, residual_px, inlier, X, spacing_m=None, grid=(8, 8)
                ) -> CalibrationReport:
    """Figures from the bundle output: xy/residual_px (C,T,M,2), inlier (C,T,M), X (T,M,3) m."""
    C = len(cameras)
    e2 = np.sum(residual_px ** 2, axis=3)
    rms = np.array([np.sqrt(np.nanmean(e2[c][inlier[c]])) if inlier[c].any() else np.nan
                    for c in range(C)])
    n_obs = inlier.reshape(C, -1).sum(axis=1)
    cov = np.zeros(C)
    rays = []
    for c, cam in enumerate(cameras):
        p = xy[c][inlier[c]]
        if len(p) == 0:
            continue
        w, h = cam.size
        gx = np.clip((p[:, 0] / w * grid[0]).astype(int), 0, grid[0] - 1)
        gy = np.clip((p[:, 1] / h * grid[1]).astype(int), 0, grid[1] - 1)
        cov[c] = len(np.unique(gy * grid[0] + gx)) / (grid[0] * grid[1])
        o, d = cam.unproject(p)
        v = X[inlier[c]] - o
        rays.append(np.linalg.norm(v - (v * d).sum(1, keepdims=True) * d, axis=1))
    ray = float(np.nanmean(np.concatenate(rays)) * 1000) if rays else np.nan
    mean_err = float(np.nanmean(np.sqrt(e2[inlier])))
    wm = wsd = ws = np.nan
    if spacing_m is not None:
        L = np.linalg.norm(X[:, -1] - X[:, 0], axis=1) * 1000
        L = L[np.isfinite(L)]
        if L.size:
            wm, wsd = float(L.mean()), float(L.std(ddof=1)) if L.size > 1 else 0.0
            ws = 100 * wsd / wm
    return CalibrationReport(camera_names=tuple(c.name for c in cameras), rms_px=rms,
                             n_obs=n_obs, coverage=cov, mean_error_px=mean_err,
                             wand_mean_mm=wm, wand_sd_mm=wsd, wand_score=ws,
                             mean_ray_error_mm=ray)
