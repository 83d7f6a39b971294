"""Marker files round-trip through our writer and independent readers (ezc3d)."""
import numpy as np
import pytest

from reconstruct.marker_files import (MarkerData, read_c3d, read_markers, write_markers)

ATOL_M = 1e-6  # float32 storage of millimetres: ~1e-4 mm resolution at 2 m


def _data(rng, T=50, M=7, rate=120.0):
    p = rng.uniform(-2, 2, size=(T, M, 3))
    p[5:9, 2] = np.nan  # a gap
    p[0, 6] = np.nan
    labels = tuple(f"mk{i}" for i in range(M))
    return MarkerData(positions=p, labels=labels, rate_hz=rate)


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".csv"])
def test_roundtrip(tmp_path, suffix):
    d = _data(np.random.default_rng(0))
    path = write_markers(d, tmp_path / f"x{suffix}")
    back = read_markers(path)
    assert back.labels == d.labels
    assert back.rate_hz == pytest.approx(d.rate_hz)
    np.testing.assert_array_equal(np.isnan(back.positions), np.isnan(d.positions))
    np.testing.assert_allclose(back.positions, d.positions, atol=ATOL_M, equal_nan=True)


def test_c3d_independent_reader(tmp_path):
    import ezc3d
    d = _data(np.random.default_rng(1))
    path = write_markers(d, tmp_path / "x.c3d")
    c = ezc3d.c3d(str(path))
    assert c["parameters"]["POINT"]["UNITS"]["value"][0].strip() == "mm"
    assert c["parameters"]["POINT"]["RATE"]["value"][0] == pytest.approx(120.0)
    assert [s.strip() for s in c["parameters"]["POINT"]["LABELS"]["value"]] == list(d.labels)
    pts = c["data"]["points"]  # (4, M, T) mm, NaN where residual < 0
    xyz = np.transpose(pts[:3], (2, 1, 0)) / 1000.0
    np.testing.assert_array_equal(np.isnan(xyz), np.isnan(d.positions))
    np.testing.assert_allclose(xyz, d.positions, atol=ATOL_M, equal_nan=True)


def test_real_c3d_files_read(shared_data):
    for name in ["ktk_tennis_serve_optitrack.c3d", "arm_4-2-3_markers_120fps.c3d",
                 "c3dorg_sample01_Eb015pi.c3d", "c3dorg_sample02_pc_real.c3d"]:
        d = read_c3d(shared_data / "c3d" / name)
        assert d.n_frames > 0 and d.n_markers > 0
        assert np.isfinite(d.positions).any()
    tennis = read_c3d(shared_data / "c3d" / "ktk_tennis_serve_optitrack.c3d")
    assert tennis.n_markers == 39 and tennis.n_frames == 1092
    assert tennis.rate_hz == pytest.approx(50.0)
    # a person's markers lie within a few metres, so units came through as metres
    assert np.nanmax(np.abs(tennis.positions)) < 10.0
    with pytest.warns(UserWarning, match="announces 3679 frames, the data holds 3678"):
        basket = read_c3d(shared_data / "c3d" / "ktk_basket_sprint.c3d")
    assert basket.n_frames == 3678


def test_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match="positions.shape"):
        MarkerData(positions=np.zeros((3, 4)), labels=("a",), rate_hz=100)
    with pytest.raises(ValueError, match="labels"):
        MarkerData(positions=np.zeros((3, 2, 3)), labels=("a",), rate_hz=100)
    with pytest.raises(ValueError, match="rate_hz"):
        MarkerData(positions=np.zeros((3, 1, 3)), labels=("a",), rate_hz=0)
    with pytest.raises(FileNotFoundError, match="nope.trc"):
        read_markers(tmp_path / "nope.trc")
    with pytest.raises(ValueError, match="unknown marker file type"):
        write_markers(_data(np.random.default_rng(0)), tmp_path / "x.xyz")
    (tmp_path / "bad.trc").write_text("hello\n")
    with pytest.raises(ValueError, match="not a TRC"):
        read_markers(tmp_path / "bad.trc")
    (tmp_path / "bin.trc").write_bytes(bytes([0xff, 0xfe, 0x00, 0x81]) * 50)
    with pytest.raises(ValueError, match="bin.trc: not a text marker file"):
        read_markers(tmp_path / "bin.trc")
    (tmp_path / "folder.c3d").mkdir()
    with pytest.raises(ValueError, match="folder.c3d: not a file"):
        read_markers(tmp_path / "folder.c3d")
    empty = MarkerData(positions=np.zeros((0, 2, 3)), labels=("a", "b"), rate_hz=100)
    with pytest.raises(ValueError, match="no frames to write"):
        write_markers(empty, tmp_path / "empty.c3d")
    assert not list(tmp_path.glob("empty.c3d*"))


def test_truncated_c3d_is_refused(tmp_path):
    """A C3D cut short (a copy interrupted) is an error, not a shorter recording; one frame
    short of the header's count is read with a warning (an exporter's off-by-one: the
    ktk basketball file of ../shared/data announces 3679 frames and holds 3678)."""
    d = _data(np.random.default_rng(0))
    full = write_markers(d, tmp_path / "full.c3d").read_bytes()
    cut = tmp_path / "cut.c3d"
    cut.write_bytes(full[:len(full) - 3 * 512])
    with pytest.raises(ValueError, match="cut.c3d: truncated C3D file: the header announces "
                                         f"{d.n_frames} frames"):
        read_markers(cut)


def test_c3d_with_more_than_255_markers_uses_labels2(tmp_path):
    """A long unlabelled take has hundreds of trajectories: POINT:LABELS2, LABELS3, ...
    carry the labels past 255; an independent reader sees every marker and label."""
    import ezc3d
    rng = np.random.default_rng(5)
    P = rng.normal(size=(6, 600, 3))
    P[2, 300] = np.nan
    labels = tuple(f"T{i}" for i in range(600))
    path = write_markers(MarkerData(positions=P, labels=labels, rate_hz=120.0),
                         tmp_path / "big.c3d")
    back = read_markers(path)
    assert back.labels == labels
    np.testing.assert_allclose(back.positions, P, atol=1e-6)   # float32 mm storage
    c = ezc3d.c3d(str(path))
    assert c["data"]["points"].shape == (4, 600, 6)
    point = c["parameters"]["POINT"]
    got = list(point["LABELS"]["value"]) + list(point["LABELS2"]["value"]) \
        + list(point["LABELS3"]["value"])
    assert [s.strip() for s in got] == list(labels)
    xyz = np.transpose(c["data"]["points"][:3], (2, 1, 0)) / 1000.0
    ok = np.isfinite(P)
    np.testing.assert_allclose(xyz[ok], P[ok], atol=1e-6)
