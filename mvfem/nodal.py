"""Point terms of the energy: chordae tethers and contact pairs, assembled beside the UFL forms.

A chord pulls one node toward a fixed papillary point; a contact pair couples a node with the
three nodes of a triangle on the other side of a gap. Neither is an integral over the mesh, so
they are not UFL forms: each term is a small numpy function of the current nodal positions that
returns element blocks (node indices, forces, stiffness), and :class:`PointTerms` adds them to
the residual vector and the tangent matrix that SNES assembles from the forms.

Everything here happens on rank 0, which holds all P1 nodes in the global numbering (the
owned blocks of every rank, in rank order): a valve has a few thousand nodes, and the pair
search and the tethers cost milliseconds. Rows and columns of Dirichlet dofs are dropped
(PETSc ignores negative indices), so the terms never disturb the boundary conditions. Under
mpirun the other ranks sleep meanwhile (:func:`idle_wait`) and lend rank 0 their cores
(:func:`lend_cores`), and rank 0 sends each rank its own rows of the forces and the tangent.
"""

from __future__ import annotations

import time
import numpy as np
from petsc4py import PETSc

__all__ = ["Blocks", "NodalView", "PointTerms", "add_csr", "csr_rows", "smooth_penalty",
           "lumped_area", "idle_wait", "lend_cores"]

#: seconds the ranks other than 0 sleep between two looks at the barrier of :func:`idle_wait`
IDLE_POLL_S = 2e-4


def idle_wait(comm) -> None:
    """Collective: the ranks other than 0 wait for rank 0 asleep, not spinning.

    The point terms are computed on rank 0 alone. Meanwhile the other ranks used to wait in
    the next collective (a ``bcast``, a vector's or a matrix's assembly), where Open MPI
    polls, holding their cores, so rank 0's kernels had one thread under ``mpirun -n 2`` on
    two cores where a serial run has two. Here they wait on a non-blocking barrier that
    they look at every :data:`IDLE_POLL_S`, and rank 0's kernels get their cores
    (:func:`lend_cores`). Every rank calls it where rank 0's own work ends."""
    if comm.size == 1:
        return
    req = comm.Ibarrier()
    if comm.rank == 0:
        req.Wait()
        return
    while not req.Test():
        time.sleep(IDLE_POLL_S)


def lend_cores(comm) -> int:
    """Collective: give rank 0, which computes the point terms, the cores of every rank on its
    host (its affinity widened to their union, its kernels' threads that many), as the others
    sleep while it does (:func:`idle_wait`). Not where ``MVFEM_THREADS`` or
    ``OMP_NUM_THREADS`` sets the threads. Returns rank 0's kernel threads (every rank)."""
    import os
    import socket

    from mvfem import kernels

    if comm.size == 1:
        return kernels.threads()
    try:
        mine = sorted(os.sched_getaffinity(0))
    except AttributeError:
        mine = []
    every = comm.gather((socket.gethostname(), mine), root=0)
    n = 0
    if comm.rank == 0:
        fixed = any(os.environ.get(v, "").strip() for v in ("MVFEM_THREADS", "OMP_NUM_THREADS"))
        cores = sorted({c for host, cs in every if host == every[0][0] for c in cs})
        if not fixed and cores and len(cores) > len(mine) and kernels.load() is not None:
            # the kernels' threads are made now, with every core allowed; this thread goes
            # back to its own core, where its single-threaded work does not meet a rank
            # that polls
            try:
                os.sched_setaffinity(0, cores)
            except OSError:   # not allowed here: the kernels keep their share
                pass
            else:
                try:
                    kernels.threads(len(cores))
                    kernels.load()[1].team_size()
                finally:
                    os.sched_setaffinity(0, mine)
        n = kernels.threads()
    return int(comm.bcast(n, root=0))


