"""Skeleton outputs on random simulated figures: marker sets, fit back, BVH (bvhio).

Usage: python benchmarks/bench_skeleton_outputs.py [n_figures=10] [n_frames=400]
Per random tree (5-20 segments, 2-4 markers per segment, n_frames at 120 Hz):
- marker sets: every trajectory cut at 1-3 random occlusions (3-40 frames) into new ids
  plus 5 ghosts; a figure counts as merged when every physical marker gets exactly one id
  and no id mixes two markers (figures with two markers of one segment closer than 20 mm
  are counted apart: hw_sim placed such markers before its 20 mm default spacing);
- fit back (1 mm noise and noise-free, true number of segments): median per-frame joint
  error (hinges perpendicular to the axis) of the closed-form fit, of the IK after it and
  of the solver's own per-frame estimate; mean marker deviation;
- BVH: max |bvhio world position - fitted joint| (m).
Times: the merge against the solver (``solve_skeleton``) on the same figure, the fit back
against the solver. The hip .sto residual is printed when ../shared/data is present.
"""
from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hw_sim.articulated import animate, random_tree  # noqa: E402
from skeleton.bvh import Y_UP_FROM_Z_UP, write_bvh  # noqa: E402
from skeleton.fit import fit_skeleton  # noqa: E402
from skeleton.ik import refine_fit  # noqa: E402
from skeleton.markersets import merge_fragments  # noqa: E402
from skeleton.pipeline import solve_skeleton  # noqa: E402
from skeleton.rigid_skeleton import build_rigid_skeleton  # noqa: E402
from tests.skeleton._figures import (fragment, joint_errors, marker_spacing,  # noqa: E402
                                     segment_map)




def bvh_error(rig, fit):
    import bvhio
    with tempfile.TemporaryDirectory() as d:
        p = write_bvh(Path(d) / "s.bvh", rig, fit)
        root = bvhio.readAsHierarchy(str(p))
        names = list(rig.segment_names)
        T = fit.joint_centres.shape[0]
        err = 0.0
        for f in range(T):
            root.loadPose(f)
            for j, _, _ in root.layout():
                w = Y_UP_FROM_Z_UP @ fit.joint_centres[f, names.index(j.Name)]
                err = max(err, float(np.abs(np.array(j.PositionWorld) - w).max()))
    return err


