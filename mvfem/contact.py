r"""Contact between leaflets and within a leaflet: barriers on the distances between the surfaces.

Energy, in the manner of IPC (Li et al. 2020): every free node ``s`` and every triangle ``T``
of the deformed surface, and every two edges, that were not neighbours in the open valve
(reference distance above ``exclusion``) and are now closer than the contact thickness
``delta`` form a pair, found with KD-trees. With ``d`` the (unsigned) distance from the node
to its closest point ``q = sum_i xi_i x_i`` on ``T``,

.. math:: \Pi = \sum_{(s, T)} A_s\, b(d) + \sum_{(e, f)} w_{ef}\, m(c_{ef})\, b(d_{ef}),\qquad
          \partial d/\partial x_s = \nu,\quad \partial d/\partial x_i = -\xi_i \nu,
          \quad \nu = (x_s - q)/d

with ``A_s`` the node's lumped area, ``b`` IPC's log barrier (:func:`barrier`, stiffness
``kappa`` in Pa/mm): C2 where a pair enters at ``d = delta`` and unbounded as ``d -> 0``, so
no finite load (a chord pulling a free edge, say) presses a node onto the other leaflet; and
for edges the segment distance ``d_ef``, weight ``w = kappa l_e l_f / 4`` and IPC's mollifier
``m`` of ``c = |e x f|^2``, which switches a pair off smoothly as the edges turn parallel
(:func:`edge_edge_energy`). Node-triangle pairs alone let an edge slide through another
between the nodes (the closed demo valve had 67 edges of one leaflet through the other, up
to 0.84 mm deep). The distance to a triangle is continuously differentiable away from it, so
the residual has no jumps: there is no "nearest triangle" to switch between and no side to
choose (a nearest-triangle penalty with sides did not get the valve past its first contact,
Newton cycling between pairings; a bounded quadratic penalty let chordae pull free-edge nodes
onto the other leaflet, where Newton stalled). The tangent is the exact Hessian, the
distances' curvature in closed form where the kernels are compiled, else by central
differences of their exact gradients (:func:`distance_hessian`, :func:`edge_edge_hessian`).

No crossing: the energy alone cannot stop an update from carrying a node through a triangle,
or an edge through an edge, in one jump. :meth:`Contact.step_limit` scales every update so
that nothing passes through anything admissible on the way (continuous collision detection,
vertex-face and edge-edge, every pair of edges); the pseudo-time steps and SNES's precheck apply
it, so no state has a leaflet passed through another, and :meth:`Contact.penetration`
measures it (edges crossing triangles) in the final state. A pair can cross only where its
coplanarity cubic changes sign; the cubic's critical points split the update into parts on
which it is monotone, so each root is found alone, however close to another (:func:`_first_root`;
sign changes on sixteen equal parts, until session 31, missed both roots of a node through a
triangle and back, and a first root that shared its part with two more). (A conservative
bound on the closing distance, as in IPC's additive CCD, throttled nodes sliding along the
other leaflet; a side remembered from the last accepted state reported false crossings.)

The search: Verlet lists. The admissible pairs closer than the thickness plus a skin are found
once (KD-trees, the exclusion tests) and kept while no node has moved half the skin since:
every pair closer than the thickness is then in them (:meth:`Contact._lists`), and the step
limit uses them too while they reach twice the update's largest motion (a pair closes by at
most that much); beyond that, it uses them for the pairs of nodes, triangles and edges that
move at most a quarter of their reach, and the swept search for the others. Where a few nodes
have moved further (a pseudo-time step's trial states), the lists are patched: the pairs of
those nodes, and of their triangles and edges, searched afresh (:meth:`Contact._patch`). The
lists keep each pair's distance where they were built, so a call skips the pairs that their
nodes' motion since cannot have brought within reach. A compiled distance over the lists picks
the few pairs that need the exact (numpy) distance, so the pairs, distances and closest points
are those of a full search at every call, bit for bit. On the 647 contact calls recorded from
the 2 mm demo, replayed: 40 -> 11 ms a call for the pairs and their energy, 33 -> 12 ms for a
step limit (110 list builds).
"""

from __future__ import annotations

import logging

import numpy as np

from mvfem.nodal import Blocks, NodalView

__all__ = ["Contact", "closest_point_on_triangles", "segment_distance", "barrier",
           "distance_gradient", "distance_hessian", "barrier_blocks", "project_psd"]

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


