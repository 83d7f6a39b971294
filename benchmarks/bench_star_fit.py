"""Star fits: the compiled Levenberg-Marquardt (skeleton.star_lm) against stop 22's
vectorised NumPy one (kept below as the named baseline, same algorithm and stop rules), on
the stars the skeleton solver fits: every star fit of the 1 mm figures given (seeds of
benchmarks/bench_skeleton.py), at 150 frames (skeleton.star_fit.STAR_FRAMES) and 600.

Usage: python benchmarks/bench_star_fit.py [seeds=94019,7009,5021,4043,97022]
Prints per frame count: the stars fitted, seconds for all with each, the ratio, and the
largest difference of their sums of squares in units of the residual variance (the star
margins' unit; the junction and re-link steps decide at 200).
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import skeleton.junctions as junctions  # noqa: E402
import skeleton.relink as relink  # noqa: E402
import skeleton.star_fit as star_fit  # noqa: E402
from hw_sim.articulated import animate, random_tree  # noqa: E402


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors -> (F, 3, 3) rotation matrices."""
    th = np.linalg.norm(w, axis=1)
    k = np.where(th[:, None] > 1e-12, w / np.maximum(th, 1e-300)[:, None], 0.0)
    K = np.zeros((w.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def numpy_star_lm(X, seg, R, t, y, js, z, j0, pull_mm, max_iter, tol, stop_var):
    """Baseline: stop 22's NumPy loop of skeleton.star_fit, on star_lm's arguments (R, t, y,
    js, z refined in place); returns (status, data ssq, iterations) as star_lm does."""
    F, N = X.shape[:2]
    K = js.shape[0]
    n = [int(np.sum(seg == k)) for k in range(K + 1)]
    n_fr = 6 + 3 * K
    G0 = F * n_fr
    n_y = 3 * n[0]
    off_z = G0 + n_y + 3 * K + np.concatenate([[0], np.cumsum([3 * m for m in n[1:]])])
    n_par = int(off_z[-1])
    Xs = X
    Rs = [R[k].copy() for k in range(K + 1)]
    y, js = y.copy(), js.copy()
    zs = [z[int(np.sum(n[1:k + 1])):int(np.sum(n[1:k + 2]))].copy() for k in range(K)]
    it = 0
    t = t.copy()
    n_g = n_par - G0
    # Jacobian structure: per marker, its 3x3 blocks and their first column in a frame's
    # dense row block (the frame's own parameters, then the global ones at n_fr + ...)
    blocks = []                              # (marker, kind, k, column)
    for i in range(n[0]):
        blocks += [(i, "wh", 0, 0), (i, "t", 0, 3), (i, "y", 0, n_fr + 3 * i)]
    i = n[0]
    for k in range(K):
        for q in range(n[k + 1]):
            blocks += [(i, "whj", k, 0), (i, "t", k, 3), (i, "j", k, n_fr + n_y + 3 * k),
                       (i, "wk", (k, q), 6 + 3 * k),
                       (i, "z", (k, q), n_fr + off_z[k] - G0 + 3 * q)]
            i += 1

    def skew(v):                             # (F, 3) -> (F, 3, 3), skew(v) u = v x u
        S = np.zeros(v.shape[:-1] + (3, 3))
        S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
        S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
        return S

    def model():
        out = [np.einsum("fij,nj->fni", Rs[0], y) + t[:, None]]
        for k in range(K):
            Jk = t + np.einsum("fij,j->fi", Rs[0], js[k])
            out.append(np.einsum("fij,nj->fni", Rs[k + 1], zs[k]) + Jk[:, None])
        return np.concatenate(out, axis=1)

    def jacobian():
        """(F, 3N, n_fr + n_g) dense per-frame Jacobian: the frame's own parameters, then
        the global ones."""
        Jd = np.zeros((F, 3 * N, n_fr + n_g))
        for m, kind, k, col in blocks:
            if kind == "wh":
                v = -skew(np.einsum("fij,j->fi", Rs[0], y[m]))
            elif kind == "t":
                v = np.eye(3)
            elif kind == "y":
                v = Rs[0]
            elif kind == "whj":
                v = -skew(np.einsum("fij,j->fi", Rs[0], js[k]))
            elif kind == "j":
                v = Rs[0]
            elif kind == "wk":
                v = -skew(np.einsum("fij,j->fi", Rs[k[0] + 1], zs[k[0]][k[1]]))
            else:
                v = Rs[k[0] + 1]
            Jd[:, 3 * m:3 * m + 3, col:col + 3] = v
        # gauge: the hub's local frame (6) and each member's (3) are free; the first
        # frame's parameters (as many) stay at their start, which fixes them
        Jd[0, :, :n_fr] = 0.0
        return Jd

    def apply(d):
        """the state after the step ``d`` (rotations by left increments)"""
        p = d[:G0].reshape(F, n_fr)
        new_R = [_rodrigues(p[:, :3]) @ Rs[0]] + [
            _rodrigues(p[:, 6 + 3 * k:9 + 3 * k]) @ Rs[k + 1] for k in range(K)]
        new = (new_R, t + p[:, 3:6], y + d[G0:G0 + n_y].reshape(-1, 3),
               js + d[G0 + n_y:G0 + n_y + 3 * K].reshape(K, 3),
               [zs[k] + d[off_z[k]:off_z[k + 1]].reshape(-1, 3) for k in range(K)])
        return new

    r = (model() - Xs).reshape(F, 3 * N)
    jcol = slice(n_y, n_y + 3 * K)           # the joints' columns among the global ones

    def prior(js_):                          # the joints' pull towards their starts (mm^2)
        d = (js_ - j0) / pull_mm
        return float(np.sum(d * d))

    ssq = float(np.sum(r * r)) + prior(js)
    lam = None
    eye_f, eye_g = np.eye(n_fr), np.eye(n_g)
    it = 0
    for it in range(1, max_iter + 1):
        Jd = jacobian()
        Jf, Jg = Jd[:, :, :n_fr], Jd[:, :, n_fr:]
        JfT = Jf.transpose(0, 2, 1)
        U = JfT @ Jf
        W = JfT @ Jg
        Jg2 = Jg.reshape(-1, n_g)
        V = Jg2.T @ Jg2
        V[jcol, jcol] += np.eye(3 * K) / pull_mm ** 2
        ef = (JfT @ r[:, :, None])[:, :, 0]
        eg = Jg2.T @ r.ravel()
        eg[jcol] += (js - j0).ravel() / pull_mm ** 2
        scale = float(np.mean(np.concatenate([np.diagonal(U, axis1=1, axis2=2).ravel(),
                                              np.diag(V)])))
        if lam is None:
            lam = 1e-4
        while True:
            # damped normal equations by the Schur complement on the global parameters:
            # (U + D) df + W dg = -ef, W^T df + (V + D) dg = -eg
            Ud = U + lam * (np.diagonal(U, axis1=1, axis2=2)[:, :, None] * eye_f
                            + 1e-9 * scale * eye_f)
            Vd = V + lam * (np.diag(V) * eye_g + 1e-9 * scale * eye_g)
            try:
                Ui_W = np.linalg.solve(Ud, W)
                Ui_e = np.linalg.solve(Ud, ef[:, :, None])[:, :, 0]
                W2 = W.reshape(-1, n_g)
                Sc = Vd - W2.T @ Ui_W.reshape(-1, n_g)
                dg = np.linalg.solve(Sc, -(eg - W2.T @ Ui_e.ravel()))
            except np.linalg.LinAlgError as exc:
                return 2, np.inf, it
            df = -Ui_e - Ui_W @ dg
            dx = np.concatenate([df.ravel(), dg])
            if not np.isfinite(dx).all():
                return 2, np.inf, it
            saved = (Rs, t, y, js, zs)
            Rs, t, y, js, zs = apply(dx)
            r_new = (model() - Xs).reshape(F, 3 * N)
            s_new = float(np.sum(r_new * r_new)) + prior(js)
            if s_new < ssq:
                break
            Rs, t, y, js, zs = saved
            lam *= 10.0
            if lam > 1e8:
                return 1, float(np.sum(r * r)), it
        done = ssq - s_new < max(tol * ssq, stop_var * s_new / r_new.size)
        r, ssq = r_new, s_new
        lam = max(lam / 3.0, 1e-9)
        if done:
            break
    return 0, float(np.sum(r * r)), it


def main(seeds="94019,7009,5021,4043,97022"):
    from benchmarks.bench_skeleton import run   # (bench_skeleton imports this module)
    calls = []
    compiled = star_fit.star_lm

    def capture(traj, members, group, hub, centre, n_frames=star_fit.STAR_FRAMES):
        calls.append((traj, members, group, hub, centre))
        return star_fit.star_misfit(traj, members, group, hub, centre, n_frames)

    junctions.star_misfit = relink.star_misfit = capture
    for seed in (int(s) for s in str(seeds).split(",")):
        g = np.random.default_rng(seed)
        fig = random_tree(int(g.integers(5, 21)), (2, 4), rng=g)
        mo = animate(fig, 600, rng=g, rom_deg=float(g.uniform(45, 90)))
        run(fig, mo, 1e-3, seed % 1000)
    junctions.star_misfit = relink.star_misfit = star_fit.star_misfit
    for nf in (star_fit.STAR_FRAMES, 600):
        out = {}
        for name, lm in (("NumPy", numpy_star_lm), ("compiled", compiled)):
            star_fit.star_lm = lm
            t0 = time.perf_counter()
            out[name] = ([star_fit.star_misfit(*c, n_frames=nf) for c in calls],
                         time.perf_counter() - t0)
        star_fit.star_lm = compiled
        dev = max((abs(a.ssq_m2 - b.ssq_m2) / (a.ssq_m2 / a.n_res)
                   for a, b in zip(out["NumPy"][0], out["compiled"][0]) if a.ok and b.ok),
                  default=0.0)
        t_np, t_c = out["NumPy"][1], out["compiled"][1]
        print(f"{len(calls)} stars at {nf} frames: NumPy {t_np:.2f} s, compiled {t_c:.2f} s "
              f"(ratio {t_c / t_np:.3f}); largest difference {dev:.1e} residual variances")


if __name__ == "__main__":
    main(*sys.argv[1:2])
