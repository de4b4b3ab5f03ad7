"""Nonlinear solution with PETSc SNES (petsc4py), and adaptive load stepping.

dolfinx 0.5 has no SNES-backed problem class, so :class:`SNESProblem` wires the assembly of a
residual form and its Jacobian into a ``PETSc.SNES`` whose options live under their own prefix
(never the global unprefixed database). :class:`LoadStepper` drives a load parameter from 0 to
1 (or any target), halves the step and restores the last converged state on failure, and grows
it after easy steps.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from mpi4py import MPI
from petsc4py import PETSc

__all__ = ["SNESProblem", "SolveInfo", "LoadStepper", "StepRecord", "PseudoTransient",
           "PseudoTimeRecord", "DEFAULT_OPTIONS", "reason_name", "stop_on_interrupt",
           "stop_asked", "stop_cause", "agree_on_stop"]

log = logging.getLogger(__name__)

#: SNES/KSP options every problem starts from (a scene's [solver] may override them)
DEFAULT_OPTIONS = {
    # trust-region Newton: fewer iterations than newtonls + backtracking from slack states
    # of the exponential laws (measured on the clamped disk, README)
    "snes_type": "newtontr",
    "snes_linesearch_type": "bt",
    "snes_rtol": 1e-9,
    "snes_atol": 1e-10,
    "snes_stol": 0.0,
    "snes_max_it": 30,
    "ksp_type": "preonly",
    "pc_type": "lu",
    "pc_factor_mat_solver_type": "mumps",
    # MUMPS workspace margin (%): pivoting on a nearly singular tangent needs more than 20 %
    "mat_mumps_icntl_14": 50,
}

_REASONS = {v: k for k, v in vars(PETSc.SNES.ConvergedReason).items() if isinstance(v, int)}
#: double precision's unit roundoff (PseudoTransient.floor)
EPS = float(np.finfo(float).eps)


class _StopRequest:
    """Whether Ctrl-C or SIGTERM asked the solve under way to stop (:func:`stop_on_interrupt`);
    ``signum``: which."""

    def __init__(self) -> None:
        self.asked = False
        #: a second Ctrl-C came (its KeyboardInterrupt may have been swallowed: see
        #: :func:`_again`)
        self.again = False
        self.active = False
        self.signum: int | None = None
        self.rank = 0  # (the line a signal prints is rank 0's)

    @property
    def name(self) -> str:
        """``Ctrl-C`` or ``SIGTERM``."""
        return _name(self.signum or signal.SIGINT)

    @property
    def cause(self) -> str:
        """Who stopped it, for the stop reason: ``the user (Ctrl-C)`` or ``SIGTERM``."""
        return "the user (Ctrl-C)" if self.name == "Ctrl-C" else self.name

    @property
    def exit_code(self) -> int:
        """The shell's code for a command that a signal stopped: 128 + its number."""
        return 128 + int(self.signum or signal.SIGINT)


_STOP = _StopRequest()

#: the signals a serial solve stops on at its next step (:func:`stop_on_interrupt`), with
#: Python's own disposition of each: Ctrl-C raises KeyboardInterrupt, SIGTERM ends the process
_SIGNALS = {signal.SIGINT: signal.default_int_handler, signal.SIGTERM: signal.SIG_DFL}


def _name(signum: int) -> str:
    return "Ctrl-C" if signum == signal.SIGINT else signal.Signals(signum).name


def _on_signal(signum, frame) -> None:
    name = _name(signum)
    if _STOP.asked:  # the second: at once, as without this handler
        if signum == signal.SIGINT:
            _STOP.again = True
            raise KeyboardInterrupt
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    _STOP.asked, _STOP.signum = True, signum
    if _STOP.rank != 0:
        return
    try:  # (the step under way may take a second)
        os.write(2, f"\nmvfem: {name}: stopping after this step and writing the last accepted "
                    f"state ({name} again stops at once, writing nothing more)\n".encode())
    except OSError:
        pass


@contextlib.contextmanager
def stop_on_interrupt(comm):
    """Within this context, the first Ctrl-C (SIGINT) or SIGTERM (a batch system's time limit,
    ``timeout``, ``kill``) asks the steppers to stop at their next step (:func:`stop_asked`,
    checked by :class:`LoadStepper` and :class:`PseudoTransient` before each step), which
    leaves the last accepted state in ``u`` for the caller to write; a second one acts at once,
    as outside (Ctrl-C raises ``KeyboardInterrupt``, SIGTERM ends the process). Yields the
    request (``.asked``, ``.cause``, ``.exit_code``; still readable after the context).

    Only the main thread does so, for each signal whose disposition is Python's own: a
    program that handles a signal itself or ignores it keeps its own. On several ranks the
    steppers ask all of them (:func:`stop_asked` with their communicator, a collective call at
    each step boundary), so every rank stops at the same step, whichever got the signal:
    Open MPI 4's mpirun sends every rank SIGTERM ``odls_base_sigkill_timeout`` seconds after
    a Ctrl-C and SIGKILL as long after that (1 s by default: the state is written first,
    ``mvfem.outputs._write_state_first``, but the rest of a larger mesh's outputs needs
    ``--mca odls_base_sigkill_timeout 5``; Slurm's KillWait, 30 s, at a time limit). Nested
    contexts (a coarser level solved inside a finer one's set-up) share the outermost's
    request."""
    if _STOP.active:
        yield _STOP
        return
    _STOP.asked, _STOP.again, _STOP.signum, _STOP.rank = False, False, None, comm.rank
    mine = []
    if threading.current_thread() is threading.main_thread():
        mine = [sig for sig, default in _SIGNALS.items() if signal.getsignal(sig) is default]
    if not mine:
        yield _STOP
        return
    previous = {sig: signal.signal(sig, _on_signal) for sig in mine}
    _STOP.active = True
    try:
        yield _STOP
    finally:
        _STOP.active = False
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def _again() -> None:
    """Raise the KeyboardInterrupt of a second Ctrl-C again: raised inside a callback or a
    finaliser that ran when the signal came, Python swallows it ("Exception ignored in:
    <function _get_module_lock.<locals>.cb ...>", a fresh-cache test suite in session 60),
    and the run went on to write its outputs as after one Ctrl-C."""
    if _STOP.again:
        raise KeyboardInterrupt


def stop_asked(comm=None) -> bool:
    """Whether Ctrl-C or SIGTERM asked the solve under way to stop (:func:`stop_on_interrupt`).
    With a communicator of several ranks, collective: whether it asked any of them, and then
    the request is every rank's (the signal the same, SIGTERM where they differ). A second
    Ctrl-C whose KeyboardInterrupt was swallowed raises it here (:func:`_again`)."""
    if _STOP.active:
        _again()
    if comm is None or comm.size == 1:
        return _STOP.active and _STOP.asked
    return agree_on_stop(comm, _STOP.active)


def agree_on_stop(comm, active: bool = True) -> bool:
    """Collective: make the request of every rank that of any (``active``: this rank's
    request counts, inside :func:`stop_on_interrupt`); whether there is one. After the
    context, the same for the steps' last one: a signal may reach one rank after the last
    check. A second Ctrl-C whose KeyboardInterrupt was swallowed raises it (:func:`_again`)."""
    _again()
    mine = int(_STOP.signum or 0) if (active and _STOP.asked) else 0
    signum = comm.allreduce(mine, op=MPI.MAX) if comm.size > 1 else mine
    if signum:
        _STOP.asked, _STOP.signum = True, signum
    return bool(signum)


