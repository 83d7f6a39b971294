"""Blob detection: reconstruct.blobs.detect_blobs vs cv2.SimpleBlobDetector (baseline).

1280x1024 8-bit frames with 50 markers (3-8 px) rendered by hw_sim.render.render_frame;
speed in frames/s on one core and centroid RMS error vs the rendered truth.
Run: .venv/bin/python benchmarks/bench_blobs.py
"""

import time

import cv2
import numpy as np

from calibration.camera import Camera
from hw_sim.render import render_frame
from reconstruct.blobs import BlobConfig, detect_blobs

N_FRAMES = 20
N_BLOBS = 50
MATCH_PX = 1.5


def make_frames(rng):
    K = np.array([[1000.0, 0, 639.5], [0, 1000.0, 511.5], [0, 0, 1]])
    cam = Camera(name="c", size=(1280, 1024), K=K, dist=np.zeros(5), R=np.eye(3),
                 t=np.zeros(3))
    frames = []
    for _ in range(N_FRAMES):
        gx, gy = np.meshgrid(np.arange(10), np.arange(5))
        xy = np.column_stack([gx.ravel() * 120 + 80, gy.ravel() * 180 + 120]).astype(float)
        xy += rng.uniform(-20, 20, xy.shape)
        z = rng.uniform(2.0, 5.0, N_BLOBS)
        pts = np.column_stack([(xy - K[:2, 2]) / 1000.0 * z[:, None], z])
        diam = rng.uniform(3.0, 8.0, N_BLOBS) * z / 1000.0  # 3-8 px
        img, tr = render_frame(cam, pts, diam, rng=rng, bit_depth=8)
        frames.append((img, tr.xy[tr.visible]))
    return frames


def rms(found, truth):
    if len(found) == 0:
        return float("nan"), 0
    d = np.linalg.norm(found[None] - truth[:, None], axis=2)
    j = d.argmin(axis=1)
    ok = d[np.arange(len(truth)), j] < MATCH_PX
    return float(np.sqrt(np.mean(d[np.arange(len(truth)), j][ok] ** 2))), int(ok.sum())


def run(name, fn, frames):
    t0 = time.perf_counter()
    out = [fn(img) for img, _ in frames]
    fps = len(frames) / (time.perf_counter() - t0)
    errs, hit, tot = [], 0, 0
    for found, (_, truth) in zip(out, frames):
        e, n = rms(found, truth)
        errs.append(e ** 2 * n)
        hit += n
        tot += len(truth)
    return name, fps, float(np.sqrt(np.nansum(errs) / max(hit, 1))), hit / tot


def main():
    cv2.setNumThreads(1)
    frames = make_frames(np.random.default_rng(0))
    cfg = BlobConfig(bit_depth=8)
    cfg_g = BlobConfig(bit_depth=8, refine="gaussian")
    p = cv2.SimpleBlobDetector_Params()
    p.filterByColor, p.blobColor = True, 255
    p.minThreshold, p.maxThreshold, p.thresholdStep = 20, 220, 20
    p.filterByArea, p.minArea, p.maxArea = True, 2, 400
    p.filterByCircularity = p.filterByConvexity = p.filterByInertia = False
    p.minDistBetweenBlobs = 3
    sbd = cv2.SimpleBlobDetector_create(p)

    def sbd_fn(img):
        return np.array([k.pt for k in sbd.detect(img)]).reshape(-1, 2)

    rows = [run("detect_blobs", lambda img: detect_blobs(img, cfg).xy, frames),
            run("SimpleBlobDetector", sbd_fn, frames),
            run("detect_blobs gauss", lambda img: detect_blobs(img, cfg_g).xy, frames)]
    print(f"{N_FRAMES} frames 1280x1024 8-bit, {N_BLOBS} blobs 3-8 px, 1 core")
    print(f"{'method':<20} {'frames/s':>9} {'RMS px':>8} {'found':>6}")
    for name, fps, e, f in rows:
        print(f"{name:<20} {fps:9.1f} {e:8.4f} {f:6.1%}")
    _, f1, e1, _ = rows[1]
    for name, f0, e0, _ in (rows[0], rows[2]):
        print(f"ratio {name}/SimpleBlobDetector: speed x{f0 / f1:.2f}, RMS error x{e0 / e1:.3f}")


if __name__ == "__main__":
    main()
