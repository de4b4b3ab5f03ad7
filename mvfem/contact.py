"""Contact between leaflets and within a leaflet: a penalty on the gap to the opposite surface.

Every free node ``s`` is paired with the nearest triangle ``T`` of the deformed surface that was
not its neighbour in the open valve (reference distance above ``exclusion``): the pairs come
from a KD-tree on the triangle centroids. For a pair, with the unit normal ``n`` of ``T`` and
the barycentric coordinates ``xi`` of the closest point, both frozen when the pairs are built,
and ``sigma`` the side of ``T`` the node is on,

.. math:: g = \\sigma\\, n\\cdot(x_s - \\textstyle\\sum_i \\xi_i x_i),\\qquad
          \\Pi = A_s\\, \\phi(\\delta - g)

with ``A_s`` the node's lumped area, ``delta`` the contact thickness and ``phi`` the rounded
one-sided quadratic of :func:`mvfem.nodal.smooth_penalty` (stiffness ``k`` in Pa/mm): a
pressure ``k (delta - g)`` pushes the surfaces apart once they come closer than ``delta``.
The pairs are rebuilt at every evaluation of the residual (``n`` and ``xi`` at the current
positions; the tangent treats them as fixed, ``A_s phi'' dg dg^T``). Where the closest point is
on the boundary of the other sheet the gap is the distance to it (never a penetration). Every
node is a slave and every triangle a master (two-pass), which covers leaflet-leaflet and self
contact alike.

The side ``sigma`` of a pair comes from the node's memory of the last accepted state
(:meth:`Contact.remember`): the side of the triangle it was paired with then, carried over to
the new triangle through the turn of the normal. A node found on the other side of its
(interior-projected) triangle than remembered has passed through the surface, which
:meth:`Contact.crossings` reports so that the load step is cut back. Frozen pairs within a
step were tried first and gave spurious intrusions of 2.5 mm as the leaflets swung.
"""

from __future__ import annotations

import numpy as np

from mvfem.nodal import Blocks, NodalView, smooth_penalty

__all__ = ["Contact", "closest_point_on_triangles"]


def closest_point_on_triangles(p, a, b, c):
    """Closest points of points ``p`` on triangles ``(a, b, c)`` (all (m, 3), row-wise).

    Returns (distance, barycentric (m, 3), inside) with ``inside`` True where the closest point
    is interior (the orthogonal projection falls in the triangle).
    """
    ab, ac, ap = b - a, c - a, p - a
    d00 = np.einsum("ij,ij->i", ab, ab)
    d01 = np.einsum("ij,ij->i", ab, ac)
    d11 = np.einsum("ij,ij->i", ac, ac)
    d20 = np.einsum("ij,ij->i", ap, ab)
    d21 = np.einsum("ij,ij->i", ap, ac)
    den = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / den
    w = (d00 * d21 - d01 * d20) / den
    bary = np.stack([1 - v - w, v, w], axis=1)
    inside = np.all(bary >= 0, axis=1)
    best_bary = bary.copy()
    best = np.full(len(p), np.inf)
    q = a + v[:, None] * ab + w[:, None] * ac
    best[inside] = np.linalg.norm(p[inside] - q[inside], axis=1)
    # otherwise the closest point is on an edge
    verts = (a, b, c)
    for i, j in ((0, 1), (1, 2), (2, 0)):
        e = verts[j] - verts[i]
        t = np.clip(np.einsum("ij,ij->i", p - verts[i], e) / np.einsum("ij,ij->i", e, e), 0, 1)
        dist = np.linalg.norm(p - verts[i] - t[:, None] * e, axis=1)
        better = ~inside & (dist < best)
        best[better] = dist[better]
        bb = np.zeros((better.sum(), 3))
        bb[:, i] = 1 - t[better]
        bb[:, j] = t[better]
        best_bary[better] = bb
    return best, best_bary, inside


def _normals(x, tri):
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    return n / np.linalg.norm(n, axis=1)[:, None]


