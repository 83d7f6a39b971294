"""``mocap reconstruct``: CSV from hw_sim.observe and a ``mocap capture --sim`` recording, to
C3D / TRC / CSV files read back by independent readers and compared with hw_sim truth."""
import numpy as np
import pytest

from calibration.rig_io import save_rig
from capture.detections import write_detections_csv
from hw_sim.observe import observe
from hw_sim.rig import make_rig
from hw_sim.scenes import figure
from mocap.cli import main
from tests.reconstruct.simdata import match_points, reconstructable

RATE_HZ = 120.0
N_FRAMES = 180
MATCH_M = 0.005            # a sample counts as a true marker within this distance
MIN_MATCHED = 0.995        # samples of the file that are a true marker
MIN_FOUND = 0.99           # markers seen by >= 2 cameras present in the file at that frame
RMS_3D_M = 0.0005          # 0.05 px at ~5 m, f ~1200 px (see tests/reconstruct/test_pipeline)
# the simulated recording: 640 x 512 px, f ~600 px, 14 mm markers at ~5.5 m are ~1.5 px blobs
# (a few single samples are off by 3-5 mm where blobs touch in a view)
SIM_RMS_M = 0.002
SIM_MAX_M = 0.010
SIM_RADIUS_M, SIM_PERIOD_S = 0.5, 4.0          # hw_sim.sim_camera.orbiting_markers defaults
SIM_Z = 1.25 + 0.2 * np.linspace(-1, 1, 8)      # orbiting_markers(8, height_m=1.25)


@pytest.fixture(scope="module")
def csv_session(tmp_path_factory):
    d = tmp_path_factory.mktemp("csv")
    rig = make_rig(8, dist=(-0.05, 0.01, 0.0, 0.0, 0.0), rng=3)
    scene = figure(N_FRAMES, RATE_HZ, 4)
    obs = observe(rig, scene, rng=5, noise_px=0.05, spurious_per_frame=0.25)
    save_rig(rig, d / "rig.toml")
    write_detections_csv(obs.detections, d / "det.csv")
    return d, rig, obs


def _ezc3d_points(path):
    import ezc3d
    c = ezc3d.c3d(str(path))
    par = c["parameters"]["POINT"]
    assert par["UNITS"]["value"][0].strip() == "mm"
    pts = np.transpose(c["data"]["points"][:3], (2, 1, 0)) / 1000.0    # (T, M, 3) m
    labels = [s.strip() for s in par["LABELS"]["value"]]
    return pts, float(par["RATE"]["value"][0]), labels, c["header"]["points"]["first_frame"]


def _read_trc(path):
    """A plain TRC parse (not our reader): 5 header lines, Frame#, Time, X1 Y1 Z1 ..."""
    lines = path.read_text().splitlines()
    keys, vals = lines[1].split("\t"), lines[2].split("\t")
    meta = dict(zip(keys, vals))
    names = [s for s in lines[3].split("\t")[2:] if s.strip()]
    rows = []
    for ln in lines[5:]:
        if not ln.strip():
            continue
        cells = ln.split("\t")
        rows.append([float(x) if x.strip() else np.nan for x in cells[2:2 + 3 * len(names)]])
    return np.array(rows).reshape(len(rows), len(names), 3), meta, names


def _score(pts, obs, first=0):
    """Matched fraction, found fraction and RMS of a (T, M, 3) file against truth."""
    need = reconstructable(obs)
    n_s = n_match = n_need = n_found = 0
    errs = []
    for t in range(pts.shape[0]):
        p = pts[t][np.all(np.isfinite(pts[t]), axis=1)]
        truth = obs.positions[first + t]
        m = match_points(p, truth, MATCH_M)
        n_s += len(p)
        n_match += int((m >= 0).sum())
        found = np.zeros(truth.shape[0], bool)
        found[m[m >= 0]] = True
        n_need += int(need[first + t].sum())
        n_found += int((found & need[first + t]).sum())
        errs.append(np.linalg.norm(p[m >= 0] - truth[m[m >= 0]], axis=1))
    e = np.concatenate(errs)
    return n_match / n_s, n_found / n_need, float(np.sqrt(np.mean(e ** 2)))


def test_csv_to_c3d_matches_truth(csv_session, capsys):
    d, rig, obs = csv_session
    out = d / "out.c3d"
    rc = main(["reconstruct", str(d / "det.csv"), "--calibration", str(d / "rig.toml"),
               "-o", str(out), "--workers", "2"])
    assert rc == 0
    text = capsys.readouterr()
    assert "reconstruction: " in text.err and "100%" in text.err      # progress on stderr
    assert "trajectories" in text.out and "x session duration" in text.out
    pts, rate, labels, first = _ezc3d_points(out)
    assert rate == pytest.approx(RATE_HZ)
    assert pts.shape[0] == N_FRAMES and len(labels) == pts.shape[1]
    assert labels[0] == "T1"
    matched, found, rms = _score(pts, obs)
    assert matched >= MIN_MATCHED, matched
    assert found >= MIN_FOUND, found
    assert rms < RMS_3D_M, rms