def stop_cause() -> str:
    """Who asked the solve to stop: ``the user (Ctrl-C)`` or ``SIGTERM``."""
    return _STOP.cause


def reason_name(reason: int) -> str:
    """Name of a SNES converged/diverged reason, e.g. ``CONVERGED_FNORM_RELATIVE``."""
    return _REASONS.get(reason, str(reason))


@dataclass
class SolveInfo:
    """Outcome of one SNES solve."""

    converged: bool
    iterations: int
    reason: str
    residual_norm: float
    assembly_s: float = 0.0
    solve_s: float = 0.0


def _set_up_on_a_tiny_matrix(comm, prefix: str) -> None:
    """Set up a linear solver of the options under ``prefix`` on the identity of one row a
    rank (collective): its preconditioner and factorisation package are made, and refused
    if PETSc has no such thing."""
    A = PETSc.Mat().createAIJ(((1, None), (1, None)), nnz=(1, 0), comm=comm)
    ksp = PETSc.KSP().create(comm)
    try:
        start, _ = A.getOwnershipRange()
        A.setValue(start, start, 1.0)
        A.assemble()
        ksp.setOptionsPrefix(prefix)
        ksp.setOperators(A)
        ksp.setFromOptions()
        ksp.setUp()
    finally:
        ksp.destroy()
        A.destroy()


