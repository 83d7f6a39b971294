"""Real recording: the 4-2-3 marker arm (three segments in a chain)."""
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
