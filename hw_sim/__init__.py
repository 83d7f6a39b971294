"""A simulated motion-capture rig that behaves like hardware and always returns ground truth.

Modules (one job each):

- ``hw_sim.rig``: ``make_rig(n_cameras=8, *, size=(1280, 1024), fov_deg=56.0, ...,
  dist=None, rng=None) -> calibration.camera.Rig`` -- cameras ``cam_1..cam_N`` ringed
  around a 4 x 4 x 2.5 m volume (z up, floor z = 0), aimed at its centre (0, 0, 1.25).
- ``hw_sim.scenes``: ``MarkerScene`` (positions (T, M, 3), diameters, rate, labels,
  occluder capsules, wand / joint truth) and builders ``static_markers``, ``wand``,
  ``figure`` (articulated humanoid from ``hw_sim.articulated``).
- ``hw_sim.observe``: ``observe(rig, scene, rng, ...) -> Observation`` -- the fast
  object-mode path: a ``capture.detections.Detections2D`` table plus per-row truth,
  visibility (T, C, M), occlusion and merged blobs; ``visibility(...)`` for the geometry.
- ``hw_sim.render``: ``render_frame(camera, points, diameters_m, rng, ...) -> (image, truth)``
  and ``render_scene(rig, scene, frame_index, rng, ...) -> SceneFrame`` -- IR frames with
  sub-pixel Gaussian blobs, background, read and shot noise, 8/10/12/16-bit.
- ``hw_sim.articulated``: the humanoid figure and its motion.
- ``hw_sim.syncbox``, ``hw_sim.sim_camera``: a simulated sync box and triggered cameras
  following the ``capture`` protocols.

Every random function takes ``rng`` (a ``numpy.random.Generator`` or an int seed).
Conventions: docs/conventions.md.

The main names are importable from the package (lazily): ``make_rig``, ``MarkerScene``,
``static_markers``, ``wand``, ``figure``, ``Observation``, ``visibility``, ``render_frame``,
``render_scene`` (the function ``observe`` shares its module's name: import it as
``from hw_sim.observe import observe``).
"""
from __future__ import annotations

import importlib

_LAZY = {
    "make_rig": "hw_sim.rig",
    "MarkerScene": "hw_sim.scenes",
    "static_markers": "hw_sim.scenes",
    "wand": "hw_sim.scenes",
    "figure": "hw_sim.scenes",
    "Observation": "hw_sim.observe",
    "visibility": "hw_sim.observe",
    "render_frame": "hw_sim.render",
    "render_scene": "hw_sim.render",
}

__all__ = sorted(_LAZY)


def __getattr__(name):
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module 'hw_sim' has no attribute {name!r}")
    return getattr(importlib.import_module(mod), name)
