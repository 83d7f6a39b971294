"""mocap skeleton: a C3D / TRC from a hw_sim figure -> BVH + skeleton JSON + tables."""
from __future__ import annotations

import numpy as np
import pytest

from hw_sim.articulated import animate, random_tree
from mocap.cli import main
from reconstruct.marker_files import MarkerData, write_markers
from skeleton.app import run_skeleton
from skeleton.report import read_skeleton_json
from tests.skeleton._figures import fragment, joint_errors, segment_map


@pytest.fixture(scope="module")
def figure():
    fig = random_tree(5, (3, 4), rng=8)
    return fig, animate(fig, 240, rng=8)


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("suffix", [".c3d", ".trc"])
def test_cli_writes_bvh_and_report(tmp_path, capsys, figure, suffix):
    fig, mo = figure
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / f"m{suffix}")
    bvh, rep = tmp_path / "s.bvh", tmp_path / "s.json"
    code = main(["skeleton", str(src), "-o", str(bvh), "--report", str(rep), "--seed", "1"])
    out = capsys.readouterr()
    assert code == 0
    assert "[skeleton] segments: 5" in out.err and "fit back" in out.err
    assert "joint costs: 10/10 segment pairs" in out.err        # progress within the step
    assert "5 segments, " in out.out and "Average deviation" in out.out
    rig = read_skeleton_json(rep)
    assert rig.n_segments == 5 and rig.marker_names == fig.marker_names
    text = bvh.read_text()
    assert text.startswith("HIERARCHY") and text.count("JOINT ") == 4
    assert "Frames: 240" in text
    # files store mm with float32 (C3D) / 6 decimals (TRC): deviations stay sub-0.1 mm
    import json
    d = json.loads(rep.read_text())
    assert d["extra"]["mean_marker_deviation_mm"] < 0.1


def test_cli_segments_flag_and_missing_file(tmp_path, capsys, figure):
    fig, mo = figure
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / "m.trc")
    assert main(["skeleton", str(src), "-o", str(tmp_path / "a.bvh"), "--segments", "4"]) == 0
    assert "4 segments, " in capsys.readouterr().out
    assert main(["skeleton", str(tmp_path / "nope.c3d"), "-o", str(tmp_path / "b.bvh")]) == 2


def test_run_skeleton_on_tracker_fragments(figure):
    """The library entry: fragments with new ids -> one id per marker -> the true skeleton."""
    fig, mo = figure
    X, owner = fragment(mo.markers, 3, n_gaps=(1, 3), gap_frames=(3, 20))
    labels = tuple(f"T{i:03d}" for i in range(X.shape[1]))
    run = run_skeleton(MarkerData(positions=X, labels=labels, rate_hz=mo.rate_hz),
                       n_segments=None, rng=0)
    assert run.markersets.n_markers == fig.n_markers
    phys = np.array([owner[g[0]] for g in run.markersets.groups])
    assert sorted(phys) == list(range(fig.n_markers))
    # segment labels of the merged markers, in truth order
    lab = np.empty(fig.n_markers, int)
    lab[phys] = run.result.labels
    segmap = segment_map(fig, lab)
    assert segmap is not None and run.rigid.n_segments == fig.n_segments
    err = joint_errors(fig, mo, run.rigid.parents, run.fit.joint_centres, segmap)
    assert np.isfinite(err).mean() > 0.9 and np.nanmax(err) < 1e-8   # exact where fitted


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_cli_reports_a_junction(tmp_path, capsys):
    """Two siblings whose joints coincide: the summary and the JSON name the junction and
    the hub the solver chose (here the true parent)."""
    import json

    from tests.skeleton.test_junctions import _junction_figure
    fig, p, a, b = _junction_figure(0)
    mo = animate(fig, 600, rng=0, rom_deg=60.0)
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / "m.c3d")
    rep = tmp_path / "s.json"
    assert main(["skeleton", str(src), "-o", str(tmp_path / "s.bvh"), "--report", str(rep),
                 "--no-merge"]) == 0
    out = capsys.readouterr()
    d = json.loads(rep.read_text())
    rig = read_skeleton_json(rep)
    lab = np.array([int(rig.marker_segment[rig.marker_names.index(n)])
                    for n in fig.marker_names])
    segmap = segment_map(fig, lab)
    assert segmap is not None
    names = {f"seg{segmap[s]}" for s in (p, a, b)}
    found = [j for j in d["extra"]["junctions"] if set(j["segments"]) == names]
    assert len(found) == 1 and found[0]["hub"] == f"seg{segmap[p]}"
    assert found[0]["joint_spread_m"] < 1e-6          # coincident joints, no noise
    assert "junction: " in out.out and "junction: " in out.err