def _distance_gradient_np(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
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


def _distance_hessian_np(y: np.ndarray, rel: float = 1e-4) -> np.ndarray:
    """(m, 12, 12) Hessian of the node-triangle distance: central differences of its exact
    gradient (:func:`distance_gradient`) with steps ``rel`` x the distance, symmetrised."""
    m = len(y)
    d, _ = _distance_gradient_np(y)
    h = np.maximum(rel * d, 1e-12)
    H = np.empty((m, 12, 12))
    for j in range(12):
        e = np.zeros(12)
        e[j] = 1.0
        _, gp = _distance_gradient_np(y + h[:, None] * e)
        _, gm = _distance_gradient_np(y - h[:, None] * e)
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


def segment_closest(p0, p1, q0, q1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Distance and closest-point parameters ``(d, s, t)`` of segments ``[p0, p1]`` and
    ``[q0, q1]`` (row-wise, (m, 3) each): the clamped closest points ``p0 + s (p1 - p0)`` and
    ``q0 + t (q1 - q0)`` of the two lines (Ericson, Real-Time Collision Detection 5.1.9),
    degenerate (point) segments included."""
    d1, d2, r = p1 - p0, q1 - q0, p0 - q0
    a = np.einsum("ij,ij->i", d1, d1)
    e = np.einsum("ij,ij->i", d2, d2)
    b = np.einsum("ij,ij->i", d1, d2)
    c = np.einsum("ij,ij->i", d1, r)
    f = np.einsum("ij,ij->i", d2, r)
    eps = 1e-24
    pa, pe = a > eps, e > eps
    safe = lambda v: np.where(v != 0, v, 1.0)  # noqa: E731
    den = a * e - b * b
    s = np.where(pa & pe & (den > 1e-12 * a * e), (b * f - c * e) / safe(den), 0.0)
    s = np.where(pa & ~pe, -c / safe(a), s)
    s = np.clip(s, 0.0, 1.0)
    t = np.where(pe, (b * s + f) / safe(e), 0.0)
    t_c = np.clip(t, 0.0, 1.0)
    s = np.where(pa & (t != t_c), np.clip((t_c * b - c) / safe(a), 0.0, 1.0), s)
    d = np.linalg.norm(p0 + s[:, None] * d1 - (q0 + t_c[:, None] * d2), axis=1)
    return d, s, t_c


def segment_distance(p0, p1, q0, q1) -> np.ndarray:
    """Distances between segments ``[p0, p1]`` and ``[q0, q1]`` (see :func:`segment_closest`)."""
    return segment_closest(p0, p1, q0, q1)[0]


def _edge_edge_energy_np(y: np.ndarray, weight, eps_x, delta: float) -> tuple[np.ndarray, ...]:
    r"""Mollified barrier of edge pairs and its gradient, for stacked ``y`` = (a0, a1, b0, b1)
    coordinates (m, 12):

    .. math:: E = w\, m(c)\, b(d),\qquad c = |(a_1 - a_0) \times (b_1 - b_0)|^2,\quad
              m(c) = (2 - c/\epsilon_x)\, c/\epsilon_x \ (c < \epsilon_x),\ 1 \text{ else}

    with ``d`` the segment distance and ``b`` :func:`barrier` with unit stiffness (IPC's
    edge-edge term: the mollifier ``m`` switches the pair off smoothly where the edges turn
    parallel, where the closest points jump; parallel edges are held apart by the
    node-triangle pairs). By the envelope theorem ``dd/da0 = (1 - s) nu``, ``dd/da1 = s nu``,
    ``dd/db0 = -(1 - t) nu``, ``dd/db1 = -t nu``. Returns (E, dE/dy (m, 12), d)."""
    m = len(y)
    a0, a1, b0, b1 = (y[:, 3 * i:3 * i + 3] for i in range(4))
    d, s_, t_ = segment_closest(a0, a1, b0, b1)
    ca, cb = a0 + s_[:, None] * (a1 - a0), b0 + t_[:, None] * (b1 - b0)
    nu = (ca - cb) / np.maximum(d, 1e-300)[:, None]
    gd = np.concatenate([(1 - s_)[:, None] * nu, s_[:, None] * nu,
                         -(1 - t_)[:, None] * nu, -t_[:, None] * nu], axis=1)
    ea, eb = a1 - a0, b1 - b0
    n = np.cross(ea, eb)
    c = np.einsum("ij,ij->i", n, n)
    dc_a, dc_b = 2 * np.cross(eb, n), 2 * np.cross(n, ea)
    gc = np.concatenate([-dc_a, dc_a, -dc_b, dc_b], axis=1)
    r = c / eps_x
    small = r < 1
    moll = np.where(small, (2 - r) * r, 1.0)
    dmoll = np.where(small, 2 * (1 - r) / eps_x, 0.0)
    b, db, _ = barrier(d, delta, 1.0)
    b = np.where(d < delta, b, 0.0)
    E = weight * moll * b
    grad = (weight * dmoll * b)[:, None] * gc + (weight * moll * db)[:, None] * gd
    return E, grad.reshape(m, 12), d


def _edge_edge_hessian_np(y, weight, eps_x, delta: float, rel: float = 1e-4) -> np.ndarray:
    """(m, 12, 12) Hessian of :func:`edge_edge_energy`: central differences of its exact
    gradient with steps ``rel`` x the distance, symmetrised."""
    m = len(y)
    d = _edge_edge_energy_np(y, weight, eps_x, delta)[2]
    h = np.maximum(rel * d, 1e-12)
    H = np.empty((m, 12, 12))
    for j in range(12):
        e = np.zeros(12)
        e[j] = 1.0
        gp = _edge_edge_energy_np(y + h[:, None] * e, weight, eps_x, delta)[1]
        gm = _edge_edge_energy_np(y - h[:, None] * e, weight, eps_x, delta)[1]
        H[:, :, j] = (gp - gm) / (2 * h[:, None])
    return 0.5 * (H + H.transpose(0, 2, 1))


def distance_gradient(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance from node to triangle and its gradient (m, 12) for stacked ``y`` = (node,
    vertex a, b, c) coordinates (m, 12): by the envelope theorem, ``d d/d x_s = nu`` and
    ``d d / d x_i = -xi_i nu`` with ``nu`` the unit vector from the closest point. Compiled
    (:mod:`mvfem.kernels`) where a C compiler is available, else numpy."""
    from mvfem import kernels

    if kernels.load() is None or len(y) == 0:
        return _distance_gradient_np(y)
    return kernels.point_triangle_gradient(y)


def _into(out: np.ndarray | None, H: np.ndarray) -> np.ndarray:
    """``H``, copied into ``out`` when that is given."""
    if out is None:
        return H
    out[...] = H
    return out


def distance_hessian(y: np.ndarray, rel: float = 1e-4, out: np.ndarray | None = None
                     ) -> np.ndarray:
    """(m, 12, 12) Hessian of the node-triangle distance: exact where the kernels are
    compiled (:mod:`mvfem.kernels`), else central differences of its exact gradient with
    steps ``rel`` x the distance, symmetrised; written into ``out`` (C-contiguous) when
    given."""
    from mvfem import kernels

    if len(y) == 0:
        return np.zeros((0, 12, 12)) if out is None else out
    if kernels.load() is None:
        return _into(out, _distance_hessian_np(y, rel))
    return kernels.point_triangle_hessian(y, out=out)


def barrier_blocks(y: np.ndarray, dphi: np.ndarray, ddphi: np.ndarray, dd: np.ndarray,
                   out: np.ndarray) -> np.ndarray:
    """(m, 12, 12) node-triangle barrier blocks ``dphi d2d + ddphi dd dd^T`` (``dd`` (m, 12)
    the distances' gradients) into ``out``: compiled in one pass, else the same operations in
    numpy over :func:`distance_hessian`."""
    from mvfem import kernels

    if len(y) and kernels.load() is not None:
        return kernels.point_triangle_stiffness(y, dphi, ddphi, dd, out=out)
    nt = distance_hessian(y, out=out)
    nt *= dphi[:, None, None]
    nt += ddphi[:, None, None] * dd[:, :, None] * dd[:, None, :]
    return nt


def edge_edge_energy(y: np.ndarray, weight, eps_x, delta: float) -> tuple[np.ndarray, ...]:
    """(E, dE/dy (m, 12), d) of the mollified edge-edge barrier (see
    :func:`_edge_edge_energy_np` for the formula; compiled or numpy)."""
    from mvfem import kernels

    if kernels.load() is None or len(y) == 0:
        return _edge_edge_energy_np(y, weight, eps_x, delta)
    return kernels.edge_edge_energy(y, weight, eps_x, delta)


def edge_edge_hessian(y, weight, eps_x, delta: float, rel: float = 1e-4,
                      out: np.ndarray | None = None) -> np.ndarray:
    """(m, 12, 12) Hessian of :func:`edge_edge_energy`: exact where the kernels are compiled
    (:mod:`mvfem.kernels`), else central differences of its exact gradient with steps
    ``rel`` x the distance, symmetrised; written into ``out`` (C-contiguous) when given."""
    from mvfem import kernels

    if len(y) == 0:   # (the numpy version's 24 passes over nothing cost 12 ms)
        return np.zeros((0, 12, 12)) if out is None else out
    if kernels.load() is None:
        return _into(out, _edge_edge_hessian_np(y, weight, eps_x, delta, rel))
    return kernels.edge_edge_hessian(y, weight, eps_x, delta, out=out)


def _fast_triangle_distance(x: np.ndarray, cells: np.ndarray, s: np.ndarray,
                            t: np.ndarray, bary: bool = False):
    """Distances of the nodes ``x[s]`` to the triangles ``cells[t]``, with ``bary`` also the
    closest points' barycentric coordinates: compiled (:mod:`mvfem.kernels`) where a C
    compiler is available, else numpy (:func:`closest_point_on_triangles`). The candidates'
    prefilter and the pairs' values alike, so the same whatever the search."""
    from mvfem import kernels

    if kernels.load() is None or len(s) == 0:
        tri = cells[t]
        d, xi, _ = closest_point_on_triangles(x[s], x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]])
        return (d, xi) if bary else d
    return kernels.point_triangle_distance(x, cells, s, t, bary=bary)


def _fast_segment_distance(x: np.ndarray, edges: np.ndarray, i: np.ndarray,
                           j: np.ndarray) -> np.ndarray:
    """Distances of the segments ``edges[i]`` and ``edges[j]``: compiled or numpy (the
    candidates' prefilter, and the pairs' distances)."""
    from mvfem import kernels

    if kernels.load() is None or len(i) == 0:
        a, b = edges[i], edges[j]
        return segment_distance(x[a[:, 0]], x[a[:, 1]], x[b[:, 0]], x[b[:, 1]])
    return kernels.segment_distance(x, edges, i, j)


def _swept_pairs(P, mP, rP, Q, mQ, rQ, classes: int = 6, symmetric: bool = False):
    """Index pairs (i, j), with the distance of ``P_i`` and ``Q_j``, of moving balls that may
    meet: centre distance <= ``rP_i + rQ_j + mP_i + mQ_j`` (radii ``r``, motions ``m``); in
    no particular order. The pairs need ``d <= 2 max(mP_i, mQ_j) + rP_i + rQ_j``: points and
    balls are grouped by their motion (halving classes) and each group searched with its own
    radius, so that a structure moving everywhere still only pairs what is within the reach
    of its own motion.

    Each pair is searched once, from the side that moves faster: the points of a class
    against the other side's points of that class or slower, and the other side's points of
    a class against this side's strictly slower ones (or still). Searching each class
    against everything found most pairs twice, and sorting out the copies (``np.unique`` of
    millions of keys) took half of a call on the demo refined twice. ``symmetric``: ``P`` and
    ``Q`` are the same points, and each unordered pair comes once, as ``i < j``.
    """
    from scipy.spatial import cKDTree

    empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
    top = max(float(mP.max(initial=0.0)), float(mQ.max(initial=0.0)))
    if top == 0.0 or len(P) == 0 or len(Q) == 0:
        return empty
    r_pair = float(rP.max(initial=0.0)) + float(rQ.max(initial=0.0))

    def search(A, a, B, b, radius):
        """Pairs of the points ``A[a]`` and ``B[b]`` within ``radius`` (indices into A, B)."""
        if len(a) == 0 or len(b) == 0:
            return None
        h = cKDTree(A[a]).sparse_distance_matrix(cKDTree(B[b]), radius, output_type="ndarray")
        return a[h["i"]], b[h["j"]], h["v"]

    found = []
    cls = np.full(len(P), classes)  # each point's class (symmetric: also Q's), still: last
    hi = top
    for k in range(classes):
        lo = 0.0 if k == classes - 1 else hi / 2
        radius = 2 * hi + r_pair
        ps = np.flatnonzero((mP > lo) & ((mP <= hi) | (k == 0)))
        cls[ps] = k
        # this class's points of P against Q's points as slow or slower (on the first
        # class, hi = top: every point of Q)
        found.append(search(P, ps, Q, np.flatnonzero(mQ <= hi), radius))
        if not symmetric:
            # Q's points of this class against P's strictly slower points (or still ones)
            qs = np.flatnonzero((mQ > lo) & ((mQ <= hi) | (k == 0)))
            found.append(search(P, np.flatnonzero(mP <= lo), Q, qs, radius))
        hi = lo
        if hi == 0.0:
            break
    found = [f for f in found if f is not None]
    if not found:
        return empty
    i = np.concatenate([f[0] for f in found])
    j = np.concatenate([f[1] for f in found])
    d = np.concatenate([f[2] for f in found])
    if symmetric:
        # a pair within a class is found both ways, a pair across classes once (from its
        # faster point): keep one of each, as (smaller, larger)
        once = (cls[j] > cls[i]) | (i < j)
        i, j, d = np.minimum(i, j)[once], np.maximum(i, j)[once], d[once]
    keep = d <= rP[i] + rQ[j] + mP[i] + mQ[j]
    return i[keep], j[keep], d[keep]