class Blocks:
    """Element contributions of a point term: ``m`` elements of ``k`` nodes each.

    Attributes:
        nodes: (m, k) global node indices.
        force: (m, k, 3) gradient of the term's energy with respect to each node's position
            (Pa mm^2 = uN: the residual's unit).
        stiffness: (m, 3k, 3k) Hessian blocks, rows ordered node-major (x, y, z of node 0, ...);
            a term may pass a function that computes them, called on first access (a residual
            evaluated at a trial state that is then refused never needs them).
        energy: the term's energy (Pa mm^3 = uJ).
        csr: optional; a function returning the stiffness summed into CSR rows over every dof
            (indptr, cols, vals; fixed dofs left out), which the tangent then uses in place
            of the blocks (a term with a fixed pattern, the hinges, sums its own).
        project: optional; a function replacing stiffness blocks in place by what the term
            gives when ``convex`` (contact: their positive semidefinite part), which
            :meth:`PointTerms.convexify` applies to blocks already computed instead of
            evaluating the term again.
    """

    def __init__(self, nodes: np.ndarray, force: np.ndarray, stiffness, energy: float = 0.0):
        self.nodes, self.force, self.energy = nodes, force, energy
        self._stiffness = stiffness
        self.csr = None
        self.project = None

    @property
    def stiffness(self) -> np.ndarray:
        if callable(self._stiffness):
            self._stiffness = self._stiffness()
        return self._stiffness


def smooth_penalty(d: np.ndarray, k, eps) -> tuple[np.ndarray, ...]:
    """A C2 one-sided quadratic penalty and its first two derivatives.

    .. math:: \\phi(d) = k d^3 / (6\\epsilon) \\ (0 < d < \\epsilon), \\quad
              k (d^2/2 - \\epsilon d/2 + \\epsilon^2/6) \\ (d \\ge \\epsilon),\\quad 0 \\ (d \\le 0)

    so ``phi' = k (d - eps/2)`` once ``d > eps``: a spring of stiffness ``k`` whose onset is
    rounded over ``eps``; Newton meets no jump in the tangent when a chord tightens or a
    contact pair closes. ``k`` and ``eps`` may be arrays shaped like ``d``.
    """
    d = np.asarray(d, dtype=float)
    small = (d > 0) & (d < eps)
    big = d >= eps
    phi = np.where(small, k * d**3 / (6 * eps), 0.0) + \
        np.where(big, k * (d**2 / 2 - eps * d / 2 + eps**2 / 6), 0.0)
    dphi = np.where(small, k * d**2 / (2 * eps), 0.0) + np.where(big, k * (d - eps / 2), 0.0)
    ddphi = np.where(small, k * d / eps, 0.0) + np.where(big, k, 0.0)
    return phi, dphi, ddphi


def lumped_area(x: np.ndarray, cells: np.ndarray) -> np.ndarray:
    """(N,) area per node of a triangle mesh at positions ``x``: a third of each adjacent
    triangle's."""
    a = 0.5 * np.linalg.norm(np.cross(x[cells[:, 1]] - x[cells[:, 0]],
                                      x[cells[:, 2]] - x[cells[:, 0]]), axis=1)
    return np.bincount(cells.ravel(), np.repeat(a / 3, 3), len(x))