class SNESProblem:
    """Newton's method for ``F(u; v) = 0`` with Dirichlet conditions, via PETSc SNES.

    Args:
        F: residual form (UFL, linear in the test function).
        u: the unknown ``fem.Function``; holds the initial guess and receives the solution.
        bcs: Dirichlet conditions (their values may change between solves).
        J: Jacobian form; ``ufl.derivative(F, u)`` when omitted.
        prefix: PETSc options prefix of this problem.
        options: options set under the prefix, on top of :data:`DEFAULT_OPTIONS`.
        form_compiler_params / jit_params: passed to ``fem.form``.
        point_terms: optional :class:`mvfem.nodal.PointTerms` (chordae, contact) added to the
            residual and the tangent after the forms.
        potential: optional scalar form whose derivative is ``F`` (on the free dofs), or
            ``F`` plus ``load`` when that is given; with the point terms' energies it is
            :meth:`evaluate_energy`, a merit function.
        load: optional load form (linear in the test function) that ``F`` subtracts and that
            has no potential (a follower pressure on a surface with free edges): the merit's
            change along an update adds its work, :meth:`load_work`.
        sparsity: optional bilinear form whose couplings the matrix makes room for, never
            assembled (the hinges, a point term, couple the two cells of each interior edge:
            inserted into a matrix without room, 0.8 s went to reallocation in every fresh
            matrix of a disk).
    """

    def __init__(self, F, u, bcs=(), J=None, prefix: str = "mvfem_", options: dict | None = None,
                 form_compiler_params: dict | None = None, jit_params: dict | None = None,
                 point_terms=None, potential=None, load=None, sparsity=None):
        import ufl
        from dolfinx import fem
        from dolfinx.fem import petsc as fpetsc

        self.u = u
        self.bcs = list(bcs)
        self.comm = u.function_space.mesh.comm
        # the options first, before seconds of form compilation: a rejected one is bad input,
        # said at once and alone (no progress line before it)
        self.snes = PETSc.SNES().create(self.comm)
        self.prefix = prefix
        self.snes.setOptionsPrefix(prefix)
        opts = PETSc.Options(prefix)
        self._options = {**DEFAULT_OPTIONS, **(options or {})}
        for k, v in self._options.items():
            opts[k] = v
        try:
            self.snes.setFromOptions()
            self.snes.getKSP().setFromOptions()
            self.snes.getKSP().getPC().setFromOptions()
            # values the options database takes but the objects check only when used (a
            # negative snes_max_it at the first solve, an unknown factorisation package at the
            # first factorisation: tracebacks after the forms' compilation and a first step)
            self.snes.setTolerances(*self.snes.getTolerances())
            self.snes.getKSP().setTolerances(*self.snes.getKSP().getTolerances())
            _set_up_on_a_tiny_matrix(self.comm, prefix)
        except PETSc.Error as e:
            raise ValueError(f"PETSc rejected the options {options or {}} (error code "
                             f"{e.ierr})") from None
        if J is None:
            J = ufl.derivative(F, u, ufl.TrialFunction(u.function_space))
        kw = dict(form_compiler_params=form_compiler_params or {}, jit_params=jit_params or {})
        pattern = None
        if sparsity is not None:
            # on J's own arguments: a cold FFCx compile sets variant='equispaced' on the space's
            # elements, and arguments made after it hash unlike (though equal to) those made
            # before, which UFL refuses in one form ("Found different Arguments with same number
            # and part"; tests/test_valve_terms.py::test_pattern_form_made_after_a_cold_compile)
            mine = sorted(sparsity.arguments(), key=lambda a: a.number())
            theirs = sorted(J.arguments(), key=lambda a: a.number())
            sparsity = ufl.replace(sparsity, dict(zip(mine, theirs)))
            pattern = J + sparsity
        self.L = fem.form(F, **kw)
        self.a = fem.form(J, **kw)
        # the tangent with its load part symmetrised (_symmetric_form), compiled when asked for
        self._sym_ufl = (J, load, kw) if load is not None else None
        self._a_sym = None
        self._ksp_sym: PETSc.KSP | None = None
        self._pattern = (fem.form(pattern, **kw) if pattern is not None else self.a,
                         fem.form(sparsity, **kw) if sparsity is not None else None)
        self.Pi = fem.form(potential, **kw) if potential is not None else None
        self.P = fem.form(load, **kw) if load is not None else None
        self._pv = fpetsc.create_vector(self.P) if self.P is not None else None
        self.point_terms = point_terms if point_terms else None
        #: how often the matrix was given room for new couplings of the point terms
        self.regrowths = 0
        self.A, self._room = self._first_matrix()
        self.b = fpetsc.create_vector(self.L)
        self.x = u.vector.copy()
        self.assembly_s = 0.0
        self.solve_s = 0.0
        # proximal term k * M (u - u_c), M a diagonal (lumped) weight: see set_proximal
        self._prox_k = 0.0
        self._prox_w: PETSc.Vec | None = None
        self._prox_c: PETSc.Vec | None = None
        self._work = self.x.duplicate()
        self._diagonal: PETSc.Vec | None = None  # the unshifted tangent's (evaluate_tangent)

        self.snes.setFunction(self._residual, self.b)
        self.snes.setJacobian(self._jacobian, self.A)
        self.step_scalings = 0
        if self.point_terms is not None and any(hasattr(t, "step_limit")
                                                for t in self.point_terms.terms):
            # line-search Newton only: newtontr does not call the precheck
            self.snes.setLineSearchPreCheck(self._precheck)

    def forms_matrix(self) -> PETSc.Mat:
        """A new matrix with the pattern of the forms' tangent and of ``sparsity`` (no point
        terms' couplings), zero."""
        from dolfinx.fem import petsc as fpetsc

        pattern, sparsity = self._pattern
        A = fpetsc.create_matrix(pattern)
        if sparsity is not None:  # insert the pattern: the first assembly drops unused room
            fpetsc.assemble_matrix(A, sparsity)
            A.assemble()
        return A

    def _gather_pattern(self, A: PETSc.Mat):
        """``A``'s nonzero pattern, every row in the global numbering, on rank 0 (indptr,
        cols); None elsewhere (collective)."""
        if not A.assembled:  # (the forms' pattern, preallocated, is kept by assembling them)
            from dolfinx.fem import petsc as fpetsc

            fpetsc.assemble_matrix(A, self.a, bcs=self.bcs)
            A.assemble()
        ai, aj, _ = A.getValuesCSR()
        parts = self.comm.gather((np.asarray(ai, dtype=np.int64), np.asarray(aj, dtype=np.int64)),
                                 root=0)
        if self.comm.rank != 0:
            return None
        counts = np.concatenate([np.diff(i) for i, _ in parts])
        return np.r_[0, np.cumsum(counts)].astype(np.int64), np.concatenate([j for _, j in parts])

    def _make_room(self, parts: list) -> None:
        """Re-preallocate ``A`` on the union of its pattern and the point terms' ``parts``
        when these couple dofs the pattern lacks (collective). Without it PETSc grows a row
        at a time on insertion, copying the whole matrix each time: the first contact tangent
        of the 0.5 mm demo valve (0.86 million new entries) took 53 s and 63 774 mallocs, and
        new pairs cost tens of ms on later steps. The pattern only grows (entries of pairs
        that part are kept as zeros), so the factorisation's analysis is redone only here."""
        from mvfem import kernels
        from mvfem.nodal import idle_wait

        mine = None
        if self.comm.rank == 0 and parts:
            if kernels.load() is None:
                mine = self._union(parts)
            else:   # only the parts that add entries are merged (the hinges' fixed one: once)
                grow = [p for p in parts if kernels.csr_missing(self._room, p)]
                mine = self._union(grow) if grow else None
        idle_wait(self.comm)
        if not self.comm.bcast(mine is not None, root=0):
            return
        # (one process: its rows are all of them, no scatter; 0.13-0.19 s of the
        # twice-refined demo's run went to pickling the pattern to itself)
        ip, jp = mine[0] if self.comm.size == 1 else self.comm.scatter(mine, root=0)
        IT = PETSc.IntType
        self.A.setPreallocationCSR((ip.astype(IT), jp.astype(IT)))
        self.A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
        self.regrowths += 1

    def _first_matrix(self) -> tuple[PETSc.Mat, tuple | None]:
        """The matrix as constructed (collective): the forms' and ``sparsity``'s pattern, and
        with point terms the room they start from (:meth:`_gather_pattern`; their contact
        pairs couple nodes the forms do not, :meth:`_make_room` grows it)."""
        A = self.forms_matrix()
        if self.point_terms is None:
            return A, None
        A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
        return A, self._gather_pattern(A)

    def reset_pattern(self) -> None:
        """Make the matrix anew with the pattern it had when constructed (the forms' and
        ``sparsity``'s; collective): the room for the point terms' couplings is made again as
        they come, and the solvers analyse the new matrix. A pseudo-time solve started again
        from the same state then takes the same path, bit for bit; started on the room an
        earlier solve grew, it does not (MUMPS orders the larger pattern otherwise, and
        roundoff moves these paths: ``scripts/level_variants.py``)."""
        self.A.destroy()
        self.A, self._room = self._first_matrix()
        self.snes.setJacobian(self._jacobian, self.A)
        for ksp in (self.snes.getKSP(), self._ksp_sym):
            if ksp is not None:
                ksp.reset()   # (its factorisation freed; type and options kept)

    def _union(self, parts: list) -> list | None:
        """Rank 0: the union of the pattern and the CSR ``parts``, kept as the new pattern,
        split into each rank's rows (local indptr, global columns); None when it is no larger
        (what the numpy fallback, which has no compiled check, finds out here)."""
        from mvfem import kernels
        from mvfem.nodal import csr_rows

        if kernels.load() is not None:
            # a merge of the sorted rows in C: scipy's sum of the patterns as matrices, then
            # sorting it, took 0.76-0.78 of the 1.8-1.9 s of room made in the twice-refined
            # demo's run, the merges 0.13 s (README "The matrix's room merged in C")
            room = self._room
            for p in parts:
                room = kernels.csr_union(room, p)
            if len(room[1]) == len(self._room[1]):
                return None
            self._room = room
        else:
            from scipy import sparse

            n = self.A.getSize()[0]
            union = None
            for ip, jp in [self._room] + [(p[0], p[1]) for p in parts]:
                m = sparse.csr_matrix((np.ones(len(jp)), jp, ip), shape=(n, n))
                union = m if union is None else union + m
            if union.nnz == len(self._room[1]):
                return None
            union.sort_indices()
            self._room = (union.indptr.astype(np.int64), union.indices.astype(np.int64))
        ranges = self.A.getOwnershipRanges()
        return [csr_rows(self._room, lo, hi) for lo, hi in zip(ranges[:-1], ranges[1:])]

    def _precheck(self, x: PETSc.Vec, y: PETSc.Vec, *args) -> bool:
        """Scale the Newton update (x_new = x - y) to what the point terms allow."""
        alpha = self.point_terms.step_limit(x.array_r, -y.array_r)
        if alpha < 1.0:
            y.scale(alpha)
            self.step_scalings += 1
            return True
        return False

    def _update_u(self, x: PETSc.Vec) -> None:
        x.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)
        x.copy(self.u.vector)
        self.u.vector.ghostUpdate(addv=PETSc.InsertMode.INSERT, mode=PETSc.ScatterMode.FORWARD)

    def _residual(self, snes, x, b) -> None:
        from dolfinx.fem import petsc as fpetsc

        t0 = time.perf_counter()
        self._update_u(x)
        with b.localForm() as bl:
            bl.set(0.0)
        fpetsc.assemble_vector(b, self.L)
        fpetsc.apply_lifting(b, [self.a], bcs=[self.bcs], x0=[x], scale=-1.0)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fpetsc.set_bc(b, self.bcs, x, -1.0)
        if self.point_terms is not None:
            self.point_terms.add_residual(x, b)
        if self._prox_k > 0:
            x.copy(self._work)
            self._work.axpy(-1.0, self._prox_c)
            self._work.pointwiseMult(self._work, self._prox_w)
            b.axpy(self._prox_k, self._work)
        # a state where the exponential laws overflow must not pass as a residual: PETSc's
        # line search backtracks on inf, and SNES stops with DIVERGED_FNORM_NAN otherwise
        if not np.all(np.isfinite(b.array_r)):
            with b.localForm() as bl:
                bl.set(np.inf)
        self.assembly_s += time.perf_counter() - t0

    def _jacobian(self, snes, x, A, P, form=None) -> None:
        from dolfinx.fem import petsc as fpetsc

        t0 = time.perf_counter()
        parts = None
        if self.point_terms is not None:
            parts = self.point_terms.tangent_parts(x)
            if A.handle == self.A.handle:
                self._make_room(parts)
        A.zeroEntries()
        fpetsc.assemble_matrix(A, self.a if form is None else form, bcs=self.bcs)
        A.assemble()
        if parts is not None:
            self.point_terms.insert(A, parts)
        if self._prox_k > 0:
            self._prox_w.copy(self._work)
            self._work.scale(self._prox_k)
            A.setDiagonal(self._work, addv=PETSc.InsertMode.ADD_VALUES)
            A.assemble()
        self.assembly_s += time.perf_counter() - t0

    def set_proximal(self, k: float, weights: PETSc.Vec | None = None,
                     centre: PETSc.Vec | None = None) -> None:
        """Add ``k W (u - c)`` to the residual and ``k W`` to the Jacobian diagonal.

        ``W`` is a diagonal weight (e.g. the lumped mass, zero on Dirichlet rows) and ``c`` the
        centre (e.g. the last converged state). ``k = 0`` removes the term.
        """
        self._prox_k = float(k)
        if weights is not None:
            self._prox_w = weights
        if centre is not None:
            self._prox_c = centre
        if self._prox_k > 0 and (self._prox_w is None or self._prox_c is None):
            raise ValueError("set_proximal needs weights and a centre")

    def set_tolerances(self, rtol: float | None = None, atol: float | None = None) -> None:
        """Change the SNES relative/absolute residual tolerances."""
        r, a, st, it = self.snes.getTolerances()
        self.snes.setTolerances(rtol=r if rtol is None else rtol, atol=a if atol is None else atol,
                                stol=st, max_it=it)

    def solve(self) -> SolveInfo:
        """Solve from the current ``u``; on return ``u`` holds the last Newton iterate."""
        a0, t0 = self.assembly_s, time.perf_counter()
        self.u.vector.copy(self.x)
        self.snes.solve(None, self.x)
        self._update_u(self.x)
        reason = self.snes.getConvergedReason()
        fnorm = self.snes.getFunctionNorm()
        total = time.perf_counter() - t0
        assembly = self.assembly_s - a0
        self.solve_s += total - assembly
        return SolveInfo(converged=reason > 0 and bool(np.isfinite(fnorm)),
                         iterations=self.snes.getIterationNumber(), reason=reason_name(reason),
                         residual_norm=float(fnorm), assembly_s=assembly, solve_s=total - assembly)

    def evaluate_residual(self, x: PETSc.Vec) -> float:
        """Residual of the problem as posed (no proximal term) at ``x`` into ``self.b``; its
        norm (inf where the laws overflow)."""
        k = self._prox_k
        self._prox_k = 0.0
        try:
            self._residual(self.snes, x, self.b)
        finally:
            self._prox_k = k
        return self.b.norm()

    @property
    def has_energy(self) -> bool:
        return self.Pi is not None

    def evaluate_energy(self, x: PETSc.Vec) -> float:
        """Total potential at ``x`` (collective): the form's plus the point terms' energies
        (inf where it is not finite)."""
        from dolfinx import fem

        t0 = time.perf_counter()
        self._update_u(x)
        e = self.comm.allreduce(fem.assemble_scalar(self.Pi), op=MPI.SUM)
        if self.point_terms is not None:
            e += self.point_terms.energy(x.array_r)
        self.assembly_s += time.perf_counter() - t0
        return float(e) if np.isfinite(e) else np.inf

    def load_work(self, x: PETSc.Vec, y: PETSc.Vec) -> float:
        r"""Work of the ``load`` form along the straight path from ``x`` to ``y``
        (collective; 0 without one), by Simpson's rule:

        .. math:: W = \int_0^1 P(x + s d)\cdot d\, ds = \tfrac16 (P_0 + 4 P_{1/2} + P_1)
                  \cdot d,\qquad d = y - x

        exact for a follower pressure (its nodal forces are quadratic in the positions, the
        integrand cubic in ``s``) and a dead load. A follower pressure on a surface with free
        edges (a valve's leaflets) is not conservative: ``-p`` x the swept volume differs in
        its derivative from the load by a free-edge term, on the demo valve at rest as large
        as the load itself (8.1e5 against 8.5e5 in norm), and as the merit it stopped the
        dilated and the patient valves short of equilibrium (README, Solving)."""
        from dolfinx.fem import petsc as fpetsc

        if self.P is None:
            return 0.0
        t0 = time.perf_counter()
        d = y.copy()
        z = x.copy()
        try:
            d.axpy(-1.0, x)
            work = 0.0
            for weight, s in ((1.0, 0.0), (4.0, 0.5), (1.0, 1.0)):
                x.copy(z)
                z.axpy(s, d)
                self._update_u(z)
                with self._pv.localForm() as pl:
                    pl.set(0.0)
                fpetsc.assemble_vector(self._pv, self.P)
                self._pv.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
                work += weight * self._pv.dot(d)
        finally:
            d.destroy()
            z.destroy()
        self.assembly_s += time.perf_counter() - t0
        return float(work / 6.0)

    def evaluate_tangent(self, x: PETSc.Vec, shift: float, symmetric: bool = False) -> None:
        """Tangent at ``x`` plus ``shift`` x the proximal weights on the diagonal, into
        ``self.A``; with ``symmetric``, the load's part replaced by its symmetric part (see
        :meth:`symmetric_solver`). Its unshifted diagonal is kept for :meth:`shift_tangent`.
        The forms are assembled at ``x`` itself: the last evaluation may have left ``u``
        elsewhere (:meth:`load_work` at ``x + (y - x)``, ``y`` to roundoff)."""
        self._update_u(x)
        k = self._prox_k
        self._prox_k = 0.0
        try:
            self._jacobian(self.snes, x, self.A, self.A,
                           form=self._symmetric_form() if symmetric else None)
        finally:
            self._prox_k = k
        #: the unshifted tangent's infinity norm (the largest row sum): the scale of the
        #: residual that roundoff of the positions alone gives (PseudoTransient.floor)
        self.tangent_norm = self.A.norm(PETSc.NormType.INFINITY)
        t0 = time.perf_counter()
        self._diagonal = self.A.getDiagonal(self._diagonal)
        self.assembly_s += time.perf_counter() - t0
        self.shift_tangent(shift)

    def shift_tangent(self, shift: float) -> None:
        """``self.A`` = the last :meth:`evaluate_tangent`'s tangent plus ``shift`` x the
        proximal weights on the diagonal, bit for bit what that call gives with ``shift``
        (the same sums, entry by entry): for a pseudo-time step refused at the same state,
        whose tangent differs only in the weight ``k``: a fresh evaluation costs the forms,
        the point terms' blocks and rows, and the residual at the state again, 0.2 s a
        refusal on the twice-refined demo's finest level (README, "Nested levels")."""
        t0 = time.perf_counter()
        if self._diagonal is None:
            raise RuntimeError("shift_tangent before evaluate_tangent")
        if shift > 0:
            self._prox_w.copy(self._work)
            self._work.scale(float(shift))
            self._work.axpy(1.0, self._diagonal)
        else:
            self._diagonal.copy(self._work)
        self.A.setDiagonal(self._work, addv=PETSc.InsertMode.INSERT_VALUES)
        self.A.assemble()
        self.assembly_s += time.perf_counter() - t0

    def _symmetric_form(self):
        """The compiled tangent whose ``load`` part is symmetrised:
        ``J + (J_l - J_l^T) / 2``, ``J_l`` the load's derivative (``J`` has ``-J_l``)."""
        if self._a_sym is None:
            import ufl
            from dolfinx import fem

            J, load, kw = self._sym_ufl
            test, trial = sorted(J.arguments(), key=lambda a: a.number())
            Jl = ufl.derivative(load, self.u, trial)
            sym = J + 0.5 * (Jl - ufl.adjoint(Jl, reordered_arguments=(test, trial)))
            self._a_sym = fem.form(sym, **kw)
        return self._a_sym

    def symmetric_solver(self) -> PETSc.KSP | None:
        r"""A direct solver of the symmetric tangent (:meth:`evaluate_tangent` with
        ``symmetric``): MUMPS's LDL^T of ``self.A``'s upper triangle, which reads half the
        matrix and factorises it in 0.77-0.85 x the time of LU (README, "Nested levels"). None
        where the problem has no ``load`` form (its tangent is symmetric: the LU is as
        good) or its linear solver is not the default LU with MUMPS.

        The tangent of a follower pressure on a surface with free edges is not symmetric
        (the pressure has no potential); the rest of the tangent is. Its symmetric part keeps
        the fixed points of a pseudo-time step and its descent on the potential, so a step far
        from Newton's regime needs nothing more; near the solution the exact tangent's LU
        converges quadratically."""
        if self._sym_ufl is None:
            return None
        o = self._options
        if (o.get("ksp_type"), o.get("pc_type"), o.get("pc_factor_mat_solver_type")) != \
                ("preonly", "lu", "mumps"):
            return None
        if self._ksp_sym is None:
            ksp = PETSc.KSP().create(self.comm)
            ksp.setOptionsPrefix(self.prefix + "sym_")
            opts = PETSc.Options(self.prefix + "sym_")
            for k, v in self._sym_options().items():
                opts[k] = v
            ksp.setFromOptions()
            ksp.getPC().setFromOptions()
            self._ksp_sym = ksp
        return self._ksp_sym

    def _sym_options(self) -> dict:
        """The symmetric solver's options (under ``prefix + "sym_"``): the LU's, as LDL^T."""
        o = {k: v for k, v in self._options.items() if k.startswith(("mat_mumps_", "pc_factor_"))}
        return {**o, "ksp_type": "preonly", "pc_type": "cholesky"}

    def residual_norm(self) -> float:
        """The l2 norm of the residual at the current ``u`` (boundary rows included)."""
        self.u.vector.copy(self.x)
        self._residual(self.snes, self.x, self.b)
        return self.b.norm()

    def destroy(self) -> None:
        """Free the PETSc objects and this problem's prefixed options: PETSc's options
        table is finite (a test session of 300 solves filled it: error 55 setting one)."""
        for obj in (self.snes, self.A, self.b, self.x, self._work, self._pv, self._ksp_sym,
                    self._diagonal):
            if obj is not None:
                obj.destroy()
        opts = PETSc.Options(self.prefix)
        for k in self._options:
            opts.delValue(k)
        if self._ksp_sym is not None:
            opts = PETSc.Options(self.prefix + "sym_")
            for k in self._sym_options():
                opts.delValue(k)


