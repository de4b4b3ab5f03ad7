"""Grid sequencing: start a closure from the closed state of a coarser mesh (``solver.coarse_start``).

A fine valve closed from the open state spends most of its pseudo-time steps swinging the
leaflets shut at the pace the tangent allows (the 1 mm demo: 579-678 steps). The same scene
on a mesh twice as coarse closes in a fraction of the time; its closed state, moved onto the
fine mesh, leaves the fine solve the end game only. Three things make that start usable
(measured on the demo at 1 mm from 2 mm, README "Grid sequencing"):

- the transfer (:func:`transfer`): each fine reference node is projected onto the nearest
  coarse reference triangle and carried by that triangle's deformation, its offset from the
  triangle in the triangle's rotated frame; clamped dofs keep their Dirichlet values (zero,
  or a prescribed motion's, complete: nested levels of a repair).
  A state in which an edge crosses a triangle is tried again with every fine node on the
  deformed coarse surface itself (no offsets: nested levels then lie on the coarse closed
  surface, which does not cross, but where a new node projects just across a coarse edge),
  then scaled back toward the open state (0.9, 0.8, 0.7 x: a coarse closure that passed
  through itself at a fold, within the contact's exclusion, unfolds), and refused if it
  still crosses (the contact barrier is unsigned: such a start would stay crossed); the
  solve then starts from the open state;
- fine cells that straddle a crease of the coarse closed surface come out crushed (exponents
  of the Fung laws up to 400, a residual of 1e92, every pseudo-time step refused). The laws'
  exponent is continued linearly beyond :data:`START_CAP` instead of ``MAX_EXPONENT`` until
  every cell has relaxed below 0.9 of it (the continuation only differs beyond the cap, so
  the residual does not jump when the cap is raised);
- pseudo-time starts at :data:`START_WEIGHT` x the usual weight: the state is near
  equilibrium, and the usual first steps are wild.

Smoothing the transferred displacement (Jacobi sweeps) made the crushed cells worse (chords
across a fold shorten): not used.

Nested levels (``mesh.refine``, session 17) use the same transfer and start: the fine mesh is
the coarse one split 1-to-4, so the coarse nodes move exactly and each new node goes with the
coarse triangle it came from; where that state crosses, it is smoothed where it crosses
(:func:`unfold`, session 43) before it would be scaled back. The transferred state has no crushed cells, yet its residual
is still several times the load (8x on the demo refined once; the same with the new nodes on
the coarse flat triangles instead of the curved surface): the stress jumps between coarse
triangles are unbalanced at the new nodes. The fine solve still needs 120-180 pseudo-time
steps on the demo refined once and ~310 refined twice (README, "Nested levels").
"""

from __future__ import annotations

import numpy as np

__all__ = ["transfer", "transfer_nodes", "unfold", "START_CAP", "START_WEIGHT", "SCALES",
           "UNFOLD_SWEEPS", "CRUSHED_AREA", "crushed_cells"]

#: the Fung laws' exponent cap while a transferred state relaxes
START_CAP = 10.0
#: the first pseudo-time weight of a sequenced start, x the stabiliser scale
START_WEIGHT = 1e4
#: where the transferred state crosses, it is scaled back toward the open state by the first
#: of these that does not (:func:`transfer`); a state that needs more is refused
SCALES = (0.9, 0.8, 0.7)
#: on a nested level, where the transferred state crosses, the nodes near the crossing are
#: first smoothed in place (:func:`unfold`) by at most this many sweeps; only a state that
#: still crosses is scaled back (``SCALES``). Not for a start from another mesh
#: (``solver.coarse_start``): the 4 mm demo from a 6.5 mm closure (36 edges crossing)
#: unfolded in 2 sweeps took 1180 steps, against 196 from the open state, where its scaled
#: state is refused (README, "Nested levels")
UNFOLD_SWEEPS = 10
#: a transferred state with a cell squeezed below this fraction of its reference area is not
#: used (:func:`transfer`): the plane-stress laws' thickness stretch ``1 / J`` of a sliver
#: overflows the capped exponent. The P2 resection with the 36 mm ring at 3 mm refined twice:
#: its new nodes put on the coarse closed surface near the sutured cut made 5 slivers (areas
#: down to 4e-15 of their reference), the smoothing of its 4 crossing edges kept them, and
#: the finest level sat at 1e26-1e32 x the load for 1500 steps (exponent 1.6e31); the
#: smoothed state with the offsets, the next tried, has 0.054 at least (README "Nested
#: levels", session 51)
CRUSHED_AREA = 0.01