def test_cli_refuses_bad_paths_before_any_work(tmp_path, capsys, figure):
    """Output checks come first: a BVH never overwrites its input, a missing folder or a
    folder as output is refused before the solve (and before any output is written)."""
    fig, mo = figure
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / "m.c3d")
    before = src.read_bytes()
    cases = [(["-o", str(src)], "same file as the input"),
             (["-o", str(tmp_path / "no" / "s.bvh")], "does not exist"),
             (["-o", str(tmp_path)], "is a folder"),
             (["-o", str(tmp_path / "s.bvh"), "--report", str(tmp_path / "s.bvh")],
              "same file as -o"),
             (["-o", str(tmp_path / "s.bvh"), "--report", str(tmp_path / "no" / "r.json")],
              "does not exist")]
    for args, msg in cases:
        assert main(["skeleton", str(src)] + args) == 2
        err = capsys.readouterr().err
        assert msg in err and "[skeleton] read" not in err, err
    assert src.read_bytes() == before and not (tmp_path / "s.bvh").exists()
    (tmp_path / "folder.c3d").mkdir()
    assert main(["skeleton", str(tmp_path / "folder.c3d"), "-o", str(tmp_path / "s.bvh")]) == 2
    assert "not a file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["skeleton", str(src), "-o", str(tmp_path / "s.bvh"), "--segments", "0"])


def test_cli_explains_empty_and_short_recordings(tmp_path, capsys, figure):
    fig, mo = figure
    cases = [(np.full_like(mo.markers, np.nan), "no marker has a sample"),
             (mo.markers[:5], "has 5 frames, fewer than min_frames=10")]
    for k, (x, msg) in enumerate(cases):
        src = write_markers(MarkerData(positions=x, labels=fig.marker_names,
                                       rate_hz=mo.rate_hz), tmp_path / f"m{k}.trc")
        assert main(["skeleton", str(src), "-o", str(tmp_path / "s.bvh")]) == 2
        assert msg in capsys.readouterr().err
    # --segments above the number of markers is refused before the solve
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / "m.trc")
    n = fig.n_markers + 1
    assert main(["skeleton", str(src), "-o", str(tmp_path / "s.bvh"), "--segments", str(n)]) == 2
    err = capsys.readouterr().err
    assert f"n_segments={n}: more segments than the {fig.n_markers} markers" in err
    assert "segments:" not in err


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_a_marker_without_samples_is_named_and_left_out(tmp_path, capsys, figure):
    fig, mo = figure
    x = mo.markers.copy()
    x[:, 2] = np.nan
    src = write_markers(MarkerData(positions=x, labels=fig.marker_names, rate_hz=mo.rate_hz),
                        tmp_path / "m.c3d")
    for extra in ([], ["--no-merge"]):
        assert main(["skeleton", str(src), "-o", str(tmp_path / "s.bvh")] + extra) == 0
        out = capsys.readouterr()
        assert f"1 of {fig.n_markers} trajectories have no sample and are left out: " \
               f"{fig.marker_names[2]}" in out.err
        assert f"5 segments, {fig.n_markers - 1} markers" in out.out


def test_cli_warns_when_the_skeleton_fits_poorly(tmp_path, capsys, figure):
    """Five segments forced into one rigid body: the fit misses the markers by centimetres,
    and the run says so (the figure's own five segments fit exactly: no warning)."""
    fig, mo = figure
    src = write_markers(MarkerData(positions=mo.markers, labels=fig.marker_names,
                                   rate_hz=mo.rate_hz), tmp_path / "m.trc")
    assert main(["skeleton", str(src), "-o", str(tmp_path / "a.bvh"), "--segments", "1"]) == 0
    err = capsys.readouterr().err
    assert "[skeleton] warning: mean marker deviation" in err and "fit this rigid" in err
    assert "Mean of empty slice" not in err          # no NumPy noise for one segment
    assert main(["skeleton", str(src), "-o", str(tmp_path / "b.bvh")]) == 0
    assert "warning: mean marker deviation" not in capsys.readouterr().err


def test_mocap_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0 and capsys.readouterr().out.startswith("mocap 0.")
