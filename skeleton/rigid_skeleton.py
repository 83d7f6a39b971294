"""Rigid skeleton (bone offsets, marker offsets, hinge axes) from a solved skeleton.

``build_rigid_skeleton(trajectories (T, M, 3), result: SkeletonResult, marker_names=None)
-> RigidSkeleton``. The thesis' skeleton parameterisation (000, section 3.8.1): each segment
is lined up on a reference frame by Horn's absolute orientation (``skeleton.rigid.kabsch``)
using its markers (plus its joint centres when it carries fewer than three markers); every
marker and joint then has a cloud of local positions, whose mean after rejecting the points
farther than one standard deviation from the first mean is its offset. The skeleton is put
back together from the root outwards: a segment's frame has its origin at its proximal joint
(the root's at its markers' centroid) and the orientation of the world at its reference
frame (the first frame seeing every alignment point; one common frame when one exists).
The root is the solver's unless that carries fewer than three markers: then the tree is
hung from the nearest segment with three (the fit back poses the root from its markers).
Conventions: docs/conventions.md [arrays], [units], [errors]; docs/skeleton_outputs.md.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import breadth_first_order, shortest_path

from skeleton.rigid import kabsch

__all__ = ["RigidSkeleton", "build_rigid_skeleton"]


def _ro(a, dtype=np.float64) -> np.ndarray:
    a = np.array(a, dtype=dtype)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, kw_only=True)
class RigidSkeleton:
    """A tree of rigid segments (shape letters: S segments, M markers).

    Attributes:
        segment_names: (S,) names ("seg0", ...).
        parents: (S,) int, -1 for the root.
        root: the root segment.
        marker_names: (M,) names.
        marker_segment: (M,) int segment of each marker.
        marker_offsets: (M, 3) m, marker in its segment's frame.
        joint_offsets: (S, 3) m, segment s's proximal joint in its parent's frame (root: 0).
        hinge: (S,) bool, the joint of s with its parent is a hinge.
        hinge_axes_parent: (S, 3) unit hinge axis in the parent's frame (NaN: ball joint).
        hinge_axes_child: (S, 3) the same axis in segment s's frame.
        joint_residual_m: (S,) rms residual of the joint fit (NaN for the root).
        end_sites: (S, 3) m, the markers' centroid in each segment's frame (BVH End Site).
    """

    segment_names: tuple[str, ...]
    parents: np.ndarray
    root: int
    marker_names: tuple[str, ...]
    marker_segment: np.ndarray
    marker_offsets: np.ndarray
    joint_offsets: np.ndarray
    hinge: np.ndarray
    hinge_axes_parent: np.ndarray
    hinge_axes_child: np.ndarray
    joint_residual_m: np.ndarray
    end_sites: np.ndarray

    def __post_init__(self):
        S = len(self.segment_names)
        par = np.asarray(self.parents)
        if par.shape != (S,) or (par < 0).sum() != 1 or par[self.root] != -1:
            raise ValueError(f"parents={par.tolist()}, root={self.root}: expected ({S},) with "
                             "exactly one -1 at the root")
        M = len(self.marker_names)
        for name, shape in (("marker_segment", (M,)), ("marker_offsets", (M, 3)),
                            ("joint_offsets", (S, 3)), ("hinge", (S,)),
                            ("hinge_axes_parent", (S, 3)), ("hinge_axes_child", (S, 3)),
                            ("joint_residual_m", (S,)), ("end_sites", (S, 3))):
            a = np.asarray(getattr(self, name))
            if a.shape != shape:
                raise ValueError(f"{name}.shape={a.shape}, expected {shape}")
        ms = np.asarray(self.marker_segment)
        if M and (ms.min() < 0 or ms.max() >= S):
            raise ValueError(f"marker_segment={ms.tolist()}, expected ints in [0, {S})")
        object.__setattr__(self, "segment_names", tuple(str(s) for s in self.segment_names))
        object.__setattr__(self, "marker_names", tuple(str(s) for s in self.marker_names))
        object.__setattr__(self, "root", int(self.root))
        for name in ("parents", "marker_segment"):
            object.__setattr__(self, name, _ro(getattr(self, name), np.int64))
        object.__setattr__(self, "hinge", _ro(self.hinge, bool))
        for name in ("marker_offsets", "joint_offsets", "hinge_axes_parent", "hinge_axes_child",
                     "joint_residual_m", "end_sites"):
            object.__setattr__(self, name, _ro(getattr(self, name)))

    @property
    def n_segments(self) -> int:
        return len(self.segment_names)

    @property
    def n_markers(self) -> int:
        return len(self.marker_names)

    @property
    def children(self) -> tuple[tuple[int, ...], ...]:
        return tuple(tuple(int(c) for c in np.flatnonzero(self.parents == s))
                     for s in range(self.n_segments))

    @property
    def order(self) -> np.ndarray:
        """(S,) segments root first, every parent before its children (breadth first)."""
        out, i = [self.root], 0
        kids = self.children
        while i < len(out):
            out.extend(kids[out[i]])
            i += 1
        return np.array(out, np.int64)

    @property
    def bone_lengths(self) -> np.ndarray:
        """(S,) m, distance from the parent's origin to segment s's joint (root: NaN): for a
        chain, the length of the parent bone between its two joints."""
        L = np.linalg.norm(self.joint_offsets, axis=1)
        L[self.root] = np.nan
        return L


def _robust_mean(cloud: np.ndarray) -> np.ndarray:
    """Mean of (N, 3) points after dropping those farther than one sd from the mean."""
    m = cloud.mean(0)
    d = np.linalg.norm(cloud - m, axis=1)
    sd = np.sqrt(np.mean(d ** 2))
    keep = d <= sd * (1 + 1e-9) + 1e-15
    return cloud[keep].mean(0)


def _fit_root(parents: np.ndarray, root: int, n_markers: np.ndarray) -> int:
    """The solver's root when it carries >= 3 markers, else the nearest segment (in joints;
    ties: more markers, lower index) that does: the fit back poses the root from its own
    markers (the rotation-point thesis' condition for drawing the whole figure)."""
    if n_markers[root] >= 3 or not (n_markers >= 3).any():
        return root
    hops = _hops(parents, root)
    cand = np.flatnonzero(n_markers >= 3)
    return int(cand[np.lexsort((cand, -n_markers[cand], hops[cand]))[0]])


def _tree_graph(parents: np.ndarray) -> csr_matrix:
    """Undirected adjacency of the tree given by ``parents`` (-1 = root)."""
    child = np.flatnonzero(parents >= 0)
    S = parents.size
    return csr_matrix((np.ones(child.size), (child, parents[child])), shape=(S, S))


def _hops(parents: np.ndarray, start: int) -> np.ndarray:
    """Joints between ``start`` and every segment (-1 where unreachable)."""
    d = shortest_path(_tree_graph(parents), unweighted=True, directed=False, indices=start)
    return np.where(np.isfinite(d), d, -1).astype(np.int64)


def _reroot(parents: np.ndarray, root: int) -> np.ndarray:
    """Parents of the same tree hung from ``root``."""
    order, pred = breadth_first_order(_tree_graph(parents), root, directed=False)
    if order.size != parents.size:
        raise ValueError(f"parents={parents.tolist()} is not one tree")
    new = pred.astype(np.int64)
    new[root] = -1
    return new


def build_rigid_skeleton(trajectories, result, marker_names=None) -> RigidSkeleton:
    """Rigid skeleton from ``trajectories`` (T, M, 3) m and a ``SkeletonResult``.

    Raises ValueError when a segment has no frame that sees enough points to line it up
    (fewer than three markers-plus-joints)."""
    traj = np.asarray(trajectories, np.float64)
    if traj.ndim != 3 or traj.shape[2] != 3:
        raise ValueError(f"trajectories.shape={traj.shape}, expected (T, M, 3)")
    T, M = traj.shape[:2]
    labels = np.asarray(result.labels)
    if labels.shape != (M,):
        raise ValueError(f"result.labels.shape={labels.shape}, expected ({M},)")
    S = int(result.n_segments)
    old_par = np.asarray(result.parents, np.int64)
    n_mk = np.bincount(labels, minlength=S)
    root = _fit_root(old_par, int(result.root), n_mk)
    parents = _reroot(old_par, root)
    # every edge keeps its joint (world track and fit); only its direction may flip
    old_child = np.array([s if parents[s] < 0 or old_par[s] == parents[s] else parents[s]
                          for s in range(S)])
    jc_old = np.asarray(result.joint_centres, np.float64)      # (T, S, 3) proximal joints
    jc = jc_old[:, old_child]
    jc[:, root] = np.nan
    if marker_names is None:
        marker_names = tuple(f"M{i:03d}" for i in range(M))
    if len(marker_names) != M:
        raise ValueError(f"len(marker_names)={len(marker_names)}, expected {M}")
    children = [np.flatnonzero(parents == s) for s in range(S)]

    # alignment points of every segment: its markers, plus its joints when < 3 markers
    align = []
    for s in range(S):
        mk = [traj[:, m] for m in np.flatnonzero(labels == s)]
        jt = ([] if s == root else [jc[:, s]]) + [jc[:, c] for c in children[s]]
        pts = mk + (jt if len(mk) < 3 else [])
        if len(pts) < 3:
            raise ValueError(f"segment {s} has {len(mk)} markers and {len(jt)} joints: "
                             "need three points to line it up (a leaf segment needs two "
                             "markers: ask for fewer segments)")
        align.append(np.stack(pts, 1))                          # (T, P, 3)
    full = np.stack([~np.isnan(a).any(axis=(1, 2)) for a in align], 1)   # (T, S)
    common = np.flatnonzero(full.all(1))

    # per-frame world_from_segment rotation (segment axes = world axes at its ref frame)
    W = np.full((T, S, 3, 3), np.nan)
    local_clouds = {}
    for s in range(S):
        ok = np.flatnonzero(full[:, s])
        if ok.size == 0:
            raise ValueError(f"segment {s}: no frame sees all of its {align[s].shape[1]} "
                             "alignment points")
        f_ref = int(common[0]) if common.size else int(ok[0])
        R, t = kabsch(align[s][ok], align[s][f_ref])            # local = R x + t
        W[ok, s] = np.transpose(R, (0, 2, 1))
        local_clouds[s] = (ok, R, t)

    def local_mean(s, X):
        """Robust mean of world points X (T, 3) in segment s's frame."""
        ok, R, t = local_clouds[s]
        x = X[ok]
        good = ~np.isnan(x).any(1)
        if not good.any():
            return np.full(3, np.nan)
        loc = np.einsum("tij,tj->ti", R[good], x[good]) + t[good]
        return _robust_mean(loc)

    origin = np.zeros((S, 3))
    marker_local = np.full((M, 3), np.nan)
    for s in range(S):
        for m in np.flatnonzero(labels == s):
            marker_local[m] = local_mean(s, traj[:, m])
        origin[s] = (marker_local[labels == s].mean(0) if s == root
                     else local_mean(s, jc[:, s]))
    if np.isnan(origin).any() or np.isnan(marker_local).any():
        raise ValueError("a joint or marker never appears with its segment's alignment points")
    marker_offsets = marker_local - origin[labels]
    joint_offsets = np.zeros((S, 3))
    for s in range(S):
        if s != root:
            joint_offsets[s] = local_mean(parents[s], jc[:, s]) - origin[parents[s]]
    if np.isnan(joint_offsets).any():
        raise ValueError("a joint centre never appears with its parent's alignment points")
    end_sites = np.array([marker_offsets[labels == s].mean(0) for s in range(S)])

    hinge = np.zeros(S, bool)
    ax_p = np.full((S, 3), np.nan)
    ax_c = np.full((S, 3), np.nan)
    res = np.full(S, np.nan)
    for s in range(S):
        if s == root:
            continue
        j = result.joints[old_child[s]]
        if j is None:
            continue
        res[s] = j.residual_m
        if not (j.ok and j.hinge and np.isfinite(j.axis_local).all()):
            continue
        # JointFit: ref 0 is the (solver's) parent, markers_a; ref 1 the child
        ref_seg = old_par[old_child[s]] if j.ref == 0 else old_child[s]
        # JointFit's frame: world axes at the first frame seeing all of ref_seg's markers
        ref_markers = np.flatnonzero(labels == ref_seg)
        seen = np.flatnonzero(~np.isnan(traj[:, ref_markers]).any(axis=(1, 2)))
        both = np.flatnonzero(full[:, parents[s]] & full[:, s])
        if seen.size == 0 or not full[seen[0], ref_seg] or both.size == 0:
            continue
        a_world0 = j.axis_local / np.linalg.norm(j.axis_local)
        a_ref = W[seen[0], ref_seg].T @ a_world0                # in ref_seg's frame
        aw = np.einsum("tij,j->ti", W[both, ref_seg], a_ref)    # world axis per frame
        other = s if ref_seg == parents[s] else parents[s]
        a_oth = np.einsum("tji,tj->ti", W[both, other], aw).mean(0)
        a_oth /= np.linalg.norm(a_oth)
        hinge[s] = True
        ax_p[s], ax_c[s] = (a_ref, a_oth) if ref_seg == parents[s] else (a_oth, a_ref)
    return RigidSkeleton(segment_names=tuple(f"seg{s}" for s in range(S)), parents=parents,
                         root=root, marker_names=tuple(marker_names), marker_segment=labels,
                         marker_offsets=marker_offsets, joint_offsets=joint_offsets,
                         hinge=hinge, hinge_axes_parent=ax_p, hinge_axes_child=ax_c,
                         joint_residual_m=res, end_sites=end_sites)

