"""k-nearest-neighbour index over fixed points: a compiled k-d tree.

The planner asks for the m nearest training inputs of a few tens of queries per iteration;
scipy's cKDTree answered them at a per-call cost (argument handling, result arrays) that a
compiled query from numba avoids, and the validity test (`NeighbourIndex.valid`) can stop as
soon as its answer is known. The answers are scipy's: distances are computed the way
cKDTree computes them (`_sqdist`, four interleaved partial sums, then their sum; checked
against scipy in the tests), neighbours farther than the bound are left out (strictly
nearer, as there) and reported as distance inf and index ``len(points)``, nearest first.
Only the order of neighbours at exactly equal distances may differ from scipy's.
"""

from __future__ import annotations

import numba
import numpy as np

_LEAF_SIZE = 32  # measured: 8, 16, 32, 64 within 20% of each other
_STACK = 128  # nodes pending in a search: at most one per level of the tree (< 64 levels)


@numba.njit(cache=True, inline="always")
def _sqdist(data, r, q):
    """Squared distance of ``data[r]`` to ``q`` summed as scipy's cKDTree sums it (four
    interleaved partial sums, their sum, then the remaining coordinates in order), so that
    the distances are bit for bit scipy's."""
    n = q.shape[0]
    a0 = 0.0
    a1 = 0.0
    a2 = 0.0
    a3 = 0.0
    i = 0
    while i + 4 <= n:
        d0 = data[r, i] - q[i]
        d1 = data[r, i + 1] - q[i + 1]
        d2 = data[r, i + 2] - q[i + 2]
        d3 = data[r, i + 3] - q[i + 3]
        a0 += d0 * d0
        a1 += d1 * d1
        a2 += d2 * d2
        a3 += d3 * d3
        i += 4
    s = a0 + a1 + a2 + a3
    while i < n:
        d = data[r, i] - q[i]
        s += d * d
        i += 1
    return s


@numba.njit(cache=True)
def _layout(n, leaf_size):
    """The tree's shape for n points: the number of inner nodes and each node's range of
    leaf positions. Nodes are numbered as a heap (children 2i+1, 2i+2); ranges halve ([lo,
    mid), [mid, hi), mid = (lo + hi) // 2) down to at most ``leaf_size`` points."""
    levels = 0
    size = n
    while size > leaf_size:
        size = (size + 1) // 2
        levels += 1
    n_inner = (1 << levels) - 1
    n_nodes = 2 * n_inner + 1
    lo_of = np.zeros(n_nodes, np.int64)
    hi_of = np.zeros(n_nodes, np.int64)
    hi_of[0] = n
    for node in range(n_inner):
        lo, hi = lo_of[node], hi_of[node]
        mid = (lo + hi) // 2
        a, b = 2 * node + 1, 2 * node + 2
        lo_of[a], hi_of[a], lo_of[b], hi_of[b] = lo, mid, mid, hi
    return n_inner, lo_of, hi_of


@numba.njit(cache=True)
def _boxes(data, n_inner, lo_of, hi_of):
    """Each node's tight bounding box (least and greatest coordinates) of its points in leaf
    order ``data``, built up from the leaves: a leaf's one coordinate at a time in locals
    (each bound read and written once, not per point)."""
    n_nodes, dim = lo_of.shape[0], data.shape[1]
    box = np.empty((n_nodes, 2, dim))
    for node in range(n_nodes - 1, -1, -1):
        if node >= n_inner:
            lo, hi = lo_of[node], hi_of[node]
            for j in range(dim):
                least, greatest = np.inf, -np.inf
                for r in range(lo, hi):
                    v = data[r, j]
                    least = min(least, v)
                    greatest = max(greatest, v)
                box[node, 0, j] = least
                box[node, 1, j] = greatest
        else:
            a, b = 2 * node + 1, 2 * node + 2
            for j in range(dim):
                box[node, 0, j] = min(box[a, 0, j], box[b, 0, j])
                box[node, 1, j] = max(box[a, 1, j], box[b, 1, j])
    return box


