r"""Contact between leaflets and within a leaflet: a barrier on the distance to the other surface.

Energy: every free node ``s`` and every triangle ``T`` of the deformed surface that was not
its neighbour in the open valve (reference distance above ``exclusion``) and is now closer
than the contact thickness ``delta`` form a pair, found with a KD-tree on the triangle
centroids. With ``d`` the (unsigned) distance from the node to its closest point
``q = sum_i xi_i x_i`` on ``T``,

.. math:: \Pi = \sum_{(s, T)} A_s\, b(d),\qquad
          \partial d/\partial x_s = \nu,\quad \partial d/\partial x_i = -\xi_i \nu,
          \quad \nu = (x_s - q)/d

with ``A_s`` the node's lumped area and ``b`` IPC's log barrier (:func:`barrier`, stiffness
``kappa`` in Pa/mm): C2 where a pair enters at ``d = delta`` and unbounded as ``d -> 0``, so
no finite load (a chord pulling a free edge, say) presses a node onto the other leaflet. The
distance to a triangle is continuously differentiable away from it, so the residual has no
jumps: there is no "nearest triangle" to switch between and no side to choose (a
nearest-triangle penalty with sides did not get the valve past its first contact, Newton
cycling between pairings; a bounded quadratic penalty let chordae pull free-edge nodes onto
the other leaflet, where Newton stalled). The price: a node opposite a vertex pairs with
every triangle around it, so the contact stiffness varies by up to the vertex valence over
the surface; the contact pressure at equilibrium still balances the load. The tangent is the
exact Hessian ``A_s (b'' dd dd^T + b' d2d)``, the curvature ``d2d`` by central differences of
the exact gradient (:func:`distance_hessian`); it may be indefinite pair by pair (a node
repelled by a vertex), the assembled tangent of a stable state is not.

No crossing: the energy alone cannot stop a Newton update from carrying a node through a
triangle in one jump (then the unsigned distance pushes it on through). :meth:`step_limit`
scales every update so that no node passes through an admissible triangle on the way
(vertex-face continuous collision detection); line-search Newton applies it to each update
(``SNESProblem``'s precheck), so no iterate, hence no state, has a leaflet passed through
another. (A conservative bound on the closing distance, as in IPC's additive CCD, was tried
first: it also throttled nodes sliding along the other leaflet, and Newton stalled. A side
remembered from the last accepted state was used before that, and its carry-over between
triangles reported false crossings.)
"""

from __future__ import annotations

import logging

import numpy as np

from mvfem.nodal import Blocks, NodalView

__all__ = ["Contact", "closest_point_on_triangles", "barrier", "distance_gradient",
           "distance_hessian"]

log = logging.getLogger(__name__)


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


