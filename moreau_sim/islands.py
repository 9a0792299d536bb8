"""A projection's islands (docs/theory.md §1.3, islands): with M block diagonal by kinematic tree, two rows are coupled
(G_ij = w_i'M^-1 w_j can be nonzero) only where they touch a common tree, so the rows fall into islands, the
connected components of the graph of rows and trees, each an independent projection on its own trees' velocities.
A pile of boxes in a bin is a hundred columns, each a few dozen rows; one projection of all its thousands of rows
refactors them all at every move of the active set (src/step.cpp project mirrors this rule)."""

from __future__ import annotations

import numpy as np


def islands(W: np.ndarray, blocks) -> list[tuple[np.ndarray, np.ndarray]] | None:
    """(velocities, rows) of each island of the rows W (nv, m), ascending each, the islands in the order of their
    first rows; a tree belongs to the island of the rows that touch it (a tree no row touches to none). blocks:
    (first velocity, nv) of each tree, in order, covering 0 .. nv (Forest.blocks). None where there is one island
    only, W is not finite or a row touches no velocity."""
    nv, m = W.shape
    if not np.isfinite(W).all():
        return None
    tree = np.empty(nv, dtype=np.int64)
    for t, (first, n) in enumerate(blocks):
        tree[first:first + n] = t
    parent = list(range(len(blocks)))

    def root(t: int) -> int:
        while parent[t] != t:
            parent[t] = parent[parent[t]]
            t = parent[t]
        return t

    first_tree = np.full(m, -1, dtype=np.int64)  # the first tree each row touches (ascending velocities)
    for j in range(m):
        touched = tree[np.flatnonzero(W[:, j])]
        if not touched.size:
            return None
        first_tree[j] = touched[0]
        for t in touched[1:].tolist():  # union by the smaller root: the same forest in any order of the unions
            a, b = root(int(touched[0])), root(t)
            if a != b:
                parent[max(a, b)] = min(a, b)
    label = {}  # root -> island, numbered by first row
    of_row = np.array([label.setdefault(root(int(t)), len(label)) for t in first_tree.tolist()], dtype=np.int64)
    if len(label) < 2:
        return None
    dofs: list[list[int]] = [[] for _ in label]
    for t, (first, n) in enumerate(blocks):
        k = label.get(root(t))
        if k is not None and n:
            dofs[k].extend(range(first, first + n))
    return [(np.array(d, dtype=np.int64), np.flatnonzero(of_row == k)) for k, d in enumerate(dofs)]