class NodalView:
    """All P1 nodes of a vector space in one global numbering, gathered on rank 0.

    Attributes (rank 0; empty elsewhere):
        X: (N, 3) reference positions.
        cells: (C, 3) triangles in global node indices, in the order of the ``cell_ids``.
        cell_ids: (C,) global cell index of each triangle (ownership order).
        cell_tag: (C,) region tag value of each triangle (0 where untagged).
        free: (N, 3) True where the dof has no Dirichlet condition.
        area: (N,) lumped reference area of each node (one third of each adjacent triangle).
    """

    def __init__(self, V, bcs=(), cell_tags=None):
        from dolfinx import fem
        from dolfinx.fem import petsc as fpetsc

        msh = V.mesh
        self.comm = comm = msh.comm
        if V.ufl_element().degree() != 1:
            raise ValueError("chordae and contact need P1 displacement (solver.degree = 1)")
        imap = V.dofmap.index_map
        self.bs = V.dofmap.index_map_bs
        self.n_owned = imap.size_local
        self.offset = imap.local_range[0]
        coords = V.tabulate_dof_coordinates()[: self.n_owned]
        tdim = msh.topology.dim
        n_cells = msh.topology.index_map(tdim).size_local
        cell_dofs = V.dofmap.list.array.reshape(-1, 3)[:n_cells]
        cells = imap.local_to_global(cell_dofs.ravel()).reshape(-1, 3)
        cell_ids = msh.topology.index_map(tdim).local_range[0] + np.arange(n_cells)
        tag = np.zeros(n_cells, dtype=np.int32)
        if cell_tags is not None:
            own = cell_tags.indices < n_cells
            tag[cell_tags.indices[own]] = cell_tags.values[own]
        mask = fem.Function(V)
        mask.x.array[:] = 1.0
        fpetsc.set_bc(mask.vector, list(bcs), scale=0.0)
        free = mask.x.array[: self.n_owned * self.bs] != 0.0
        parts = comm.gather((coords, cells, cell_ids, tag, free), root=0)
        if comm.rank == 0:
            self.X = np.concatenate([p[0] for p in parts])
            self.cells = np.concatenate([p[1] for p in parts]).astype(np.int64)
            self.cell_ids = np.concatenate([p[2] for p in parts])
            self.cell_tag = np.concatenate([p[3] for p in parts])
            self.free = np.concatenate([p[4] for p in parts]).reshape(-1, 3)
            self.area = lumped_area(self.X, self.cells)
        else:
            self.X = np.zeros((0, 3))
            self.cells = np.zeros((0, 3), dtype=np.int64)
            self.cell_ids = np.zeros(0, dtype=np.int64)
            self.cell_tag = np.zeros(0, dtype=np.int32)
            self.free = np.zeros((0, 3), dtype=bool)
            self.area = np.zeros(0)
        # every node's three global dofs, -1 where fixed (rank 0): what dof_indices gathers
        dofs = 3 * np.arange(len(self.free))[:, None] + np.arange(3)
        self._dofs = np.where(self.free, dofs, -1).astype(PETSc.IntType)
        lend_cores(comm)

    def gather(self, owned: np.ndarray) -> np.ndarray | None:
        """Owned dof values of every rank (a flat array of this rank's) -> (N, 3) on rank 0."""
        parts = self.comm.gather(np.asarray(owned)[: self.n_owned * self.bs], root=0)
        if self.comm.rank == 0:
            return np.concatenate(parts).reshape(-1, 3)
        return None

    def node_of_point(self, points: np.ndarray, tol: float = 1e-6) -> np.ndarray:
        """Global node index of each given reference point (rank 0; ValueError if absent)."""
        from scipy.spatial import cKDTree

        dist, idx = cKDTree(self.X).query(np.asarray(points, dtype=float).reshape(-1, 3))
        if np.any(dist > tol * max(1.0, float(np.abs(self.X).max()))):
            raise ValueError(f"{int(np.sum(dist > tol))} point(s) are not mesh nodes")
        return idx

    def dof_indices(self, nodes: np.ndarray) -> np.ndarray:
        """(m, 3k) global scalar dof indices of node blocks, -1 where a dof is fixed: a
        gather from the table of every node's three, built with the view (for the 165,000
        contact blocks of the 0.5 mm valve 8 ms a residual, against 30 ms of arithmetic on
        them)."""
        nodes = np.asarray(nodes)
        return self._dofs[nodes].reshape(len(nodes), -1)


def add_csr(A: PETSc.Mat, csr, first: int = 0) -> None:
    """Add ``(indptr, cols, vals)``, consecutive rows from global row ``first`` (by default
    rows over every dof in the global numbering), to ``A`` in one ``setValuesIJV`` (no
    assembly)."""
    IT = PETSc.IntType
    indptr, cols, vals = csr
    A.setValuesIJV(indptr.astype(IT), cols.astype(IT), vals, addv=PETSc.InsertMode.ADD_VALUES,
                   rowmap=np.arange(first, first + len(indptr) - 1, dtype=IT))


def csr_rows(csr, lo: int, hi: int) -> tuple:
    """Rows ``lo:hi`` of a CSR tuple ``(indptr, cols[, vals])`` (a pattern or a matrix), as
    the same tuple with ``indptr`` from 0: a rank's own rows of rows over every dof."""
    ip = csr[0][lo:hi + 1]
    return (ip - ip[0],) + tuple(a[ip[0]:ip[-1]] for a in csr[1:])


