"""Speed of the simulated rig: rendering a full IR frame and the object-mode observation.

Baseline for rendering: the naive way, a full-image Gaussian per blob (what a window-free
renderer does). Run: .venv/bin/python benchmarks/bench_hw_sim.py
"""
from __future__ import annotations

import time

import numpy as np

from hw_sim.observe import observe
from hw_sim.render import blob_sigma_px, render_frame
from hw_sim.rig import make_rig
from hw_sim.scenes import static_markers, wand


def naive_render(camera, points, diameters_m, rng):
    w, h = camera.size
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    img = np.full((h, w), 0.03, np.float32)
    uv = camera.project(points)
    s = blob_sigma_px(diameters_m * camera.K[0, 0] / camera.depth(points))
    for (u, v), sg in zip(uv, s):
        img += 0.85 * np.exp(-((xs - u) ** 2 + (ys - v) ** 2) / (2 * sg * sg))
    img += rng.standard_normal((h, w), dtype=np.float32) * 0.004
    return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)


def _time(f, n):
    f()
    t0 = time.perf_counter()
    for _ in range(n):
        f()
    return (time.perf_counter() - t0) / n


def main():
    rig = make_rig(8)
    cam = rig[0]
    scene = static_markers(50, 1, rng=1)
    P = scene.positions[0]
    g = np.random.default_rng(0)
    t_ours = _time(lambda: render_frame(cam, P, 0.014, g), 20)
    t_clean = _time(lambda: render_frame(cam, P, 0.014, g, noise_sigma=0.0, full_well_e=None), 20)
    t_naive = _time(lambda: naive_render(cam, P, np.full(50, 0.014), g), 2)
    print(f"render 1280x1024, 50 blobs, 8-bit, read+shot noise: {t_ours * 1e3:7.2f} ms")
    print(f"render 1280x1024, 50 blobs, noise-free:             {t_clean * 1e3:7.2f} ms")
    print(f"baseline full-image Gaussian per blob:               {t_naive * 1e3:7.2f} ms"
          f"  (ours is {t_naive / t_ours:.0f}x faster)")
    for name, sc in (("wand 3 markers x 2000 frames", wand(2000, rng=1)),
                     ("40 static markers x 1000 frames", static_markers(40, 1000, rng=1))):
        t = _time(lambda: observe(rig, sc, rng=2, spurious_per_frame=0.5), 2)
        print(f"observe (8 cameras) {name}: {t:6.3f} s")


if __name__ == "__main__":
    main()
