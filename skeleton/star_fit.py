"""A junction's star model fitted to all its markers: which hub explains the data best.

``star_misfit(traj (T, M, 3), members, group, hub, centre (T, 3)) -> StarFit``.
Segments meeting at (nearly) one point can be linked by any of several trees, and the joint
costs of pairs compare fits over different markers with different frame noise, so they tell
sibling joints a few mm apart from their parent poorly. Here every candidate tree of a group
(the star around each candidate hub) is fitted as one articulated model to the *same*
markers: per frame the hub's pose (6) and each other member's rotation (3) about its ball
joint; over all frames the hub's marker offsets, each joint's position in the hub and each
member's marker offsets from its joint. Every star of a group has the same number of
parameters, so their residual sums of squares compare directly (a likelihood ratio under
Gaussian marker noise). A sibling hung from its sibling instead of their common parent
carries the parent's joint about the sibling's: its markers miss by about the joint gap times
the sibling's rotation in every frame, which the model cannot absorb (moving the sibling
moves its own markers with the lever arm), so siblings a fraction of a mm apart separate
at 1 mm marker noise over a few hundred frames, where the pairwise costs do not (see
``skeleton.junctions``). The solve is Levenberg-Marquardt with the analytic Jacobian, the
normal equations reduced to the global parameters by the Schur complement of the per-frame
blocks (bundle adjustment's structure), the gauge (each segment's local frame) fixed by
holding the first frame's pose parameters at their start, and each joint pulled weakly
towards its start (``JOINT_PULL_MM``: a hinge's centre is free along its axis, and without
the pull the fit crawls after the noise along it for hundreds of iterations, so stars were
compared part-converged; the sum of squares returned is the data's). It starts in closed form: each
segment's rotations by Kabsch of its markers and its joint's start point (a frame even for
two markers). Written here rather than with SciPy's ``least_squares`` (finite-difference
Jacobian with its sparsity, lsmr): that took 0.6-1.1 s per star on 3-segment groups, this
takes 0.04-0.2 s, which is what lets the solver test every tree triple (``skeleton.relink``).
Conventions: docs/conventions.md [arrays], [units], [rotations].
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from threadpoolctl import ThreadpoolController

__all__ = ["StarFit", "star_misfit", "STAR_FRAMES", "VAR_FLOOR_M2"]

STAR_FRAMES = 150   # frames sampled (evenly) for the fit
VAR_FLOOR_M2 = 1e-10  # residual variance floor (10 um RMS) for margins in units of it: noise-
                      # free fits reach ~1e-20, and stars of exactly coincident joints are
                      # equivalent: a margin over that would count the solver's convergence
JOINT_PULL_MM = 20.0  # each joint is pulled towards its start: 20 mm off adds 1 mm^2 (the
                      # residual variance per residual is ~0.05 mm^2 at 1 mm noise). Without
                      # it a hinge's centre, free along its axis, runs off with the noise and
                      # the fit crawls after it for hundreds of iterations (seed 97022's true
                      # star: unconverged after 400; with it: 7-12)
MAX_ITER = 50       # Levenberg-Marquardt iterations ...
TOL = 1e-6          # ... until the sum of squares falls by less than this fraction, or by
STOP_VAR = 0.1      # less than this x the residual variance (hub margins are 200x that)


class StarFit(NamedTuple):
    """ok/reason; ssq_m2: residual sum of squares (m^2) over n_res residuals; n_par: the
    model's parameters (gauge freedoms included: the same for every hub of one group);
    n_iter: Levenberg-Marquardt iterations (``MAX_ITER``: stopped before converging)."""

    ok: bool
    reason: str
    ssq_m2: float
    n_res: int
    n_par: int
    n_iter: int = 0


def _rodrigues(w: np.ndarray) -> np.ndarray:
    """(F, 3) rotation vectors -> (F, 3, 3) rotation matrices."""
    th = np.linalg.norm(w, axis=1)
    k = np.where(th[:, None] > 1e-12, w / np.maximum(th, 1e-300)[:, None], 0.0)
    K = np.zeros((w.shape[0], 3, 3))
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -k[:, 2], k[:, 1], -k[:, 0]
    K[:, 1, 0], K[:, 2, 0], K[:, 2, 1] = k[:, 2], -k[:, 1], k[:, 0]
    s, c = np.sin(th)[:, None, None], np.cos(th)[:, None, None]
    return np.eye(3) + s * K + (1 - c) * (K @ K)


def _frames(P: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(F, n, 3) points -> rotations (F, 3, 3) and centroids (F, 3) with
    P_f - cen_f ~ R_f (P_0 - cen_0) (Kabsch, det +1)."""
    cen = P.mean(1)
    Q = P - cen[:, None]
    H = np.einsum("ni,fnj->fij", Q[0], Q)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.ones((len(P), 3))
    D[:, 2] = d
    return np.einsum("fji,fj,fkj->fik", Vt, D, U), cen


_BLAS: ThreadpoolController | None = None


def star_misfit(traj: np.ndarray, members, group, hub: int, centre,
                n_frames: int = STAR_FRAMES) -> StarFit:
    """The star of ``group`` (segment indices) around ``hub`` fitted to the group's markers
    (``members[s]``: marker indices of segment s) on ``n_frames`` frames sampled evenly
    among those where every marker and start point is seen. ``centre``: the junction point
    (T, 3), the start of every joint; or a mapping member -> (T, 3), the start of that
    member's joint with the hub, for every member but the hub. Fewer than 10 such frames:
    a StarFit that is not ok and says so."""
    # small dense products: BLAS threads only contend (1.0 s -> 0.13 s for one fit on a
    # loaded 2-core machine); the controller is made once (finding the BLAS libraries took
    # 5 ms per fit)
    global _BLAS
    if _BLAS is None:
        _BLAS = ThreadpoolController()
    with _BLAS.limit(limits=1, user_api="blas"):
        return _star_misfit(traj, members, group, hub, centre, n_frames)