def test_csv_with_camera_indices_to_trc_and_csv(csv_session, tmp_path, capsys):
    d, rig, obs = csv_session
    # the same table with camera indices instead of names, without the header comment
    src = (d / "det.csv").read_text().splitlines()[1:]
    names = list(rig.names)
    rows = [src[0]] + [",".join([r.split(",")[0], str(names.index(r.split(",")[1]))]
                                + r.split(",")[2:]) for r in src[1:]]
    csv_idx = tmp_path / "det_idx.csv"
    csv_idx.write_text("\n".join(rows) + "\n")
    out = tmp_path / "out.trc"
    rc = main(["reconstruct", str(csv_idx), "--calibration", str(d / "rig.toml"), "-o",
               str(out), "--rate", "120", "--workers", "1", "--fill-max-gap", "4",
               "--cutoff-hz", "20"])
    assert rc == 0, capsys.readouterr().err
    pts_mm, meta, names_trc = _read_trc(out)
    assert meta["Units"] == "mm" and float(meta["DataRate"]) == pytest.approx(RATE_HZ)
    matched, found, rms = _score(pts_mm / 1000.0, obs)
    assert matched >= MIN_MATCHED and found >= MIN_FOUND and rms < RMS_3D_M
    assert "samples gap-filled" in capsys.readouterr().out
    out_csv = tmp_path / "out.csv"
    assert main(["reconstruct", str(csv_idx), "--calibration", str(d / "rig.toml"), "-o",
                 str(out_csv), "--rate", "120", "--workers", "1"]) == 0
    head = [ln for ln in out_csv.read_text().splitlines() if not ln.startswith("#")][0].split(",")
    assert head[:3] == ["frame", "time_s", "T1_x"]


def test_recording_of_frames_matches_truth(tmp_path, capsys):
    rec = tmp_path / "session"
    assert main(["capture", "--sim", "--cameras", "4", "--size", "640", "512", "--duration",
                 "0.8", "--rate", "50", "--out", str(rec)]) == 0
    capsys.readouterr()
    out = tmp_path / "rec.c3d"
    # calibration: the recording's own (sim_rig.toml), then given explicitly
    assert main(["reconstruct", str(rec), "-o", str(out)]) == 0
    assert "blob detection" in capsys.readouterr().out
    assert main(["reconstruct", str(rec), "--calibration", str(rec / "sim_rig.toml"),
                 "-o", str(out)]) == 0
    pts, rate, labels, _ = _ezc3d_points(out)
    assert rate == pytest.approx(50.0)
    ok = np.all(np.isfinite(pts), axis=2)
    assert ok.sum() >= 0.95 * 8 * pts.shape[0]                 # 8 markers, nearly always
    # truth of orbiting_markers: radius, height of each marker, common phase, angular rate
    def check(err_m):
        assert np.sqrt(np.mean(err_m ** 2)) < SIM_RMS_M and np.max(np.abs(err_m)) < SIM_MAX_M

    check(np.hypot(pts[..., 0], pts[..., 1])[ok] - SIM_RADIUS_M)
    k = np.argmin(np.abs(pts[..., 2, None] - SIM_Z), axis=-1)    # which marker (T, M)
    check((pts[..., 2] - SIM_Z[k])[ok])
    a = np.arctan2(pts[..., 1], pts[..., 0]) - 2 * np.pi * k / 8  # = common phase
    ph = np.angle(np.nanmean(np.exp(1j * a), axis=1))             # (T,)
    check(np.angle(np.exp(1j * (a - ph[:, None])))[ok] * SIM_RADIUS_M)
    step = np.median(np.diff(np.unwrap(ph)))
    assert step == pytest.approx(2 * np.pi / SIM_PERIOD_S / 50.0, rel=0.05)
    for m in range(pts.shape[1]):                                 # one marker per trajectory
        assert len(set(k[ok[:, m], m].tolist())) == 1


@pytest.mark.parametrize("case", ["missing_input", "missing_calibration", "bad_suffix",
                                  "unknown_camera"])
def test_clear_errors(csv_session, tmp_path, capsys, case):
    d, _, _ = csv_session
    args = [str(d / "det.csv"), "--calibration", str(d / "rig.toml"), "-o",
            str(tmp_path / "o.c3d")]
    if case == "missing_input":
        args[0] = str(tmp_path / "nope.csv")
        want = "nope.csv"
    elif case == "missing_calibration":
        args[2] = str(tmp_path / "nope.toml")
        want = "nope.toml"
    elif case == "bad_suffix":
        args[4] = str(tmp_path / "o.xyz")
        want = ".xyz"
    else:
        bad = tmp_path / "bad.csv"
        bad.write_text("frame,camera,x,y\n0,cam_1,1.0,2.0\n0,cam_99,3.0,4.0\n")
        args[0] = str(bad)
        want = "cam_99"
    assert main(["reconstruct", *args]) == 2
    err = capsys.readouterr().err
    assert "error" in err and want in err
    assert not (tmp_path / "o.c3d").exists()