def main(n_fig=10, T=400):
    rows = []
    for k in range(n_fig):
        g = np.random.default_rng(1000 + k)
        fig = random_tree(int(g.integers(5, 21)), (2, 4), rng=1000 + k)
        mo = animate(fig, T, rng=1000 + k, rom_deg=60.0)
        X, owner = fragment(mo.markers + g.normal(0, 1e-3, mo.markers.shape), k,
                            n_gaps=(1, 4), gap_frames=(3, 40))
        t0 = time.perf_counter()
        ms = merge_fragments(X)
        t_merge = time.perf_counter() - t0
        pure = all(len({owner[f] for f in grp}) == 1 for grp in ms.groups)
        one = sorted(owner[grp[0]] for grp in ms.groups) == list(range(fig.n_markers))
        r = {"S": fig.n_segments, "M": fig.n_markers, "F": X.shape[1], "merged": pure and one,
             "pure": pure, "physical": marker_spacing(fig) >= 0.02, "t_merge": t_merge}
        for noise in (0.0, 1e-3):
            tr = mo.markers + g.normal(0, noise, mo.markers.shape)
            t0 = time.perf_counter()
            res = solve_skeleton(tr, mo.rate_hz, n_segments=fig.n_segments, rng=0)
            t_solve = time.perf_counter() - t0
            segmap = segment_map(fig, res.labels)
            try:
                rig = build_rigid_skeleton(tr, res)
            except ValueError as e:
                r[f"fit{noise}"] = f"rigid skeleton failed: {e}"
                continue
            t0 = time.perf_counter()
            fit0 = fit_skeleton(tr, rig, mo.rate_hz)
            t_fit = time.perf_counter() - t0
            t0 = time.perf_counter()
            fit = refine_fit(tr, rig, fit0)
            t_ik = time.perf_counter() - t0
            try:
                e0 = joint_errors(fig, mo, rig.parents, fit0.joint_centres, segmap)
                ef = joint_errors(fig, mo, rig.parents, fit.joint_centres, segmap)
                es = joint_errors(fig, mo, res.parents, res.joint_centres, segmap)
                r[f"fit{noise}"] = (np.nanmedian(ef), np.nanmedian(es),
                                    np.nanmean(fit.marker_deviation(tr)), np.nanmedian(e0),
                                    np.nanmean(fit0.marker_deviation(tr)))
            except (AssertionError, TypeError):
                r[f"fit{noise}"] = "topology/segments wrong"
            r[f"t_solve{noise}"], r[f"t_fit{noise}"], r[f"t_ik{noise}"] = t_solve, t_fit, t_ik
            if noise == 0.0:
                r["bvh"] = bvh_error(rig, fit)
        rows.append(r)
        f0, f1 = r.get("fit0.0"), r.get("fit0.001")
        fmt = (lambda f: f"{1e3 * f[3]:.3f}/{1e3 * f[0]:.3f}/{1e3 * f[1]:.3f}/{1e3 * f[2]:.3f}"
               if isinstance(f, tuple) else str(f))
        print(f"fig {k}: S={r['S']:2d} M={r['M']:2d} fragments={r['F']:3d} merged={r['merged']}"
              f" (pure={r['pure']}, spacing>=20mm={r['physical']}) merge {t_merge:.2f}s | "
              f"joint median closed/IK/solver, IK marker dev mm: exact {fmt(f0)}  1mm {fmt(f1)} | "
              f"bvh {r.get('bvh', np.nan):.2e} m", flush=True)
    phys = [r for r in rows if r["physical"]]
    print(f"\nmarker sets: {sum(r['merged'] for r in phys)}/{len(phys)} physical figures "
          f"merged exactly; {sum(r['merged'] for r in rows)}/{len(rows)} all; "
          f"{sum(r['pure'] for r in rows)}/{len(rows)} without a wrong merge")
    for key, lab in (("fit0.0", "noise-free"), ("fit0.001", "1 mm noise")):
        v = np.array([r[key] for r in rows if isinstance(r.get(key), tuple)])
        if v.size:
            print(f"fit back {lab} (median over {len(v)} figures of the per-figure median "
                  f"per-frame joint error): closed form {1e3 * np.median(v[:, 3]):.3f} mm, IK "
                  f"{1e3 * np.median(v[:, 0]):.3f} mm, solver per-frame "
                  f"{1e3 * np.median(v[:, 1]):.3f} mm; mean marker deviation closed form "
                  f"{1e3 * np.median(v[:, 4]):.3f} mm, IK {1e3 * np.median(v[:, 2]):.3f} mm")
    print(f"BVH (bvhio) max position error: {max(r.get('bvh', 0) for r in rows):.2e} m "
          "(target 1e-4 m)")
    tm = np.array([r["t_merge"] for r in rows])
    ts = np.array([r["t_solve0.0"] for r in rows])
    tf = np.array([r["t_fit0.0"] for r in rows if "t_fit0.0" in r])
    ti = np.array([r["t_ik0.0"] for r in rows if "t_ik0.0" in r])
    print(f"time per figure ({T} frames): merge {tm.mean():.2f} s, solve {ts.mean():.2f} s, "
          f"closed-form fit {tf.mean():.3f} s, IK {ti.mean():.3f} s; ratios to the solver in "
          f"the same run: merge {tm.sum() / ts.sum():.2f}, fit {tf.sum() / ts.sum():.3f}, "
          f"IK {ti.sum() / ts.sum():.3f}")
    sto = Path(__file__).resolve().parents[2] / "shared/data/joint_centres/" \
        "fjc_hip_synthetic_OutputsVec3.sto"
    if sto.exists():
        from skeleton.joints import fit_joint
        from tests.skeleton.test_hip_centre import PELVIS, THIGH, read_sto_vec3
        _, Xh, _ = read_sto_vec3(sto)
        f = fit_joint(Xh, PELVIS, THIGH)
        print(f"hip (.sto): residual {1e3 * f.residual_m:.2e} mm (target <= 0.1 mm), "
              f"hinge (planar motion) = {f.hinge}")


if __name__ == "__main__":
    a = [int(x) for x in sys.argv[1:]]
    main(*a)
