"""skeleton.star_fit: a junction's star model fitted to all its markers, vs hw_sim truth."""
from __future__ import annotations

import numpy as np
import pytest

from hw_sim.articulated import animate, random_tree
from skeleton.pipeline import lowpass
from skeleton.star_fit import STAR_FRAMES, star_misfit
from tests.skeleton._figures import members


def _siblings(seed, min_gap_m, max_gap_m, soft_tissue_m=0.0):
    """The first random figure from ``seed`` on with two siblings whose joints on their
    parent lie between the gaps given (``soft_tissue_m``: hw_sim's soft-tissue artefacts,
    the same motion otherwise). Returns (fig, motion, parent, a, b, gap_m)."""
    for s in range(seed, seed + 500):
        g = np.random.default_rng(s)
        fig = random_tree(int(g.integers(5, 12)), (3, 4), rng=g)
        for p in range(fig.n_segments):
            ch = np.flatnonzero(fig.parents == p)
            for i, a in enumerate(ch):
                for b in ch[i + 1:]:
                    d = float(np.linalg.norm(fig.joint_offsets[a] - fig.joint_offsets[b]))
                    if min_gap_m <= d <= max_gap_m:
                        mo = animate(fig, 600, rng=g, rom_deg=60.0,
                                     soft_tissue_m=soft_tissue_m)
                        return fig, mo, p, int(a), int(b), d
    raise AssertionError("no such siblings")


@pytest.mark.parametrize("seed", [0, 100])
def test_true_star_fits_exact_data_and_a_sibling_hub_does_not(seed):
    """Noise-free markers: the star around the true parent reproduces them to ~0 (the
    model holds exactly), the star around either sibling misses by the joint gap times
    the sibling's rotation."""
    fig, mo, p, a, b, gap = _siblings(seed, 0.005, 0.03)
    c = 0.5 * (mo.joint_centres[:, a] + mo.joint_centres[:, b])
    fits = {h: star_misfit(mo.markers, members(fig), {p, a, b}, h, c) for h in (p, a, b)}
    assert all(f.ok for f in fits.values())
    rms = {h: np.sqrt(f.ssq_m2 / f.n_res) for h, f in fits.items()}
    assert rms[p] < 1e-6, rms
    assert min(rms[a], rms[b]) > 20 * max(rms[p], 1e-7), (gap, rms)
    assert len({f.n_par for f in fits.values()}) == 1     # the same model size whatever hub


def test_true_star_residual_is_the_marker_noise():
    """1 mm white noise on raw markers: the true star's residual per coordinate is the
    noise less the share the parameters absorb (n_par of n_res), within 5 %."""
    fig, mo, p, a, b, _ = _siblings(0, 0.005, 0.03)
    noisy = mo.markers + np.random.default_rng(1).normal(0, 1e-3, mo.markers.shape)
    c = 0.5 * (mo.joint_centres[:, a] + mo.joint_centres[:, b])
    f = star_misfit(noisy, members(fig), {p, a, b}, p, c)
    expected = 1e-6 * (1 - f.n_par / f.n_res)
    assert abs(f.ssq_m2 / f.n_res / expected - 1) < 0.05, f


@pytest.mark.parametrize("seed", [0, 100, 200])
def test_parent_hub_wins_for_siblings_a_few_mm_apart_at_one_mm_noise(seed):
    """Siblings 4-8 mm apart, 1 mm noise, low-passed as the solver does: the true hub's
    star fits best, by more than the margin the junction step trusts (STAR_MARGIN x the
    residual variance). (The pairwise joint costs do not tell such siblings apart; the
    margin grows with the gap squared, so at 1-2 mm it is often below STAR_MARGIN.)"""
    from skeleton.junctions import STAR_MARGIN
    fig, mo, p, a, b, gap = _siblings(seed, 0.004, 0.008)
    noisy = mo.markers + np.random.default_rng(2).normal(0, 1e-3, mo.markers.shape)
    data = lowpass(noisy, mo.rate_hz)
    c = 0.5 * (mo.joint_centres[:, a] + mo.joint_centres[:, b])
    fits = {h: star_misfit(data, members(fig), {p, a, b}, h, c) for h in (p, a, b)}
    var = fits[p].ssq_m2 / fits[p].n_res
    margin = min(fits[a].ssq_m2, fits[b].ssq_m2) - fits[p].ssq_m2
    assert margin > STAR_MARGIN * var, (gap, margin / var)


