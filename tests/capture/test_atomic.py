"""capture.atomic: a result file is replaced whole or left as it was, and no ``*.tmp`` stays."""
from __future__ import annotations

import numpy as np
import pytest

from calibration.rig_io import load_rig, save_rig
from capture.atomic import atomic_file
from hw_sim.rig import make_rig
from reconstruct.marker_files import MarkerData, read_markers, write_markers


def test_a_finished_write_replaces_the_file(tmp_path):
    p = tmp_path / "out.txt"
    p.write_text("old")
    with atomic_file(p) as f:
        f.write("new")
        assert p.read_text() == "old"               # not visible before the block ends
    assert p.read_text() == "new" and sorted(tmp_path.iterdir()) == [p]


def test_a_failed_write_leaves_the_file_and_no_tmp(tmp_path):
    p = tmp_path / "out.bin"
    p.write_bytes(b"old")
    with pytest.raises(RuntimeError, match="disk gone"):
        with atomic_file(p, "wb") as f:
            f.write(b"half a fi")
            raise RuntimeError("disk gone")
    assert p.read_bytes() == b"old" and sorted(tmp_path.iterdir()) == [p]
    with pytest.raises(RuntimeError):
        with atomic_file(tmp_path / "new.bin", "wb") as f:
            raise RuntimeError("before any byte")
    assert sorted(tmp_path.iterdir()) == [p]            # no empty or partial new file


def test_bad_mode_is_refused(tmp_path):
    with pytest.raises(ValueError, match="mode='a'"):
        with atomic_file(tmp_path / "x", "a"):
            pass


def test_a_calibration_that_fails_to_serialise_keeps_the_previous_one(tmp_path):
    """A value TOML cannot hold (a NumPy integer) fails the write: the rig saved before is
    still there, whole, and no rig.toml.tmp is left (stop 27's report of a stray *.tmp)."""
    rig = make_rig(2, rng=0)
    p = save_rig(rig, tmp_path / "rig.toml")
    before = p.read_bytes()
    with pytest.raises(TypeError, match="int64"):
        save_rig(rig, p, metadata={"frames": np.int64(3)})
    assert p.read_bytes() == before and sorted(tmp_path.iterdir()) == [p]
    assert len(load_rig(p)) == 2


@pytest.mark.parametrize("suffix", [".c3d", ".trc", ".csv"])
def test_marker_files_are_replaced_whole(tmp_path, suffix, monkeypatch):
    """A marker file write that fails part-way (here: the disk fills after the first write
    call) leaves the previous file readable and nothing beside it."""
    rng = np.random.default_rng(0)
    data = MarkerData(positions=rng.normal(size=(20, 3, 3)), labels=("a", "b", "c"),
                      rate_hz=100.0)
    p = write_markers(data, tmp_path / f"m{suffix}")
    before = p.read_bytes()
    import builtins
    real_open = builtins.open

    def failing_open(file, mode="r", *a, **kw):
        f = real_open(file, mode, *a, **kw)
        if str(file).endswith(".tmp"):
            write = f.write

            def once(b):
                write(b)
                raise OSError(28, "No space left on device")
            f.write = once
        return f
    monkeypatch.setattr(builtins, "open", failing_open)
    with pytest.raises(OSError, match="No space"):
        write_markers(MarkerData(positions=data.positions * 2, labels=data.labels,
                                 rate_hz=100.0), p)
    monkeypatch.undo()
    assert p.read_bytes() == before and sorted(tmp_path.iterdir()) == [p]
    np.testing.assert_allclose(read_markers(p).positions, data.positions, atol=1e-4)
