"""Calibration TOML: round trip, camera order for 12+ cameras, malformed files."""
import numpy as np
import pytest

from calibration.camera import Camera, Rig, look_at
from calibration.rig_io import CalibrationFileError, load_rig, save_rig


def _rig(n):
    cams = []
    rng = np.random.default_rng(n)
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at((4 * np.cos(a), 4 * np.sin(a), 2.5), (0, 0, 1.25))
        cams.append(Camera.from_params(name=f"cam_{i}", size=(1280, 1024),
                                       fx=1200 + rng.normal(), dist=rng.normal(0, 0.01, 5),
                                       R=R, t=t))
    return Rig(cameras=tuple(cams))


@pytest.mark.parametrize("n", [3, 12, 16])
def test_roundtrip_keeps_order_and_values(tmp_path, n):
    rig = _rig(n)
    path = save_rig(rig, tmp_path / "calibration.toml")
    back = load_rig(path)
    assert back.names == rig.names  # cam_10 stays after cam_9
    pts = np.random.default_rng(0).uniform(-1, 1, (50, 3)) + [0, 0, 1.25]
    np.testing.assert_allclose(back.project(pts), rig.project(pts), atol=1e-9)
    for a, b in zip(rig, back):
        np.testing.assert_allclose(a.R, b.R, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, atol=1e-12)
        np.testing.assert_allclose(a.dist, b.dist, atol=0)


def test_reads_anipose_layout_without_metadata(tmp_path):
    text = """
[cam_0]
name = "A"
size = [ 752.0, 480.0,]
matrix = [ [ 800.0, 0.0, 376.0,], [ 0.0, 800.0, 240.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ -0.1, 0.01, 0.0, 0.0,]
rotation = [ 0.0, 0.1, 0.0,]
translation = [ 0.0, 0.0, 2.0,]

[cam_1]
name = "B"
size = [ 752.0, 480.0,]
matrix = [ [ 800.0, 0.0, 376.0,], [ 0.0, 800.0, 240.0,], [ 0.0, 0.0, 1.0,],]
distortions = [ 0.0, 0.0, 0.0, 0.0,]
rotation = [ 0.0, 0.0, 0.0,]
translation = [ 0.5, 0.0, 2.0,]

[metadata]
adjusted = false
"""
    p = tmp_path / "c.toml"
    p.write_text(text)
    rig = load_rig(p)
    assert rig.names == ["A", "B"]
    assert rig[0].dist.tolist() == [-0.1, 0.01, 0.0, 0.0, 0.0]


def test_malformed_files_name_the_problem(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.toml"):
        load_rig(tmp_path / "missing.toml")
    p = tmp_path / "bad.toml"
    p.write_text("[cam_1\nname=")
    with pytest.raises(CalibrationFileError, match="malformed TOML"):
        load_rig(p)
    p.write_text('[cam_1]\nname = "a"\nsize = [10.0, 10.0]\nmatrix = [[1,0,0],[0,1,0],[0,0,1]]\n'
                 'distortions = [0,0,0,0]\nrotation = [0,0,0]\n')
    with pytest.raises(CalibrationFileError, match="missing field 'translation'"):
        load_rig(p)
    p.write_text('[cam_1]\nname = "a"\nsize = [10.0, 10.0]\nmatrix = [[1,0,0],[0,1,0]]\n'
                 'distortions = [0,0,0,0]\nrotation = [0,0,0]\ntranslation = [0,0,0]\n')
    with pytest.raises(CalibrationFileError, match="'matrix' has shape"):
        load_rig(p)
    save_rig(_rig(2), p)
    text = p.read_text()
    assert '"cam_1",\n]' in text
    p.write_text(text.replace('"cam_1",\n]', '"cam_9",\n]'))
    with pytest.raises(CalibrationFileError, match="order does not match"):
        load_rig(p)
