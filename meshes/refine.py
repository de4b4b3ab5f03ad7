"""Uniform 1-to-4 refinement of triangle meshes (topology only; the caller places the new nodes).

Each refinement splits every triangle at its edge midpoints into four similar ones, so the
coarse mesh's nodes, edges and cells survive as nodes, pairs of edges and groups of four cells
of the fine one: the meshes of successive levels are nested (a coarse closed state is a fine
starting state with nothing to interpolate across cells).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cell_edges", "split", "split_edges"]


def cell_edges(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The (k, 2) unique edges (sorted pairs, in lexicographic order) of the triangles
    ``cells`` (m, 3), and (3, m) each cell side's edge: row 0 the sides 0-1, row 1 the sides
    1-2, row 2 the sides 2-0 (an edge bounding one cell is on the boundary:
    ``np.bincount(sides.ravel()) == 1``)."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    e = np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]], cells[:, [2, 0]]])
    edges, inverse = np.unique(np.sort(e, axis=1), axis=0, return_inverse=True)
    return edges, inverse.reshape(3, -1)


def split(cells: np.ndarray, n_points: int) -> tuple[np.ndarray, np.ndarray]:
    """One 1-to-4 split of the triangles ``cells`` (m, 3) on ``n_points`` nodes.

    Returns:
        ``(edges, new_cells)``: the (k, 2) unique edges (sorted pairs), whose midpoints are the
        new nodes ``n_points + i`` in that order, and the (4m, 3) new triangles, the four
        children of cell ``c`` at rows ``c, m + c, 2m + c, 3m + c`` (the three corners' first,
        then the middle one), each oriented as its parent.
    """
    cells = np.asarray(cells, dtype=np.int64)
    edges, sides = cell_edges(cells)
    m01, m12, m20 = n_points + sides
    v0, v1, v2 = cells.T
    new = np.concatenate([np.stack([v0, m01, m20], axis=1), np.stack([m01, v1, m12], axis=1),
                          np.stack([m20, m12, v2], axis=1), np.stack([m01, m12, m20], axis=1)])
    return edges, new


def split_edges(lines: np.ndarray, edges: np.ndarray, n_points: int) -> np.ndarray:
    """The (2k, 2) halves of the (k, 2) mesh edges ``lines`` after :func:`split` (``edges``,
    ``n_points`` as given to and returned by it): ``(a, b)`` becomes ``(a, m)`` at row ``i`` and
    ``(m, b)`` at row ``k + i``. Raises ``ValueError`` for a line that is not a mesh edge."""
    lines = np.asarray(lines, dtype=np.int64).reshape(-1, 2)
    if len(lines) == 0:
        return lines.copy()
    width = int(max(edges.max(initial=0), lines.max())) + 1
    keys = edges[:, 0] * width + edges[:, 1]
    lo, hi = lines.min(axis=1), lines.max(axis=1)
    want = lo * width + hi
    at = np.searchsorted(keys, want)  # np.unique sorted the edges lexicographically
    at = np.minimum(at, len(keys) - 1)
    if np.any(keys[at] != want):
        raise ValueError("a line to split is not an edge of the triangles")
    m = n_points + at
    return np.concatenate([np.stack([lines[:, 0], m], axis=1),
                           np.stack([m, lines[:, 1]], axis=1)])
