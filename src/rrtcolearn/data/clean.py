"""Alg. 3 (clean_data): remove the local-optimum bias from a generated dataset.

The paper's pseudo-code has two misprints, corrected here: the point removed from a close pair
is the one with the *higher* cost (the text says so; the pseudo-code writes argmin), and the
distance compared with ``d`` is the one between the sampled point and its neighbour.

Both variants find neighbours with a uniform grid of cell size 2d over the learning inputs
(x0, x1): a ball of radius d then touches at most two cells per dimension.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numba
import numpy as np

from rrtcolearn.data.dataset import Dataset
from rrtcolearn.learn.features import QueryFeatures


@dataclass(frozen=True)
class CleaningResult:
    """Which rows were kept, and for each removed row the cheaper row that removed it."""

    keep: np.ndarray  # (N,) bool
    removed: np.ndarray  # (R,) row indices in removal order
    removed_by: np.ndarray  # (R,) the pair partner that was kept at that moment
    draws: int  # random draws made (randomized variant)


class _Grid:
    """Points sorted by grid cell, with per-cell ranges, for fixed-radius neighbour queries."""

    def __init__(self, points: np.ndarray, radius: float):
        cell = 2.0 * radius
        lo = points.min(axis=0)
        coords = np.floor((points - lo) / cell).astype(np.int64)
        dims = coords.max(axis=0) + 2
        if np.prod(dims.astype(np.float64)) > 2.0**62:
            raise ValueError("cleaning grid too fine for the data's extent; increase d")
        key = np.zeros(len(points), dtype=np.int64)
        for j in range(points.shape[1]):
            key = key * dims[j] + coords[:, j]
        self.order = np.argsort(key, kind="stable")
        self.points = np.ascontiguousarray(points[self.order])
        sorted_keys = key[self.order]
        self.cell_keys, starts = np.unique(sorted_keys, return_index=True)
        self.cell_starts = np.append(starts, len(points)).astype(np.int64)
        self.lo = lo
        self.cell = cell
        self.dims = dims.astype(np.int64)
        self.table_keys, self.table_cells = _build_table(self.cell_keys)

    @classmethod
    def or_none(cls, points: np.ndarray, radius: float) -> _Grid | None:
        """The grid, or None when its cells cannot be numbered in 63 bits."""
        try:
            return cls(points, radius)
        except ValueError:
            return None


# a query visits 2^D cells: beyond this many input dimensions a k-d tree is cheaper (the
# 8-D inputs of the 4-state systems keep the grid)
_GRID_MAX_DIM = 10


def _neighbour_lists_kdtree(points: np.ndarray, radius: float
                            ) -> tuple[np.ndarray, np.ndarray]:
    """The CSR lists of `_neighbour_lists` (neighbours closer than ``radius``, nearest first,
    ties by index) from scipy's k-d tree, for inputs of many dimensions."""
    from scipy.spatial import cKDTree

    n = len(points)
    pairs = cKDTree(points).query_pairs(radius, output_type="ndarray")
    if len(pairs):
        diff = points[pairs[:, 0]] - points[pairs[:, 1]]
        d2 = np.einsum("ij,ij->i", diff, diff)
        keep = d2 < radius * radius
        pairs, d2 = pairs[keep], d2[keep]
    else:
        d2 = np.empty(0)
    rows = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    cols = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    dist = np.concatenate([d2, d2])
    order = np.lexsort((cols, dist, rows))
    indptr = np.zeros(n + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
    return indptr, cols[order]


_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


@numba.njit(cache=True)
def _slot(key, mask):
    return np.int64((np.uint64(key) * _HASH_MULT) >> np.uint64(20)) & mask


@numba.njit(cache=True)
def _build_table(cell_keys):
    size = 1
    while size < 2 * cell_keys.shape[0]:
        size *= 2
    mask = size - 1
    table_keys = np.full(size, -1, dtype=np.int64)
    table_cells = np.empty(size, dtype=np.int64)
    for c in range(cell_keys.shape[0]):
        s = _slot(cell_keys[c], mask)
        while table_keys[s] != -1:
            s = (s + 1) & mask
        table_keys[s] = cell_keys[c]
        table_cells[s] = c
    return table_keys, table_cells


@numba.njit(cache=True)
def _lookup(key, table_keys, table_cells):
    """Index of the cell with ``key`` in the sorted cell list, or -1 when it is empty."""
    mask = table_keys.shape[0] - 1
    s = _slot(key, mask)
    while True:
        k = table_keys[s]
        if k == key:
            return table_cells[s]
        if k == -1:
            return -1
        s = (s + 1) & mask


@numba.njit(cache=True)
def _neighbour_lists(pts, table_keys, table_cells, starts, lo, cell, dims, radius, indices,
                     dists):
    """CSR lists of every point's neighbours closer than ``radius``, nearest first.

    Points are visited in grid order so the cells a query touches are mostly in cache; the
    lists then let the cleaning loops, which visit points in random order, touch only one
    contiguous list and the alive flags per query. Returns the filled length, or -1 when the
    preallocated ``indices``/``dists`` are too short.
    """
    n, dim = pts.shape
    cap = indices.shape[0]
    indptr = np.zeros(n + 1, dtype=np.int64)
    base = np.empty(dim, dtype=np.int64)
    other = np.empty(dim, dtype=np.int64)
    r2 = radius * radius
    fill = 0
    for i in range(n):
        for j in range(dim):
            f = (pts[i, j] - lo[j]) / cell
            c = int(np.floor(f))
            base[j] = c
            other[j] = c - 1 if f - c < 0.5 else c + 1
        row_start = fill
        for combo in range(1 << dim):
            key = 0
            inside = True
            for j in range(dim):
                c = other[j] if (combo >> j) & 1 else base[j]
                if c < 0 or c >= dims[j]:
                    inside = False
                key = key * dims[j] + c
            if not inside:
                continue
            a = _lookup(key, table_keys, table_cells)
            if a < 0:
                continue
            for q in range(starts[a], starts[a + 1]):
                if q == i:
                    continue
                d2 = 0.0
                for j in range(dim):
                    diff = pts[q, j] - pts[i, j]
                    d2 += diff * diff
                if d2 < r2:
                    if fill == cap:
                        return indptr, -1
                    indices[fill] = q
                    dists[fill] = d2
                    fill += 1
        # insertion sort by (distance, index): lists are short, and ties need a fixed order
        for a in range(row_start + 1, fill):
            di, ii = dists[a], indices[a]
            b = a - 1
            while b >= row_start and (dists[b] > di or (dists[b] == di and indices[b] > ii)):
                dists[b + 1] = dists[b]
                indices[b + 1] = indices[b]
                b -= 1
            dists[b + 1] = di
            indices[b + 1] = ii
        indptr[i + 1] = fill
    return indptr, fill


@numba.njit(cache=True)
def _first_alive(i, indptr, indices, alive):
    for q in range(indptr[i], indptr[i + 1]):
        if alive[indices[q]]:
            return indices[q]
    return -1


@numba.njit(cache=True)
def _clean_random_block(u, state, k_max, cost, alive, alive_list, pos, indptr, indices,
                        removed, removed_by):
    # state = [n_alive, k, n_removed]
    n_alive, k, n_removed = state[0], state[1], state[2]
    used = 0
    for t in range(u.shape[0]):
        if k >= k_max or n_alive < 2:
            break
        used += 1
        idx = alive_list[int(u[t] * n_alive)]
        nb = _first_alive(idx, indptr, indices, alive)
        if nb < 0:
            k += 1
            continue
        k = 0
        if cost[idx] > cost[nb]:
            high, low = idx, nb
        else:
            high, low = nb, idx
        alive[high] = False
        p = pos[high]
        last = alive_list[n_alive - 1]
        alive_list[p] = last
        pos[last] = p
        n_alive -= 1
        removed[n_removed] = high
        removed_by[n_removed] = low
        n_removed += 1
    state[0], state[1], state[2] = n_alive, k, n_removed
    return used


@numba.njit(cache=True)
def _clean_greedy(order, kept, indptr, indices, removed, removed_by):
    n_removed = 0
    for idx in order:
        nb = _first_alive(idx, indptr, indices, kept)
        if nb < 0:
            kept[idx] = True
        else:
            removed[n_removed] = idx
            removed_by[n_removed] = nb
            n_removed += 1
    return n_removed


def clean_indices(
    inputs: np.ndarray,
    cost: np.ndarray,
    *,
    d: float = 0.05,
    k_max: int = 5000,
    method: str = "randomized",
    seed: int | np.random.SeedSequence = 0,
    block: int = 1 << 18,
    progress: Callable[[int, int], None] | None = None,
) -> CleaningResult:
    """Alg. 3 on learning inputs (N, D) with costs (N,).

    ``method="randomized"`` is the paper's algorithm: draw a uniformly random remaining point,
    find its nearest remaining neighbour, and if it is closer than ``d`` remove the costlier of
    the two; stop after ``k_max`` consecutive draws without a removal.
    ``method="greedy"`` is a deterministic variant: visit points by increasing cost and keep a
    point only if no kept point lies within ``d``; afterwards no two kept points are within d.
    ``progress(draws, removed)`` is called after each block of draws.
    """
    if d <= 0:
        raise ValueError("cleaning radius d must be positive")
    n = len(cost)
    points = np.asarray(inputs, dtype=np.float64)
    grid = None if points.shape[1] > _GRID_MAX_DIM else _Grid.or_none(points, d)
    if grid is None:
        # many dimensions (a cell's 2^D neighbours) or a grid too fine: a k-d tree instead
        perm = np.arange(n)
        indptr, indices = _neighbour_lists_kdtree(points, float(d))
    else:
        perm = grid.order
        capacity = 8 * n + 16
        while True:
            indices = np.empty(capacity, dtype=np.int64)
            indptr, fill = _neighbour_lists(grid.points, grid.table_keys, grid.table_cells,
                                            grid.cell_starts, grid.lo, grid.cell, grid.dims,
                                            float(d), indices, np.empty(capacity))
            if fill >= 0:
                break
            capacity *= 4
        indices = indices[:fill]
    cost_s = np.ascontiguousarray(cost[perm], dtype=np.float64)
    removed = np.empty(n, dtype=np.int64)
    removed_by = np.empty(n, dtype=np.int64)
    draws = 0
    if method == "randomized":
        alive = np.ones(n, dtype=np.bool_)
        alive_list = np.arange(n, dtype=np.int64)
        pos = np.arange(n, dtype=np.int64)
        state = np.array([n, 0, 0], dtype=np.int64)
        rng = np.random.default_rng(seed)
        while state[1] < k_max and state[0] >= 2:
            u = rng.random(block)
            draws += _clean_random_block(u, state, int(k_max), cost_s, alive, alive_list, pos,
                                         indptr, indices, removed, removed_by)
            if progress is not None:
                progress(draws, int(state[2]))
        n_removed = int(state[2])
        kept_sorted = alive
    elif method == "greedy":
        kept_sorted = np.zeros(n, dtype=np.bool_)
        order = np.argsort(cost_s, kind="stable")
        n_removed = _clean_greedy(order, kept_sorted, indptr, indices, removed, removed_by)
        if progress is not None:
            progress(n, n_removed)
    else:
        raise ValueError(f"unknown cleaning method {method!r}; use 'randomized' or 'greedy'")
    keep = np.empty(n, dtype=np.bool_)
    keep[perm] = kept_sorted
    return CleaningResult(
        keep=keep,
        removed=perm[removed[:n_removed]],
        removed_by=perm[removed_by[:n_removed]],
        draws=draws,
    )


def clean_data(data: Dataset, scale: np.ndarray | None = None,
               features: QueryFeatures | None = None, **kwargs
               ) -> tuple[Dataset, CleaningResult]:
    """Alg. 3 on a dataset's (x0, x1) inputs as the learners see them: mapped by
    ``features`` (x1 - x0 along invariant coordinates, `learn.features`; none: the raw rows)
    and the state coordinates weighted by ``scale`` (n,) as in the learners' distance; returns
    the kept rows and the cleaning record. Without invariant coordinates the inputs are the
    raw rows, bit for bit."""
    if features is None:
        inputs = data.inputs if scale is None else data.inputs * np.tile(scale, 2)
    else:
        inputs = features.transform(data.inputs)
        if scale is not None:
            inputs = inputs * features.scale(scale)
    result = clean_indices(inputs, data.cost, **kwargs)
    return data.take(result.keep), result