def distance_gradient(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from node to triangle and its gradient (m, 12) for stacked ``y`` = (node,
    vertex a, b, c) coordinates (m, 12): by the envelope theorem, ``d d/d x_s = nu`` and
    ``d d / d x_i = -xi_i nu`` with ``nu`` the unit vector from the closest point."""
    m = len(y)
    p, a, b, c = (y[:, 3 * i:3 * i + 3] for i in range(4))
    d, xi, _ = closest_point_on_triangles(p, a, b, c)
    q = xi[:, 0:1] * a + xi[:, 1:2] * b + xi[:, 2:3] * c
    nu = (p - q) / np.maximum(d, 1e-300)[:, None]
    coef = np.concatenate([np.ones((m, 1)), -xi], axis=1)
    return d, (coef[:, :, None] * nu[:, None, :]).reshape(m, 12)


def distance_hessian(y: np.ndarray, rel: float = 1e-4) -> np.ndarray:
    """(m, 12, 12) Hessian of the node-triangle distance: central differences of its exact
    gradient (:func:`distance_gradient`) with steps ``rel`` x the distance, symmetrised."""
    m = len(y)
    d, _ = distance_gradient(y)
    h = np.maximum(rel * d, 1e-12)
    H = np.empty((m, 12, 12))
    for j in range(12):
        e = np.zeros(12)
        e[j] = 1.0
        _, gp = distance_gradient(y + h[:, None] * e)
        _, gm = distance_gradient(y - h[:, None] * e)
        H[:, :, j] = (gp - gm) / (2 * h[:, None])
    return 0.5 * (H + H.transpose(0, 2, 1))


def barrier(d: np.ndarray, delta: float, kappa) -> tuple[np.ndarray, ...]:
    r"""IPC's log barrier and its first two derivatives in ``d`` (0 for ``d >= delta``).

    .. math:: b(d) = -\kappa (d - \delta)^2 \ln(d/\delta), \quad 0 < d < \delta

    C2 at ``d = delta`` (a pair enters with no energy, force or stiffness) and unbounded as
    ``d -> 0``: no finite load presses a node onto a triangle. Its pressure
    ``-b'(d) = kappa delta`` at ``d = 0.53 delta``.
    """
    d = np.asarray(d, dtype=float)
    on = (d > 0) & (d < delta)
    x = np.where(on, d, delta)
    g = x - delta
    lg = np.log(x / delta)
    b = np.where(on, -kappa * g**2 * lg, np.where(d <= 0, np.inf, 0.0))
    db = np.where(on, -kappa * (2 * g * lg + g**2 / x), 0.0)
    ddb = np.where(on, -kappa * (2 * lg + 4 * g / x - g**2 / x**2), 0.0)
    return b, db, ddb


def _tri_radius(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """Distance from each triangle's centroid to its furthest vertex: every point of the
    triangle is this close to the centroid (the KD-trees hold centroids)."""
    xc = x[cells]
    return np.linalg.norm(xc - xc.mean(axis=1)[:, None, :], axis=2).max(axis=1)


def _normals(x, tri):
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    return n / np.linalg.norm(n, axis=1)[:, None]


class Contact:
    """Node-to-triangle barrier contact over a whole surface (rank 0 finds the pairs).

    Args:
        view: the global node view.
        thickness: contact thickness ``delta``, mm (surfaces are kept this far apart).
        stiffness: barrier stiffness ``kappa``, Pa/mm (contact pressure ``kappa delta`` at
            about half the thickness).
        exclusion: node and triangle closer than this in the open (reference) surface never
            pair (they are neighbours on one sheet), mm (default the larger of 3 longest edges
            and 4 ``thickness``).
    """

    def __init__(self, view: NodalView, thickness: float, stiffness: float,
                 exclusion: float | None = None):
        self.view = view
        self.thickness = float(thickness)
        self.stiffness = float(stiffness)
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
        self.exclusion = float(exclusion if exclusion is not None
                               else max(3 * self._max_edge, 4 * self.thickness))
        self._excluded = self._excluded_pairs() if view.comm.rank == 0 else None

    def _excluded_pairs(self) -> np.ndarray:
        """Sorted keys ``s * n_cells + t`` of the (node, triangle) pairs that never interact:
        a vertex of ``t`` within ``exclusion`` of ``s`` in the reference surface."""
        from scipy.spatial import cKDTree

        X, cells = self.view.X, self.view.cells
        if len(self.slaves) == 0 or len(cells) == 0:
            return np.zeros(0, dtype=np.int64)
        node_cells = [[] for _ in range(len(X))]
        for t, tri in enumerate(cells):
            for i in tri:
                node_cells[i].append(t)
        near = cKDTree(X).query_ball_point(X[self.slaves], self.exclusion)
        keys = [s * len(cells) + np.unique(np.concatenate([node_cells[j] for j in nb]))
                for s, nb in zip(self.slaves, near)]
        return np.unique(np.concatenate(keys).astype(np.int64))

    # --- reporting ----------------------------------------------------------------------------
    def penetration(self, x: np.ndarray) -> dict:
        """How far the surfaces at ``x`` pass through each other, and how close they come.

        ``max_penetration_mm``: over every mesh edge that crosses an admissible triangle (both
        its ends further than ``exclusion`` from the triangle in the reference surface), the
        depth of its shallower end behind the triangle's plane; 0 when no edge crosses.
        ``max_intrusion_mm``: the deepest intrusion into the contact thickness, ``thickness -
        d`` over the node-triangle pairs (the barrier lets pairs come closer than the thickness
        under load: that is not a penetration). Also ``min_distance_mm``, ``active_pairs`` and
        ``intersections`` (crossing edge-triangle pairs)."""
        _, _, _, d = self.active_pairs(x)
        depth, count = self.intersections(x)
        out = {"max_penetration_mm": depth, "intersections": count, "active_pairs": len(d)}
        if len(d) == 0:
            return {**out, "max_intrusion_mm": 0.0, "min_distance_mm": None}
        return {**out, "max_intrusion_mm": float(self.thickness - d.min()),
                "min_distance_mm": float(d.min())}

    def intersections(self, x: np.ndarray) -> tuple[float, int]:
        """(depth, count) of the mesh edges that cross admissible triangles at ``x``:
        segment-triangle tests (Moller-Trumbore) on candidates from a KD-tree of centroids;
        the depth of a crossing is the distance of the edge's shallower end to the plane."""
        from scipy.spatial import cKDTree

        cells = self.view.cells
        if len(self.slaves) == 0 or len(cells) == 0:
            return 0.0, 0
        e = np.unique(np.sort(np.concatenate([cells[:, [0, 1]], cells[:, [1, 2]],
                                              cells[:, [2, 0]]]), axis=1), axis=0)
        mid = 0.5 * (x[e[:, 0]] + x[e[:, 1]])
        half = 0.5 * np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
        r_tri = _tri_radius(x, cells)
        hits = cKDTree(mid).sparse_distance_matrix(
            cKDTree(x[cells].mean(axis=1)), float(half.max() + r_tri.max()), output_type="ndarray")
        ei, t = hits["i"].astype(np.int64), hits["j"].astype(np.int64)
        ok = hits["v"] <= half[ei] + r_tri[t]
        ei, t = ei[ok], t[ok]
        a, b = e[ei, 0], e[ei, 1]
        tri = cells[t]
        shares = np.any(tri == a[:, None], axis=1) | np.any(tri == b[:, None], axis=1)
        keep = ~shares
        keep[keep] = self._admissible(a[keep], t[keep]) & self._admissible(b[keep], t[keep])
        a, b, tri = a[keep], b[keep], tri[keep]
        if len(a) == 0:
            return 0.0, 0
        p, q = x[a], x[b]
        v0, v1, v2 = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
        n = np.cross(v1 - v0, v2 - v0)
        n /= np.linalg.norm(n, axis=1)[:, None]
        dp = np.einsum("ij,ij->i", p - v0, n)
        dq = np.einsum("ij,ij->i", q - v0, n)
        cross = dp * dq < 0
        tt = np.where(cross, dp / np.where(cross, dp - dq, 1.0), 0.0)
        hit = p + tt[:, None] * (q - p)
        _, _, inside = closest_point_on_triangles(hit, v0, v1, v2)
        found = cross & inside
        if not found.any():
            return 0.0, 0
        depth = np.minimum(np.abs(dp[found]), np.abs(dq[found]))
        return float(depth.max()), int(found.sum())

    # --- energy -----------------------------------------------------------------------------
    def _near(self, x: np.ndarray, radius: float):
        """(node, triangle) index pairs, slaves only, with the node within ``radius`` of the
        triangle's centroid, and that distance."""
        from scipy.spatial import cKDTree

        cells = self.view.cells
        nodes = cKDTree(x[self.slaves])
        cents = cKDTree(x[cells].mean(axis=1))
        hits = nodes.sparse_distance_matrix(cents, radius, output_type="ndarray")
        return self.slaves[hits["i"]], hits["j"].astype(np.int64), hits["v"]

    def active_pairs(self, x: np.ndarray, within: float | None = None):
        """Every admissible (node, triangle) pair closer than ``within`` (default the
        thickness) at ``x``: slave nodes, triangle indices, barycentric coordinates of the
        closest points, distances."""
        within = self.thickness if within is None else float(within)
        cells = self.view.cells
        empty = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros((0, 3)), np.zeros(0))
        if len(self.slaves) == 0 or len(cells) == 0:
            return empty
        s, t, _ = self._near(x, within + float(_tri_radius(x, cells).max(initial=0.0)))
        keep = self._admissible(s, t)
        s, t = s[keep], t[keep]
        tri = cells[t]
        dist, bary, _ = closest_point_on_triangles(x[s], x[tri[:, 0]], x[tri[:, 1]],
                                                   x[tri[:, 2]])
        near = dist < within
        return s[near], t[near], bary[near], dist[near]

    def _admissible(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Node and triangle further apart than ``exclusion`` in the reference surface."""
        keys = s.astype(np.int64) * len(self.view.cells) + t
        pos = np.searchsorted(self._excluded, keys)
        pos[pos == len(self._excluded)] = 0
        return self._excluded[pos] != keys if len(self._excluded) else np.ones(len(s), bool)

    def step_limit(self, x: np.ndarray, dx: np.ndarray, keep: float = 0.2) -> float:
        """Largest fraction ``alpha`` <= 1 of the update ``dx`` along which no node passes
        through an admissible triangle (vertex-face continuous collision detection).

        Along ``x + t dx`` a node meets the plane of a triangle where the cubic
        ``det[a - p, b - p, c - p](t)`` changes sign; it passes through the triangle when its
        closest point there is inside. The update is cut to ``(1 - keep)`` of the first such
        ``t``. Candidate pairs: those whose distance could close at all, i.e. closer than the
        largest relative motion (moving node and triangle together changes nothing). Newton
        updates are scaled by it (SNESProblem's precheck), so no iterate has a leaflet passed
        through another, however large the update. Edge-edge crossings are not checked.
        """
        if len(self.slaves) == 0 or not np.any(dx):
            return 1.0
        cells = self.view.cells
        r_tri = _tri_radius(x, cells)
        s, t, dc = self._swept_candidates(x, dx, r_tri)
        tri = cells[t]
        w = dx[tri] - dx[s][:, None, :]                    # relative motion of the vertices
        # the pair's distance is at least dc - r_tri and closes by at most max |w|
        can = (dc - r_tri[t] <= np.linalg.norm(w, axis=2).max(axis=1))
        # the node's path and the triangle's swept box must overlap (margin: the crossing
        # test's tolerance)
        pad = 1e-3 * max(self._max_edge, 1e-12)
        ps, pe = x[s], x[s] + dx[s]
        vs, ve = x[tri], x[tri] + dx[tri]
        lo_t = np.minimum(vs.min(axis=1), ve.min(axis=1)) - pad
        hi_t = np.maximum(vs.max(axis=1), ve.max(axis=1)) + pad
        can &= np.all((np.maximum(ps, pe) >= lo_t) & (np.minimum(ps, pe) <= hi_t), axis=1)
        can[can] = self._admissible(s[can], t[can])
        s, t, tri, w = s[can], t[can], tri[can], w[can]
        if len(s) == 0:
            return 1.0
        u = x[tri] - x[s][:, None, :]                      # (m, 3, 3) vertices - node

        def det(a, b, c):
            return np.einsum("ij,ij->i", a, np.cross(b, c))

        ua, ub, uc = u[:, 0], u[:, 1], u[:, 2]
        wa, wb, wc = w[:, 0], w[:, 1], w[:, 2]
        coef = np.stack([det(ua, ub, uc),
                         det(wa, ub, uc) + det(ua, wb, uc) + det(ua, ub, wc),
                         det(wa, wb, uc) + det(wa, ub, wc) + det(ua, wb, wc),
                         det(wa, wb, wc)], axis=1)
        # a cubic whose Bernstein coefficients on [0, 1] share one strict sign has no root
        # there (convex hull property): most candidate pairs never reach coplanarity
        c0, c1, c2, c3 = coef.T
        bern = np.stack([c0, c0 + c1 / 3, c0 + (2 * c1 + c2) / 3, c0 + c1 + c2 + c3], axis=1)
        may = (bern.min(axis=1) <= 0) & (bern.max(axis=1) >= 0)
        s, t, tri, coef, u = s[may], t[may], tri[may], coef[may], u[may]
        if len(s) == 0:
            return 1.0
        first = self._first_crossing(coef, x[s], dx[s], x[tri], dx[tri])
        alpha = min(1.0, (1 - keep) * float(first.min(initial=np.inf)))
        if alpha < 0.05 and log.isEnabledFor(logging.DEBUG):
            i = int(np.argmin(first))
            v = self.view
            log.debug(f"      contact cuts the update to {alpha:.3g}: node {s[i]} (tag "
                      f"{v.cell_tag[np.flatnonzero((v.cells == s[i]).any(axis=1))[0]]}, "
                      f"|dx| {np.linalg.norm(dx[s[i]]):.3g} mm) through triangle {t[i]} "
                      f"(tag {v.cell_tag[t[i]]}), distance {np.linalg.norm(u[i].mean(0)):.3g}")
        return alpha

    def _swept_candidates(self, x: np.ndarray, dx: np.ndarray, r_tri: np.ndarray,
                          classes: int = 6):
        """(node, triangle) pairs, slaves only, that the update ``dx`` could bring together,
        with their centroid distance ``dc``: a pair's distance closes by at most ``|dx_s| +
        m_T`` (``m_T`` the largest motion of a vertex of ``T``), so it needs ``dc <= 2
        max(|dx_s|, m_T) + r_T``. Nodes and triangles are grouped by their motion (halving
        classes), and each group searched with its own radius: a leaflet swinging shut moves
        everywhere, but pairs only within the reach of their own motion are candidates."""
        from scipy.spatial import cKDTree

        cells = self.view.cells
        motion = np.linalg.norm(dx, axis=1)
        m_node = motion[self.slaves]
        m_tri = motion[cells].max(axis=1)
        top = max(float(m_node.max(initial=0.0)), float(m_tri.max(initial=0.0)))
        if top == 0.0:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
        r_max = float(r_tri.max(initial=0.0))
        cent = x[cells].mean(axis=1)
        node_tree, cent_tree = cKDTree(x[self.slaves]), cKDTree(cent)
        found = []
        hi = top
        for k in range(classes):
            lo = 0.0 if k == classes - 1 else hi / 2
            radius = 2 * hi + r_max
            ns = np.flatnonzero((m_node > lo) & (m_node <= hi)) if k else \
                np.flatnonzero(m_node > lo)
            ts = np.flatnonzero((m_tri > lo) & (m_tri <= hi)) if k else np.flatnonzero(m_tri > lo)
            if len(ns):
                h = cKDTree(x[self.slaves[ns]]).sparse_distance_matrix(
                    cent_tree, radius, output_type="ndarray")
                found.append((ns[h["i"]], h["j"].astype(np.int64), h["v"]))
            if len(ts):
                h = node_tree.sparse_distance_matrix(cKDTree(cent[ts]), radius,
                                                     output_type="ndarray")
                found.append((h["i"].astype(np.int64), ts[h["j"]], h["v"]))
            hi = lo
            if hi == 0.0:
                break
        if not found:
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
        si = np.concatenate([f[0] for f in found])
        tj = np.concatenate([f[1] for f in found])
        dc = np.concatenate([f[2] for f in found])
        key, first = np.unique(si * len(cells) + tj, return_index=True)
        si, tj, dc = si[first], tj[first], dc[first]
        keep = dc - r_tri[tj] <= m_node[si] + m_tri[tj]
        return self.slaves[si[keep]], tj[keep], dc[keep]

    def _first_crossing(self, coef, p, dp, v, dv, samples: int = 16) -> np.ndarray:
        """Earliest t in [0, 1] where each moving node passes through its moving triangle
        (inf where it does not): sign changes of the coplanarity cubic on ``samples``
        sub-intervals, refined by bisection, kept where the node is then inside the
        triangle (with a margin of 1e-3 of the longest edge)."""
        m = len(coef)
        out = np.full(m, np.inf)

        def f(tt):
            return coef[:, 0] + tt * (coef[:, 1] + tt * (coef[:, 2] + tt * coef[:, 3]))

        grid = np.linspace(0.0, 1.0, samples + 1)
        vals = np.stack([f(np.full(m, g)) for g in grid], axis=1)   # (m, samples + 1)
        tol = 1e-3 * max(self._max_edge, 1e-12)
        todo = np.ones(m, dtype=bool)
        for i in range(samples):
            change = todo & (vals[:, i] * vals[:, i + 1] <= 0) & (vals[:, i] != 0)
            if not change.any():
                continue
            idx = np.flatnonzero(change)
            a = np.full(len(idx), grid[i])
            b = np.full(len(idx), grid[i + 1])
            fa = vals[idx, i]
            c = coef[idx]
            for _ in range(40):
                mid = 0.5 * (a + b)
                fm = c[:, 0] + mid * (c[:, 1] + mid * (c[:, 2] + mid * c[:, 3]))
                left = fa * fm <= 0
                b = np.where(left, mid, b)
                a = np.where(left, a, mid)
                fa = np.where(left, fa, fm)
            tc = a  # the crossing is at or just after a: stopping before it is safe
            pt = p[idx] + tc[:, None] * dp[idx]
            vt = v[idx] + tc[:, None, None] * dv[idx]
            dist, _, _ = closest_point_on_triangles(pt, vt[:, 0], vt[:, 1], vt[:, 2])
            hit = dist <= tol
            out[idx[hit]] = tc[hit]
            todo[idx[hit]] = False
        return out

    def __call__(self, x: np.ndarray) -> Blocks:
        s, t, xi, d = self.active_pairs(x)
        m = len(s)
        if m == 0:
            return Blocks(np.zeros((0, 4), dtype=np.int64), np.zeros((0, 4, 3)),
                          np.zeros((0, 12, 12)))
        tri = self.view.cells[t]
        diff = x[s] - np.einsum("ij,ijk->ik", xi, x[tri])
        nu = np.zeros_like(diff)
        ok = d > 1e-12
        nu[ok] = diff[ok] / d[ok, None]
        if not ok.all():  # on the triangle: its normal (either side pushes apart)
            nu[~ok] = _normals(x, tri[~ok])
        k = self.stiffness * self.view.area[s]
        phi, dphi, ddphi = barrier(d, self.thickness, k)
        coef = np.concatenate([np.ones((m, 1)), -xi], axis=1)
        dd = coef[:, :, None] * nu[:, None, :]          # (m, 4, 3): d(d)/dx
        force = dphi[:, None, None] * dd
        flat = dd.reshape(m, 12)
        # the full Hessian b'' dd dd^T + b' d2d: without the curvature of the distance
        # (Gauss-Newton) Newton converged linearly and the demo needed twice the iterations
        def stiffness() -> np.ndarray:
            y = np.concatenate([x[s][:, None, :], x[tri]], axis=1).reshape(m, 12)
            return ddphi[:, None, None] * flat[:, :, None] * flat[:, None, :] \
                + dphi[:, None, None] * distance_hessian(y)

        nodes = np.concatenate([s[:, None], tri], axis=1)
        return Blocks(nodes, force, stiffness, float(phi.sum()))
