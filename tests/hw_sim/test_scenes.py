"""hw_sim.scenes: marker scenes hold their truth and cover the volume."""
import numpy as np
import pytest

from hw_sim.rig import volume_bounds
from hw_sim.scenes import MarkerScene, static_markers, wand

EXACT_M = 1e-12


def test_static_markers_are_static_separated_and_inside():
    s = static_markers(25, 6, rng=1, min_separation_m=0.2)
    assert s.positions.shape == (6, 25, 3)
    assert np.all(s.positions == s.positions[0])
    d = np.linalg.norm(s.positions[0][:, None] - s.positions[0][None], axis=-1)
    assert d[np.triu_indices(25, 1)].min() >= 0.2
    lo, hi = volume_bounds()
    assert np.all(s.positions >= lo) and np.all(s.positions <= hi)
    assert np.array_equal(static_markers(25, 6, rng=1).positions,
                          static_markers(25, 6, rng=1).positions)
    assert s.labels[0] == "M1" and s.marker_diameter_m.shape == (25,)


@pytest.mark.parametrize("spacing", [(0, 250, 500), (0, 500), (0, 150, 400, 600)])
def test_wand_is_rigid_collinear_and_inside(spacing):
    s = wand(600, spacing_mm=spacing, rng=2)
    P = s.positions
    sp = np.asarray(spacing, float) / 1000
    assert np.allclose(s.wand_spacing_m, sp - sp[0], atol=EXACT_M)
    axis = (P[:, -1] - P[:, 0]) / np.linalg.norm(P[:, -1] - P[:, 0], axis=1, keepdims=True)
    for i in range(len(sp)):
        along = np.einsum("ti,ti->t", P[:, i] - P[:, 0], axis)
        assert np.allclose(along, sp[i] - sp[0], atol=1e-12)
        off = P[:, i] - P[:, 0] - along[:, None] * axis
        assert np.abs(off).max() < 1e-12
    lo, hi = volume_bounds()
    assert np.all(P >= lo) and np.all(P <= hi)


def test_wand_covers_volume_and_orientations():
    s = wand(1500, rng=3)
    c = s.positions.mean(1)
    lo, hi = volume_bounds()
    span = (c.max(0) - c.min(0)) / (hi - lo)
    assert np.all(span > 0.7)
    d = s.positions[:, -1] - s.positions[:, 0]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d *= np.sign(d[:, 2:3] + 1e-300)  # a wand axis is a line: fold onto the upper hemisphere
    # all orientation bins of the hemisphere are visited: elevation x azimuth 3 x 6
    el = np.digitize(d[:, 2], [1 / 3, 2 / 3])
    az = np.digitize(np.arctan2(d[:, 1], d[:, 0]), np.linspace(-np.pi, np.pi, 7)[1:-1])
    counts = np.zeros((3, 6), int)
    np.add.at(counts, (el, az), 1)
    assert counts.min() > 0, counts


def test_at_time_loops_and_drops_absent():
    P = np.zeros((4, 3, 3))
    P[:, :, 0] = np.arange(4)[:, None]
    P[2, 1] = np.nan
    s = MarkerScene(positions=P, marker_diameter_m=[0.01] * 3, rate_hz=10, labels="abc")
    pts, d = s.at_time(0.2)
    assert pts.shape == (2, 3) and np.all(pts[:, 0] == 2) and d.shape == (2,)
    assert np.all(s.at_time(0.5)[0][:, 0] == 1)  # frame 5 -> 1 (loops)


@pytest.mark.parametrize("kw, msg", [
    (dict(positions=np.zeros((2, 3))), "positions.shape"),
    (dict(marker_diameter_m=[0.01] * 2), "marker_diameter_m.shape"),
    (dict(rate_hz=0), "rate_hz"),
    (dict(labels=("a",)), "labels"),
    (dict(occluder_segments=np.zeros((2, 1, 2, 3))), "together"),
    (dict(occluder_segments=np.zeros((3, 1, 2, 3)), occluder_radii_m=[0.1]),
     "occluder_segments.shape"),
    (dict(occluder_segments=np.zeros((2, 1, 2, 3)), occluder_radii_m=[0.1, 0.2]),
     "occluder_radii_m.shape"),
])
def test_bad_scene(kw, msg):
    base = dict(positions=np.zeros((2, 3, 3)), marker_diameter_m=[0.01] * 3, rate_hz=100,
                labels=("a", "b", "c"))
    base.update(kw)
    with pytest.raises(ValueError, match=msg):
        MarkerScene(**base)


def test_bad_wand():
    with pytest.raises(ValueError, match="spacing_mm"):
        wand(10, spacing_mm=(0,))
    with pytest.raises(ValueError, match="spacing_mm"):
        wand(10, spacing_mm=(0, 300, 200))


def test_figure_scene_has_body_occluders():
    from hw_sim.observe import observe
    from hw_sim.rig import make_rig
    from hw_sim.scenes import figure

    s = figure(40, 100.0, rng=1)
    T, M, _ = s.positions.shape
    assert T == 40 and 30 <= M <= 60
    assert s.occluder_segments.shape[:2] == (40, s.occluder_radii_m.size)
    assert 10 <= s.occluder_radii_m.size <= 25
    assert np.array_equal(s.positions, figure(40, 100.0, rng=1).positions)
    obs = observe(make_rig(8), s, rng=2, noise_px=0.0)
    # a surface marker faces about half the ring: the body hides it from many cameras,
    # yet most markers stay seen by >= 2 cameras (measured ~0.5 and ~0.88 for this seed)
    assert 0.2 < obs.occluded.mean() < 0.7
    seen = obs.visible.sum(1)
    assert np.mean(seen >= 2) > 0.75


def test_figure_wires_articulated_output(monkeypatch):
    """figure() passes markers, capsules, radii, labels and joints through unchanged."""
    import sys
    import types

    from hw_sim.scenes import figure

    T = 5
    markers = np.random.default_rng(0).normal(size=(T, 3, 3))
    caps = np.random.default_rng(1).normal(size=(T, 2, 2, 3))
    fake = types.ModuleType("hw_sim.articulated")
    fig = types.SimpleNamespace(marker_names=("a", "b", "c"), capsule_radii_m=np.array([0.1, 0.2]))
    fake.humanoid = lambda rng: fig
    fake.animate = lambda f, n, rate, rng=None, rom_deg=90.0: types.SimpleNamespace(
        markers=markers[:n], capsules=caps[:n], joint_centres=np.zeros((n, 4, 3)))
    monkeypatch.setitem(sys.modules, "hw_sim.articulated", fake)
    s = figure(T, 50.0, rng=0, rom_deg=120.0)
    assert np.array_equal(s.positions, markers)
    assert np.array_equal(s.occluder_segments, caps)
    assert np.array_equal(s.occluder_radii_m, [0.1, 0.2])
    assert s.labels == ("a", "b", "c") and s.rate_hz == 50.0
    assert s.joint_centres.shape == (T, 4, 3)