def _boxes_overlap(a, da, b, db, pad: float) -> np.ndarray:
    """Whether the boxes swept by the point sets ``a`` (m, k, 3) and ``b`` (m, l, 3) moving by
    ``da``, ``db`` overlap (with margin ``pad``)."""
    lo_a = np.minimum(a.min(axis=1), (a + da).min(axis=1))
    hi_a = np.maximum(a.max(axis=1), (a + da).max(axis=1))
    lo_b = np.minimum(b.min(axis=1), (b + db).min(axis=1)) - pad
    hi_b = np.maximum(b.max(axis=1), (b + db).max(axis=1)) + pad
    return np.all((hi_a >= lo_b) & (lo_a <= hi_b), axis=1)


def _coplanarity_cubic(u: np.ndarray, w: np.ndarray) -> np.ndarray:
    """(m, 4) coefficients (constant first) of ``det[u_0 + t w_0, u_1 + t w_1, u_2 + t w_2]``
    for (m, 3, 3) vectors ``u`` and their rates ``w``."""
    def det(a, b, c):
        return np.einsum("ij,ij->i", a, np.cross(b, c))

    ua, ub, uc = u[:, 0], u[:, 1], u[:, 2]
    wa, wb, wc = w[:, 0], w[:, 1], w[:, 2]
    return np.stack([det(ua, ub, uc),
                     det(wa, ub, uc) + det(ua, wb, uc) + det(ua, ub, wc),
                     det(wa, wb, uc) + det(wa, ub, wc) + det(ua, wb, wc),
                     det(wa, wb, wc)], axis=1)


def _may_vanish(coef: np.ndarray) -> np.ndarray:
    """False where the cubic surely has no root in [0, 1]: its Bernstein coefficients there
    share one strict sign (convex hull property)."""
    c0, c1, c2, c3 = coef.T
    bern = np.stack([c0, c0 + c1 / 3, c0 + (2 * c1 + c2) / 3, c0 + c1 + c2 + c3], axis=1)
    return (bern.min(axis=1) <= 0) & (bern.max(axis=1) >= 0)


def _first_root(coef: np.ndarray, touching) -> np.ndarray:
    """Earliest t in [0, 1] per cubic where it changes sign and ``touching(idx, t)`` holds
    (inf where never). The cubic's critical points split [0, 1] into at most three parts on
    each of which it is monotone, so a part holds a root only where the cubic changes sign
    over it, and then one only: every root is found, however close to another (a node through
    a triangle and back within one update included), by bisection from the left (the t
    returned is at or just before the root: stopping there is safe). Each round bisects
    every cubic's next part with a sign change at once."""
    m = len(coef)
    out = np.full(m, np.inf)
    c = coef

    def f(tt, cc=c):
        return cc[:, 0] + tt * (cc[:, 1] + tt * (cc[:, 2] + tt * cc[:, 3]))

    # critical points: the roots of 3 c3 t^2 + 2 c2 t + c1 (the stable quadratic formula;
    # a linear or constant derivative where c3 or both c3 and c2 vanish)
    A, B, C = 3.0 * c[:, 3], 2.0 * c[:, 2], c[:, 1]
    disc = B * B - 4.0 * A * C
    q = -0.5 * (B + np.copysign(np.sqrt(np.maximum(disc, 0.0)), B))
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(A != 0, q / A, np.nan)
        r2 = np.where(q != 0, C / q, np.nan)
    real = disc >= 0
    crit = np.stack([np.where(real, r1, np.nan), np.where(real, r2, np.nan)], axis=1)
    crit = np.where((crit > 0) & (crit < 1), crit, 1.0)          # (outside: an empty part)
    crit.sort(axis=1)
    ends = np.concatenate([np.zeros((m, 1)), crit, np.ones((m, 1))], axis=1)   # (m, 4)
    vals = np.stack([f(ends[:, i]) for i in range(4)], axis=1)
    change = (vals[:, :-1] * vals[:, 1:] <= 0) & (vals[:, :-1] != 0)          # (m, 3)
    rows = np.flatnonzero(change.any(axis=1))
    start = np.zeros(m, dtype=np.int64)          # parts before it have been tried
    while len(rows):
        later = change[rows] & (np.arange(3) >= start[rows, None])
        has = later.any(axis=1)
        rows = rows[has]
        if not len(rows):
            break
        k = later[has].argmax(axis=1)            # the next part with a sign change
        a, b = ends[rows, k], ends[rows, k + 1]
        fa = vals[rows, k]
        cr = c[rows]
        for _ in range(50):
            mid = 0.5 * (a + b)
            fm = f(mid, cr)
            left = fa * fm <= 0
            b = np.where(left, mid, b)
            a = np.where(left, a, mid)
            fa = np.where(left, fa, fm)
        hit = touching(rows, a)
        out[rows[hit]] = a[hit]
        start[rows] = k + 1
        rows = rows[~hit]
    return out


def project_psd(K: np.ndarray) -> np.ndarray:
    """Each symmetric block of ``K`` (m, n, n) replaced, in place, by its positive
    semidefinite part: the eigenvalues below zero set to zero (IPC's projected Newton).

    The barrier's exact Hessian ``b'' dd dd^T + b' d2d`` is indefinite: ``b' < 0`` and the
    distance's curvature ``d2d`` couples the node with the triangle's rotation. On the demo
    valve refined twice every one of its 165 000 blocks had a negative eigenvalue, the most
    negative (-7.8e5) of the order of the largest positive one (1.9e6): pseudo-time's
    ``k M`` does not outweigh that, and Newton's update can climb the potential.

    Compiled (:func:`mvfem.kernels.psd_project`: each block's eigenproblem in C, a contact
    block's in the 9 coordinates relative to its first node, since a translation leaves the
    distance unchanged; on the kernels' threads), 4-5x faster than numpy's batched ``eigh``
    (LAPACK; 0.15-0.17 s against 0.71-0.75 s for 117,000 blocks on 2 threads,
    ``scripts/psd_projection.py``), which is the fallback: long stacks split over the
    kernels' threads (``eigh`` releases the GIL), with OpenBLAS on one thread
    (:func:`mvfem.kernels.one_blas_thread`).
    The same blocks either way, to roundoff. A point whose rows and columns are zero (a node
    that the pair's closest points leave out) keeps them zero, exactly: the projection's
    roundoff would otherwise couple it in the matrix's pattern."""
    from mvfem import kernels

    n = K.shape[-1]
    if kernels.load() is not None and K.ndim == 3 and n % 3 == 0 and 3 <= n <= 12 \
            and K.dtype == np.float64 and K.flags.c_contiguous:
        fail = kernels.psd_project(K)
        if fail.any():
            with kernels.one_blas_thread():
                K[fail] = _project_psd(K[fail])
        return K
    return project_psd_numpy(K)