def test_star_misfit_rejects_bad_input_and_reports_unseen_markers():
    fig, mo, p, a, b, _ = _siblings(0, 0.005, 0.03)
    c = mo.joint_centres[:, a]
    with pytest.raises(ValueError, match="hub"):
        star_misfit(mo.markers, members(fig), {a, b}, p, c)
    with pytest.raises(ValueError, match="hub"):
        star_misfit(mo.markers, members(fig), {p}, p, c)
    hidden = mo.markers.copy()
    hidden[:, members(fig)[a][0]] = np.nan
    f = star_misfit(hidden, members(fig), {p, a, b}, p, c)
    assert not f.ok and "frames" in f.reason and not np.isfinite(f.ssq_m2)


def test_star_reports_its_fitted_joints_on_the_fitted_frames():
    """StarFit.joints: each member's joint with the hub in world coordinates, on the frames
    fitted (NaN elsewhere): started 15 mm off, the true star's joints come back to the true
    joints (ball joints of 3-4-marker segments, 1 mm noise)."""
    for seed in range(0, 1000, 100):
        fig, mo, p, a, b, _ = _siblings(seed, 0.02, 0.2)
        if fig.joint_types[a] == fig.joint_types[b] == "ball":   # a hinge's centre is free
            break                                                # along its axis
    else:
        raise AssertionError("no siblings with two ball joints")
    noisy = mo.markers + np.random.default_rng(4).normal(0, 1e-3, mo.markers.shape)
    data = lowpass(noisy, mo.rate_hz)
    off = np.array([0.015, 0.0, 0.0])
    f = star_misfit(data, members(fig), {p, a, b}, p,
                       {a: mo.joint_centres[:, a] + off, b: mo.joint_centres[:, b] + off})
    assert f.ok and set(f.joints) == {a, b}
    for s in (a, b):
        fitted = ~np.isnan(f.joints[s]).any(1)
        assert fitted.sum() == STAR_FRAMES
        err = np.linalg.norm(f.joints[s][fitted] - mo.joint_centres[fitted, s], axis=1)
        assert np.median(err) < 0.003, (s, np.median(err))


def test_residual_tau_counts_frames_that_move_together():
    """White residuals: tau ~1; each value held for 5 frames (a moving sum of 5 white
    samples): tau ~5 (1 + 2 sum_k (1 - k/5)); a constant: 1 (nothing to correlate)."""
    from skeleton.star_fit import residual_tau
    w = np.random.default_rng(0).normal(size=(4000, 6))
    assert abs(residual_tau(w) - 1) < 0.15
    held = np.cumsum(w, 0)
    held = held[5:] - held[:-5]
    assert abs(residual_tau(held) - 5) < 0.6
    assert residual_tau(np.ones((100, 3))) == 1.0


def test_soft_tissue_residuals_move_together_and_widen_the_margin_unit():
    """The true star's residuals: raw 1 mm noise, tau ~1; low-passed as the solver does,
    below TAU_REF (the unit is the residual variance); with skin markers sliding 2 mm on
    their bones (hw_sim's soft_tissue_m) far above it, and the margin's unit grows by
    tau / TAU_REF."""
    from skeleton.star_fit import TAU_REF, margin_unit
    fig, mo, p, a, b, _ = _siblings(0, 0.005, 0.03)
    c = 0.5 * (mo.joint_centres[:, a] + mo.joint_centres[:, b])
    g = np.random.default_rng(1)
    noisy = mo.markers + g.normal(0, 1e-3, mo.markers.shape)
    raw = star_misfit(noisy, members(fig), {p, a, b}, p, c)
    low = star_misfit(lowpass(noisy, mo.rate_hz), members(fig), {p, a, b}, p, c)
    assert raw.tau < 1.5 and 1.5 < low.tau < TAU_REF, (raw.tau, low.tau)
    assert margin_unit(low) == low.ssq_m2 / low.n_res
    soft = _siblings(0, 0.005, 0.03, soft_tissue_m=2e-3)[1]
    assert np.abs(soft.joint_centres - mo.joint_centres).max() < 1e-12   # same motion
    sft = star_misfit(lowpass(soft.markers + g.normal(0, 1e-3, mo.markers.shape), mo.rate_hz),
                      members(fig), {p, a, b}, p, c)
    assert sft.tau > 3 * TAU_REF, sft.tau
    assert margin_unit(sft) == pytest.approx(sft.ssq_m2 / sft.n_res * sft.tau / TAU_REF)