@numba.njit(cache=True)
def _build(points, leaf_size):
    """A balanced k-d tree: the points in leaf order (a copy), their original rows, each
    node's bounding box, the number of inner nodes and each node's range of leaf positions
    (`_layout`). A node splits at the median of the widest side of its cell (the root's box
    cut by the splits above); the boxes are then the tight ones of each node's points
    (`_boxes`)."""
    n, dim = points.shape
    data = points.copy()
    rows = np.arange(n)
    n_inner, lo_of, hi_of = _layout(n, leaf_size)
    cell = np.empty((lo_of.shape[0], 2, dim))
    for j in range(dim):
        cell[0, 0, j] = np.inf
        cell[0, 1, j] = -np.inf
        for r in range(n):
            cell[0, 0, j] = min(cell[0, 0, j], data[r, j])
            cell[0, 1, j] = max(cell[0, 1, j], data[r, j])
    tmp = np.empty(dim)
    for node in range(n_inner):
        lo, hi = lo_of[node], hi_of[node]
        mid = (lo + hi) // 2
        a, b = 2 * node + 1, 2 * node + 2
        cell[a] = cell[node]
        cell[b] = cell[node]
        if hi - lo < 2:
            continue
        best, spread = 0, -1.0
        for j in range(dim):
            if cell[node, 1, j] - cell[node, 0, j] > spread:
                best, spread = j, cell[node, 1, j] - cell[node, 0, j]
        # quickselect on coordinate `best`: rows [lo, mid) <= data[mid, best] <= rows [mid, hi)
        left, right = lo, hi - 1
        while left < right:
            pivot = data[(left + right) // 2, best]
            i, j = left, right
            while i <= j:
                while data[i, best] < pivot:
                    i += 1
                while data[j, best] > pivot:
                    j -= 1
                if i <= j:
                    tmp[:] = data[i]
                    data[i] = data[j]
                    data[j] = tmp
                    t = rows[i]
                    rows[i] = rows[j]
                    rows[j] = t
                    i += 1
                    j -= 1
            if mid <= j:
                right = j
            elif mid >= i:
                left = i
            else:
                break
        cell[a, 1, best] = data[mid, best]
        cell[b, 0, best] = data[mid, best]
    return data, rows, _boxes(data, n_inner, lo_of, hi_of), n_inner, lo_of, hi_of


@numba.njit(cache=True)
def _from_rows(points, rows, leaf_size):
    """`_build`'s tree from its ``rows`` (the leaf order it found): the same arrays without
    the median searches."""
    data = np.empty_like(points)
    for r in range(rows.shape[0]):
        data[r] = points[rows[r]]
    n_inner, lo_of, hi_of = _layout(points.shape[0], leaf_size)
    return data, rows, _boxes(data, n_inner, lo_of, hi_of), n_inner, lo_of, hi_of


@numba.njit(cache=True, inline="always")
def _boxdist(box, node, q):
    """Squared distance from q to the node's bounding box (zero inside it)."""
    s = 0.0
    for j in range(q.shape[0]):
        v = box[node, 0, j] - q[j]
        if v <= 0.0:
            v = q[j] - box[node, 1, j]
            if v <= 0.0:
                continue
        s += v * v
    return s


@numba.njit(cache=True)
def _insert(best_d, best_r, k, d, r):
    """Insert (d, r) into the ascending list of the k best (d < best_d[k - 1] holds)."""
    j = k - 1
    while j > 0 and best_d[j - 1] > d:
        best_d[j] = best_d[j - 1]
        best_r[j] = best_r[j - 1]
        j -= 1
    best_d[j] = d
    best_r[j] = r


@numba.njit(cache=True)
def _search(data, box, n_inner, lo_of, hi_of, q, best_d, best_r, k, accept, stack, stack_d):
    """Depth-first k-NN search of the tree, nearer child first, a node skipped when its
    bounding box lies beyond the k-th best squared distance so far (``best_d``, ascending,
    with the points' leaf positions in ``best_r``; -1 where none yet). With ``accept`` > 0
    the search stops (returns True) once the k best found so far have distances summing to
    at most ``accept``. ``stack``/``stack_d``: scratch for the nodes still to visit (an
    explicit stack: numba's cache cannot hold recursive functions)."""
    if data.shape[0] == 0:
        return False
    stack[0] = 0
    stack_d[0] = _boxdist(box, 0, q)
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        # a hair of slack: a box's distance never rounds above that of a point inside it
        if not stack_d[top] * (1.0 - 1e-12) < best_d[k - 1]:
            continue
        while node < n_inner:
            a, b = 2 * node + 1, 2 * node + 2
            da, db = _boxdist(box, a, q), _boxdist(box, b, q)
            if db < da:
                a, b, da, db = b, a, db, da
            if db * (1.0 - 1e-12) < best_d[k - 1]:
                stack[top] = b
                stack_d[top] = db
                top += 1
            if da * (1.0 - 1e-12) < best_d[k - 1]:
                node = a
            else:
                node = -1
                break
        if node < 0:
            continue
        for r in range(lo_of[node], hi_of[node]):
            d = _sqdist(data, r, q)
            if d < best_d[k - 1]:
                _insert(best_d, best_r, k, d, r)
        if accept > 0.0 and best_r[k - 1] >= 0:
            s = 0.0
            for j in range(k):
                s += np.sqrt(best_d[j])
            if s <= accept:
                return True
    return False


@numba.njit(cache=True)
def _query(data, rows, box, n_inner, lo_of, hi_of, x, k, bound2):
    """(distances, indices) (Q, k) of the k nearest points to each row of x, nearer than
    sqrt(bound2); missing neighbours as (inf, n)."""
    n_q = x.shape[0]
    n = data.shape[0]
    dist = np.full((n_q, k), np.inf)
    idx = np.full((n_q, k), n, np.int64)
    best_d = np.empty(k)
    best_r = np.empty(k, np.int64)
    stack = np.empty(_STACK, np.int64)
    stack_d = np.empty(_STACK)
    for i in range(n_q):
        best_d[:] = bound2
        best_r[:] = -1
        _search(data, box, n_inner, lo_of, hi_of, x[i], best_d, best_r, k, 0.0, stack,
                stack_d)
        for j in range(k):
            if best_r[j] >= 0:
                dist[i, j] = np.sqrt(best_d[j])
                idx[i, j] = rows[best_r[j]]
    return dist, idx


@numba.njit(cache=True)
def _first_valid(data, box, n_inner, lo_of, hi_of, x, order, k, threshold):
    """The first row of x, taken in ``order``, whose k nearest points have distances summing
    to at most ``threshold`` (V's test), or -1: what `NeighbourIndex.first_valid` decides for each
    row, stopping at the first valid one."""
    best_d = np.empty(k)
    best_r = np.empty(k, np.int64)
    stack = np.empty(_STACK, np.int64)
    stack_d = np.empty(_STACK)
    # valid: the nearest point within threshold / k (k distances summing to at most the
    # threshold), and the k-th within threshold - (k - 1) * nearest; a hair wide, so that
    # rounding never drops a neighbour (both bounds only prune)
    near2 = (threshold / k * (1.0 + 1e-9)) ** 2
    for i in order:
        q = x[i]
        best_d[0] = near2
        best_r[0] = -1
        _search(data, box, n_inner, lo_of, hi_of, q, best_d, best_r, 1, 0.0, stack, stack_d)
        if best_r[0] < 0:
            continue
        reach = max(threshold - (k - 1) * np.sqrt(best_d[0]), 0.0) * (1.0 + 1e-9)
        best_d[:] = reach * reach
        best_r[:] = -1
        if _search(data, box, n_inner, lo_of, hi_of, q, best_d, best_r, k, threshold, stack,
                   stack_d):
            return i
    return -1


@numba.njit(cache=True)
def _permutation_kind(rows):
    """2 if ``rows`` is range(len(rows)), 1 if another permutation of it, 0 if none (one
    pass, a byte per row: no temporary the size of ``rows``)."""
    n = rows.shape[0]
    seen = np.zeros(n, np.uint8)
    identity = True
    for i in range(n):
        r = rows[i]
        if r < 0 or r >= n or seen[r]:
            return 0
        seen[r] = 1
        identity = identity and r == i
    return 2 if identity else 1


def _as_rows(rows) -> np.ndarray:
    """Row numbers as a contiguous int32 or int64 array (other dtypes as int64)."""
    rows = np.asarray(rows)
    return np.ascontiguousarray(rows, dtype=rows.dtype if rows.dtype in (np.int32, np.int64)
                                else np.int64)


def check_permutation(rows: np.ndarray, n: int) -> np.ndarray:
    """``rows`` (n,) as int32 or int64 (another dtype as int64), ValueError unless it is a
    permutation of range(n) (a saved leaf order read from a file)."""
    rows = _as_rows(rows)
    if rows.shape != (n,) or not _permutation_kind(rows):
        raise ValueError("the saved neighbour index is not a permutation of the points")
    return rows


class NeighbourIndex:
    """Euclidean k-NN over fixed points (the paper's distance on (x0, x1))."""

    def __init__(self, points: np.ndarray, rows: np.ndarray | None = None):
        self.points = np.ascontiguousarray(points, dtype=np.float64)
        if self.points.ndim != 2:
            raise ValueError(f"points must be 2-D (N, D), got shape {self.points.shape}")
        if rows is None:
            self._tree = _build(self.points, _LEAF_SIZE)
        else:  # a saved leaf order (`rows`): checked to be a permutation of the points
            rows = _as_rows(rows)
            kind = _permutation_kind(rows) if rows.shape == (len(self.points),) else 0
            if not kind:
                raise ValueError("the saved neighbour index is not a permutation of the "
                                 "points")
            if kind == 2:
                # points already in leaf order (`LearnedFunctions` stores them so): the tree
                # is the points themselves, not a second copy of them
                layout = _layout(len(rows), _LEAF_SIZE)
                self._tree = (self.points, rows, _boxes(self.points, *layout), *layout)
            else:
                self._tree = _from_rows(self.points, rows, _LEAF_SIZE)
        # load the compiled queries now (numba's cache), not in the first plan
        self.query(self.points[:0], 1)
        self.first_valid(self.points[:0], np.empty(0, np.int64), 1, 0.0)

    def __len__(self) -> int:
        return self.points.shape[0]

    @property
    def rows(self) -> np.ndarray:
        """The points' leaf order: all `NeighbourIndex(points, rows)` needs to rebuild the
        tree without its median searches."""
        return self._tree[1]

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """The least and greatest coordinates (D,) each of the points: the tree's root box,
        already computed (inf and -inf without points)."""
        box = self._tree[2]
        return box[0, 0], box[0, 1]

    def query(self, x: np.ndarray, k: int, max_distance: float = np.inf
              ) -> tuple[np.ndarray, np.ndarray]:
        """Distances and indices (Q, k) of the k nearest points to each row of ``x`` (Q, D).

        Neighbours farther than ``max_distance`` are reported with distance inf and index
        ``len(self)``; bounding the search makes queries far from the data cheap.
        """
        x = np.ascontiguousarray(np.atleast_2d(x), dtype=np.float64)
        if x.shape[1] != self.points.shape[1]:
            raise ValueError(f"queries must have {self.points.shape[1]} columns, got "
                             f"{x.shape[1]}")
        if k < 1:
            raise ValueError(f"k must be at least 1, got {k}")
        return _query(*self._tree, x, int(k), float(max_distance) ** 2)

    def first_valid(self, x: np.ndarray, order: np.ndarray, k: int, threshold: float) -> int:
        """The first row of ``x`` in ``order`` whose ``k`` nearest points lie at distances
        summing to at most ``threshold`` (the validity classifier's test; the same answer as
        `query` with ``max_distance=threshold`` and the distances summed), or -1. A row's
        search stops as soon as k points with such distances are found, or once its nearest
        point is known to be farther than ``threshold / k``."""
        data, _, box, n_inner, lo_of, hi_of = self._tree
        return int(_first_valid(data, box, n_inner, lo_of, hi_of,
                                np.ascontiguousarray(x, dtype=np.float64),
                                np.asarray(order, dtype=np.int64), int(k), float(threshold)))
