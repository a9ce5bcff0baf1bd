"""Maximum-weight bipartite matching (the assignment problem), in numpy.

The metric matches predictions to ground truths so that the sum of the matched weights (quantized IoUs) is as
large as possible, as Waymo's Hungarian matcher does. scipy is not a dependency, so this module solves the
rectangular assignment problem itself with the shortest augmenting path method (Kuhn-Munkres with
potentials, O(n^2 m) for n rows <= m columns): rows are added one at a time, each by a Dijkstra-like search
over reduced costs, and the dual potentials keep every reduced cost non-negative.
"""

from __future__ import annotations

import numpy as np


def _min_cost_assignment(cost: np.ndarray) -> np.ndarray:
    """(n, m) float64 costs with n <= m -> (n,) column of every row, all distinct, minimizing the total.

    Indices below are 1-based for rows and columns; column 0 is a virtual column that holds the row being
    inserted. owner[j] is the row assigned to column j (0: free), back[j] the previous column on the
    shortest path to j, u / v the row / column potentials.
    """
    n, m = cost.shape
    u = np.zeros(n + 1)  # (n + 1,)
    v = np.zeros(m + 1)  # (m + 1,)
    owner = np.zeros(m + 1, np.int64)  # (m + 1,)
    back = np.zeros(m + 1, np.int64)  # (m + 1,)
    for row in range(1, n + 1):
        owner[0] = row
        col = 0
        dist = np.full(m + 1, np.inf)  # (m + 1,) shortest reduced distance to each column so far
        done = np.zeros(m + 1, bool)  # (m + 1,) columns whose distance is final
        while owner[col] != 0:
            done[col] = True
            r = owner[col]
            reduced = cost[r - 1] - u[r] - v[1:]  # (m,) reduced cost of the edges leaving row r
            closer = ~done[1:] & (reduced < dist[1:])
            dist[1:][closer] = reduced[closer]
            back[1:][closer] = col
            open_dist = np.where(done[1:], np.inf, dist[1:])  # (m,)
            nxt = int(np.argmin(open_dist)) + 1
            delta = open_dist[nxt - 1]
            u[owner[done]] += delta
            v[done] -= delta
            dist[1:][~done[1:]] -= delta
            col = nxt
        while col != 0:  # flip the path: every column on it takes the row of its predecessor
            prev = back[col]
            owner[col] = owner[prev]
            col = prev
    assigned = np.zeros(n, np.int64)  # (n,)
    cols = np.nonzero(owner[1:])[0]
    assigned[owner[cols + 1] - 1] = cols
    return assigned


def max_weight_matching(weights: np.ndarray) -> np.ndarray:
    """(N, M) non-negative weights -> (N,) matched column of every row, or -1.

    The matching maximizes the sum of the weights of its pairs; pairs of weight 0 are reported as unmatched
    (-1), so only positive-weight pairs count. Ties between equally heavy matchings are broken arbitrarily.
    """
    w = np.asarray(weights, np.float64)
    if w.ndim != 2:
        raise ValueError(f"expected a (N, M) weight matrix, got shape {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("weights must be finite and non-negative")
    n, m = w.shape
    match = np.full(n, -1, np.int64)  # (N,)
    if n == 0 or m == 0:
        return match
    if n <= m:
        match[:] = _min_cost_assignment(-w)
    else:
        cols_to_rows = _min_cost_assignment(-w.T)  # (M,) row of every column
        match[cols_to_rows] = np.arange(m)
    rows = np.nonzero(match >= 0)[0]
    match[rows[w[rows, match[rows]] <= 0]] = -1
    return match