def transfer_nodes(Xc: np.ndarray, cells_c: np.ndarray, Uc: np.ndarray, Xf: np.ndarray,
                   candidates: int = 8, offsets: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Displacements (n, 3) of points ``Xf`` on the reference surface of a coarse triangle mesh
    (nodes ``Xc``, triangles ``cells_c``, nodal displacements ``Uc``), and each point's distance
    to that surface. A point goes to ``sum xi_i x_i`` on the closest of the ``candidates``
    triangles nearest by centroid (``xi`` its closest point's barycentric coordinates there),
    plus its offset from that closest point carried from the reference triangle's frame to the
    deformed one's (along the normal where the point projects inside the triangle). A rigid
    motion of the coarse mesh moves every point rigidly."""
    from scipy.spatial import cKDTree

    from mvfem.contact import closest_point_on_triangles

    a, b, c = (Xc[cells_c[:, i]] for i in range(3))
    _, cand = cKDTree((a + b + c) / 3).query(Xf, k=min(candidates, len(cells_c)))
    cand = cand.reshape(len(Xf), -1)
    best = np.full(len(Xf), np.inf)
    bary = np.zeros((len(Xf), 3))
    tri = np.zeros(len(Xf), dtype=np.int64)
    for j in range(cand.shape[1]):
        t = cand[:, j]
        d, xi, _ = closest_point_on_triangles(Xf, a[t], b[t], c[t])
        closer = d < best
        best[closer], bary[closer], tri[closer] = d[closer], xi[closer], t[closer]

    def frame(p, q, r):
        """(m, 3, 3) orthonormal frames: rows the unit edge p->q, the in-plane normal to it,
        the unit normal."""
        e1 = q - p
        e1 /= np.linalg.norm(e1, axis=1)[:, None]
        n = np.cross(q - p, r - p)
        n /= np.linalg.norm(n, axis=1)[:, None]
        return np.stack([e1, np.cross(n, e1), n], axis=1)

    x = Xc + Uc
    xa, xb, xc = (x[cells_c[tri, i]] for i in range(3))
    q0 = bary[:, :1] * a[tri] + bary[:, 1:2] * b[tri] + bary[:, 2:] * c[tri]
    q1 = bary[:, :1] * xa + bary[:, 1:2] * xb + bary[:, 2:] * xc
    # the offset from the closest point (along the normal inside the triangle, partly in its
    # plane beyond an edge) in the reference triangle's frame, carried by the deformed one's
    if not offsets:  # onto the deformed coarse surface itself
        return q1 - Xf, best
    local = np.einsum("mij,mj->mi", frame(a[tri], b[tri], c[tri]), Xf - q0)
    return q1 + np.einsum("mij,mi->mj", frame(xa, xb, xc), local) - Xf, best


def unfold(X: np.ndarray, cells: np.ndarray, free: np.ndarray, U: np.ndarray,
           near: np.ndarray, radius: float, crosses, sweeps: int = UNFOLD_SWEEPS):
    """Smooth a crossing out of the displaced mesh ``X + U`` where it crosses, leaving the rest.

    ``near``: the nodes of the crossing edges and triangles; every node within ``radius`` of
    them in the reference surface ``X`` moves toward the mean of its neighbours' positions
    (mesh edges of ``cells``) by the weight ``w = s(1 - d / radius)``, ``s`` the smoothstep
    ``3 t^2 - 2 t^3`` and ``d`` the distance to the nearest of ``near`` (1 on those nodes, 0
    from ``radius`` on); nodes with a fixed dof (``free`` (N, 3) False) stay. A sweep at a
    time (every moving node from the positions before the sweep), until ``crosses(U)`` (a
    count) is 0, at most ``sweeps`` times.

    Returns ``(U, sweeps)``: the displacement that no longer crosses (the nodes that did not
    move keep theirs bit for bit) and the sweeps it took, or ``(None, sweeps)`` when it still
    crosses. A fold that passes through itself within a coarse mesh's contact exclusion is a
    crease a cell or two wide: flattened there, the rest of the closed state is carried over
    as it is, where scaling the state back toward the open one (``SCALES``) distorts every
    cell that rotated while the valve closed (README, "Nested levels")."""
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    from mvfem.meshes.refine import cell_edges

    if len(near) == 0:  # nothing to smooth where nothing is said to cross
        return None, 0
    d, _ = cKDTree(X[near]).query(X)
    t = np.clip(1.0 - d / radius, 0.0, 1.0)
    w = t * t * (3.0 - 2.0 * t)
    move = (w > 0) & free.all(axis=1)
    e, _ = cell_edges(cells)  # each edge once, whatever the triangles sharing it
    n = len(X)
    A = sp.coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])),
                      shape=(n, n)).tocsr()
    deg = np.asarray(A.sum(axis=1)).ravel()
    x = X + U
    wm = w[move, None]
    out = U.copy()
    for k in range(1, sweeps + 1):
        mean = (A[move] @ x) / deg[move, None]
        x[move] = (1.0 - wm) * x[move] + wm * mean
        out[move] = x[move] - X[move]
        if not crosses(out):
            return out, k
    return None, sweeps


def crushed_cells(X: np.ndarray, cells: np.ndarray, U: np.ndarray,
                  below: float = CRUSHED_AREA) -> int:
    """How many triangles of the displaced mesh ``X + U`` have less than ``below`` x their
    reference area (slivers, flipped or not: the area is unsigned)."""
    def area(P):
        return np.linalg.norm(np.cross(P[cells[:, 1]] - P[cells[:, 0]],
                                       P[cells[:, 2]] - P[cells[:, 0]]), axis=1)
    return int(np.count_nonzero(area(X + U) < below * area(X)))


def transfer(coarse, fine, scales=SCALES, sweeps: int = 0, clamp: np.ndarray | None = None
             ) -> dict:
    """Set ``fine.u`` (a :class:`mvfem.model.Model`) to the closed state of ``coarse`` (a
    solved model of the same scene on another mesh), collective. Returns what happened:
    ``{"used": bool, "reason": str, "max_distance_mm": float, "offsets": bool, "scale":
    float}``; when not used, ``fine.u`` is left as it was (the open state).

    Where the moved state crosses with the offsets and without, the one without is smoothed
    where it crosses (:func:`unfold`, at most ``sweeps`` sweeps within the contact's
    exclusion of the crossing: ``unfolded`` the sweeps it took; nested levels), then the one
    with them, else scaled by the first of ``scales`` whose state does not cross (the one
    without the offsets first; ``scale``; ``crossings`` the moved state's count in every
    case). No state with a cell squeezed below ``CRUSHED_AREA`` of its reference area is used
    (:func:`crushed_cells`; ``crushed``: how many such cells the states passed over had at
    most). A coarse closure can pass through itself at a fold
    within the contact's exclusion (an edge through a triangle of the same leaflet with an
    end within 1 mm of it in the reference surface: not a contact pair there, so neither
    pushed apart nor counted); split, the fine edges' ends are beyond it, and the fine level
    sees the crossing. The demo at 16.5 kPa refined once: 2 edges; scaled back to 0.8 the
    middle level of the demo refined twice took 115 steps, smoothed in one sweep 85 (36-62
    where nothing crosses; README, "Nested levels").

    ``clamp`` (rank 0; (N, 3) displacements of the fine nodes, read at the fixed dofs only):
    the fine level's Dirichlet values where a prescribed motion has moved them (a ring: the
    coarse closure has its annulus on the ring, and the new annulus nodes go onto the ring's
    curve, not onto the chords between the coarse ones); zero without it."""
    comm = fine.comm
    cv, fv = coarse.view, fine.view
    if cv is None or fv is None:
        return {"used": False, "reason": "no nodal view (not a P1 valve)"}
    n_c = coarse.V.dofmap.index_map.size_local * 3
    Uc = cv.gather(coarse.u.x.array[:n_c])
    out = None
    Uf = None
    if comm.rank == 0:
        # with each node's offset from the coarse surface carried, else (where that state
        # crosses: offsets up to the sagitta of coarse facets, 0.3 mm on the 5 mm valve,
        # against leaflets ~0.15 mm apart in contact) on the deformed coarse surface
        def crossings(U):
            return fine.contact.intersections(fv.X + U)[1] if fine.contact is not None else 0

        worst = 0  # the most crushed cells of a state passed over

        def usable(U) -> bool:
            nonlocal worst
            n = crushed_cells(fv.X, fv.cells, U)
            worst = max(worst, n)
            return n == 0

        moved = []  # (offsets, state, its crossing edges), with the offsets first
        found = False
        for offsets in (True, False):
            Uf, dist = transfer_nodes(cv.X, cv.cells, Uc, fv.X, offsets=offsets)
            # the clamp: zero, or the prescribed motion's values
            Uf[~fv.free] = 0.0 if clamp is None else clamp[~fv.free]
            crossing = crossings(Uf)
            moved.append((offsets, Uf, crossing))
            found = not crossing and usable(Uf)
            if found:
                break
        out = {"used": found, "offsets": offsets, "scale": 1.0, "reason": "",
               "max_distance_mm": float(dist.max(initial=0.0))}
        # (the last moved state's count that crosses: the one without the offsets where both do)
        crossing = 0 if found else next((c for _, _, c in moved[::-1] if c), 0)
        if crossing:
            out["crossings"] = crossing
        tries = moved[::-1]  # (the one without the offsets first, as before session 51)
        if not out["used"] and sweeps > 0 and fine.contact is not None:
            for offsets, U, c in tries:
                if not c:
                    continue
                smooth, k = unfold(fv.X, fv.cells, fv.free, U, fine.contact.crossing_nodes(
                    fv.X + U), fine.contact.exclusion, crossings, sweeps)
                if smooth is not None and usable(smooth):
                    Uf = smooth
                    out.update(used=True, unfolded=k, offsets=offsets)
                    break
        if not out["used"]:
            for offsets, U, _ in tries:
                for scale in scales:
                    scaled = np.where(fv.free, scale * U, U)   # (the clamp's values kept)
                    if not crossings(scaled) and usable(scaled):
                        Uf = scaled
                        out.update(used=True, scale=float(scale), offsets=offsets)
                        break
                if out["used"]:
                    break
        if worst:
            out["crushed"] = worst
        if not out["used"]:
            least = f" (and scaled by {min(scales):g})" if len(scales) else ""
            why = (f"{crossing} edge(s) of the transferred state cross a triangle"
                   if crossing else "")
            if worst:
                why += (" and " if why else "") + (f"{worst} cell(s) squeezed below "
                                                   f"{CRUSHED_AREA:g} of their area")
            out["reason"] = (f"{why}, with the offsets from the coarse surface and "
                             f"without{least}")
    out = comm.bcast(out, root=0)
    if not out["used"]:
        return out
    # each rank's owned nodes are a contiguous range of the global numbering
    ranges = comm.gather((fv.offset, fv.n_owned), root=0)
    parts = [Uf[o:o + n].ravel() for o, n in ranges] if comm.rank == 0 else None
    mine = comm.scatter(parts, root=0)
    fine.u.x.array[: len(mine)] = mine
    fine.u.x.scatter_forward()
    return out
