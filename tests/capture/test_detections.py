"""2D detections table and its CSV form."""
import numpy as np
import pytest

from capture.detections import Detections2D, read_detections_csv, write_detections_csv


def test_csv_roundtrip_with_names_and_indices(tmp_path):
    rng = np.random.default_rng(0)
    names = tuple(f"cam_{i}" for i in range(12))
    frames = [[rng.uniform(0, 1000, (rng.integers(0, 4), 2)) for _ in names] for _ in range(20)]
    det = Detections2D.from_per_frame(frames, names, rate_hz=120.0)
    p = write_detections_csv(det, tmp_path / "obs.csv")
    back = read_detections_csv(p)
    assert back.camera_names == names and back.rate_hz == 120.0
    np.testing.assert_array_equal(back.frame, det.frame)
    np.testing.assert_array_equal(back.camera, det.camera)
    np.testing.assert_array_equal(back.xy, det.xy)  # repr() keeps every bit
    # indices instead of names, with the rig's names supplied
    p2 = tmp_path / "idx.csv"
    p2.write_text("frame,camera,x,y\n0,11,1.5,2.5\n0,2,3.0,4.0\n1,10,5,6\n1,2,nan,nan\n")
    d2 = read_detections_csv(p2, camera_names=names)
    assert d2.camera.tolist() == [2, 11, 10] and len(d2) == 3
    per = d2.per_camera(d2.frame_slices()[0])
    assert per[11].tolist() == [[1.5, 2.5]]


def test_bad_inputs(tmp_path):
    with pytest.raises(ValueError, match=r"xy.shape=\(3,\)"):
        Detections2D(frame=[0], camera=[0], xy=np.zeros(3), camera_names=("a",))
    with pytest.raises(ValueError, match="camera index out of range"):
        Detections2D(frame=[0], camera=[3], xy=np.zeros((1, 2)), camera_names=("a",))
    with pytest.raises(FileNotFoundError):
        read_detections_csv(tmp_path / "none.csv")
    p = tmp_path / "bad.csv"
    p.write_text("frame,cam,x,y\n0,0,1,2\n")
    with pytest.raises(ValueError, match="expected at least frame,camera,x,y"):
        read_detections_csv(p)
    p.write_text("frame,camera,x,y\n0,zz,1,2\n")
    with pytest.raises(ValueError, match="unknown camera 'zz'"):
        read_detections_csv(p, camera_names=("a", "b"))
    p.write_text("frame,camera,x,y\nzero,0,1,2\n")
    with pytest.raises(ValueError, match=":2: bad row"):
        read_detections_csv(p)


def test_csv_roundtrip_keeps_blob_areas(tmp_path):
    """Blob areas (which correspondence uses to spot merged blobs) survive the CSV; a file
    without the column reads back without areas."""
    rng = np.random.default_rng(1)
    det = Detections2D(frame=np.array([0, 0, 1]), camera=np.array([0, 1, 1]),
                       xy=rng.uniform(0, 100, (3, 2)), camera_names=("a", "b"), rate_hz=100.0,
                       area_px=np.array([12.0, 30.5, 7.25]))
    back = read_detections_csv(write_detections_csv(det, tmp_path / "a.csv"))
    np.testing.assert_array_equal(back.area_px, det.area_px)
    np.testing.assert_array_equal(back.xy, det.xy)
    p = tmp_path / "plain.csv"
    p.write_text("frame,camera,x,y\n0,a,1,2\n")
    assert read_detections_csv(p).area_px is None
    p.write_text("frame,camera,x,y,area_px\n0,a,1,2,big\n")
    with pytest.raises(ValueError, match="big"):
        read_detections_csv(p)
