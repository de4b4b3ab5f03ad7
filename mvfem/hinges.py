"""The hinge bending energy as a compiled point term (the fast path of :mod:`mvfem.forms.bending`).

The form :func:`mvfem.forms.bending.hinge_energy` integrated over the interior edges with one
quadrature point is, on a P1 mesh, a sum over the hinges (an interior edge and its two
triangles) of

.. math:: \\Pi_b = \\sum_e \\frac{D\\, l_e}{\\bar h_e}\\bigl(1 - \\cos(\\theta_e - \\theta_{0,e})\\bigr)

with ``l_e`` the reference length of the edge, ``h_e`` the mean of the two triangles'
reference diameters (their longest edges, as ``ufl.CellDiameter``) and ``theta`` the dihedral
angle. As a UFL form over interior facets it cost 14 of the 20-27 ms of one tangent assembly of
the demo valve (the second derivative of two normalised cross products on both sides of each
edge). Here the angle's gradient is closed-form (:func:`mvfem.kernels.hinge_energy`) and its
curvature is by central differences of that gradient, in C, per hinge of four nodes, on rank 0
with the chordae and the contact. ``tests/test_valve_terms.py`` checks energy, residual and
tangent against the UFL form; where the kernels cannot be compiled (or the space is P2) the
form is used.
"""

from __future__ import annotations

import numpy as np

from mvfem.nodal import Blocks, NodalView

__all__ = ["Hinges", "hinges_of"]


def hinges_of(cells: np.ndarray) -> np.ndarray:
    """(m, 4) hinges ``(c, d, a, b)`` of a triangle mesh: each edge ``a-b`` shared by exactly two
    triangles, ``c`` the third node of the first of them and ``d`` of the second (in the order
    of ``cells``), ``a < b``."""
    return _hinges_and_cells(cells)[0]


def _hinges_and_cells(cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`hinges_of` and (m, 2) the indices of each hinge's two triangles."""
    cells = np.asarray(cells, dtype=np.int64)
    if len(cells) == 0:
        return np.zeros((0, 4), dtype=np.int64), np.zeros((0, 2), dtype=np.int64)
    n = len(cells)
    pairs = [(0, 1, 2), (1, 2, 0), (2, 0, 1)]
    a = np.concatenate([cells[:, i] for i, _, _ in pairs])
    b = np.concatenate([cells[:, j] for _, j, _ in pairs])
    opp = np.concatenate([cells[:, k] for _, _, k in pairs])
    cell = np.tile(np.arange(n), 3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((cell, hi, lo))
    lo, hi, opp, cell = lo[order], hi[order], opp[order], cell[order]
    same = (lo[1:] == lo[:-1]) & (hi[1:] == hi[:-1])
    first = np.flatnonzero(same)
    # an edge of three or more triangles (non-manifold) has no hinge: the form's interior
    # facets need two cells too
    triple = np.zeros(len(first), dtype=bool)
    if len(first) > 1:
        run = np.r_[False, first[1:] == first[:-1] + 1]
        triple = run | np.r_[run[1:], False]
    first = first[~triple]
    hinges = np.stack([opp[first], opp[first + 1], lo[first], hi[first]], axis=1)
    return hinges, np.stack([cell[first], cell[first + 1]], axis=1)


def _cell_diameters(X: np.ndarray, cells: np.ndarray) -> np.ndarray:
    p = X[cells]
    lengths = np.linalg.norm(p[:, [1, 2, 0]] - p, axis=2)
    return lengths.max(axis=1)


class Hinges:
    """Hinge bending of the leaflets on the nodes of a :class:`NodalView` (callable: positions
    (N, 3) -> :class:`Blocks`, rank 0).

    Args:
        view: the nodal view (rank 0 holds the mesh).
        D: bending stiffness ``E_b h^3 / 12`` (Pa mm^3).
        rel: step of the central differences of the angle's gradient, relative to the edge.
    """

    def __init__(self, view: NodalView, D: float, rel: float = 1e-4):
        from mvfem import kernels

        self.view, self.D, self.rel = view, float(D), float(rel)
        self._kernels = kernels
        X, cells = view.X, view.cells
        self.nodes, two = _hinges_and_cells(cells)
        if len(self.nodes):
            # the mean of the diameters of each hinge's two triangles
            diam = _cell_diameters(X, cells)
            h = 0.5 * (diam[two[:, 0]] + diam[two[:, 1]])
            length = np.linalg.norm(X[self.nodes[:, 3]] - X[self.nodes[:, 2]], axis=1)
            self.k = self.D * length / h
            self.c0, self.s0 = kernels.hinge_cos_sin(X[self.nodes].reshape(-1, 12))
        else:
            self.k = self.c0 = self.s0 = np.zeros(0)
        self._csr = self._pattern()

    def _pattern(self):
        """The tangent's fixed CSR pattern over the free dofs (rows every dof, as the point
        terms' rows): (indptr, cols, where each of the hinges' 144 Hessian entries goes in it,
        number of entries)."""
        free = self.view.free
        N, H = len(free), len(self.nodes)
        # the node pairs the hinges couple (16 a hinge), once each; then their 3 x 3 blocks
        # of free dofs, whose keys are distinct: sorting those is the pattern (a unique of
        # the 144 dof keys of every hinge took 0.4 s on the demo refined twice)
        pairs = (self.nodes[:, :, None] * N + self.nodes[:, None, :]).ravel()
        upair, which = np.unique(pairs, return_inverse=True)
        p, q = upair // N, upair % N
        key = ((3 * p[:, None, None] + np.arange(3)[None, :, None]) * (3 * N)
               + 3 * q[:, None, None] + np.arange(3)[None, None, :])
        ok = (free[p][:, :, None] & free[q][:, None, :]).ravel()
        kept = key.ravel()[ok]
        order = np.argsort(kept)
        uniq = kept[order]
        pos = np.full(ok.size, -1, dtype=np.int64)
        pos[np.flatnonzero(ok)[order]] = np.arange(len(uniq))
        # each hinge's 144 entries, row-major over its 12 dofs (node a's i, node b's j)
        place = pos.reshape(-1, 3, 3)[which.reshape(H, 4, 4)]  # [h, a, b, i, j]
        place = place.transpose(0, 1, 3, 2, 4).reshape(H, 144)
        indptr = np.r_[0, np.cumsum(np.bincount(uniq // (3 * N), minlength=3 * N))]
        return indptr, uniq % (3 * N), place, len(uniq)

    def tangent_csr(self, y: np.ndarray):
        """(indptr, cols, vals) of the hinges' tangent at stacked coordinates ``y``: the
        Hessians summed into the fixed pattern, in C (bucketing the demo's 26 000 hinge blocks
        with the contact's took 6.7 ms a tangent, a bincount of the Hessians 1.5)."""
        indptr, cols, place, nnz = self._csr
        vals = self._kernels.hinge_hessian_add(y, self.c0, self.s0, self.k, place, nnz, self.rel)
        return indptr, cols, vals

    def __call__(self, x: np.ndarray) -> Blocks:
        if len(self.nodes) == 0:
            return Blocks(self.nodes, np.zeros((0, 4, 3)), np.zeros((0, 12, 12)), 0.0)
        y = x[self.nodes].reshape(-1, 12)
        E, g = self._kernels.hinge_energy(y, self.c0, self.s0, self.k)

        def stiffness():
            return self._kernels.hinge_hessian(y, self.c0, self.s0, self.k, self.rel)

        blk = Blocks(self.nodes, g.reshape(-1, 4, 3), stiffness, float(E.sum()))
        blk.csr = lambda: self.tangent_csr(y)
        return blk
