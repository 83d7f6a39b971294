"""Real recordings: the 4-2-3 marker arm (three segments in a chain); the tennis serve's left
leg (foot on the shank)."""
from __future__ import annotations

import numpy as np
import pytest

from skeleton.pipeline import solve_skeleton

ARM = "c3d/arm_4-2-3_markers_120fps.c3d"
T_USED = None  # all frames (10,608 at 120 Hz)


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("k", [3, None])
def test_arm_segments_and_chain(shared_data, k):
    """K given, and K chosen automatically (eigengap): the same three segments and chain."""
    from reconstruct.marker_files import read_markers

    d = read_markers(shared_data / ARM)
    res = solve_skeleton(d.positions[:T_USED], d.rate_hz, n_segments=k, rng=0)
    assert res.n_segments == 3
    groups = sorted(tuple(np.flatnonzero(res.labels == s).tolist()) for s in range(3))
    assert groups == [(0, 1, 2, 3), (4, 5), (6, 7, 8)]
    # chain: the two-marker segment is the middle one (the root, tree centre)
    mid = res.labels[4]
    assert res.root == mid
    assert sorted(res.parents.tolist()) == sorted([-1, mid, mid])


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_tennis_foot_hangs_from_its_shank(shared_data):
    """kineticstoolkit's OptiTrack tennis serve: the left foot (LHEE, LTOE) is linked to the
    shank (LANK, LTIB), not the thigh (LKNE, LTHI). The foot-thigh pair is false but fits a
    joint in the foot's frame completed by its (true) ankle anchor, 0.64x the floor, and
    misfits in the thigh's, completed by its (true) hip anchor, 2.79x: the completed-frame
    test must keep the larger. Stop 29 measured a veto by the smaller (78a2534, reverted):
    the foot hung from the thigh and the mean marker deviation rose 12.33 -> 13.14 mm."""
    from reconstruct.marker_files import read_markers
    from skeleton.app import run_skeleton

    run = run_skeleton(read_markers(shared_data / "c3d" / "ktk_tennis_serve_optitrack.c3d"),
                       rng=0)      # as `mocap skeleton` solves it
    res = run.result
    names = [str(n).split(":")[-1] for n in run.rigid.marker_names]
    seg = {n: int(res.labels[i]) for i, n in enumerate(names)}
    foot, shank, thigh = seg["LHEE"], seg["LANK"], seg["LKNE"]
    assert seg["LTOE"] == foot and seg["LTIB"] == shank and seg["LTHI"] == thigh
    assert len({foot, shank, thigh}) == 3

    def linked(a, b):
        return res.parents[a] == b or res.parents[b] == a

    assert linked(foot, shank) and not linked(foot, thigh)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_tennis_serve_fits_within_10_mm(shared_data):
    """The tennis serve as ``mocap skeleton`` solves it: mean marker deviation after the fit
    back 7.81 mm (stop 37). The recording's merged markers have gaps; with the low-pass
    cutting 1.5 periods of its cut-off from every run end (``skeleton.pipeline.TRIM_PERIODS``
    before stop 37) the costs lost the frames around every gap: 15.53 mm on stop 36's code,
    17.72 mm with only that trim put back."""
    from reconstruct.marker_files import read_markers
    from skeleton.app import run_skeleton

    run = run_skeleton(read_markers(shared_data / "c3d" / "ktk_tennis_serve_optitrack.c3d"),
                       rng=0)
    assert run.deviation.overall_mean_m < 0.010


def _segments_by_name(shared_data, stem):
    """Marker names per segment as ``mocap skeleton`` segments the recording: fragments merged
    into markers, 6 Hz low-passed (the data is noisy), automatic segment count."""
    from reconstruct.marker_files import read_markers
    from skeleton.markersets import merge_fragments
    from skeleton.pipeline import lowpass
    from skeleton.segments import segment_markers

    d = read_markers(shared_data / "c3d" / f"{stem}.c3d")
    sets = merge_fragments(np.asarray(d.positions, np.float64), min_frames=10)
    names = [str(d.labels[g[0]]).split(":")[-1] for g in sets.groups]
    seg = segment_markers(lowpass(sets.positions, d.rate_hz, trim=True), None, rng=0)
    return [{names[i] for i in np.flatnonzero(seg.labels == s)} for s in range(seg.n_segments)]


@pytest.mark.filterwarnings("ignore::UserWarning")
@pytest.mark.parametrize("stem", ["cmu_85_02", "cmu_85_12"])
def test_cmu_legs_segment_anatomically(shared_data, stem):
    """CMU's 41-marker set: the pelvis (LFWT RFWT LBWT RBWT) is one segment, each thigh is
    its THI and KNE markers, and no segment mixes the pelvis, thigh, shank (SHN ANK) and
    foot (MT5 TOE) of a leg. The eigengap's count (11 and 9) left clusters that were not
    rigid; split and folded back one marker at a time, they came out as {pelvis + RTHI},
    {RKNE RSHN RANK} (85_12) and {RTHI RKNE RSHN}, {LSHN LANK LHEE LMT5 LTOE} (85_02), and
    the trees hung a foot from the other thigh. The automatic count now rises until every
    segment is rigid (or as rigid as any count makes it): 13 and 15 segments."""
    segs = _segments_by_name(shared_data, stem)
    assert {"LFWT", "RFWT", "LBWT", "RBWT"} in segs
    for side in "LR":
        assert {f"{side}THI", f"{side}KNE"} in segs
        parts = [{"LFWT", "RFWT", "LBWT", "RBWT"}, {f"{side}THI", f"{side}KNE"},
                 {f"{side}SHN", f"{side}ANK"}, {f"{side}MT5", f"{side}TOE"}]
        for s in segs:
            assert sum(bool(s & p) for p in parts) <= 1, (side, s)


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_tennis_segments_do_not_change_with_gaps(shared_data):
    """kineticstoolkit's tennis serve and its copy with NaN gaps segment alike: the left upper
    arm (LELB LUPA) apart from the forearm and hand (LFIN LFRM LWRA LWRB). Before the
    rigidity-driven count the two copies differed (eigengap 12 and 7) and LFRM sat on the
    upper arm in a cluster 7.6x the noise level."""
    a = _segments_by_name(shared_data, "ktk_tennis_serve_optitrack")
    b = _segments_by_name(shared_data, "ktk_tennis_serve_with_gaps")
    assert sorted(map(sorted, a)) == sorted(map(sorted, b))
    assert {"LELB", "LUPA"} in a and {"LFIN", "LFRM", "LWRA", "LWRB"} in a