class PointTerms:
    """Adds point terms (callables ``x -> Blocks`` on rank 0) to a residual and a tangent.

    ``x`` is the (N, 3) array of current nodal positions. Collective: every rank calls
    :meth:`add_residual` and :meth:`add_jacobian`; only rank 0 evaluates the terms.
    """

    def __init__(self, view: NodalView, terms=()):
        self.view = view
        self.terms = list(terms)
        self.time_s = 0.0     # energy, residual and tangent contributions (inside the assembly)
        self.limit_s = 0.0    # step limits (inside SNES, outside the assembly)
        self._last: list[Blocks] = []
        self._last_x: np.ndarray | None = None

    def __bool__(self) -> bool:
        return bool(self.terms)

    def convexify(self, on: bool) -> bool:
        """Ask the terms that can (a ``convex`` attribute: contact) for positive semidefinite
        stiffness blocks (``on``) or their exact Hessians. Blocks whose stiffness is still to
        be computed (the last evaluation's, after a residual) take the setting in force when
        it is. Exact blocks already computed are projected in place where the term gives
        the way (``Blocks.project``; the same blocks as a new evaluation's, without the
        distances, the lists' filter and the Hessians again: at 117,000 contact blocks
        0.06-0.07 s, against a fine step's 1.4-2.3 s on the demo refined twice;
        ``scripts/psd_projection.py``); else, and on the way back to exact ones, the
        blocks are computed afresh at the next evaluation. Returns whether any term can."""
        able = [t for t in self.terms if hasattr(t, "convex")]
        changed = any(t.convex != bool(on) for t in able)
        for t in able:
            t.convex = bool(on)
        if not changed:
            return bool(able)
        stale = False
        for t, blk in zip(self.terms, self._last):
            if not hasattr(t, "convex") or callable(blk._stiffness):
                continue
            if on and blk.project is not None:
                blk.project(blk._stiffness)
            else:
                stale = True
        idle_wait(self.view.comm)
        if stale:
            self._last_x = None
        return bool(able)

    def positions(self, x_owned: np.ndarray) -> np.ndarray | None:
        u = self.view.gather(x_owned)
        return None if u is None else self.view.X + u

    def evaluate(self, x_owned: np.ndarray) -> list[Blocks]:
        """The terms' blocks at ``x`` (collective); SNES asks for the residual and then the
        tangent at the same state, so the last evaluation is reused."""
        x = self.positions(x_owned)
        if x is None:
            blocks = []
        elif self._last_x is not None and np.array_equal(x, self._last_x):
            blocks = self._last
        else:
            blocks = [t(x) for t in self.terms]
            self._last_x, self._last = x, blocks
        idle_wait(self.view.comm)
        return blocks

    def energy(self, x_owned: np.ndarray) -> float:
        """Sum of the terms' energies at ``x`` (collective; every rank gets it). Timed with
        the residual and tangent contributions (``time_s``): in Newton's regime a trial's
        potential is evaluated before its residual (if any), so the contact evaluation is
        mostly here."""
        t0 = time.perf_counter()
        e = sum(blk.energy for blk in self.evaluate(x_owned))
        e = float(self.view.comm.bcast(e, root=0))
        self.time_s += time.perf_counter() - t0
        return e

    def step_limit(self, x_owned: np.ndarray, dx_owned: np.ndarray,
                   squeeze: float | None = None) -> float:
        """Fraction of the update ``dx`` the terms allow (collective; 1 without limits).
        ``squeeze``: also no barrier pair closer than this fraction of its distance at ``x``
        (the terms' ``squeeze_limit``: for moves the potential does not judge)."""
        limiters = [t for t in self.terms if hasattr(t, "step_limit")]
        if not limiters:
            return 1.0
        t0 = time.perf_counter()
        x = self.positions(x_owned)
        dx = self.view.gather(dx_owned)
        alpha = 1.0
        if x is not None:
            for t in limiters:
                a = t.step_limit(x, dx)
                if squeeze is not None and hasattr(t, "squeeze_limit"):
                    a = t.squeeze_limit(x, dx, a, keep=squeeze)
                alpha = min(alpha, a)
        idle_wait(self.view.comm)
        alpha = self.view.comm.bcast(alpha, root=0)
        self.limit_s += time.perf_counter() - t0
        return alpha

    def add_residual(self, x: PETSc.Vec, b: PETSc.Vec) -> None:
        """Add the terms' forces to ``b`` (collective). On one process through ``setValues``;
        on more, rank 0 sums them into one array over every dof and sends each rank the
        slice of its rows, which it adds to its own entries: ``setValues`` of other ranks'
        entries went through PETSc's stash, whose assembly took 0.45 s of the 2 mm demo
        refined once under ``mpirun -n 2`` (README "MPI scaling")."""
        t0 = time.perf_counter()
        blocks = self.evaluate(x.array_r)
        comm = self.view.comm
        if comm.size == 1:
            for blk in blocks:
                if len(blk.nodes) == 0:
                    continue
                dofs = self.view.dof_indices(blk.nodes).ravel()
                keep = dofs >= 0
                b.setValues(dofs[keep], blk.force.reshape(-1)[keep],
                            addv=PETSc.InsertMode.ADD_VALUES)
            b.assemblyBegin()
            b.assemblyEnd()
        else:
            slices = None
            if comm.rank == 0:
                f = np.zeros(3 * len(self.view.free))
                for blk in blocks:
                    if len(blk.nodes) == 0:
                        continue
                    dofs = self.view.dof_indices(blk.nodes).ravel()
                    keep = dofs >= 0
                    f += np.bincount(dofs[keep], blk.force.reshape(-1)[keep], len(f))
                r = b.getOwnershipRanges()
                slices = [f[lo:hi] for lo, hi in zip(r[:-1], r[1:])]
            mine = comm.scatter(slices, root=0)
            with b.localForm() as bl:
                bl.array[: len(mine)] += mine
        self.time_s += time.perf_counter() - t0

    def add_jacobian(self, x: PETSc.Vec, A: PETSc.Mat) -> None:
        """Add the blocks' stiffness to ``A`` (fixed dofs left out) in one ``setValuesIJV``
        for all rows, their global indices in rowmap (setValuesCSR takes this rank's rows
        only; other ranks' rows are stashed and sent by assemble): a setValues per row cost
        12 s of a 97 s demo. The rows are built by :meth:`_stiffness_csr`, sorting 16 pairs of
        nodes per contact pair instead of 144 entries: scipy's coo -> csr and sort of the
        entries took 19 of 37 ms a call on the demo; on its recorded states the call now takes
        6 ms (33 before), the same matrix to 1e-15."""
        self.insert(A, self.tangent_parts(x))

    def tangent_parts(self, x: PETSc.Vec) -> list:
        """The terms' tangent at ``x`` as CSR parts over every dof (rank 0; none elsewhere),
        collective: what :meth:`insert` adds to a matrix."""
        t0 = time.perf_counter()
        blocks = self.evaluate(x.array_r)
        parts = [self._stiffness_csr([blk for blk in blocks if blk.csr is None])]
        parts += [blk.csr() for blk in blocks if blk.csr is not None and len(blk.nodes)]
        idle_wait(self.view.comm)
        self.time_s += time.perf_counter() - t0
        return [csr for csr in parts if csr is not None]

    def insert(self, A: PETSc.Mat, parts: list) -> None:
        """Add the CSR parts of :meth:`tangent_parts` to ``A`` and assemble it (collective).
        On more than one process rank 0 sends each rank its rows of the parts, which it adds
        as its own: other ranks' rows set on rank 0 went through PETSc's stash, whose
        assemblies took 1.2 s of the 2 mm demo refined once under ``mpirun -n 2``."""
        t0 = time.perf_counter()
        comm = self.view.comm
        if comm.size == 1:
            for csr in parts:
                add_csr(A, csr)
        else:
            rows = None
            if comm.rank == 0:
                r = A.getOwnershipRanges()
                rows = [[csr_rows(csr, lo, hi) for csr in parts] for lo, hi in zip(r[:-1], r[1:])]
            lo = A.getOwnershipRange()[0]
            for csr in comm.scatter(rows, root=0):
                add_csr(A, csr, first=lo)
        A.assemble()
        self.time_s += time.perf_counter() - t0

    def _stiffness_csr(self, blocks: list[Blocks]):
        """(indptr, cols, vals) of the sum of the blocks' stiffness over the free dofs, rows
        and columns sorted, every dof a row (None without blocks): compiled
        (:func:`mvfem.kernels.elements_csr`, bucketing each element's node rows by matrix
        row: at 0.5 mm, 146 000 contact pairs, 183 -> 133 ms an insertion, the index arrays
        of every 3 x 3 block no longer built in numpy), else numpy. The same sums in the
        same order either way.

        The 3 x 3 node blocks that are zero are left out
        (:func:`mvfem.kernels.csr_drop_zero_blocks`), so the matrix has no room for them: a
        contact pair's 12 x 12 block couples only the nodes of its closest points (the node
        and the closest vertex, edge or face of the triangle; the closest parts of two
        edges). The rest of the block is exactly zero, and with it the matrix of the
        twice-refined demo's finest level held 0.75 million of its 2.13 million entries as
        zeros, which MUMPS factorised: 4.7e9 flops for LDL^T instead of 2.4e9 (README,
        "Nested levels")."""
        from mvfem import kernels

        blocks = [blk for blk in blocks if len(blk.nodes)]
        if not blocks:
            return None
        if kernels.load() is None:
            return self._stiffness_csr_np(blocks)
        return kernels.csr_drop_zero_blocks(kernels.elements_csr(
            len(self.view.free), self.view.free, [(blk.nodes, blk.stiffness) for blk in blocks]))

    def _stiffness_csr_np(self, blocks: list[Blocks]):
        """:meth:`_stiffness_csr` in numpy. The pairs of nodes (16 per contact pair) are
        sorted, not the entries (144): their 3 x 3 blocks are laid out as matrix rows by
        index arithmetic, and every entry of every block is summed into its place by one
        ``bincount``, in the blocks' order."""
        free = self.view.free
        N = len(free)
        some = free.any(axis=1)
        keys, todo = [], []
        for blk in blocks:
            m, k = blk.nodes.shape
            rows = np.repeat(blk.nodes, k, axis=1).ravel()     # block (a, b) of element e
            cols = np.tile(blk.nodes, (1, k)).ravel()          # at e k^2 + a k + b
            # a node with every dof fixed adds nothing: past the last key
            keys.append(np.where(some[rows] & some[cols], rows * N + cols, N * N))
            todo.append(blk)
        key = np.concatenate(keys)
        order = np.argsort(key)
        sk = key[order]
        new = np.r_[True, sk[1:] != sk[:-1]]
        which = np.empty(len(key), dtype=np.int64)            # each block's distinct block
        which[order] = np.cumsum(new) - 1
        uk = sk[new]
        uk = uk[uk < N * N]
        nb = len(uk)
        br, bc = uk // N, uk % N                               # sorted by row, then column
        # matrix row 3 r + i holds row i of every block of block row r, in column order: the
        # entry (i, j) of the p-th block of row r goes to 9 start_r + 3 n_r i + 3 p + j
        nper = np.bincount(br, minlength=N)
        start = np.r_[0, np.cumsum(nper)[:-1]]
        pos = np.arange(nb) - start[br]
        i, j = np.arange(3)[:, None], np.arange(3)[None, :]
        dst = (9 * start[br] + 3 * pos)[:, None, None] + (3 * nper[br])[:, None, None] * i + j
        dst = np.concatenate([dst.reshape(nb, 9), np.full((1, 9), 9 * nb)])   # (and a bin
        places, values, off = [], [], 0                                       # for the fixed)
        for blk in todo:
            m, k = blk.nodes.shape
            w = dst[which[off:off + m * k * k]].reshape(m, k, k, 3, 3)
            off += m * k * k
            places.append(w.transpose(0, 1, 3, 2, 4).ravel())  # the stiffness's own order
            values.append(blk.stiffness.ravel())
        vals = np.bincount(np.concatenate(places), np.concatenate(values), 9 * nb + 1)[:-1]
        cols = np.empty(9 * nb, dtype=np.int64)
        rows = np.empty(9 * nb, dtype=np.int64)
        keep = np.empty(9 * nb, dtype=bool)
        d = dst[:nb].reshape(nb, 3, 3)
        cols[d] = 3 * bc[:, None, None] + j
        rows[d] = 3 * br[:, None, None] + i
        keep[d] = free[br][:, :, None] & free[bc][:, None, :]
        # (and no 3 x 3 block of zeros: kernels.csr_drop_zero_blocks)
        keep[d] &= (keep[d] & (vals[d] != 0)).any(axis=(1, 2))[:, None, None]
        indptr = np.r_[0, np.cumsum(np.bincount(rows[keep], minlength=3 * N))]
        return indptr, cols[keep], vals[keep]