def project_psd_numpy(K: np.ndarray) -> np.ndarray:
    """:func:`project_psd` by numpy's batched ``eigh``, long stacks split over the kernels'
    threads."""
    from mvfem import kernels

    n = kernels.threads() if len(K) > 4096 else 1
    with kernels.one_blas_thread():  # (OpenBLAS's own threads only slow 12 x 12 blocks)
        if n > 1:
            from concurrent.futures import ThreadPoolExecutor

            cuts = np.linspace(0, len(K), n + 1).astype(int)
            with ThreadPoolExecutor(n) as pool:
                list(pool.map(lambda ab: _project_psd(K[ab[0]:ab[1]]),
                              zip(cuts[:-1], cuts[1:])))
            return K
        return _project_psd(K)


def _project_psd(K: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(K)
    neg = w[:, 0] < 0
    if neg.any():
        Kn = K[neg]
        Vn = V[neg]
        P = (Vn * np.maximum(w[neg], 0.0)[:, None, :]) @ np.swapaxes(Vn, 1, 2)
        # a point whose rows (and columns) are zero stays out, exactly (as the kernel's)
        m, n = Kn.shape[0], Kn.shape[1]
        out = (Kn.reshape(m, n // 3, 3 * n) == 0).all(axis=2).repeat(3, axis=1)
        P[out[:, :, None] | out[:, None, :]] = 0.0
        K[neg] = P
    return K


def _normals(x, tri):
    n = np.cross(x[tri[:, 1]] - x[tri[:, 0]], x[tri[:, 2]] - x[tri[:, 0]])
    return n / np.linalg.norm(n, axis=1)[:, None]


def _merge_sorted(a, b, da, c, d, dc, n: int):
    """The pairs ``(a, b)`` and ``(c, d)``, each sorted by ``a n + b`` and none in both, as one
    list so sorted, with their values ``da`` and ``dc``."""
    if len(c) == 0:
        return a, b, da
    at = np.searchsorted(a * n + b, c * n + d)
    return np.insert(a, at, c), np.insert(b, at, d), np.insert(da, at, dc)


class _Lists:
    """Verlet lists: every admissible node-triangle pair ``(s, t)`` and edge pair ``(i, j)``
    closer than the thickness plus the skin at the positions ``x`` they were built at, and
    their distances there (``d_nt``, ``d_ee``; lower bounds of them in patched lists)."""

    __slots__ = ("x", "s", "t", "i", "j", "d_nt", "d_ee")

    def __init__(self, x, s, t, i, j, d_nt, d_ee):
        self.x, self.s, self.t, self.i, self.j = x, s, t, i, j
        self.d_nt, self.d_ee = d_nt, d_ee

    def drift(self, x: np.ndarray) -> np.ndarray:
        """Each node's distance from its position ``self.x`` to ``x``."""
        return np.sqrt(np.einsum("ij,ij->i", x - self.x, x - self.x))


class Contact:
    """Barrier contact over a whole surface, node-triangle and edge-edge (rank 0 finds the
    pairs).

    Args:
        view: the global node view.
        thickness: contact thickness ``delta``, mm (surfaces are kept this far apart).
        stiffness: barrier stiffness ``kappa``, Pa/mm (contact pressure ``kappa delta`` at
            about half the thickness).
        exclusion: node and triangle (edge and edge) closer than this in the open (reference)
            surface never pair: they are neighbours on one sheet, mm (default the larger of
            twice the thickness and 1.5 shortest edges, so that a flat sheet's own nodes never
            feel the barrier). Small on purpose: the curtain folds at the commissures and
            creases where it is compressed, and those folds touch themselves; with 6 mm the
            closed demo valve had 83 edges through its own folds.
        skin: Verlet skin of the candidate lists, mm (default twice the thickness: on the
            demo's recorded calls 0.5, 1, 1.5 and 2 mm gave 7.3, 6.9, 7.3 and 7.9 s of contact
            search and step limits, 171 to 64 list builds; the thickness itself on meshes
            whose median edge is shorter than the thickness, where the candidates per node
            grow as ((thickness + skin) / h)^2: on the demo refined twice, 0.5 mm against 1 mm
            filtered 0.34 + 1.06 against 1.1 + 3.2 million candidates a call, and took 243.5
            against 270.0 s of contact in 9 list builds against 4, the same 290 fine steps):
            the admissible pairs closer than ``thickness + skin`` are searched once and
            reused until the nodes have moved half the skin, patched where only a few have
            (see :meth:`_lists`); 0 searches
            in full at every call. The pairs found are the same either way.
    """

    def __init__(self, view: NodalView, thickness: float, stiffness: float,
                 exclusion: float | None = None, skin: float | None = None):
        self.view = view
        self.thickness = float(thickness)
        self.stiffness = float(stiffness)
        #: stiffness blocks projected onto their positive semidefinite part (IPC's projected
        #: Newton; :func:`project_psd`): set by the solver for one tangent where the exact one
        #: gave an update that does not descend (:class:`mvfem.solver.PseudoTransient`)
        self.convex = False
        self._verlet: list[_Lists] = []
        #: how often the candidate lists were built (a full search each)
        self.list_builds = 0
        #: lists kept, the latest first: a refused trial state sends the solve back to
        #: where it was (131 -> 110 builds on the demo's calls with two)
        self.keep_lists = 2
        #: (x, lists, reach, node-triangle and edge distances over the lists) of the last
        #: filter
        self._memo: tuple | None = None
        #: kept lists are patched at a state (:meth:`_patch`), not rebuilt, while at most
        #: this fraction of the nodes have left them
        self.patch_fraction = 0.05
        #: how often lists were patched
        self.list_patches = 0
        #: (x, reach, lists) of the last patch
        self._patched: tuple | None = None
        min_edge, median_edge = 0.0, np.inf
        if view.comm.rank == 0:
            self.slaves = np.flatnonzero(view.free.any(axis=1))
            edges = np.concatenate([view.cells[:, [0, 1]], view.cells[:, [1, 2]],
                                    view.cells[:, [2, 0]]])
            lengths = np.linalg.norm(view.X[edges[:, 0]] - view.X[edges[:, 1]], axis=1)
            self._max_edge = float(lengths.max(initial=0.0))
            min_edge = float(lengths.min(initial=0.0))
            median_edge = float(np.median(lengths)) if len(lengths) else np.inf
        else:
            self.slaves = np.zeros(0, dtype=np.int64)
            self._max_edge = 0.0
        # only rank 0 searches, so the defaults need not agree across ranks
        self.exclusion = float(exclusion if exclusion is not None
                               else max(2 * self.thickness, 1.5 * min_edge))
        self.skin = float(skin if skin is not None else self.thickness
                          if median_edge < self.thickness else 2 * self.thickness)
        self._excluded = self._excluded_pairs() if view.comm.rank == 0 else None
        #: crossing tests' tolerance: 1e-3 of the longest edge
        self._tol = 1e-3 * max(self._max_edge, 1e-12)
        if view.comm.rank == 0 and len(view.cells):
            from mvfem.meshes.refine import cell_edges

            self._edges, of_cell = cell_edges(view.cells)
            of_cell = of_cell.ravel()  # each cell side's edge (cells' first sides, then ...)
            self._edge_mid_ref = 0.5 * (view.X[self._edges[:, 0]] + view.X[self._edges[:, 1]])
            self._edge_len_ref = np.linalg.norm(view.X[self._edges[:, 1]]
                                                - view.X[self._edges[:, 0]], axis=1)
            #: each edge's label (that of a cell it bounds) and whether it bounds one cell
            self._edge_label = np.zeros(len(self._edges), dtype=np.int64)
            self._edge_label[of_cell] = np.tile(np.asarray(view.cell_tag, dtype=np.int64), 3)
            self._edge_boundary = np.bincount(of_cell, minlength=len(self._edges)) == 1
        else:
            self._edges = np.zeros((0, 2), dtype=np.int64)
            self._edge_mid_ref = np.zeros((0, 3))
            self._edge_len_ref = np.zeros(0)
            self._edge_label = np.zeros(0, dtype=np.int64)
            self._edge_boundary = np.zeros(0, dtype=bool)
        self._excluded_edges = self._excluded_edge_pairs()
        #: slack of the lists' validity tests against roundoff in the distances, mm
        self._margin = 1e-9 * max(self._max_edge, 1.0)
        #: whether the energy has edge pairs between two interior edges of different labels
        #: (leaflets). Not where the median edge is no longer than the thickness: there the
        #: node-triangle pairs alone keep two facing leaflets apart between the nodes, and
        #: those edge pairs, half of the closed valve's contact, bend the potential down along
        #: the updates (their curvature outweighed the membrane's along every update that
        #: climbed on the demo refined twice; without them its finest level took 34-47
        #: steps instead of 93-149 at 15.5-17 kPa, README "Edge pairs between facing
        #: leaflets"). On coarser meshes they are what keeps the leaflets apart between the
        #: nodes (without them the 4 mm valves of the hard cases passed through each other).
        #: Pairs within a label and pairs with a boundary edge (free edge, annulus) stay; the
        #: step limit checks every pair of edges whatever this says.
        self.facing_edge_pairs = bool(median_edge > self.thickness)

    def _excluded_edge_pairs(self) -> np.ndarray:
        """Sorted keys ``i * n_edges + j``, ``i < j``, of the edge pairs that never interact:
        a shared vertex, or midpoints within ``exclusion`` in the reference surface. Either
        puts the midpoints within the longest edge or the exclusion of each other; where the
        exclusion is the longer (the default on meshes finer than twice the thickness), the
        shared vertices need no test of their own. The demo refined three times: 19.3 million
        keys in 2.8 s, where a test of every pair's vertices and a ``np.unique`` of the keys
        took 8.2 s (session 58)."""
        from scipy.spatial import cKDTree

        e, mid = self._edges, self._edge_mid_ref
        if len(e) < 2:
            return np.zeros(0, dtype=np.int64)
        longest = float(self._edge_len_ref.max())
        reach = max(self.exclusion, longest)
        pairs = cKDTree(mid).query_pairs(reach * (1 + 1e-6), output_type="ndarray")
        i, j = pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)  # (i < j, each once)
        del pairs
        gap = mid[i] - mid[j]
        near = ~(np.sqrt(np.einsum("ij,ij->i", gap, gap)) > self.exclusion)
        del gap
        if self.exclusion < longest:
            a, b = e[i], e[j]
            near |= ((a[:, 0] == b[:, 0]) | (a[:, 0] == b[:, 1]) | (a[:, 1] == b[:, 0])
                     | (a[:, 1] == b[:, 1]))
        keys = i[near] * len(e) + j[near]
        keys.sort()
        return keys

    def _excluded_pairs(self) -> np.ndarray:
        """Sorted keys ``s * n_cells + t`` of the (node, triangle) pairs that never interact:
        a vertex of ``t`` within ``exclusion`` of ``s`` in the reference surface. The pairs
        are the nonzeros of (slave near node) x (node in cell), a sparse product that merges
        the triangles met through two or three of their vertices (the demo refined three
        times: 10 million keys in 0.9 s, against 3.7 s expanding every (node, cell of a near
        node) and ``np.unique``, session 58)."""
        import scipy.sparse as sp
        from scipy.spatial import cKDTree

        X, cells = self.view.X, self.view.cells
        if len(self.slaves) == 0 or len(cells) == 0:
            return np.zeros(0, dtype=np.int64)
        near = cKDTree(X[self.slaves]).sparse_distance_matrix(
            cKDTree(X), self.exclusion, output_type="ndarray")
        n = len(X)
        near_nodes = sp.csr_matrix((np.ones(len(near), dtype=np.int8),
                                    (self.slaves[near["i"]], near["j"])), shape=(n, n))
        del near
        in_cell = sp.csr_matrix((np.ones(cells.size, dtype=np.int8),
                                 (cells.ravel(), np.repeat(np.arange(len(cells)), 3))),
                                shape=(n, len(cells)))
        pairs = (near_nodes @ in_cell).tocsr()  # (entries 1 to 3: no int8 overflow)
        pairs.sort_indices()
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(pairs.indptr))
        return rows * len(cells) + pairs.indices

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
        a, b, tri, dp, dq = self._crossings(x)
        if len(a) == 0:
            return 0.0, 0
        return float(np.minimum(np.abs(dp), np.abs(dq)).max()), int(len(a))

    def crossing_nodes(self, x: np.ndarray) -> np.ndarray:
        """Sorted indices of the nodes of every edge that crosses an admissible triangle at
        ``x`` and of those triangles (:meth:`intersections`)."""
        a, b, tri, _, _ = self._crossings(x)
        return np.unique(np.concatenate([a, b, tri.ravel()]))

    def _crossings(self, x: np.ndarray):
        """The crossing edges' ends ``a``, ``b`` (m,), the triangles they cross (m, 3), and
        the ends' signed distances to those triangles' planes (:meth:`intersections`)."""
        from scipy.spatial import cKDTree

        cells, e = self.view.cells, self._edges
        none = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros((0, 3), dtype=np.int64),) + \
            (np.zeros(0),) * 2
        if len(self.slaves) == 0 or len(cells) == 0:
            return none
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
            return none
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
        return a[found], b[found], tri[found], dp[found], dq[found]

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
        closest points, distances; sorted by node, then triangle."""
        within = self.thickness if within is None else float(within)
        cells = self.view.cells
        empty = (np.zeros(0, dtype=np.int64),) * 2 + (np.zeros((0, 3)), np.zeros(0))
        if len(self.slaves) == 0 or len(cells) == 0:
            return empty
        # another reach than the thickness is a report's (metrics.coapting_nodes: 1.5 x):
        # kept lists if they hold it as they are, else a search of the node-triangle pairs
        # alone, not lists patched or rebuilt with the edge pairs for one call (0.13 against
        # 0.77 s on the closed demo refined twice)
        lists = self._lists(x, within, build=within == self.thickness)
        if lists is None:
            s, t, _ = self._triangle_candidates(x, within)
        else:
            near = self._list_distances(x, lists, within)[0] < within + self._margin
            s, t = lists.s[near], lists.t[near]
        # the distances and closest points of the few left, computed alike whatever the
        # search: the same values
        dist, bary = _fast_triangle_distance(x, cells, s, t, bary=True)
        near = dist < within
        return s[near], t[near], bary[near], dist[near]

    def _triangle_candidates(self, x: np.ndarray, radius: float):
        """Full search: the admissible (node, triangle) pairs closer than ``radius`` at ``x``
        (and any within roundoff of it), sorted by node, then triangle."""
        r_tri = _tri_radius(x, self.view.cells)
        s, t, dc = self._near(x, radius + float(r_tri.max(initial=0.0)))
        return self._close_triangles(x, s, t, dc, r_tri, radius)

    def _close_triangles(self, x, s, t, dc, r_tri, radius):
        """Of the candidate (node, triangle) pairs ``(s, t)``, their centroid distances
        ``dc``, the admissible ones closer than ``radius`` at ``x`` (and any within roundoff
        of it), sorted by node, then triangle, and their (compiled) distances."""
        cells = self.view.cells
        keep = dc <= radius + r_tri[t]
        s, t = s[keep], t[keep]
        d = _fast_triangle_distance(x, cells, s, t)
        keep = d < radius + self._margin
        s, t, d = s[keep], t[keep], d[keep]
        order = np.argsort(s * len(cells) + t)
        s, t, d = s[order], t[order], d[order]
        keep = self._admissible(s, t)
        return s[keep], t[keep], d[keep]

    def _admissible_edges(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Edge pairs with no shared vertex whose midpoints are further apart than
        ``exclusion`` in the reference surface (a look-up in the keys of those that are not:
        a fifth of the time of testing the pairs)."""
        keys = np.minimum(i, j) * len(self._edges) + np.maximum(i, j)
        ex = self._excluded_edges
        if len(ex) == 0:
            return i != j
        pos = np.searchsorted(ex, keys)
        pos[pos == len(ex)] = 0
        return (ex[pos] != keys) & (i != j)

    def edge_pairs(self, x: np.ndarray, within: float | None = None):
        """Admissible edge pairs ``(i, j)``, ``i < j``, closer than ``within`` (default the
        thickness) at ``x``, and their distances; sorted by ``i``, then ``j``. The
        node-triangle pairs alone let an edge slide through another between the nodes (67
        edges of one leaflet through the other on the closed demo valve, up to 0.84 mm
        deep). Without :attr:`facing_edge_pairs` (meshes finer than the thickness), not the
        pairs of two interior edges of different labels."""
        within = self.thickness if within is None else float(within)
        e = self._edges
        empty = (np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0))
        if len(e) == 0:
            return empty
        lists = self._lists(x, within)
        if lists is None:
            i, j, d = self._edge_candidates(x, within)
        else:   # (the distances at x, from the routine the full search uses)
            d = self._list_distances(x, lists, within)[1]
            near = d < within + self._margin
            i, j, d = lists.i[near], lists.j[near], d[near]
        near = d < within
        if not self.facing_edge_pairs:
            lab, bnd = self._edge_label, self._edge_boundary
            near &= (lab[i] == lab[j]) | bnd[i] | bnd[j]
        return i[near], j[near], d[near]

    def _edge_candidates(self, x: np.ndarray, radius: float):
        """Full search: the admissible edge pairs ``(i, j)``, ``i < j``, closer than
        ``radius`` at ``x`` (and any within roundoff of it), sorted by ``i``, then ``j``."""
        from scipy.spatial import cKDTree

        e = self._edges
        mid = 0.5 * (x[e[:, 0]] + x[e[:, 1]])
        half = 0.5 * np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
        pairs = cKDTree(mid).query_pairs(radius + 2 * float(half.max()), output_type="ndarray")
        return self._close_edges(x, pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64),
                                 radius)

    def _close_edges(self, x, i, j, radius):
        """Of the candidate edge pairs ``(i, j)``, ``i < j``, the admissible ones closer than
        ``radius`` at ``x`` (and any within roundoff of it), sorted by ``i``, then ``j``, and
        their (compiled) distances."""
        e = self._edges
        d = _fast_segment_distance(x, e, i, j)
        keep = d < radius + self._margin
        i, j, d = i[keep], j[keep], d[keep]
        order = np.argsort(i * len(e) + j)
        i, j, d = i[order], j[order], d[order]
        keep = self._admissible_edges(i, j)
        return i[keep], j[keep], d[keep]

    def _lists(self, x: np.ndarray, reach: float, build: bool = True) -> _Lists | None:
        """Verlet lists holding every admissible pair that may be closer than ``reach`` at
        ``x``: the kept lists themselves while they are valid, else kept lists patched at
        ``x`` (:meth:`_patch`) where few nodes have left them, else lists rebuilt at ``x`` (a
        full search); None when ``reach`` is beyond them, or with ``build`` False when no
        kept lists are valid as they are (the caller searches in full).

        A node moving by at most ``D_s`` and a triangle whose vertices move by at most
        ``D_t`` (every point of it then moves by at most ``D_t``) change their distance by at
        most ``D_s + D_t``, and so do two edges. Lists built at radius ``R`` thus still hold
        every pair now closer than ``reach`` whose nodes have all moved less than ``h = (R -
        reach) / 2`` since (less a slack for the roundoff of the compiled distances that
        picked them): with no node beyond ``h`` the lists are valid as they are. The
        admissibility tests (exclusion in the reference surface) run on the searches only.
        """
        radius = self.thickness + self.skin
        if self.skin <= 0 or reach + self._margin >= radius:
            return None
        h = 0.5 * (radius - reach - self._margin)
        patch = self._patched
        if patch is not None and patch[1] >= reach and np.array_equal(patch[0], x):
            return patch[2]
        best, fewest = None, np.inf
        for lists in self._verlet:
            D = lists.drift(x)
            moved = D >= h
            if not moved.any():
                return lists
            n = int(np.count_nonzero(moved))
            if n < fewest:
                best, fewest = (lists, moved, D), n
        if not build:
            return None
        if best is not None and fewest <= self.patch_fraction * len(x):
            lists = self._patch(x, reach, *best)
            self._patched = (x.copy(), reach, lists)
            self.list_patches += 1
            return lists
        s, t, d_nt = self._triangle_candidates(x, radius)
        i, j, d_ee = self._edge_candidates(x, radius)
        self._verlet = [_Lists(x.copy(), s, t, i, j, d_nt, d_ee)] \
            + self._verlet[:self.keep_lists - 1]
        self.list_builds += 1
        return self._verlet[0]

    def _patch(self, x: np.ndarray, reach: float, lists: _Lists, moved: np.ndarray,
               D: np.ndarray) -> _Lists:
        """``lists`` made valid at ``x`` for ``reach``: the pairs of its nodes, triangles and
        edges none of whose nodes has ``moved`` (by half the lists' radius less ``reach``,
        :meth:`_lists`; ``D`` the nodes' motion since the lists' positions) are kept, and
        those of the others searched afresh at ``x`` within ``reach``; sorted as a full
        search's. A pseudo-time step's trial states move a few
        nodes far (on the demo refined twice, 1 % of them more than 0.05 mm, the farthest
        0.25-1.1 mm): patching their pairs (KD-trees of the moved against all) takes a few
        per cent of a build. The patched lists keep the positions ``lists.x`` and the
        distances there of the pairs kept; the new pairs' distances at ``x`` are put there
        as lower bounds (plus their nodes' motion since), which is what the filter of
        :meth:`_list_distances` needs."""
        from scipy.spatial import cKDTree

        cells, e = self.view.cells, self._edges
        moved_tri = moved[cells].any(axis=1)
        moved_edge = moved[e].any(axis=1)
        keep = ~(moved[lists.s] | moved_tri[lists.t])
        s, t, d_nt = lists.s[keep], lists.t[keep], lists.d_nt[keep]
        keep = ~(moved_edge[lists.i] | moved_edge[lists.j])
        i, j, d_ee = lists.i[keep], lists.j[keep], lists.d_ee[keep]
        # node-triangle pairs with a moved node, or a still node and a moved triangle
        r_tri = _tri_radius(x, cells)
        cent = x[cells].mean(axis=1)
        rad = reach + float(r_tri.max(initial=0.0))
        mover = moved[self.slaves]
        found = []
        for nodes, tris in ((self.slaves[mover], np.arange(len(cells))),
                            (self.slaves[~mover], np.flatnonzero(moved_tri))):
            if len(nodes) and len(tris):
                hit = cKDTree(x[nodes]).sparse_distance_matrix(cKDTree(cent[tris]), rad,
                                                               output_type="ndarray")
                found.append((nodes[hit["i"]], tris[hit["j"]], hit["v"]))
        if found:
            ps, pt, pd = self._close_triangles(x, *(np.concatenate(f) for f in zip(*found)),
                                               r_tri, reach)
            pd += D[ps] + D[cells[pt]].max(axis=1, initial=0.0)
            s, t, d_nt = _merge_sorted(s, t, d_nt, ps, pt, pd, len(cells))
        # edge pairs with a moved edge (two moved edges: once, as i < j)
        me = np.flatnonzero(moved_edge)
        if len(me):
            mid = 0.5 * (x[e[:, 0]] + x[e[:, 1]])
            half = 0.5 * np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
            hit = cKDTree(mid[me]).sparse_distance_matrix(
                cKDTree(mid), reach + 2 * float(half.max()), output_type="ndarray")
            a, b = me[hit["i"]], hit["j"].astype(np.int64)
            once = (a != b) & (~moved_edge[b] | (a < b))
            a, b = a[once], b[once]
            pi, pj, pd = self._close_edges(x, np.minimum(a, b), np.maximum(a, b), reach)
            pd += D[e[pi]].max(axis=1, initial=0.0) + D[e[pj]].max(axis=1, initial=0.0)
            i, j, d_ee = _merge_sorted(i, j, d_ee, pi, pj, pd, len(e))
        return _Lists(lists.x, s, t, i, j, d_nt, d_ee)

    def _list_distances(self, x: np.ndarray, lists: _Lists,
                        reach: float) -> tuple[np.ndarray, np.ndarray]:
        """The compiled distances at ``x`` of the pairs in ``lists`` that may be closer than
        ``reach``; inf for the others. A pair's distance at the lists' positions, less its
        nodes' motion since, bounds it from below: where that bound is ``reach`` or more (plus
        a slack for roundoff) the distance is not computed. Most nodes move little between
        builds, so most pairs are skipped: the finest level of the twice-refined demo
        filtered in 1.8 s instead of 4.8 s, with the same pairs. The result is kept for the
        next call at the same ``x``, and completed if that call reaches further: a
        pseudo-time step evaluates the contact at its trial state and, once the state is
        accepted, limits the next update from it."""
        from mvfem import kernels

        memo = self._memo
        same = memo is not None and memo[1] is lists and np.array_equal(memo[0], x)
        if same and memo[2] >= reach:
            return memo[3], memo[4]
        if kernels.load() is None:   # numpy: every distance
            d_nt = _fast_triangle_distance(x, self.view.cells, lists.s, lists.t)
            d_ee = _fast_segment_distance(x, self._edges, lists.i, lists.j)
            self._memo = (x.copy(), lists, np.inf, d_nt, d_ee)
            return d_nt, d_ee
        if same:   # the pairs skipped before that may be closer than this reach
            d_nt, d_ee = memo[3], memo[4]
        else:
            d_nt, d_ee = np.full(len(lists.s), np.inf), np.full(len(lists.i), np.inf)
        D = lists.drift(x)
        cut = reach + 2 * self._margin
        kernels.point_triangle_distance_cut(x, self.view.cells, lists.s, lists.t, lists.d_nt,
                                            D, cut, out=d_nt)
        kernels.segment_distance_cut(x, self._edges, lists.i, lists.j, lists.d_ee, D, cut,
                                     out=d_ee)
        self._memo = (x.copy(), lists, reach, d_nt, d_ee)
        return d_nt, d_ee

    def _edge_energy_args(self, x, i, j):
        e = self._edges
        y = x[np.concatenate([e[i], e[j]], axis=1)].reshape(len(i), 12)   # (one gather)
        la, lb = self._edge_len_ref[i], self._edge_len_ref[j]
        return y, 0.25 * self.stiffness * la * lb, 1e-3 * la**2 * lb**2

    def _admissible(self, s: np.ndarray, t: np.ndarray) -> np.ndarray:
        """Node and triangle further apart than ``exclusion`` in the reference surface."""
        keys = s.astype(np.int64) * len(self.view.cells) + t
        pos = np.searchsorted(self._excluded, keys)
        pos[pos == len(self._excluded)] = 0
        return self._excluded[pos] != keys if len(self._excluded) else np.ones(len(s), bool)

    def step_limit(self, x: np.ndarray, dx: np.ndarray, keep: float = 0.2) -> float:
        """Largest fraction ``alpha`` <= 1 of the update ``dx`` along which no node passes
        through an admissible triangle and no edge through an admissible edge (continuous
        collision detection, vertex-face and edge-edge).

        Along ``x + t dx`` a node meets the plane of a triangle where the cubic
        ``det[a - p, b - p, c - p](t)`` changes sign, and it passes through the triangle when
        its closest point there is inside; two edges cross where ``det[p1 - p0, q0 - p0,
        q1 - p0](t)`` changes sign with the segments then touching. The update is cut to
        ``(1 - keep)`` of the first such ``t``. Both checks are needed: with vertex-face alone
        the closed demo valve had 67 edges of one leaflet through the other, up to 0.84 mm
        deep (an edge slid through another between the nodes). The pseudo-time steps (and
        SNES's precheck) scale every update by it, so no state has a leaflet passed through
        another, however large the update.
        """
        if len(self.slaves) == 0 or not np.any(dx):
            return 1.0
        return min(1.0, (1 - keep) * self._first_crossing(x, dx))

    def squeeze_limit(self, x: np.ndarray, dx: np.ndarray, alpha: float, keep: float = 0.5,
                      halvings: int = 12) -> float:
        """The largest ``alpha 2^-k`` (``k <= halvings``, else 0) at which no pair of the
        barrier (node-triangle or edge-edge, within the thickness there) is closer than
        ``keep`` x its distance at ``x``, or x the thickness for a pair coming into it.

        For a move the potential does not judge: the prescribed motion's harmonic lifting
        of the interior (:class:`mvfem.run._AdaptiveRamp`). Bounded by the collision check
        alone (``step_limit``, 0.8 of the way to the first crossing), each lifting brought
        the closest pair 5-fold closer; on the dilated valve with a 36 mm ring, two facing
        edges came to 2e-10 mm over 20 calls, their barrier force to 1e13 and no update was
        admissible (README, "Repairs"). A Newton step from a lifted state restores such a
        gap about twofold (the log barrier's ``b' / b''``), so halving it is the most a
        lifting may do."""
        if len(self.slaves) == 0 or alpha <= 0.0 or not np.any(dx):
            return alpha
        for _ in range(halvings + 1):
            if self._squeezed_at_most(x, x + alpha * dx, keep):
                return alpha
            alpha *= 0.5
        return 0.0

    def _squeezed_at_most(self, x0: np.ndarray, x1: np.ndarray, keep: float) -> bool:
        """Whether every barrier pair within the thickness at ``x1`` is at least ``keep`` x
        min(its distance at ``x0``, thickness) apart."""
        s, t, _, d1 = self.active_pairs(x1)
        if len(s):
            d0 = _fast_triangle_distance(x0, self.view.cells, s, t)
            if np.any(d1 < keep * np.minimum(d0, self.thickness)):
                return False
        i, j, e1 = self.edge_pairs(x1)
        if len(i):
            e0 = _fast_segment_distance(x0, self._edges, i, j)
            if np.any(e1 < keep * np.minimum(e0, self.thickness)):
                return False
        return True

    def _first_crossing(self, x: np.ndarray, dx: np.ndarray) -> float:
        """The first crossing of a node and a triangle or of two edges along ``dx`` (a
        fraction of it in [0, 1]; inf for none)."""
        # a pair that touches (within the crossing tolerance) along the update closes by at
        # most twice the largest motion: the lists hold all such pairs when they reach that
        # far, else the swept search finds them (the large early updates), or only those
        # with a fast node, triangle or edge where the lists serve the slow ones (on the
        # twice-refined demo's finest level 6.1 -> 2.9 s of step limits, its 10 searches of
        # everything at 0.29 s each gone)
        motion = np.linalg.norm(dx, axis=1)
        reach = 2 * float(motion.max()) + self._tol
        lists = self._lists(x, reach)
        slow = None
        if lists is None and self.skin > 0:
            # a few nodes moving far (a pseudo-time step's large updates): the lists for the
            # pairs of nodes, triangles and edges that move at most a quarter of the lists'
            # reach, the swept search for the others
            slow = 0.25 * (self.thickness + self.skin - self._tol)
            reach = 2 * slow + self._tol
            lists = self._lists(x, reach)
            if lists is None:
                slow = None
        return min(self._vertex_face_first(x, dx, motion, lists, reach, slow),
                   self._edge_edge_first(x, dx, motion, lists, reach, slow))

    def _vertex_face_first(self, x: np.ndarray, dx: np.ndarray, motion: np.ndarray | None = None,
                           lists: _Lists | None = None, reach: float | None = None,
                           slow: float | None = None) -> float:
        """The first crossing of a node and a triangle along ``dx`` (fraction of it, inf for
        none); the candidates from the swept search, or from ``lists`` (valid for ``reach``),
        or with ``slow``, from the lists for the pairs of a node and a triangle both moving
        at most ``slow`` (``reach`` then ``2 slow`` plus the tolerance) and the swept search
        for the pairs with a faster one."""
        cells = self.view.cells
        motion = np.linalg.norm(dx, axis=1) if motion is None else motion
        reach = 2 * float(motion.max()) + self._tol if reach is None else reach
        r_tri = _tri_radius(x, cells)
        cent = x[cells].mean(axis=1)
        m_tri = motion[cells].max(axis=1)
        if lists is None:
            si, t, dc = _swept_pairs(x[self.slaves], motion[self.slaves],
                                     np.zeros(len(self.slaves)), cent, m_tri, r_tri)
            s = self.slaves[si]
            d_fast = _fast_triangle_distance(x, cells, s, t)
        else:
            s, t = lists.s, lists.t
            d_fast = self._list_distances(x, lists, reach)[0]
            dc = None
        if slow is not None:
            fast_node, fast_tri = motion > slow, m_tri > slow
            keep = ~(fast_node[s] | fast_tri[t])
            s, t, d_fast = s[keep], t[keep], d_fast[keep]
            mover = fast_node[self.slaves]
            found = [(s, t)]
            for nodes, tris in ((self.slaves[mover], np.arange(len(cells))),
                                (self.slaves[~mover], np.flatnonzero(fast_tri))):
                if len(nodes) and len(tris):
                    i, j, _ = _swept_pairs(x[nodes], motion[nodes], np.zeros(len(nodes)),
                                           cent[tris], m_tri[tris], r_tri[tris])
                    ok = self._admissible(nodes[i], tris[j])
                    found.append((nodes[i][ok], tris[j][ok]))
            n = len(s)
            s, t = (np.concatenate(f) for f in zip(*found))
            d_fast = np.concatenate([d_fast, _fast_triangle_distance(x, cells, s[n:], t[n:])])
        # a node that comes within the crossing tolerance of a triangle along the update was
        # no further than that plus their motions (on the demo's step limits from the lists
        # at most 2.3 % of the candidates pass, mostly none)
        near = d_fast <= self._tol + motion[s] + m_tri[t] + self._margin
        s, t = s[near], t[near]
        dc = np.linalg.norm(x[s] - cent[t], axis=1) if dc is None else dc[near]
        tri = cells[t]
        w = dx[tri] - dx[s][:, None, :]                    # relative motion of the vertices
        # the pair's distance is at least dc - r_tri and closes by at most max |w|
        can = (dc - r_tri[t] <= np.linalg.norm(w, axis=2).max(axis=1))
        # the node's path and the triangle's swept box must overlap (margin: the crossing
        # test's tolerance); boxed only where the distance allows a crossing: the same
        # pairs, but the boxes of every candidate took 3.9 of 12.7 s of step limits on the
        # demo's long updates of a trial (README "Tried in session 36"), 1.8 s so; on the
        # twice-refined demo's usual path 0.20 against 0.14 s
        c = np.flatnonzero(can)
        can[c] = _boxes_overlap(x[s[c]][:, None], dx[s[c]][:, None], x[tri[c]], dx[tri[c]],
                                self._tol)
        if lists is None:   # (the lists hold admissible pairs only, as do the mixed ones)
            can[can] = self._admissible(s[can], t[can])
        s, t, tri, w = s[can], t[can], tri[can], w[can]
        if len(s) == 0:
            return np.inf
        u = x[tri] - x[s][:, None, :]                      # (m, 3, 3) vertices - node
        coef = _coplanarity_cubic(u, w)
        may = _may_vanish(coef)
        s, tri, coef = s[may], tri[may], coef[may]
        if len(s) == 0:
            return np.inf
        p, dp, v, dv = x[s], dx[s], x[tri], dx[tri]

        def touching(idx, tc):
            pt = p[idx] + tc[:, None] * dp[idx]
            vt = v[idx] + tc[:, None, None] * dv[idx]
            return closest_point_on_triangles(pt, vt[:, 0], vt[:, 1], vt[:, 2])[0] <= self._tol

        return float(_first_root(coef, touching).min(initial=np.inf))

    def _edge_edge_first(self, x: np.ndarray, dx: np.ndarray, motion: np.ndarray | None = None,
                         lists: _Lists | None = None, reach: float | None = None,
                         slow: float | None = None) -> float:
        """The first crossing of two edges along ``dx``, as :meth:`_vertex_face_first` (an
        edge moves as its faster node)."""
        e = self._edges
        motion = np.linalg.norm(dx, axis=1) if motion is None else motion
        reach = 2 * float(motion.max()) + self._tol if reach is None else reach
        if len(e) == 0:
            return np.inf
        mid = 0.5 * (x[e[:, 0]] + x[e[:, 1]])
        half = 0.5 * np.linalg.norm(x[e[:, 1]] - x[e[:, 0]], axis=1)
        # every pair of edges: the barrier alone does not keep two interior edges apart on
        # coarse meshes (with free edges only against any edge, the prolapsing 4 mm valve
        # ended with an interior edge 0.36-1.32 mm through the other leaflet, or none,
        # depending on roundoff in the path; at 15 kPa 0.84 mm; with all pairs none of four
        # pressures, README "Hard cases")
        m_e = motion[e].max(axis=1)
        if lists is None:
            ia, ib, dc = _swept_pairs(mid, m_e, half, mid, m_e, half, symmetric=True)
            d_fast = _fast_segment_distance(x, e, ia, ib)
        else:
            ia, ib = lists.i, lists.j
            d_fast = self._list_distances(x, lists, reach)[1]
            dc = None
        if slow is not None:
            fast = m_e > slow
            keep = ~(fast[ia] | fast[ib])
            ia, ib, d_fast = ia[keep], ib[keep], d_fast[keep]
            fe, se = np.flatnonzero(fast), np.flatnonzero(~fast)
            found = [(ia, ib)]
            # the fast edges among themselves (once, i < j) and against the slow ones
            i, j, _ = _swept_pairs(mid[fe], m_e[fe], half[fe], mid[fe], m_e[fe], half[fe],
                                   symmetric=True)
            found.append((fe[i], fe[j]))
            if len(se):
                i, j, _ = _swept_pairs(mid[fe], m_e[fe], half[fe], mid[se], m_e[se], half[se])
                found.append((np.minimum(fe[i], se[j]), np.maximum(fe[i], se[j])))
            n = len(ia)
            ia, ib = (np.concatenate(f) for f in zip(*found))
            ok = self._admissible_edges(ia[n:], ib[n:])
            ia = np.concatenate([ia[:n], ia[n:][ok]])
            ib = np.concatenate([ib[:n], ib[n:][ok]])
            d_fast = np.concatenate([d_fast, _fast_segment_distance(x, e, ia[n:], ib[n:])])
        # as for vertex-face: two edges that come within the tolerance were no further apart
        # than that plus their motions
        near = d_fast <= self._tol + m_e[ia] + m_e[ib] + self._margin
        ia, ib = ia[near], ib[near]
        dc = np.linalg.norm(mid[ia] - mid[ib], axis=1) if dc is None else dc[near]
        a, b = e[ia], e[ib]
        # the segments' distance is at least dc - both half lengths and closes by at most the
        # largest relative motion of two of their points, <= max_j |dx_bj - dx_a0| +
        # |dx_a1 - dx_a0|
        closing = np.linalg.norm(dx[b] - dx[a][:, :1], axis=2).max(axis=1) \
            + np.linalg.norm(dx[a[:, 1]] - dx[a[:, 0]], axis=1)
        can = dc - half[ia] - half[ib] <= closing
        c = np.flatnonzero(can)   # (as for vertex-face: boxed only where this allows it)
        can[c] = _boxes_overlap(x[a[c]], dx[a[c]], x[b[c]], dx[b[c]], self._tol)
        if lists is None:
            can[can] = self._admissible_edges(ia[can], ib[can])
        a, b = a[can], b[can]
        if len(a) == 0:
            return np.inf
        p0, dp0 = x[a[:, 0]], dx[a[:, 0]]
        u = np.stack([x[a[:, 1]] - p0, x[b[:, 0]] - p0, x[b[:, 1]] - p0], axis=1)
        w = np.stack([dx[a[:, 1]] - dp0, dx[b[:, 0]] - dp0, dx[b[:, 1]] - dp0], axis=1)
        coef = _coplanarity_cubic(u, w)
        may = _may_vanish(coef)
        a, b, coef = a[may], b[may], coef[may]
        if len(a) == 0:
            return np.inf

        def touching(idx, tc):
            at = x[a[idx]] + tc[:, None, None] * dx[a[idx]]
            bt = x[b[idx]] + tc[:, None, None] * dx[b[idx]]
            return segment_distance(at[:, 0], at[:, 1], bt[:, 0], bt[:, 1]) <= self._tol

        return float(_first_root(coef, touching).min(initial=np.inf))

    def __call__(self, x: np.ndarray) -> Blocks:
        s, t, xi, d = self.active_pairs(x)
        ei, ej, _ = self.edge_pairs(x)
        m, me = len(s), len(ei)
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
        y_ee, w_ee, eps_ee = self._edge_energy_args(x, ei, ej)
        E_ee, g_ee, _ = edge_edge_energy(y_ee, w_ee, eps_ee, self.thickness)

        # the full Hessian b'' dd dd^T + b' d2d: without the curvature of the distance
        # (Gauss-Newton) Newton converged linearly and the demo needed twice the iterations
        # (written in place: at 0.5 mm, 146 000 pairs, the concatenated copies took 50 ms)
        def stiffness() -> np.ndarray:
            K = np.empty((m + me, 12, 12))
            y = np.concatenate([x[s][:, None, :], x[tri]], axis=1).reshape(m, 12)
            barrier_blocks(y, dphi, ddphi, flat, out=K[:m])
            edge_edge_hessian(y_ee, w_ee, eps_ee, self.thickness, out=K[m:])
            if self.convex:
                project_psd(K)
            return K

        nodes = np.concatenate([np.concatenate([s[:, None], tri], axis=1),
                                np.concatenate([self._edges[ei], self._edges[ej]], axis=1)])
        forces = np.concatenate([force, g_ee.reshape(me, 4, 3)])
        blocks = Blocks(nodes.astype(np.int64), forces, stiffness, float(phi.sum() + E_ee.sum()))
        blocks.project = project_psd  # (what `convex` does to the exact blocks)
        return blocks