@dataclass
class StepRecord:
    """One attempted load step."""

    load: float
    converged: bool
    iterations: int
    reason: str


@dataclass
class LoadStepper:
    """Adaptive continuation in a load parameter ``t`` from ``start`` to ``target``.

    ``set_load(t)`` applies the load ``t`` (scales pressure constants, boundary values, ...);
    ``solve()`` returns a :class:`SolveInfo`. A failed step restores the last converged state
    and halves the increment; ``grow`` multiplies it after a step that needed at most
    ``easy_iterations`` Newton iterations; below ``min_step`` the stepper gives up.

    Attributes:
        history: every attempted step, in order.
    """

    set_load: Callable[[float], None]
    solve: Callable[[], SolveInfo]
    get_state: Callable[[], np.ndarray]
    set_state: Callable[[np.ndarray], None]
    first_step: float = 0.25
    min_step: float = 1e-4
    max_step: float = 1.0
    grow: float = 1.5
    easy_iterations: int = 6
    max_steps: int = 500
    predictor: bool = True
    on_step: Callable[[StepRecord, "LoadStepper"], None] | None = None
    history: list[StepRecord] = field(default_factory=list)
    stop_reason: str = ""
    #: the ranks that step together (a stop asked of any stops them all), or None: this one
    comm: object = None

    def run(self, target: float = 1.0, start: float = 0.0) -> tuple[bool, float]:
        """Advance to ``target``; returns (reached, last converged load).

        With ``predictor`` each step starts from the secant extrapolation of the last two
        converged states (the first from the last state itself).
        """
        t, dt = start, min(self.first_step, target - start)
        saved = self.get_state()
        previous: tuple[float, np.ndarray] | None = None
        while t < target - 1e-14 and len(self.history) < self.max_steps:
            if stop_asked(self.comm):
                self.stop_reason = (f"stopped by {stop_cause()} after {len(self.history)} "
                                    "load steps")
                break
            t_new = min(t + dt, target)
            if self.predictor and previous is not None:
                t_old, u_old = previous
                self.set_state(saved + (saved - u_old) * ((t_new - t) / (t - t_old)))
            self.set_load(t_new)
            info = self.solve()
            rec = StepRecord(t_new, info.converged, info.iterations, info.reason)
            self.history.append(rec)
            if self.on_step is not None:
                self.on_step(rec, self)
            if info.converged:
                previous = (t, saved)
                t, saved = t_new, self.get_state()
                if info.iterations <= self.easy_iterations:
                    dt = min(dt * self.grow, self.max_step)
            else:
                self.set_state(saved)
                dt /= 2
                if dt < self.min_step * (target - start):
                    self.stop_reason = (f"load step below the minimum {self.min_step:g} after "
                                        f"{info.reason}")
                    break
        reached = t >= target - 1e-14
        if not reached and not self.stop_reason:
            self.stop_reason = f"step budget of {self.max_steps} attempts used (solver.max_steps)"
        self.set_state(saved)
        self.set_load(t)
        return reached, t

    @property
    def converged_steps(self) -> int:
        """Number of accepted load steps."""
        return sum(r.converged for r in self.history)

    @property
    def newton_iterations(self) -> int:
        """Newton iterations over all attempted steps."""
        return sum(r.iterations for r in self.history)