class Contact:
    """Node-to-triangle penalty contact over a whole surface (rank 0 holds the pairs).

    Args:
        view: the global node view.
        thickness: contact thickness ``delta``, mm (surfaces are kept this far apart).
        stiffness: penalty ``k``, Pa/mm.
        search: pairs are kept for nodes within this distance of a triangle, mm (default
            the larger of 2 ``thickness`` and the longest reference edge).
        exclusion: node and triangle closer than this in the open (reference) surface never
            pair (they are neighbours on one sheet), mm (default the larger of 3 longest edges
            and 4 ``thickness``).
        onset: rounding of the penalty onset, mm.
    """

    def __init__(self, view: NodalView, thickness: float, stiffness: float,
                 search: float | None = None, exclusion: float | None = None,
                 onset: float | None = None):
        self.view = view
        self.thickness = float(thickness)
        self.stiffness = float(stiffness)
        self.onset = float(onset if onset is not None else thickness / 4)
        self.refreshes = 0
        self.time_s = 0.0
        if view.comm.rank == 0:
            self.slaves = np.flatnonzero(view.free.any(axis=1))
            edges = np.concatenate([view.cells[:, [0, 1]], view.cells[:, [1, 2]],
                                    view.cells[:, [2, 0]]])
            self._max_edge = float(np.linalg.norm(view.X[edges[:, 0]] - view.X[edges[:, 1]],
                                                  axis=1).max(initial=0.0))
        else:
            self.slaves = np.zeros(0, dtype=np.int64)
            self._max_edge = 0.0
        # only rank 0 searches, so the defaults need not agree across ranks
        self.search = float(search if search is not None
                            else max(2 * self.thickness, self._max_edge))
        self.exclusion = float(exclusion if exclusion is not None
                               else max(3 * self._max_edge, 4 * self.thickness))
        self._empty()
        n = len(view.X)
        self._mem_sigma = np.zeros(n)
        self._mem_normal = np.zeros((n, 3))
        self._cache_x = None
        self._inside = np.zeros(0, dtype=bool)
        self._side = np.zeros(0)
        self._tri_normal = np.zeros((0, 3))

    def _empty(self) -> None:
        self.slave = np.zeros(0, dtype=np.int64)
        self.tri = np.zeros(0, dtype=np.int64)
        self.xi = np.zeros((0, 3))
        self.normal = np.zeros((0, 3))
        self.sigma = np.zeros(0)

    def __len__(self) -> int:
        return len(self.slave)

    # --- pairs ------------------------------------------------------------------------------
    def _candidates(self, x: np.ndarray):
        """Nearest admissible triangle of every slave within the search distance."""
        from scipy.spatial import cKDTree

        v = self.view
        cells = v.cells
        tree = cKDTree(x[cells].mean(axis=1))
        # a centroid is within 2/3 of the longest edge of every point of its triangle; the
        # longest edge may have grown since the reference state, allow for it
        grow = np.linalg.norm(x[cells[:, 1]] - x[cells[:, 0]], axis=1).max(initial=0.0)
        radius = self.search + max(self._max_edge, grow)
        lists = tree.query_ball_point(x[self.slaves], radius)
        counts = np.fromiter((len(li) for li in lists), dtype=np.int64, count=len(lists))
        none = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros((0, 3)), np.zeros(0),
                                                     np.zeros(0, dtype=bool))
        if counts.sum() == 0:
            return none
        s = np.repeat(self.slaves, counts)
        t = np.concatenate([np.asarray(li, dtype=np.int64) for li in lists if li])
        ref = np.min(np.linalg.norm(v.X[cells[t]] - v.X[s][:, None, :], axis=2), axis=1)
        keep = ref > self.exclusion
        s, t = s[keep], t[keep]
        tri = cells[t]
        dist, bary, inside = closest_point_on_triangles(x[s], x[tri[:, 0]], x[tri[:, 1]],
                                                        x[tri[:, 2]])
        near = dist < self.search
        if not near.any():
            return none
        s, t, dist, bary, inside = s[near], t[near], dist[near], bary[near], inside[near]
        # the nearest triangle of each slave
        order = np.lexsort((dist, s))
        s, t, dist, bary, inside = s[order], t[order], dist[order], bary[order], inside[order]
        first = np.r_[True, s[1:] != s[:-1]]
        return s[first], t[first], bary[first], dist[first], inside[first]

    def pairs_at(self, x: np.ndarray) -> None:
        """Pairs at positions ``x``: each slave with its nearest admissible triangle, normal
        and barycentric coordinates of the closest point taken at ``x``; the side from the
        slave's memory of the last accepted state (see :meth:`remember`), else from ``x``."""
        if self.view.comm.rank != 0:
            return
        if self._cache_x is not None and np.array_equal(self._cache_x, x):
            return
        import time

        t0 = time.perf_counter()
        s, t, bary, _, inside = self._candidates(x)
        tri = self.view.cells[t]
        n = _normals(x, tri)
        side = np.sign(np.einsum("ij,ij->i", n, x[s] - np.einsum("ij,ijk->ik", bary, x[tri])))
        side[side == 0] = 1.0
        known = self._mem_sigma[s] != 0
        turn = np.einsum("ij,ij->i", n[known], self._mem_normal[s[known]])
        side[known] = self._mem_sigma[s[known]] * np.where(turn >= 0, 1.0, -1.0)
        # beside an edge of the other sheet (closest point on its boundary), the gap is the
        # distance, along the line to the closest point: never a penetration
        d = x[s] - np.einsum("ij,ijk->ik", bary, x[tri])
        dist = np.linalg.norm(d, axis=1)
        out = ~inside & (dist > 1e-12)
        eff = n.copy()
        eff[out] = d[out] / dist[out, None]
        sigma = side.copy()
        sigma[out] = 1.0
        self.slave, self.tri, self.xi, self.normal, self.sigma = s, t, bary, eff, sigma
        self._side, self._tri_normal = side, n
        self._inside = inside
        self._cache_x = x.copy()
        self.refreshes += 1
        self.time_s += time.perf_counter() - t0

    def remember(self, x: np.ndarray) -> None:
        """Record, at an accepted (non-crossing) state ``x``, which side of the other surface
        every paired node is on; later pairs take their side from it."""
        if self.view.comm.rank != 0:
            return
        self.pairs_at(x)
        self._mem_sigma[:] = 0.0
        self._mem_sigma[self.slave] = self._side
        self._mem_normal[self.slave] = self._tri_normal

    def crossings(self, x: np.ndarray) -> int:
        """Nodes now on the other side of their triangle than remembered (passed through)."""
        if self.view.comm.rank != 0:
            return 0
        self.pairs_at(x)
        if len(self.slave) == 0:
            return 0
        tri = self.view.cells[self.tri]
        g = np.einsum("ij,ij->i", self._tri_normal,
                      x[self.slave] - np.einsum("ij,ijk->ik", self.xi, x[tri]))
        return int(np.sum(self._inside & (np.sign(g) != self._side) & (np.abs(g) > 0)))

    def gaps(self, x: np.ndarray) -> np.ndarray:
        """Signed gap of every pair at positions ``x`` (frozen normals)."""
        tri = self.view.cells[self.tri]
        xp = np.einsum("ij,ijk->ik", self.xi, x[tri])
        return self.sigma * np.einsum("ij,ij->i", self.normal, x[self.slave] - xp)

    def penetration(self, x: np.ndarray) -> dict:
        """Largest intrusion into the contact thickness, and crossings, at positions ``x``."""
        self.pairs_at(x)
        if len(self.slave) == 0:
            return {"max_penetration_mm": 0.0, "crossings": 0, "active_pairs": 0}
        g = self.gaps(x)
        return {"max_penetration_mm": float(max(0.0, (self.thickness - g).max())),
                "crossings": self.crossings(x),
                "active_pairs": int(np.sum(g < self.thickness))}

    # --- energy -----------------------------------------------------------------------------
    def __call__(self, x: np.ndarray) -> Blocks:
        self.pairs_at(x)
        m = len(self.slave)
        if m == 0:
            return Blocks(np.zeros((0, 4), dtype=np.int64), np.zeros((0, 4, 3)),
                          np.zeros((0, 12, 12)))
        tri = self.view.cells[self.tri]
        g = self.gaps(x)
        k = self.stiffness * self.view.area[self.slave]
        phi, dphi, ddphi = smooth_penalty(self.thickness - g, k, self.onset)
        # dg/dx: sigma n on the node, -sigma xi_i n on the triangle's vertices
        coef = np.concatenate([np.ones((m, 1)), -self.xi], axis=1) * self.sigma[:, None]
        dg = coef[:, :, None] * self.normal[:, None, :]          # (m, 4, 3)
        force = -dphi[:, None, None] * dg
        flat = dg.reshape(m, 12)
        K = ddphi[:, None, None] * flat[:, :, None] * flat[:, None, :]
        nodes = np.concatenate([self.slave[:, None], tri], axis=1)
        return Blocks(nodes, force, K, float(phi.sum()))
