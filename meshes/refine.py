"""Uniform 1-to-4 refinement of triangle meshes (topology only; the caller places the new nodes).

Each refinement splits every triangle at its edge midpoints into four similar ones, so the
coarse mesh's nodes, edges and cells survive as nodes, pairs of edges and groups of four cells
of the fine one: the meshes of successive levels are nested (a coarse closed state is a fine
starting state with nothing to interpolate across cells).
"""

from __future__ import annotations

import numpy as np

__all__ = ["cell_edges", "smooth_midpoints", "split", "split_edges", "vertex_normals"]


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


#: a boundary node where the boundary turns by more than this (deg) is a corner for
#: :func:`smooth_midpoints` (a smooth boundary sampled every ``h`` turns by ``h kappa``: the
#: demo valve's file at 3 mm turns by 8-18 deg along its annulus and free edge, and by 104 deg
#: at the free edge's two commissural tips)
CORNER_DEG = 40.0


def vertex_normals(points: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(N, 3) unit normals of the nodes of the triangles ``cells``, whatever their orientation:
    the principal axis of the outer products ``n n^T`` of the adjacent triangles' unit
    normals, each weighted by Max's ``sin(alpha) / (|e1| |e2|)`` of the triangle's corner at
    the node (edges ``e1``, ``e2``, angle ``alpha``; Max 1999: exact where the node and its
    neighbours lie on a sphere). A mean of oriented normals would cancel where neighbours are
    oriented oppositely, which a file may have; this cannot. Zero for nodes of no triangle.
    On a sphere triangulated irregularly it errs by 0.002 deg at 800 nodes, where the
    area-weighted axis errs by 1.5 deg."""
    points = np.asarray(points, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    cov = np.zeros((len(points), 3, 3))
    for i in range(3):
        p, q, r = (points[cells[:, (i + j) % 3]] for j in range(3))
        e1, e2 = q - p, r - p
        n = np.cross(e1, e2)
        twice_area = np.linalg.norm(n, axis=1)
        ok = twice_area > 0
        weight = np.where(ok, twice_area, 0.0) / np.maximum(
            (e1 * e1).sum(axis=1) * (e2 * e2).sum(axis=1), np.finfo(float).tiny)
        n = n / np.where(ok, twice_area, 1.0)[:, None]
        np.add.at(cov, cells[:, i], weight[:, None, None] * n[:, :, None] * n[:, None, :])
    out = np.zeros((len(points), 3))
    used = np.unique(cells)
    out[used] = np.linalg.eigh(cov[used])[1][:, :, 2]  # eigh sorts ascending
    return out


def smooth_midpoints(points: np.ndarray, cells: np.ndarray, edges: np.ndarray,
                     sides: np.ndarray, kind: np.ndarray | None = None) -> np.ndarray:
    """(k, 3) new nodes of the ``edges`` (:func:`split`'s, with :func:`cell_edges`' ``sides``)
    on a smooth surface through the nodes, instead of at the midpoints: the middle of each
    edge's cubic Hermite curve, ``(p0 + p1) / 2 + (t0 - t1) / 8``, whose end tangents ``t``
    are the chord ``d = p1 - p0`` projected onto
    - the nodes' tangent planes (:func:`vertex_normals`) on an interior edge (the edge curve
      of curved PN triangles, Vlachos et al. 2001);
    - the boundary curve's tangent line on a boundary edge, its direction at a node that of
      its two boundary neighbours' chord, so that a boundary keeps its own curvature (an
      annulus loop, a free edge). A boundary node with other than two boundary edges, or
      whose two are of different ``kind`` (per edge, e.g. annulus against free edge), or
      where the boundary turns by more than :data:`CORNER_DEG`, is a corner: there the
      tangent is the chord itself.

    The nodes do not move (the meshes stay nested). On a circle of radius ``R`` cut in chords
    of angle ``2 theta`` the new node is ``3 R theta^4 / 8`` off it against the midpoint's
    ``R theta^2 / 2``."""
    points = np.asarray(points, dtype=np.float64)
    edges = np.asarray(edges, dtype=np.int64)
    n = vertex_normals(points, cells)
    p0, p1 = points[edges[:, 0]], points[edges[:, 1]]
    d = p1 - p0

    def project(normal):
        return d - np.einsum("ij,ij->i", d, normal)[:, None] * normal

    t0, t1 = project(n[edges[:, 0]]), project(n[edges[:, 1]])
    boundary = np.bincount(np.asarray(sides).ravel(), minlength=len(edges)) == 1
    if boundary.any():
        be = np.flatnonzero(boundary)
        kind = np.zeros(len(edges), dtype=np.int64) if kind is None else np.asarray(kind)
        ends = np.concatenate([edges[be, 0], edges[be, 1]])
        other = np.concatenate([edges[be, 1], edges[be, 0]])
        kinds = np.concatenate([kind[be], kind[be]])
        order = np.argsort(ends, kind="stable")
        ends, other, kinds = ends[order], other[order], kinds[order]
        nodes, first, count = np.unique(ends, return_index=True, return_counts=True)
        tangent = np.full((len(points), 3), np.nan)  # nan: a corner
        second = np.minimum(first + 1, len(kinds) - 1)
        smooth = (count == 2) & (kinds[first] == kinds[second])
        # the boundary's turn at the node: beyond CORNER_DEG it is a corner (a square's)
        a = points[nodes] - points[other[first]]
        b = points[other[second]] - points[nodes]
        cos = np.einsum("ij,ij->i", a, b) / np.maximum(
            np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), np.finfo(float).tiny)
        smooth &= cos > np.cos(np.radians(CORNER_DEG))
        s = first[smooth]
        chord = points[other[s + 1]] - points[other[s]]
        tangent[nodes[smooth]] = chord / np.linalg.norm(chord, axis=1)[:, None]
        for t, end in ((t0, edges[be, 0]), (t1, edges[be, 1])):
            tau = tangent[end]
            along = np.einsum("ij,ij->i", d[be], tau)[:, None] * tau
            t[be] = np.where(np.isnan(tau).any(axis=1)[:, None], d[be], along)
    return 0.5 * (p0 + p1) + (t0 - t1) / 8.0
