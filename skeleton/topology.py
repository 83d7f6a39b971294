"""Skeleton topology: minimum spanning tree over segment pairs weighted by joint-fit cost.

``skeleton_tree(cost (S, S)) -> Topology`` (scipy.sparse.csgraph);
``tree_from_edges(S, edges (S-1, 2)) -> Topology`` roots a given tree. The root is the tree's
centre (the segment with the smallest eccentricity, i.e. the fewest hops to the farthest
segment; ties: the most connected), as for a pelvis in a human figure.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_array
from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree, shortest_path

__all__ = ["Topology", "skeleton_tree", "tree_from_edges"]


@dataclass(frozen=True, kw_only=True)
class Topology:
    """root; parents (S,) (-1 for the root); edges (S-1, 2) sorted pairs; order (S,) BFS."""

    root: int
    parents: np.ndarray
    edges: np.ndarray
    order: np.ndarray


def skeleton_tree(cost: np.ndarray, first: np.ndarray | None = None) -> Topology:
    """``first`` (S, S) bool: pairs taken before all others (Kruskal order: the tree is
    the minimum spanning tree with these pairs preferred, by cost among themselves)."""
    cost = np.asarray(cost, np.float64)
    S = cost.shape[0]
    if cost.shape != (S, S):
        raise ValueError(f"cost.shape={cost.shape}, expected (S, S)")
    w = np.where(np.isfinite(cost), cost, 1e6)
    w = np.minimum(w, w.T)
    if first is not None:
        first = np.asarray(first, bool)
        first = first | first.T
        w = np.where(first, w, w + 2 * (w[first].max() if first.any() else 0.0) + 1.0)
    i, j = np.triu_indices(S, 1)
    # explicit sparse entries (a dense input would drop near-zero costs as 'no edge')
    g = coo_array((w[i, j] + 1e-300, (i, j)), shape=(S, S)).tocsr()
    mst = minimum_spanning_tree(g).toarray()
    return _rooted((mst + mst.T) > 0)


def tree_from_edges(n_segments: int, edges) -> Topology:
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    S = int(n_segments)
    if edges.shape[0] != S - 1 or edges.size and (edges.min() < 0 or edges.max() >= S):
        raise ValueError(f"edges={edges.tolist()}, expected {S - 1} pairs of segments < {S}")
    adj = np.zeros((S, S), bool)
    adj[edges[:, 0], edges[:, 1]] = adj[edges[:, 1], edges[:, 0]] = True
    if S > 1 and np.isinf(shortest_path(adj.astype(float), unweighted=True)).any():
        raise ValueError(f"edges={edges.tolist()} do not form a tree over {S} segments")
    return _rooted(adj)


def _rooted(adj: np.ndarray) -> Topology:
    hops = shortest_path(adj.astype(float), unweighted=True, directed=False)
    ecc = hops.max(1)
    root = int(np.lexsort((-adj.sum(1), ecc))[0])
    order, pred = breadth_first_order(adj.astype(float), root, directed=False)
    parents = np.where(pred < 0, -1, pred).astype(np.int64)
    parents[root] = -1
    i, j = np.nonzero(np.triu(adj))
    return Topology(root=root, parents=parents, edges=np.column_stack([i, j]), order=order)