@dataclass
class PseudoTimeRecord:
    """One pseudo-time step: its weight ``k`` (= 1/dt), the fraction ``alpha`` of the update
    taken, the residual after it, and whether it was accepted. The residual of a refused
    step in Newton's regime whose last trial raised the potential is nan: the potential
    alone refused it, and the residual was not evaluated."""

    step: int
    weight: float
    alpha: float
    residual: float
    accepted: bool


@dataclass
class PseudoTransient:
    r"""Pseudo-transient continuation (Kelley and Keyes 1998) of ``F(u) = 0``.

    Each pseudo-time step is one Newton step on ``k M (u - u_n) + F(u) = 0`` from ``u_n``:

    .. math:: (K(u_n) + k M)\, \delta u = -F(u_n),\qquad u_{n+1} = u_n + \alpha\, \delta u

    with ``M`` the lumped nodal area (the problem's proximal weights), ``k = 1/dt`` the
    pseudo-time weight and ``alpha <= 1`` what the point terms allow (contact: no node passes
    through a triangle). ``k`` follows switched evolution relaxation, ``k_{n+1} = k_n
    ||F_{n+1}|| / ||F_n||`` (the ratio clipped to ``[1/max_growth, 1/min_growth]``, so ``dt``
    grows at least ``min_growth``-fold after every accepted step); a step whose residual is not
    finite (the exponential laws overflowed) or grew more than ``reject``-fold is refused and
    ``k`` multiplied by ``shrink`` (the next update, from the same state, keeps the tangent
    and shifts its diagonal to the new ``k``: :meth:`SNESProblem.shift_tangent`). Once ``k``
    has fallen below its start ``k0`` (Newton's regime), every later update must lower the
    merit (the potential where the problem has one, which then judges alone: no refusal for
    the residual's growth, see ``reject_descending``; else the residual), after up to
    ``backtracks`` halvings, or it is refused: the end game cannot cycle. After
    ``restart_after`` refusals in a row there (the residual is only piecewise smooth where
    contact pairs change from face to edge), the run moves in pseudo-time again from the
    current state with ``k = restart_weight k0``, at most ``restarts`` times. As ``k -> 0``
    the steps become Newton's, and the iteration converges quadratically. Every state is an
    equilibrium candidate of the problem as posed: the residual tested is that of ``F``
    alone, with no damping term, so the state returned when ``||F|| <= atol`` needs no
    removal of a stabiliser.

    ``max_move`` caps the largest displacement component of one update (the first updates
    from a slack state are wild: hundreds of mm, refused anyway, and expensive to check for
    collisions).

    A slack structure (a valve swinging shut, a flat Fung membrane with no stiffness) thus
    moves at the pace its tangent allows, with one factorisation per step (README: on the
    demo valve 180 steps where load stepping with inner pseudo-time solves took 855 Newton
    iterations and did not converge).
    """

    problem: SNESProblem
    k0: float
    atol: float
    max_steps: int = 1000
    reject: float = 5.0
    min_growth: float = 1.2
    max_growth: float = 3.0
    shrink: float = 4.0
    max_rejections: int = 30
    max_move: float | None = None
    backtracks: int = 4
    k_min: float = 1e-12
    restart_after: int = 10
    restarts: int = 5
    restart_weight: float = 1e3
    #: a restart where the last one did not halve the residual takes this times its weight
    #: (:meth:`restart_weight_after`)
    restart_growth: float = 10.0
    #: in Newton's regime, judge updates by the change of the total potential where the
    #: problem has one (``SNESProblem.evaluate_energy`` minus ``load_work``, the work of a
    #: load without potential along the update): a decrease is accepted; within
    #: ``energy_rtol`` x ``|energy|`` of no change (roundoff), the residual must fall
    use_energy: bool = True
    #: in pseudo-time (before Newton's regime), refuse updates that raise the potential
    descend: bool = True
    energy_rtol: float = 1e-13
    #: in Newton's regime, refuse an update whose residual grew more than ``reject``-fold
    #: even where the potential judges it. Off: near a contact pair the barrier's force
    #: changes fast, so an update that descends the potential can grow the residual
    #: tenfold; refused, ``k`` grew fourfold at each (seven in a row, 27 to 1.1e5, on the
    #: demo refined once, its update finally taken growing the residual anyway). Judged by
    #: the potential alone (backtracking where it rises), the demo refined once took 46-88
    #: fine steps instead of 72-199 at 15.5-17 kPa (README, "Nested levels")
    reject_descending: bool = False
    #: in Newton's regime (``k < k0``), an update that does not descend (``F . du > 0``:
    #: the tangent is indefinite there) is solved again, once, with the point terms' blocks
    #: projected onto their positive semidefinite part (:meth:`PointTerms.convexify`)
    convexify: bool = True
    #: after an accepted update that was solved again with the projected blocks
    #: (``convexify``), the next ``convex_window`` accepted updates in Newton's regime are
    #: solved with them at once, the exact tangent not tried first: where it was indefinite
    #: it mostly stays so for a step or two (the same contact pairs), and each try costs a
    #: tangent and a factorisation. Off by default; the runs use 2 on nested levels
    #: (``mvfem.run.NESTED_CONVEX_WINDOW``): the demo refined twice at 16 pressures 15.5-17.375
    #: kPa took 11 % less time, the finest level 606 steps against 677 (windows of 1, 3 and
    #: 4 gave nothing), but the demo started from a coarser closure (``coarse_start``) 10 %
    #: more steps (README, "Solving")
    convex_window: int = 0
    #: the first step's weight (``k0`` when None); ``k0`` stays the threshold of Newton's
    #: regime and the reference of the restarts. Where the first updates at ``k0`` are
    #: refused anyway (a nested level's transferred state: ``mvfem.run.NESTED_FIRST_WEIGHT``),
    #: a start at the weight of the first accepted one skips them on the same path
    k_first: float | None = None
    #: in pseudo-time (``k >= k0``, before Newton's regime), solve every update with the
    #: point terms' blocks projected (IPC's projected Newton), the exact ones kept for
    #: Newton's regime. Off: on the demo refined twice 424 s against 544 s, but the refined
    #: once 55 against 48 s, the demo the same and the hard cases 365 against 268 s (README,
    #: Solving)
    convexify_early: bool = False
    #: while ``k >= symmetric_above`` (``k0`` when None), solve the updates with the
    #: symmetric part of the tangent (:meth:`SNESProblem.symmetric_solver`: MUMPS's LDL^T,
    #: 0.77-0.85 x the time of the LU on the twice-refined demo); with smaller ``k``, near
    #: the solution, the exact one. Off: from the open state, whose tangent is far from
    #: symmetric, it took more steps (the runs use it on sequenced levels; README, Solving)
    symmetric: bool = False
    symmetric_above: float | None = None
    on_step: Callable[[PseudoTimeRecord, "PseudoTransient"], None] | None = None
    #: prescribed motion: ``ramp(f)`` sets the Dirichlet values to the fraction ``f`` of their
    #: targets (an annulus moved to a ring, say); it is called with ``n / ramp_steps`` before
    #: each of the first ``ramp_steps`` steps, so the motion is spread over them. It may move
    #: ``problem.u`` (which holds the current state when it is called: a lifting of the new
    #: Dirichlet values into the interior), and may return True once the motion is complete
    #: (no more calls; the steps go on to convergence); one that returns None is complete
    #: after its call with ``f = 1``. A run whose motion is not complete within ``ramp_steps``
    #: calls has not converged (the ramp's ``share`` attribute, the fraction reached, goes
    #: into its stop reason)
    ramp: Callable[[float], None] | None = None
    ramp_steps: int = 0
    history: list[PseudoTimeRecord] = field(default_factory=list)
    stop_reason: str = ""
    solve_s: float = 0.0
    #: how many updates were solved again with convexified point terms
    convexified: int = 0
    #: how many updates were solved with them at once (``convex_window``)
    convexified_ahead: int = 0
    #: how many updates were solved with the symmetric tangent (``symmetric``)
    symmetric_solves: int = 0
    #: a state whose residual is at most :attr:`floor` has converged whatever ``atol``:
    #: ``eps ||K||_inf (|X|_inf + |u|_inf)``, the residual that roundoff of the positions
    #: alone gives at the last tangent ``K`` (unshifted). Where the exponential law is stiff
    #: it can exceed ``atol``: the ringed valve opened at -500 Pa (3 mm), ``||K||_inf`` 1.6e12
    #: against 4.7e8 on the closed demo, converged quadratically to 8e-3 (1.7e-7 of its small
    #: load) and then sat between 6.5e-3 and 8.3e-3 for its last 20 steps, above the
    #: tolerance's 4.8e-4 and below this floor, 1.4e-2; a perturbation of 1e-12 mm of the
    #: positions changes its residual by 3.9 (README, "Converged at the roundoff floor"). On
    #: the demo the floor is 3e-6, 5000 x below ``atol``. At most ``floor_factor`` x ``atol``
    #: counts: a contact pair squeezed to 1e-10 mm has a barrier stiffness so large that its
    #: floor would pass any state. ``roundoff_floor = False``: ``atol`` alone
    roundoff_floor: bool = True
    floor_factor: float = 100.0
    #: the floor at the last tangent (capped at ``floor_factor`` x ``atol``)
    floor: float = 0.0
    #: whether the run ended on the floor (its residual above ``atol``)
    at_floor: bool = False
    #: whether Ctrl-C or SIGTERM stopped the run (:func:`stop_on_interrupt`)
    interrupted: bool = False
    #: the pseudo-time weight the next step would have taken: where a resumed run starts
    #: (``k_first``; summary.json ``pseudo_time.weight``, relative to the stabiliser scale)
    weight: float | None = None
    #: the load's norm (:func:`mvfem.run._load_scale`): where given, a stop reason states the
    #: residual and ``atol`` as fractions of it, as the progress lines do ("residual 3.81e+04
    #: above the tolerance 0.00443" said nothing a user could compare); else in uN
    load: float | None = None

    def _above(self, r: float) -> str:
        if self.load:
            return (f"residual {r / self.load:.3g} of the load, above the tolerance "
                    f"{self.atol / self.load:.3g} of it")
        return f"residual {r:.3g} above the tolerance {self.atol:.3g}"

    def run(self) -> SolveInfo:
        """Advance from the problem's current ``u`` until ``||F|| <= atol``; ``u`` holds the
        last accepted state on return (the best one when the budget runs out)."""
        pb = self.problem
        ksp = pb.snes.getKSP()
        x = pb.u.vector.copy()
        trial = x.duplicate()
        du = x.duplicate()
        rhs = x.duplicate()
        limited = pb.point_terms is not None and any(hasattr(t, "step_limit")
                                                     for t in pb.point_terms.terms)
        try:
            r = pb.evaluate_residual(x)
            if not np.isfinite(r):
                self.stop_reason = "the residual of the initial state is not finite"
                return SolveInfo(False, 0, "DIVERGED_FNORM_NAN", r)
            k, in_a_row, its, monotone, restarts = self.k0, 0, 0, False, 0
            restart_r, restart_w = None, self.restart_weight  # (the last restart's)
            if self.k_first is not None:
                k = self.k_first
            merit = pb.evaluate_energy if self.use_energy and pb.has_energy else None
            E = None  # the potential at x, once needed

            def change(E_new: float) -> float:
                """The potential's change from x to trial: the energies' change minus the
                load's work along the update (a follower pressure on a surface with free
                edges has no potential: its work is integrated, not differenced)."""
                if not np.isfinite(E_new):
                    return np.inf
                return E_new - E - pb.load_work(x, trial)

            def better(r_new: float, dE: float | None) -> bool:
                if not np.isfinite(r_new):
                    return False
                if dE is None:
                    return r_new < r
                tol = self.energy_rtol * abs(E)
                return dE < -tol or (dE <= tol and r_new < r)

            def potential() -> tuple[float, float]:
                """The trial's potential and its change from x (the potential at x first,
                once; neither leaves anything in b, which holds F of the last residual)."""
                nonlocal E
                if E is None:
                    E = merit(x)
                E_new = merit(trial)
                return E_new, change(E_new)

            def judge() -> tuple[float, float, float]:
                """Newton's regime, the potential judging: the trial's potential and its
                change, then its residual only where that change does not refuse it alone
                (a rise beyond roundoff refuses whatever the residual; nan: not evaluated).
                A skipped residual saves the forms' vector and the point terms' forces; the
                contact evaluation is the potential's too. The same path, bit for bit, and
                the demo refined twice 4 % faster (README, "Nested levels")."""
                E_new, dE = potential()
                if np.isfinite(E_new) and dE > self.energy_rtol * abs(E):
                    return np.nan, E_new, dE
                return pb.evaluate_residual(trial), E_new, dE

            sym_ksp = pb.symmetric_solver() if self.symmetric else None
            k_sym = self.k0 if self.symmetric_above is None else self.symmetric_above

            # the tangent in pb.A is that at x, with the load part symmetrised (True) or not
            # (False), and exact point terms: a refused update's next one needs only its
            # diagonal shifted to the new k (None: evaluate it)
            held = None

            def newton_update(symmetric: bool = False, convex: bool = False) -> PETSc.KSP:
                """``du = -(K(x) + k M)^-1 F(x)``, with ``F(x)`` in ``rhs`` (``K``'s load
                part symmetrised with ``symmetric``; ``convex``: with the point terms'
                blocks projected); the solver that solved it."""
                nonlocal held
                if held is not None and held == symmetric and not convex:
                    pb.shift_tangent(k)
                else:
                    pb.evaluate_tangent(x, k, symmetric=symmetric)
                    held = None if convex else symmetric
                    if self.roundoff_floor:
                        self.floor = min(EPS * pb.tangent_norm * (extent + x.norm(
                            PETSc.NormType.INFINITY)), self.floor_factor * self.atol)
                t0 = time.perf_counter()
                solver = sym_ksp if symmetric else ksp
                solver.setOperators(pb.A)
                solver.solve(rhs, du)
                self.solve_s += time.perf_counter() - t0
                self.symmetric_solves += bool(symmetric)
                du.scale(-1.0)
                return solver

            ramped = self.ramp is None
            window = 0  # accepted updates still to solve with projected blocks at once
            geometry = pb.u.function_space.mesh.geometry.x
            extent = pb.comm.allreduce(float(np.abs(geometry).max(initial=0.0)), op=MPI.MAX)
            self.floor, self.at_floor = 0.0, False
            while r > max(self.atol, self.floor) or not ramped:
                if stop_asked(pb.comm):  # x: the last accepted state
                    self.interrupted = True
                    self.stop_reason = (f"stopped by {stop_cause()} after {its} "
                                        "pseudo-time steps")
                    break
                if its >= self.max_steps:
                    self.stop_reason = (f"{self._above(r)} after {its} pseudo-time steps "
                                        "(solver.max_steps)")
                    break
                if monotone and in_a_row >= self.restart_after and restarts < self.restarts:
                    # the end game is stuck (the residual is only piecewise smooth where
                    # contact pairs change regions): move in pseudo-time again from here
                    monotone, in_a_row, restarts = False, 0, restarts + 1
                    restart_w = self.restart_weight_after(restart_w, restart_r, r)
                    restart_r = r
                    k = restart_w * self.k0
                    log.debug(f"    pseudo-time restart {restarts} at residual {r:.3g}"
                              + (f" (the last one's did not halve it: weight {restart_w:g} x)"
                                 if restart_w != self.restart_weight else ""))
                if in_a_row >= self.max_rejections:
                    self.stop_reason = (f"{in_a_row} pseudo-time steps refused in a row "
                                        f"(dt = {1 / k:.3g}): no admissible step")
                    break
                its += 1
                if self.ramp is not None and its <= max(self.ramp_steps, 1) and not ramped:
                    pb._update_u(x)
                    done = self.ramp(min(its / max(self.ramp_steps, 1), 1.0))
                    pb.u.vector.copy(x)  # the state, moved by the ramp or not
                    # complete when it says so, or (a ramp that does not say) at f = 1
                    ramped = bool(done) if done is not None else its >= max(self.ramp_steps, 1)
                    r = pb.evaluate_residual(x)  # the Dirichlet rows now hold x - g
                    E, held = None, None
                pb.b.copy(rhs)  # F(x), still in b from the last evaluation at x
                early = bool(self.convexify_early and pb.point_terms and not monotone
                             and k >= self.k0 and pb.point_terms.convexify(True))
                ahead = bool(not early and window > 0 and k < self.k0 and pb.point_terms
                             and pb.point_terms.convexify(True))
                self.convexified_ahead += ahead
                try:
                    solver = newton_update(sym_ksp is not None and k >= k_sym,
                                           convex=early or ahead)
                finally:
                    if early or ahead:
                        pb.point_terms.convexify(False)
                resolved = False
                if self.convexify and not ahead and k < self.k0 and pb.point_terms \
                        and rhs.dot(du) > 0 and pb.point_terms.convexify(True):
                    # the contact barrier's exact Hessian is indefinite (its curvature term
                    # b'(d) d2d, as large as the rest): Newton's update can climb the
                    # potential, and was refused however far it was shortened, k growing
                    # fourfold each time (7 refusals in a row on the demo refined once).
                    # The projected blocks give a descent direction; the exact ones
                    # converge faster where they do descend (IPC projects always: the demo
                    # took 292 steps, not 255)
                    try:
                        solver = newton_update(convex=True)
                        self.convexified += 1
                        resolved = True
                        log.debug(f"    convexified tangent at residual {r:.3g}")
                    finally:
                        pb.point_terms.convexify(False)
                alpha = 1.0
                if self.max_move is not None:  # wild early updates: cheaper to check, refused
                    top = du.norm(PETSc.NormType.INFINITY)
                    if top > self.max_move:
                        alpha = self.max_move / top
                if limited:
                    alpha *= pb.point_terms.step_limit(x.array_r, alpha * du.array_r)
                x.copy(trial)
                trial.axpy(alpha, du)
                monotone = monotone or k < self.k0
                # in Newton's regime an update that descends the potential may grow the
                # residual (below), so there the potential alone judges it
                judged = monotone and merit is not None and not self.reject_descending
                solved = solver.getConvergedReason() > 0
                E_new = dE = None
                if judged and solved:
                    r_new, E_new, dE = judge()
                    ok = r_new != np.inf  # nan: the potential rose (backtracking below)
                else:
                    r_new = pb.evaluate_residual(trial)
                    ok = bool(np.isfinite(r_new)) and (judged or r_new <= self.reject * r) \
                        and solved
                if ok and not monotone and merit is not None and self.descend:
                    # in pseudo-time too an update must not raise the potential: by the
                    # residual alone (a fivefold growth allowed) the patient valve cycled
                    # between 3.5e-4 and 1.8e-3 of the load for 1000 steps, k never falling
                    # to Newton's regime
                    E_new, dE = potential()
                    ok = dE <= self.energy_rtol * abs(E)
                if ok and monotone:
                    # Newton's regime (dt large): from here on every update must lower the merit
                    # (the potential, else the residual), by backtracking if need be, else it is
                    # refused and damping grows (Newton cycled between two states at dt ~ 1e300
                    # on the prolapsing valve). The potential is the natural merit of a
                    # conservative problem (the shifted step descends it wherever K + kM is
                    # positive definite); by the residual the 1 mm demo stalled at 9e-4 of the
                    # load, by the potential at 2.4e-5, and the 2 mm demo took 287 steps, not
                    # 327. The follower pressure on free-edged leaflets has no potential: with
                    # -p x the swept volume in its place (off by a free-edge term) the patient
                    # valve stalled at 4.9e-5 of the load after 1500 steps; with the pressure's
                    # work integrated along the update it converges in 375
                    if not judged and merit is not None:  # (reject_descending)
                        E_new, dE = potential()
                    if not better(r_new, dE):
                        ok = False
                        for _ in range(self.backtracks):
                            alpha *= 0.5
                            x.copy(trial)
                            trial.axpy(alpha, du)
                            if judged:
                                r_new, E_new, dE = judge()
                            else:
                                r_new = pb.evaluate_residual(trial)
                                if merit is not None:
                                    E_new, dE = potential()
                            if better(r_new, dE):
                                ok = True
                                break
                rec = PseudoTimeRecord(its, k, alpha, r_new, ok)
                self.history.append(rec)
                if self.on_step is not None:
                    self.on_step(rec, self)
                if not ok:
                    k *= self.shrink
                    in_a_row += 1
                    rhs.copy(pb.b)  # b holds F(x) again (rhs is F(x), not changed by the solve)
                    pb._update_u(x)
                    continue
                in_a_row = 0
                if resolved:
                    window = self.convex_window
                elif ahead:
                    window -= 1
                ratio = min(max(r / r_new, 1.0 / self.max_growth), self.max_growth)
                # dt grows after every accepted step, at least min_growth-fold: the residual of
                # a valve swinging shut rises and falls as the leaflets meet, and shrinking dt
                # when it rose let the demo crawl (no convergence in 1500 steps, README)
                k = max(min(k / ratio, k / self.min_growth), self.k_min * self.k0)
                trial.copy(x)
                r, E, held = r_new, E_new, None
            if not ramped and self.stop_reason:
                share = getattr(self.ramp, "share", None)
                self.stop_reason += ("; the prescribed motion is not complete" if share is None
                                     else f"; the prescribed motion reached {100 * share:.1f} %")
            self.weight = k
            converged = r <= max(self.atol, self.floor) and ramped
            self.at_floor = converged and r > self.atol
            if self.at_floor:
                log.debug(f"    converged at the roundoff floor: residual {r:.3g} <= "
                          f"{self.floor:.3g} (tolerance {self.atol:.3g})")
            return SolveInfo(converged, its, "CONVERGED_PSEUDO_TIME" if converged
                             else "DIVERGED_PSEUDO_TIME", r)
        finally:
            pb._update_u(x)
            for v in (x, trial, du, rhs):
                v.destroy()

    def restart_weight_after(self, weight: float, residual: float | None, r: float) -> float:
        """The weight (over ``k0``) of a restart at residual ``r``, the last restart's having
        been ``weight`` at ``residual`` (None: none yet): :attr:`restart_weight`, or where the
        last restart did not halve the residual :attr:`restart_growth` x its weight. From
        nearly the same state the same weight would repeat the last restart's path: the
        ringed patient valve on 1.5 mm went four times through the same 39 steps from
        residuals equal to six digits, then stopped; moving ten times slower the second
        time it converged (README, "The spread on finer meshes")."""
        if residual is not None and r > 0.5 * residual:
            return weight * self.restart_growth
        return self.restart_weight

    @property
    def accepted_steps(self) -> int:
        return sum(r.accepted for r in self.history)