def _star_misfit(traj, members, group, hub, centre, n_frames) -> StarFit:
    traj = np.asarray(traj, np.float64)
    others = [int(s) for s in sorted(group) if s != hub]
    if int(hub) not in set(int(s) for s in group) or not others:
        raise ValueError(f"hub={hub!r}, group={sorted(group)!r}: the hub must be a member of "
                         "a group of >= 2 segments")
    if isinstance(centre, dict):
        missing = [s for s in others if s not in centre]
        if missing:
            raise ValueError(f"centre has no start for members {missing} (hub {hub})")
        starts = [np.asarray(centre[s], np.float64) for s in others]
    else:
        starts = [np.asarray(centre, np.float64)] * len(others)
    if any(c.shape != (traj.shape[0], 3) for c in starts):
        raise ValueError(f"centre shapes {[c.shape for c in starts]}, expected "
                         f"({traj.shape[0]}, 3)")
    segs = [int(hub)] + others
    idx = [np.asarray(members[s], int) for s in segs]
    allm = np.concatenate(idx)
    seen = ~np.isnan(traj[:, allm]).any((1, 2))
    for c in starts:
        seen &= ~np.isnan(c).any(1)
    ok_t = np.flatnonzero(seen)
    if ok_t.size < 10:
        return StarFit(False, f"{ok_t.size} frames with every marker seen", np.inf, 0, 0)
    sel = ok_t[np.linspace(0, ok_t.size - 1, min(ok_t.size, n_frames)).astype(int)]
    F = sel.size
    X = traj[sel] * 1e3                      # mm: residuals near 1, well scaled
    cs = [c[sel] * 1e3 for c in starts]
    pts = [np.mean(cs, axis=0)] + cs         # a point beside each segment's markers
    # closed-form start: rotations of each segment from its markers and its joint's start
    R0, cen = [], []
    for ix, c in zip(idx, pts):
        R, ce = _frames(np.concatenate([X[:, ix], c[:, None]], axis=1))
        R0.append(R)
        cen.append(ce)
    Rh, th = R0[0], cen[0]
    y0 = np.einsum("fji,fnj->fni", Rh, X[:, idx[0]] - th[:, None]).mean(0)     # hub local
    j0 = np.stack([np.einsum("fji,fj->fi", Rh, c - th).mean(0) for c in cs])   # (K, 3)
    J0 = [th + np.einsum("fij,j->fi", Rh, j) for j in j0]
    zl = [np.einsum("fji,fnj->fni", R0[k + 1], X[:, idx[k + 1]] - J0[k][:, None]).mean(0)
          for k in range(len(others))]
    K = len(others)
    n = [ix.size for ix in idx]
    N = int(sum(n))
    n_fr = 6 + 3 * K                         # per frame: hub rotation, translation; members'
    G0 = F * n_fr                            # rotations; then the global parameters:
    n_y = 3 * n[0]                           # hub marker offsets, joints in the hub,
    off_z = G0 + n_y + 3 * K + np.concatenate([[0], np.cumsum([3 * m for m in n[1:]])])
    n_par = int(off_z[-1])                   # members' marker offsets from their joints
    Xs = np.concatenate([X[:, ix] for ix in idx], axis=1)     # (F, N, 3) in model order
    Rs = [R.copy() for R in R0]              # Rs[0] hub, Rs[k + 1] member k
    t = th.copy()
    y = y0.copy()
    js = j0.copy()
    zs = [z.copy() for z in zl]
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
        d = (js_ - j0) / JOINT_PULL_MM
        return float(np.sum(d * d))

    ssq = float(np.sum(r * r)) + prior(js)
    lam = None
    eye_f, eye_g = np.eye(n_fr), np.eye(n_g)
    it = 0
    for it in range(1, MAX_ITER + 1):
        Jd = jacobian()
        Jf, Jg = Jd[:, :, :n_fr], Jd[:, :, n_fr:]
        JfT = Jf.transpose(0, 2, 1)
        U = JfT @ Jf
        W = JfT @ Jg
        Jg2 = Jg.reshape(-1, n_g)
        V = Jg2.T @ Jg2
        V[jcol, jcol] += np.eye(3 * K) / JOINT_PULL_MM ** 2
        ef = (JfT @ r[:, :, None])[:, :, 0]
        eg = Jg2.T @ r.ravel()
        eg[jcol] += (js - j0).ravel() / JOINT_PULL_MM ** 2
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
                return StarFit(False, f"normal equations failed: {exc}", np.inf, r.size,
                               n_par)
            df = -Ui_e - Ui_W @ dg
            dx = np.concatenate([df.ravel(), dg])
            if not np.isfinite(dx).all():
                return StarFit(False, "normal equations not finite", np.inf, r.size, n_par)
            saved = (Rs, t, y, js, zs)
            Rs, t, y, js, zs = apply(dx)
            r_new = (model() - Xs).reshape(F, 3 * N)
            s_new = float(np.sum(r_new * r_new)) + prior(js)
            if s_new < ssq:
                break
            Rs, t, y, js, zs = saved
            lam *= 10.0
            if lam > 1e8:
                return StarFit(True, "", float(np.sum(r * r)) * 1e-6, r.size, n_par, it)
        done = ssq - s_new < max(TOL * ssq, STOP_VAR * s_new / r_new.size)
        r, ssq = r_new, s_new
        lam = max(lam / 3.0, 1e-9)
        if done:
            break
    # the data's sum of squares (the pull only guides the search along near-free directions)
    return StarFit(True, "", float(np.sum(r * r)) * 1e-6, r.size, n_par, it)
