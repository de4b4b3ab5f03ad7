"""Run a scene: build the model, ramp the pressure with SNES, write the outputs.

Start-up of laws with zero stiffness at the stress-free state: every load step is solved with
the lumped proximal term ``k M (u - u_prev)`` (``u_prev`` the last converged state), which keeps
the tangent regular on a flat or slack membrane. At full load the term is removed (a direct
solve without it, or else reductions of ``k`` ending at zero): the reported state is an
equilibrium of the problem as posed, and ``summary.json`` gives its residual relative to the
pressure load.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from mpi4py import MPI

from mvfem import kernels
from mvfem.errors import InputError, Interrupted, SolverError
from mvfem.model import MAX_EXPONENT, Model, build_model, default_size, lumped_mass
from mvfem.scene import Scene, load_scene
from mvfem.solver import (LoadStepper, PseudoTimeRecord, PseudoTransient, SNESProblem, SolveInfo,
                          StepRecord, agree_on_stop, stop_asked, stop_cause,
                          stop_on_interrupt)

__all__ = ["solve", "Result", "check_converged", "coarse_levels"]

log = logging.getLogger(__name__)
_ids = itertools.count()
#: iteration budget of the solves that remove the stabiliser, x the scene's solver.max_it
REMOVAL_ITERATIONS = 4
#: largest displacement of one pseudo-time update, x the model's length scale (sqrt(area))
MAX_MOVE = 0.1
#: a prescribed motion's lifting of the interior brings no contact pair closer than this
#: fraction of its gap (_AdaptiveRamp)
LIFT_SQUEEZE = 0.5
#: default solver.max_steps of each method
MAX_STEPS = {"load-steps": 400, "pseudo-time": 1500}
#: on a sequenced level (a closed coarser state carried over), pseudo-time updates are solved
#: with the symmetric part of the tangent (MUMPS's LDL^T) while the weight is at least this x
#: the model's stabiliser scale (the weight of a start from the open state), with the exact
#: tangent (LU) below it: PseudoTransient.symmetric_above. Not from the open state, where the
#: slack membrane's tangent is far from symmetric (README, "Solving")
SYMMETRIC_ABOVE = 1.0
#: on a nested level (``mesh.refine``: a closed coarser level of the same mesh carried over),
#: the accepted updates after a convexified re-solve that are solved with the projected
#: contact blocks at once (PseudoTransient.convex_window). Only there: on the demo refined
#: twice 11 % less time at 16 pressures, on its 3 and 4 mm meshes refined twice about the
#: same, but on the 2 mm demo started from a 3, 4 or 5 mm closure (``solver.coarse_start``)
#: 10 % more steps, and from the open state nothing to gain (README, "Solving")
NESTED_CONVEX_WINDOW = 2
#: on a nested level, the first pseudo-time weight, x its start weight (which stays the
#: threshold of Newton's regime: PseudoTransient.k_first). Every nested level of the demo
#: refined twice at 8 pressures (15.5-17.25 kPa) refused its first two updates, at 1 and 4 x
#: the start weight (the transferred state's residual grew to 1e10-1e13), and took the first
#: at 16 x: from there the paths are the same, two steps a level fewer (README, "Solving")
NESTED_FIRST_WEIGHT = 16.0
#: a resumed run's state must have its held nodes (clamp, a completed motion's loop) this
#: close to where the scene holds them (mm); a run of the same scene has them there exactly
#: (to roundoff)
HELD_MISMATCH_MM = 1e-6
#: with a prescribed motion (a ring, annulus or papillary targets, ties drawn tight), the Fung
#: laws' exponent is continued linearly beyond this (``model.exponent_cap``) until the run has
#: converged; the true law then goes on from that state. A 36 mm ring on the dilated annulus
#: compresses the cells at the annulus to 0.62-0.64 along the fibres, exponents of 19 (3 mm
#: mesh) to 31 (2 mm): with the true law every update that moved the leaflets far overshot
#: there, and pseudo-time crept through the closure at dt ~ 5e-6 mm/Pa for 500-1100 steps
#: (the 2 mm ring with neochordae stopped at 1500). Capped there the leaflets close at about
#: the pace of the unrepaired valve: the 3 mm ring 265 + 19 steps instead of 825, the 2 mm ring with
#: neochordae 677 + 36 (caps of 5, 15 and 20: 455, 655 and 825 steps; README, "Repairs")
MOTION_CAP = 10.0


@dataclass(frozen=True)
class Settling:
    """How a load step settles in pseudo-time (see ``settle_solve`` in :func:`solve`).

    Attributes:
        tol: the step has settled when the proximal force is below ``tol`` x the pressure load
            (the current one, or the full one with ``full_load``).
        budget / final_budget: proximal solves per load step, and at the full load.
        moving_ok: an intermediate load step still moving after ``budget`` solves is accepted
            (its states are equilibria of the damped problem) instead of cut back.
        easy / easy_settled: the weight halves after a solve of at most ``easy`` Newton
            iterations (``easy_settled`` for the solve that settles the step).
        removal_from_current: remove the stabiliser starting from the current weight rather
            than the scene's.
    """

    tol: float = 0.05
    full_load: bool = False
    budget: int = 60
    final_budget: int = 60
    moving_ok: bool = False
    easy: int = 5
    easy_settled: int = 3
    removal_from_current: bool = False


#: membranes, chordae without contact: as verified in scripts/verification.py and the slow tests
SLACK = Settling()
#: with contact: settling against the full load (at the first few pascals the valve would
#: otherwise swing shut in steps of p/k: 600 Newton iterations for the first 16 Pa), and load
#: steps that may end while the leaflets still move (measured on the demo valve, README)
CONTACT = Settling(full_load=True, budget=30, final_budget=300, moving_ok=True, easy=8,
                   easy_settled=8, removal_from_current=True)
MAX_STIFFENING = 1e4
#: the proximal weight may shrink to this fraction of the scene's stabilisation while a slack
#: structure moves freely (pseudo-time steps grow)
MIN_WEIGHT = 1e-2



@dataclass
class Result:
    """What :func:`solve` returns.

    Attributes:
        summary: the content of summary.json.
        u: the displacement (dolfinx Function) of the last converged state.
        model: the composed problem (mesh, kinematics, regions).
        out: the output directory, or None.
    """

    summary: dict
    u: object
    model: Model
    out: Path | None
    fields: dict | None = None
    #: the closed surface (rank 0: x, triangles, leaflet names; None elsewhere) where it was
    #: compared with the coarser level's (``compared``, :func:`_compare_levels`); the next
    #: finer level reuses it
    closed: tuple | None = None
    compared: bool = False
    #: that comparison's per-facet distances (rank 0), for ``map_level_change.png``
    level_facets: np.ndarray | None = None

    @property
    def converged(self) -> bool:
        return bool(self.summary["converged"])


def _petsc_options(model: Model, load_norm: float) -> dict:
    s = model.scene["solver"]
    # absolute tolerances only, scaled by the full pressure load: a relative test would accept
    # any state 1e-6 below a huge first residual (a predictor up the exponential)
    opts = {"snes_rtol": 0.0, "snes_atol": s["tolerance"] * load_norm,
            "snes_max_it": s["max_it"]}
    if model.contact is not None:
        # line-search Newton, whose updates the contact scales back before a leaflet could
        # pass through another (SNESProblem's precheck); trust-region Newton has no such hook
        opts["snes_type"] = "newtonls"
        # the tangent leaves out the curvature of the contact distance, so the update need not
        # descend ||F||^2 (bt stopped with DIVERGED_LINE_SEARCH); l2 got further (README)
        opts["snes_linesearch_type"] = "l2"
    if s["linear_solver"] == "iterative":
        # GAMG failed from the slack start (disk, MNY); block-Jacobi ILU(1) converged there
        opts.update({"ksp_type": "gmres", "pc_type": "bjacobi", "sub_pc_type": "ilu",
                     "sub_pc_factor_levels": 1, "ksp_rtol": 1e-8, "ksp_max_it": 1000,
                     "ksp_gmres_restart": 200, "pc_factor_mat_solver_type": None})
    for k, v in (s["petsc_options"] or {}).items():
        opts[k] = v
    return {k: v for k, v in opts.items() if v is not None}


#: load parameter t in [0, 1] -> fraction of the pressure. A membrane's deflection grows like
#: p^(1/3) from the flat state, so the cubic ramp takes steps of similar displacement.
_RAMPS = {"linear": lambda t: t, "cubic": lambda t: t**3}
#: the load parameter of a share of the load (a resumed run's start, ``solve(resume=...)``)
_RAMP_INVERSES = {"linear": lambda f: f, "cubic": lambda f: f ** (1.0 / 3.0)}


class _Progress:
    """One line per load step on rank 0, for runs longer than a couple of seconds."""

    def __init__(self, model: Model, enabled: bool):
        self.model, self.enabled, self.t0 = model, enabled, time.perf_counter()
        self.quiet_until = 2.0

    def __call__(self, rec: StepRecord, stepper: LoadStepper) -> None:
        el = time.perf_counter() - self.t0
        p = _RAMPS[self.model.scene["solver"]["ramp"]](rec.load) * self.model.p_target
        msg = (f"  step {len(stepper.history):3d}  p = {p / 1e3:8.3f} kPa"
               f"  {'ok  ' if rec.converged else 'FAIL'} {rec.iterations:2d} it  {rec.reason:<26s}"
               f" {el:6.1f} s")
        if not rec.converged:
            log.info(msg + "  (cut back)")
        elif self.enabled and el > self.quiet_until:
            log.info(msg)
        else:
            log.debug(msg)


class _PseudoTimeProgress:
    """A line every couple of seconds of a pseudo-time run on rank 0 (every step with -v)."""

    def __init__(self, load_norm: float, enabled: bool):
        self.f, self.enabled, self.t0 = load_norm or 1.0, enabled, time.perf_counter()
        self.next = 2.0

    def __call__(self, rec: PseudoTimeRecord, ptc: PseudoTransient) -> None:
        el = time.perf_counter() - self.t0
        said = ("the potential rose" if np.isnan(rec.residual)
                else f"residual {rec.residual / self.f:9.3e} of the load")
        msg = (f"  pseudo-time step {rec.step:4d}  {said}  dt {1 / rec.weight:9.3g} mm/Pa"
               f"  step x {rec.alpha:5.3f}  {'ok    ' if rec.accepted else 'refused'} {el:6.1f} s")
        if self.enabled and rec.accepted and el >= self.next:
            self.next = el + 2.0
            log.info(msg)
        else:
            log.debug(msg)


def _load_norm(model: Model) -> float:
    """||f_p||: the pressure load at the current pressure, free dofs only."""
    from dolfinx import fem
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    b = fpetsc.assemble_vector(fem.form(model.load_form))
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    fpetsc.set_bc(b, model.bcs, scale=0.0)
    n = b.norm()
    b.destroy()
    return n


#: with no pressure (a prescribed motion the load, or nothing at all), tolerances are relative
#: to the load of this pressure (Pa) instead: a nominal force scale of the membrane
NOMINAL_PRESSURE = 1e3


def _load_scale(model: Model) -> float:
    """||f_p|| at the full pressure: the force scale of the tolerances. A scene without
    pressure (its load a prescribed motion, a ring at zero pressure say, or none: the state
    stays the reference one) takes the load of :data:`NOMINAL_PRESSURE` instead; a zero
    scale would make every tolerance zero (never met) and the progress line divide by it."""
    p = model.pressure.value.copy()
    model.pressure.value = model.p_target
    if abs(model.p_target) < 1e-12:
        model.pressure.value = NOMINAL_PRESSURE
    try:
        return _load_norm(model)
    finally:
        model.pressure.value = p


def _motion_ramp(model: Model):
    """Load parameter t -> (motion fraction, pressure fraction), or None without a prescribed
    motion; applies the motion. ``solver.motion = "before-pressure"`` moves everything over
    the first half of t at zero pressure, then raises the pressure."""
    if model.ramp is None:
        return None
    before = model.scene["solver"]["motion"] == "before-pressure"

    def apply(t: float) -> tuple[float, float]:
        fm, fp = (min(2 * t, 1.0), max(2 * t - 1, 0.0)) if before else (t, t)
        model.ramp(fm)
        return fm, fp
    return apply


class _AdaptiveRamp:
    """The prescribed motion over the pseudo-time steps, advancing with the accepted ones.

    PseudoTransient calls it before each step, refused ones too, until it returns True (the
    motion complete). The first steps of a valve are refused (wild updates from the slack
    start), and a ramp counted in them ran ahead of the state: the whole ring motion in one
    update with the interior frozen by the damping, cells crushed, no admissible step
    (measured on the dilated valve with a 36 mm ring). Here the motion advances by ``1 /
    solver.ramp_steps`` after an accepted step (growing 1.5-fold after easy ones, back to that
    share at most), and after a refused step the state goes back to where it was before the
    last call and the increment is halved.

    Each call lifts the interior onto the moved rim (``model.lift``) as far as the contact
    allows: no crossing, and no barrier pair brought closer than :data:`LIFT_SQUEEZE` of its
    gap (:meth:`mvfem.contact.Contact.squeeze_limit`). Where the lifting is cut short, the
    motion (rim, papillary tips, ties) is set back to the fraction it reached, so that the
    Dirichlet values are where the clamped nodes are: the update after it moves none of
    them, and its potential is compared with that of a state on the same boundary values.

    Until session 41 the lifting was bounded by the collision check alone and the motion's
    fraction was the one asked for: on the dilated valve with the 36 mm ring (3 mm mesh) the
    lifts brought two facing edges from 0.3 mm to 2e-10 mm, the clamped nodes lagged their
    Dirichlet values, every update's jump of them raised the potential and was refused down
    to dt = 1e-13, and after ``5 x ramp_steps`` calls the rest of the motion imposed at once
    sent the residual to 1e35 (README, "Repairs")."""

    def __init__(self, model: Model, motion, history):
        self.model, self.motion, self.history = model, motion, history
        self.base = 1.0 / max(model.ramp_steps, 1)
        self.inc = self.base
        #: the fraction of the motion the state is at (the lifted rim's, the tips', ties')
        self.share = 0.0
        self.seen = 0
        #: (share, u) before the last call (u None without a lifting: the state was not moved)
        self._saved: tuple[float, np.ndarray | None] | None = None
        self.before = model.scene["solver"]["motion"] == "before-pressure"
        #: the pseudo-time step whose call completed the motion (None before)
        self.completed_at: int | None = None

    def __call__(self, f: float) -> bool:
        m = self.model
        h = self.history()
        if len(h) > self.seen:  # the outcome of the step taken from the last call's state
            if h[-1].accepted:
                self.inc = min(self.inc * 1.5, self.base)
            else:
                self.inc *= 0.5
                if self._saved is not None:
                    self.share, u = self._saved
                    if u is not None:
                        m.u.x.array[:] = u
                        m.u.x.scatter_forward()
            self.seen = len(h)
        start = self.share
        share = min(start + self.inc, 1.0)
        if self.before and start < 0.5:  # the motion alone up to 0.5 (see _motion_ramp)
            share = min(share, 0.5)
        lifted = m.lift is not None
        self._saved = (start, m.u.x.array.copy() if lifted else None)
        _, fp = self.motion(share)
        if lifted:  # the interior follows the rim (the solver's u is the state)
            alpha = m.lift(squeeze=LIFT_SQUEEZE)
            if alpha < 1.0:
                share = start + alpha * (share - start)
                _, fp = self.motion(share)
        m.pressure.value = fp * m.p_target if self.before else m.p_target
        log.debug(f"    prescribed motion at {share:.4f} (from {start:.4f})")
        self.share = share
        if share >= 1.0:
            self.completed_at = len(h) + 1
        return share >= 1.0


def _max_exponent(model: Model) -> float:
    """Largest exponent of the Fung laws, each over its own region's cells (0 when there is
    none). (Each law over every cell, as until this stop, read 23.8 on the closed 1 mm demo
    where the largest exponent was 5.8.)"""
    from mvfem.fields import cell_values
    from mvfem.forms import exponent, is_exponential

    q = 0.0
    for r in model.regions:
        if is_exponential(r.law):
            vals = cell_values(exponent(r.law, model.kin, *r.constants.values(),
                                        tension_only=r.tension_only), model.mesh)
            if r.tag is not None:
                cells = model.surface.cell_tags.find(r.tag)
                vals = vals[cells[cells < len(vals)]]
            q = max(q, float(vals.max(initial=0.0)))
    return model.comm.allreduce(q, op=MPI.MAX)


def _remove_stabiliser(model, problem, stepper, step_solve, get_state, set_state, last_converged,
                       n_owned, k_start: float) -> tuple[bool, str]:
    """Solve the problem as posed (no proximal term) at full load, from the stabilised state.

    First directly; if that fails, by proximal solves each centred on the previous state with
    the weight reduced tenfold, or more gently (down to 1.5-fold) after a failed reduction,
    then k = 0. Returns (success, reason of a failure).
    """
    def attempt(k: float) -> SolveInfo:
        problem.set_proximal(k)
        last_converged[0] = model.u.x.array[:n_owned].copy()
        info = step_solve()
        log.debug(f"    removing the stabiliser: k = {k:9.3g}  {info.iterations:3d} it  "
                  f"{info.reason}")
        stepper.history.append(StepRecord(1.0, info.converged, info.iterations, info.reason))
        return info

    # Newton on the contact barrier converges linearly (its tangent leaves out the curvature
    # of the distance): these last solves get REMOVAL_ITERATIONS x the scene's max_it
    r, a, st, max_it = problem.snes.getTolerances()
    problem.snes.setTolerances(rtol=r, atol=a, stol=st, max_it=REMOVAL_ITERATIONS * max_it)
    try:
        return _remove(attempt, get_state, set_state, k_start)
    finally:
        problem.snes.setTolerances(rtol=r, atol=a, stol=st, max_it=max_it)


def _remove(attempt, get_state, set_state, k_start: float) -> tuple[bool, str]:
    saved = get_state()
    info = attempt(0.0)
    if info.converged:
        return True, ""
    set_state(saved)
    k, factor, floor = k_start, 10.0, k_start * 1e-7
    while factor >= 1.5:
        info = attempt(k / factor if k / factor > floor else 0.0)
        if info.converged:
            saved = get_state()
            if k / factor <= floor:
                return True, ""
            k /= factor
        else:
            set_state(saved)
            factor = factor ** 0.5
    return False, f"removing the start-up stabiliser failed at k = {k:.3g}: {info.reason}"


#: a run of load steps that stops short reports the last accepted step whose tolerance was at
#: most this fraction of its own load: an equilibrium of the pressure it reports. A step is
#: solved to ``solver.step_tolerance`` of the full load, so one under a millionth of it passes
#: with no iteration at all (the undeformed disk asked for 1e9 kPa was reported converged at
#: 996.9 kPa, its residual the whole load there). Such steps stay on the path (session 55
#: solved each to this fraction of its own load too, and a Fung disk with a small
#: ``solver.first_step`` then never settled its first steps: session 56); with the default
#: ramp and first step every step carries at least a thousandth of the full load
STEP_OWN_LOAD = 1e-3


def _load_steps(model: Model, problem: SNESProblem, s: dict, max_steps: int, load_norm: float,
                tight_atol: float, mass, centre, progress: bool, start: float = 0.0):
    """Ramp the pressure (from the load parameter ``start``: a resumed run's); every load step
    settles in pseudo-time with proximal solves, then the stabiliser is removed at full load.
    Returns (success, stop reason, load fraction reached, accepted steps, Newton
    iterations)."""
    u = model.u
    n_owned = u.vector.getLocalSize()
    ramp = _RAMPS[s["ramp"]]
    last_converged = [u.x.array[:n_owned].copy()]  # the proximal centre

    motion = _motion_ramp(model)
    t_now = [start]
    step_atol = max(tight_atol, s["step_tolerance"] * load_norm)
    # the last accepted step that is an equilibrium of its own load to STEP_OWN_LOAD (load
    # parameter, state): what a run that stops short reports (with a prescribed motion, the
    # last accepted step, whatever its load)
    reportable = [start, u.x.array[:n_owned].copy()]

    def set_load(t: float) -> None:
        t_now[0] = t
        if motion is None:
            model.pressure.value = ramp(t) * model.p_target
        else:  # prescribed motion with the load parameter (before the pressure: first half)
            f_motion, f_load = motion(t)
            model.pressure.value = ramp(f_load) * model.p_target
            if model.lift is not None:  # the interior follows the rim: a start for Newton
                model.lift()
        # an intermediate step is solved to step_tolerance of the full load (STEP_OWN_LOAD)
        problem.set_tolerances(atol=step_atol)

    def _share() -> float:
        """The load applied, as a fraction of the full load (a prescribed motion's parameter
        where there is no pressure: its nominal scale, _load_scale)."""
        if model.p_target != 0.0:
            return abs(float(model.pressure.value)) / abs(model.p_target)
        return t_now[0]

    def get_state() -> np.ndarray:
        return u.x.array.copy()

    def set_state(a: np.ndarray) -> None:
        u.x.array[:] = a
        u.x.scatter_forward()

    contact = model.contact
    policy = CONTACT if contact is not None else SLACK

    def step_solve() -> SolveInfo:
        centre.array[:] = last_converged[0]
        if not np.isfinite(problem.residual_norm()):  # a predictor that overshoots into overflow
            u.x.array[:n_owned] = last_converged[0]
            u.x.scatter_forward()
        return problem.solve()

    accepted = [last_converged[0].copy()]  # the load stepper's last accepted state
    k_min = model.stabiliser_scale * MIN_WEIGHT
    k_now = [model.stabiliser_scale]
    work = mass.duplicate()

    def prox_norm(k: float) -> float:  # ||k M (u - centre)||: the force of the proximal term
        u.vector.copy(work)
        work.axpy(-1.0, centre)
        work.pointwiseMult(work, mass)
        return k * work.norm()

    def settle_solve() -> SolveInfo:
        """A load step as pseudo-time: proximal solves, each centred on the previous one,
        until the proximal force is below ``policy.tol`` x the pressure load. The weight
        grows fourfold after a failed solve and halves after easy ones (down to MIN_WEIGHT x
        the scene's stabilisation). A slack structure (a valve swinging shut) thus moves at the
        pace its Newton iterations allow (:class:`Settling`)."""
        its, t_asm, t_sol = 0, 0.0, 0.0
        last_converged[0] = accepted[0].copy()
        share = _share()
        f_now = load_norm if policy.full_load else share * load_norm
        final = share >= 1 - 1e-12
        budget = policy.final_budget if final else policy.budget
        for inner in range(budget):
            k = k_now[0]
            problem.set_proximal(k)
            start = u.x.array[:n_owned].copy()
            info = step_solve()
            its += info.iterations
            log.debug(f"    pseudo-time {inner:2d}  k = {k:9.3g}  {info.iterations:3d} it  "
                      f"{info.reason}  scaled {problem.step_scalings}")
            t_asm += info.assembly_s
            t_sol += info.solve_s
            if not info.converged:
                if k >= model.stabiliser_scale * MAX_STIFFENING:
                    return SolveInfo(False, its, info.reason, info.residual_norm, t_asm, t_sol)
                k_now[0] = 4 * k
                u.x.array[:n_owned] = start if inner else last_converged[0]
                u.x.scatter_forward()
                continue
            if prox_norm(k) <= policy.tol * f_now:
                if info.iterations <= policy.easy_settled:
                    k_now[0] = max(k / 2, k_min)
                return SolveInfo(True, its, info.reason, info.residual_norm, t_asm, t_sol)
            if info.iterations <= policy.easy:
                k_now[0] = max(k / 2, k_min)
            last_converged[0] = u.x.array[:n_owned].copy()  # next solve centred here
        if policy.moving_ok and not final:  # still moving: go on under a larger load
            return SolveInfo(True, its, "MOVING", info.residual_norm, t_asm, t_sol)
        return SolveInfo(False, its, f"NOT_SETTLED after {budget} pseudo-time steps",
                         info.residual_norm, t_asm, t_sol)

    progress_line = _Progress(model, progress)

    def on_step(rec: StepRecord, stepper: LoadStepper) -> None:
        if rec.converged:
            last_converged[0] = u.x.array[:n_owned].copy()
            accepted[0] = last_converged[0].copy()
            if motion is not None or step_atol <= (1 + 1e-9) * STEP_OWN_LOAD * _share() \
                    * load_norm:
                reportable[:] = [rec.load, accepted[0]]
        progress_line(rec, stepper)

    # intermediate states need not be tight: the final state is (see _remove_stabiliser);
    # each step's tolerance is set with its load (set_load)
    stepper = LoadStepper(set_load, settle_solve, get_state, set_state,
                          first_step=s["first_step"], min_step=s["min_step"],
                          max_steps=max_steps, on_step=on_step,
                          # (an extrapolation could cross leaflets)
                          predictor=contact is None, comm=model.comm)
    if start > 0.0:
        set_load(start)  # (a resumed run's load: the start of the ramp and of its tolerances)
    reached, t_reached = stepper.run(1.0, start)
    if not reached and t_reached > reportable[0]:  # (the steps since carried almost no load)
        t_reached = reportable[0]
        u.x.array[:n_owned] = reportable[1]
        u.x.scatter_forward()
        set_load(t_reached)
    t_reached = ramp(t_reached)
    stop_reason = stepper.stop_reason
    final_ok = False
    if reached and stop_asked(model.comm):
        stop_reason = (f"stopped by {stop_cause()} after {len(stepper.history)} load steps, "
                       "at full load but before the start-up stabiliser was removed")
    elif reached:
        problem.set_tolerances(atol=tight_atol)
        final_ok, stop_reason = _remove_stabiliser(model, problem, stepper, step_solve, get_state,
                                                   set_state, last_converged, n_owned,
                                                   max(k_now[0], model.stabiliser_scale)
                                                   if policy.removal_from_current
                                                   else model.stabiliser_scale)
    return final_ok, stop_reason, t_reached, stepper.converged_steps, stepper.newton_iterations


def _method(model: Model) -> str:
    """The scene's solver.method, "auto" resolved: pseudo-time where chordae, contact or ties
    make the structure slack (it swings shut; not the hinges), else load steps."""
    method = model.scene["solver"]["method"]
    if method == "auto":
        slack = any(t is not None for t in (model.chordae, model.contact, model.ties))
        method = "pseudo-time" if slack else "load-steps"
    return method


def _coarse_size(scene: Scene):
    """The finest level of the scene's ``solver.coarse_start`` (mm), or None."""
    c = scene["solver"].get("coarse_start")
    return min(c) if isinstance(c, list) else c


def _nested(scene: Scene, model: Model) -> bool:
    """Whether ``scene`` is closed from the closure of its next coarser nested level: a refined
    valve (``mesh.refine``) with ``solver.nested``, solved in pseudo-time. A prescribed motion
    (a ring, ties, moved tips) ramps on the coarsest level, from the open state; each finer
    level starts from the closure below with the motion complete (:func:`_coarse_start`)."""
    return bool(scene["mesh"]["refine"] and scene["solver"]["nested"]
                and _method(model) == "pseudo-time")


def _dirichlet_values(model: Model) -> np.ndarray | None:
    """The displacements the Dirichlet conditions prescribe, at every node of the nodal view
    (rank 0; zero at free dofs; None elsewhere). Collective."""
    from dolfinx.fem import petsc as fpetsc

    if model.view is None:
        return None
    w = model.u.vector.duplicate()
    w.set(0.0)
    fpetsc.set_bc(w, model.bcs)
    values = model.view.gather(w.array_r)
    w.destroy()
    return values


def _level_by_level_hint(scene: Scene) -> str:
    """What a stop reason adds where a prescribed motion ramped on a generated valve's own
    mesh did not reach its capped equilibrium: the same number of cells closed level by level,
    the motion on a mesh of twice the size and the refined level started from its closure.
    On the patient valve with a 28 mm ring, 1 mm stopped at 1500 steps where 2 mm refined
    once (5744 cells against 5619) converged; the pathological valve with a 36 mm ring at 3
    mm refined twice, on its finest mesh alone, stopped at 1500 where level by level it
    converged (README "Repairs": "The spread on finer meshes", "Refined repairs, level by
    level"). Empty for a file's mesh or a refined one (already level by level)."""
    m = scene["mesh"]
    if m["generator"] != "valve" or m["refine"]:
        return ""
    size = m.get("size") or default_size(m)
    return (f"; to close it level by level, the motion on a coarser mesh, try "
            f"mesh.size={2 * size:g} with mesh.refine=1 (about as many cells; README "
            '"Refined repairs, level by level")')


def _coarse_start(scene: Scene, model: Model, comm, progress: bool, compare: bool = False,
                  coarse: Result | None = None) -> dict:
    """Close ``scene`` on its next coarser level and move its closed state onto ``model``
    (mvfem/sequence.py): the mesh refined once less (``mesh.refine``, nested levels), else the
    mesh of ``solver.coarse_start``. What happened, for summary.json ``coarse_start``. The
    coarser levels get their method's default ``max_steps`` and ``tolerance``, whatever the
    scene sets. A level with a prescribed motion (a ring, ties, moved tips), nested or
    sequenced, takes the motion complete, its own Dirichlet values at the clamped nodes
    (``motion_complete``); where the closure below is not used, the motion ramps from the open
    state as usual.

    ``compare``: the level's closure is kept for the comparison with this one's
    (:func:`_compare_levels`): its valve metrics (``LEVEL_METRICS``) go into the record, and
    the closed surface, privately, into ``_closed``. ``coarse``: that level already solved
    (:func:`_solve_to_accuracy`), used as it is."""
    import copy

    from mvfem.scene import _make
    from mvfem.sequence import UNFOLD_SWEEPS, transfer

    m = scene["mesh"]
    size = m.get("size") or default_size(m)
    raw = copy.deepcopy(scene.raw)
    raw.setdefault("mesh", {})
    nested = _nested(scene, model)
    if nested:
        level = int(m["refine"]) - 1
        raw["mesh"]["refine"] = level
        what = f"the valve refined {level} time(s)" if level else "the unrefined valve"
        head = {"refine": level, "nested": True}
    else:
        hc = float(_coarse_size(scene))
        where = f"{scene.source}: solver.coarse_start"
        if m["generator"] == "file":
            raise InputError(f"{where}: needs a generated mesh (mesh.generator), not a file")
        if hc <= size:
            raise InputError(f"{where}: {hc:g} mm is not coarser than the mesh ({size:g} mm)")
        if _method(model) != "pseudo-time":
            raise InputError(f"{where}: needs the pseudo-time method (a valve: chordae or "
                             "contact); load steps start from zero pressure")
        levels = scene["solver"]["coarse_start"]
        coarser = [h for h in levels if h > hc] if isinstance(levels, list) else []
        if coarser:  # the coarse solve starts from the next level in its turn
            raw["solver"]["coarse_start"] = coarser
        else:
            raw["solver"].pop("coarse_start", None)
        raw["mesh"]["size"] = hc
        raw["mesh"].pop("refine", None)
        what = f"a {hc:g} mm mesh"
        head = {"size_mm": hc}
    # a coarser level is a start, not the problem the scene poses: its method's own budget,
    # not the scene's solver.max_steps, which bounds the finest level (the 1 mm hard cases cap
    # it at 300, and the 2 mm demo level below takes 222-304 steps as roundoff moves its path);
    # and the default tolerance, not the scene's: a start closed less tightly costs the next
    # level what it saved (README, "Tried in session 35 and dropped"), so a looser
    # solver.tolerance stops the scene's own level earlier on the same path
    raw.get("solver", {}).pop("max_steps", None)
    raw.get("solver", {}).pop("tolerance", None)
    t0 = time.perf_counter()
    if coarse is not None:  # (solved before: its own wall time, then the transfer's)
        res = coarse
        t0 -= res.summary["wall_time_s"]
    else:
        if comm.rank == 0 and progress:
            log.info(f"coarse start: closing {what} first")
        try:
            res = solve(_make(raw, scene.source, scene.base_dir), comm=comm, progress=progress,
                        write=False, outputs=False, compare=compare)
        except Interrupted as e:  # (from a level below this one: said there)
            if e.result is None:
                raise
            raise Interrupted(f"stopped by {stop_cause()} while closing {what} "
                              f"({e.result.summary['cells']} cells) for a coarse start, before "
                              "the scene's own mesh; nothing written",
                              exit_code=e.exit_code) from None
    info = {**head, "converged": bool(res.converged),
            "steps": res.summary["newton_iterations"],
            "cells": res.summary["cells"], "wall_time_s": time.perf_counter() - t0}
    if compare and res.converged:
        info.update(_closed_level(res))
    if res.summary.get("coarse_start"):  # its own coarser start, included in wall_time_s
        info["coarser"] = res.summary["coarse_start"]
    # a prescribed motion is complete in the closure below (a nested level's, or a coarser
    # mesh's): this level starts with it complete (its Dirichlet values, tips and ties), or
    # ramps it from the open state if that start is not used
    moving = model.ramp is not None
    if not res.converged:
        info.update(used=False, reason="the coarse solve stopped short")
    else:
        clamp = None
        if moving:
            model.ramp(1.0)
            clamp = _dirichlet_values(model)
        info.update(transfer(res.model, model, sweeps=UNFOLD_SWEEPS if nested else 0,
                             clamp=clamp))
        if moving and not info["used"]:
            model.ramp(0.0)
    if moving:
        info["motion_complete"] = bool(info["used"])
    if comm.rank == 0:
        fine = f"{model.mesh.topology.index_map(2).size_global} cells" if nested \
            else f"the {size:g} mm mesh"
        line = (f"coarse start: {info['steps']} steps, {info['wall_time_s']:.1f} s; continuing "
                f"on {fine} ")
        if info["used"]:
            if progress:
                how = ""
                if info.get("unfolded"):
                    how = (f", smoothed where {info['crossings']} edge(s) crossed a triangle "
                           f"({info['unfolded']} sweep(s))")
                elif info.get("scale", 1.0) != 1.0:
                    how = (f" x {info['scale']:g} (as moved, {info['crossings']} edge(s) "
                           "crossed a triangle)")
                log.info(line + "from its closed state" + how)
        else:
            log.warning(line + f"from the open state ({info['reason']})")
    return info


class _RaiseCap:
    """Pseudo-time progress that raises the Fung laws' exponent cap to MAX_EXPONENT once every
    cell has relaxed below 0.9 x the start's (mvfem/sequence.py)."""

    def __init__(self, inner, model: Model, info: dict):
        self.inner, self.model, self.info = inner, model, info

    def __call__(self, rec: PseudoTimeRecord, ptc: PseudoTransient) -> None:
        self.inner(rec, ptc)
        if rec.accepted and float(self.model.exponent_cap.value) != MAX_EXPONENT \
                and _relaxed(self.model, float(self.model.exponent_cap.value)):
            self.model.exponent_cap.value = MAX_EXPONENT
            self.info["cap_raised_at_step"] = rec.step


#: the valve metrics of each coarser level that summary.json records (``coarse_start``)
LEVEL_METRICS = ("coaptation_length_mm", "coaptation_trace_length_mm", "coaptation_area_mm2",
                 "tenting_height_mm", "regurgitant_orifice_area_mm2")


def _closed_level(res: Result) -> dict:
    """A coarser level's closure for the comparison with the next finer one (collective): its
    valve metrics (``valve``: ``LEVEL_METRICS``, where the scene is a valve) and its closed
    surface (``_closed``; rank 0, None elsewhere; the one its own comparison made, else
    made now)."""
    from mvfem.distance import _deformed_surface
    from mvfem.outputs import _point_outputs

    rec = {"_closed": res.closed if res.compared else _deformed_surface(res.model)}
    v = _point_outputs(res.model, contact=False).get("valve")
    if v:
        rec["valve"] = {k: v.get(k) for k in LEVEL_METRICS}
    return rec


def _compare_levels(result: Result, seq: dict, converged: bool) -> None:
    """Where the coarser level's closure was kept (``seq["_closed"]``, :func:`_coarse_start`),
    record how far this level's closure lies from it (``seq["distance_to_finer_mm"]``:
    :func:`mvfem.distance.level_change`) and keep this closure (``result.closed``) for the
    next finer level. Collective; nothing where either level stopped short."""
    from mvfem.distance import _deformed_surface, level_change

    coarser = seq.pop("_closed")
    if not converged:
        return
    comm = result.model.comm
    result.closed, result.compared = _deformed_surface(result.model), True
    block = None
    if comm.rank == 0:
        block, result.level_facets = level_change(result.closed, coarser)
    seq["distance_to_finer_mm"] = comm.bcast(block, root=0)


def coarse_levels(summary: dict) -> list[dict]:
    """summary.json ``coarse_start`` as a list of the coarser levels' records, the next coarser
    first (each record's ``coarser`` is the one after it); empty without a coarser start."""
    levels, cs = [], summary.get("coarse_start")
    while cs:
        levels.append(cs)
        cs = cs.get("coarser")
    return levels


def _relaxed(model: Model, cap: float) -> bool:
    """Whether every cell's Fung exponent is below 0.9 x ``cap`` (the cap in force: the
    sequenced start's, or a prescribed motion's), where the capped law is the true one."""
    return _max_exponent(model) < 0.9 * cap


def solve(scene: Scene | dict | str, out: str | Path | None = None, comm=MPI.COMM_WORLD,
          progress: bool = True, write: bool = True,
          initial: np.ndarray | None = None, outputs: bool = True,
          compare: bool | None = None, resume: str | Path | None = None) -> Result:
    """Solve ``scene`` (collective on ``comm``); write outputs to ``out`` when given.

    ``resume``: the output directory of an earlier run of the same mesh (one that stopped
    short, was stopped by Ctrl-C, or converged at another pressure): the solve starts from the
    state written there (:func:`mvfem.outputs.read_state`), on the scene's own mesh alone (no
    coarser levels), load steps from the pressure that run reached (a pseudo-time run at the
    full pressure in any case). A prescribed motion only where that run had completed it
    (pseudo-time: the motion then at its end from the start), and its held nodes where this
    scene holds them; not with ``mesh.accuracy``.

    ``initial``: a warm start, the local displacement array (``result.u.x.array``) of an earlier
    solve of the same mesh on the same ranks, e.g. the previous evaluation of a calibration. It
    is ignored when the scene prescribes a boundary motion (that ramp starts from the open
    state) or when its length does not match.

    ``outputs=False``: the summary keeps the solver's entries only (no displacement, regions,
    probes, contact, valve metrics nor reference step; nothing written): for the coarser
    levels of a nested or sequenced start, whose closed state alone the finer level uses
    (their metrics took 0.8 of the 44 s of the demo refined twice, README "Speed against
    error").

    ``compare`` (default: ``outputs``; never where the scene sets ``output.levels = false``):
    each coarser level of a nested or sequenced start records its valve metrics and how far
    its closure lies from the next finer level's (summary.json ``coarse_start``: ``valve``,
    ``distance_to_finer_mm``; ``timing.level_change_s``, part of ``other_s``; README "Each
    refined run measures its own mesh error"), and the outputs add ``map_level_change.png``.

    Raises:
        InputError: the scene is invalid (nothing is written; an ``out`` this call made is
            removed again: :func:`mvfem.outputs.given_back_if_unused`).
    Returns:
        A :class:`Result`; ``result.converged`` is False when the solver stopped short, in which
        case the last converged state is what the outputs show.

    OpenBLAS runs on one thread meanwhile (:func:`mvfem.kernels.one_blas_thread`; its count
    is given back afterwards): its idle thread spins (``sched_yield``) between MUMPS's calls,
    on the core that the compiled kernels' second thread or another run needs. MUMPS's
    factorisation of the twice-refined demo's 28,548-dof tangent is no slower on one thread
    (0.44-0.46 against 0.47-0.51 s), a run alone costs the same a step, and the CPU it burns
    falls by a third (README "Threads that wait, asleep", session 36).
    """
    from mvfem.outputs import given_back_if_unused

    with kernels.one_blas_thread(), given_back_if_unused():
        scene = load_scene(scene)
        if scene["mesh"]["accuracy"] is not None:
            if resume is not None:
                raise InputError(f"--resume {resume}: {scene.source} asks for mesh.accuracy, "
                                 "which closes the valve level by level from the open state; "
                                 "resume a run of one mesh (mesh.refine)")
            return _solve_to_accuracy(scene, out, comm, progress, write, outputs)
        return _solve(scene, out, comm, progress, write, initial, outputs,
                      outputs if compare is None else compare, resume=resume)


def _solve_to_accuracy(scene: Scene, out, comm, progress: bool, write: bool,
                       outputs: bool) -> Result:
    """``mesh.accuracy``: close the valve level by level, the unrefined mesh first and each
    finer level from the closure below (nested levels, bottom up), until the last refinement
    moved the closure by at most ``mesh.accuracy`` on average (``distance_to_finer_mm``:
    :func:`_compare_levels`) or ``mesh.refine`` refinements are made. Only the level it
    stops at writes outputs; summary.json ``accuracy`` says which and whether the target was
    met. A finer mesh is built only where the level below missed the target (the demo at 2
    mm: 0.1 mm stops refined once, 12 s, 0.05 mm twice, 26 s; README "A mesh chosen by
    accuracy"). Every level is closed to the scene's solver settings (any may be the last);
    no warm start."""
    import copy

    from mvfem.distance import last_move
    from mvfem.scene import _make

    target, cap = float(scene["mesh"]["accuracy"]), int(scene["mesh"]["refine"])
    if not scene["solver"]["nested"]:
        raise InputError(f"{scene.source}: mesh.accuracy: needs nested levels "
                         "(solver.nested = true)")
    if not scene["output"]["levels"]:
        raise InputError(f"{scene.source}: mesh.accuracy: needs the levels measured "
                         "(output.levels = true)")
    prev = None
    for level in range(cap + 1):
        raw = copy.deepcopy(scene.raw)
        raw["mesh"].pop("accuracy", None)
        raw["mesh"]["refine"] = level
        sc = _make(raw, scene.source, scene.base_dir)

        def more(r: Result, level=level) -> bool:
            """Whether a finer level is needed after ``r`` (and, where not, the summary's
            ``accuracy``)."""
            d = last_move(r.summary)
            if level > 0 and r.converged and d is None:   # (one stopped short has none)
                raise InputError(f"{scene.source}: mesh.accuracy: needs nested levels "
                                 "(a valve solved in pseudo-time)")
            # a level that stopped short ends the run there: its last state, exit code 3
            go = r.converged and level < cap and (level == 0 or d["mean_mm"] > target)
            if not go:
                r.summary["accuracy"] = {
                    "target_mm": target, "refine": level, "most_refine": cap,
                    "moved_mm": None if d is None else d["mean_mm"],
                    "met": bool(r.converged and d is not None and d["mean_mm"] <= target)}
            return go

        prev = _solve(sc, out, comm, progress, write, None, outputs, True, coarse=prev,
                      more=more)
        if "accuracy" in prev.summary:
            return prev
    raise AssertionError("unreachable: the last level always stops")


#: seconds of a quiet phase (set-up, outputs) before a line says what is going on
SLOW_NOTICE_S = 1.5


class _Notice:
    """``text`` logged at most once, when a quiet phase watched by :meth:`watch` is still
    running :data:`SLOW_NOTICE_S` seconds on (rank 0, with progress). A first run of a law or a mesh
    kind compiles its forms and C kernels: on the demo 4.7 s of set-up and 4 s of outputs
    in which the terminal would otherwise stay quiet. Cached, the demo's set-up and outputs
    take 0.7-0.8 s (no line); the refined demo's outputs 1.9 s (the line)."""

    def __init__(self, comm, progress: bool, text: str):
        self.on = comm.rank == 0 and progress
        self.text, self.said = text, False

    def _say(self) -> None:
        self.said = True
        log.info(self.text)

    @contextlib.contextmanager
    def watch(self):
        timer = None
        if self.on and not self.said:
            timer = threading.Timer(SLOW_NOTICE_S, self._say)
            timer.daemon = True
            timer.start()
        try:
            yield
        finally:
            if timer is not None:
                timer.cancel()


def _solve(scene, out, comm, progress: bool, write: bool, initial, outputs: bool,
           compare: bool, coarse: Result | None = None,
           more: Callable[[Result], bool] | None = None, resume=None) -> Result:
    """:func:`solve`'s body. ``coarse``: the next coarser level already closed (nested
    levels); ``more(result)``: called before the outputs, True where a finer level follows,
    and then none are made (:func:`_solve_to_accuracy`); ``resume``: :func:`solve`'s."""
    from mvfem.outputs import prepare_out_on_root, write_outputs

    t_start = time.perf_counter()
    # a coarser level solved before is this run's time, as one solved here is
    t_before = coarse.summary["wall_time_s"] if coarse is not None else 0.0
    scene = load_scene(scene)
    compare = compare and bool(scene["output"]["levels"])
    if out is not None:
        prepare_out_on_root(out, comm)
    setting_up = _Notice(comm, progress, "  setting up the model ... (a first run also "
                         "compiles its forms and kernels, cached afterwards)")
    with setting_up.watch():
        model = build_model(scene, comm)
        if outputs and scene["output"]["probes"]:
            from mvfem.outputs import check_probes_reach

            check_probes_reach(model, scene["output"]["probes"], scene.source)
        resumed = None
        if resume is not None:
            resumed = _resume(scene, model, resume)
            initial = None
    t_build = time.perf_counter() - t_start
    seq = None
    if resumed is None and (_nested(scene, model) or _coarse_size(scene) is not None):
        seq = _coarse_start(scene, model, comm, progress, compare, coarse=coarse)
    if seq is not None and seq["used"]:
        initial = None
    if initial is not None and not model.motion and len(initial) == len(model.u.x.array):
        model.u.x.array[:] = initial
        model.u.x.scatter_forward()
    s = scene["solver"]
    load_norm = _load_scale(model)
    model.pressure.value = 0.0
    with setting_up.watch():  # (not the coarser levels above: they say their own)
        try:
            problem = SNESProblem(model.residual, model.u, model.bcs,
                                  prefix=f"mvfem{next(_ids)}_",
                                  options=_petsc_options(model, load_norm),
                                  point_terms=model.point_terms, potential=model.energy,
                                  load=model.load_form, sparsity=model.sparsity)
        except ValueError as e:
            raise InputError(f"{scene.source}: solver.petsc_options: {e}") from None
        mass = lumped_mass(model)
    u = model.u
    centre = u.vector.copy()
    problem.set_proximal(model.stabiliser_scale, weights=mass, centre=centre)
    tight_atol = s["tolerance"] * load_norm
    method = _method(model)
    max_steps = s["max_steps"] or MAX_STEPS[method]
    if resumed is not None:
        if model.motion:  # completed in the run resumed (_resume): at its end from the start
            _motion_ramp(model)(1.0)
        off = _held_mismatch(model)
        if off > HELD_MISMATCH_MM:
            raise InputError(f"--resume {resumed['directory']}: the state there has nodes up "
                             f"to {off:.3g} mm from where {scene.source} holds them (its clamp, "
                             "ring or annulus target differ: a run of another scene?)")
    if comm.rank == 0 and progress:
        log.info(f"{scene.data['title'] or scene.source}: {model.V.dofmap.index_map.size_global * 3} "
                 f"dofs, pressure {model.p_target / 1e3:g} kPa, {method}")
    ptc = hook = cap_raised_at = None
    capped_stop = False
    # Ctrl-C or SIGTERM stops at the next step; the last accepted state is written
    # (stop_on_interrupt)
    with stop_on_interrupt(comm) as stop:
        if method == "pseudo-time":
            model.pressure.value = model.p_target
            # a sequenced level's Newton's regime begins 1e4 x above the usual start's weight:
            # the symmetric tangent's cheaper factorisation down to that (SYMMETRIC_ABOVE)
            sequenced = seq is not None and seq["used"]
            motion = _motion_ramp(model)
            if motion is not None and resumed is not None:
                # the run resumed had completed its motion (_resume; at its end, set above):
                # the laws' exponent capped as it still was there
                model.exponent_cap.value = MOTION_CAP if resumed["motion_capped"] \
                    else MAX_EXPONENT
            elif motion is not None and not sequenced:  # (a sequenced level's is complete)
                hook = _AdaptiveRamp(model, motion, lambda: ptc.history)
                model.exponent_cap.value = MOTION_CAP
            on_step = _PseudoTimeProgress(load_norm, progress)
            k0 = model.stabiliser_scale
            sym_above = SYMMETRIC_ABOVE * model.stabiliser_scale
            if sequenced:
                from mvfem.sequence import START_CAP, START_WEIGHT

                model.exponent_cap.value = START_CAP
                on_step = _RaiseCap(on_step, model, seq)
                k0 *= START_WEIGHT
            nested = bool(sequenced and seq.get("nested"))
            window = NESTED_CONVEX_WINDOW if nested else 0
            k_first = NESTED_FIRST_WEIGHT * k0 if nested else None
            going_on = (resumed or {}).get("pseudo_time")
            if going_on:
                # the run goes on as it was: its weight, Newton's regime's threshold and
                # tangents (from a state near the closure a start at the open state's weight
                # crawled: the demo refined twice 147 finest steps after 10, against 44)
                k0 = going_on["threshold"] * model.stabiliser_scale
                k_first = going_on["weight"] * model.stabiliser_scale
                sequenced, window = bool(going_on["symmetric"]), int(going_on["convex_window"])
            ptc = PseudoTransient(problem, k0=k0, atol=tight_atol, symmetric=sequenced,
                                  convex_window=window, k_first=k_first,
                                  symmetric_above=sym_above, max_steps=max_steps, on_step=on_step,
                                  max_move=MAX_MOVE * model.length_scale, ramp=hook,
                                  ramp_steps=max_steps if hook is not None else 0,
                                  load=load_norm)
            info = ptc.run()
            load_steps, newton_its = ptc.accepted_steps, len(ptc.history)
            convexified, symmetric = ptc.convexified, ptc.symmetric_solves
            cap = float(model.exponent_cap.value)
            if cap != MAX_EXPONENT:
                # the soft-capped problem's equilibrium: the true one only where no cell is
                # beyond the cap; else go on with the true cap from here
                relaxed = _relaxed(model, cap)
                model.exponent_cap.value = MAX_EXPONENT
                if seq is not None:   # (None: stopped with it capped, as motion's below)
                    seq["cap_raised_at_step"] = newton_its if info.converged else None
                cap_raised_at = newton_its
                # stopped short of the capped problem's equilibrium: a resumed run goes on
                # with the cap (summary.json motion.exponent_capped, _resume)
                capped_stop = not info.converged
                # (outputs: the scene's own level; a coarser level of a start is solved
                # without them, and its stop is not the one a user reads)
                if capped_stop and hook is not None and outputs and not ptc.interrupted:
                    ptc.stop_reason += _level_by_level_hint(scene)
                if hook is not None and comm.rank == 0 and progress and info.converged:
                    log.info(f"  converged with the Fung laws' exponent capped at {cap:g} "
                             f"(step {newton_its}); " + ("no cell is near the cap" if relaxed else
                                                         "the true law goes on from there"))
                if info.converged and not relaxed:
                    ptc = PseudoTransient(problem, k0=model.stabiliser_scale, atol=tight_atol,
                                          symmetric=sequenced, symmetric_above=sym_above,
                                          convex_window=window,
                                          max_steps=max(max_steps - newton_its, 1),
                                          on_step=_PseudoTimeProgress(load_norm, progress),
                                          max_move=MAX_MOVE * model.length_scale,
                                          load=load_norm)
                    info = ptc.run()
                    load_steps += ptc.accepted_steps
                    newton_its += len(ptc.history)
                    convexified += ptc.convexified
                    symmetric += ptc.symmetric_solves
                    if hook is not None and not info.converged and not ptc.interrupted:
                        # a 32 mm ring on the dilated valve: capped equilibrium at step 433, then
                        # the true law's exponent 42.5 at the annulus, a tangent whose diagonal
                        # spans 8e15, and 1067 steps at dt ~ 1e-14 mm/Pa (README, "Repairs")
                        ptc.stop_reason += (
                            f"; it had converged with the Fung laws' exponent capped at "
                            f"{cap:g} (step {cap_raised_at}), but with the true law the "
                            f"largest exponent is {_max_exponent(model):.1f}: the prescribed "
                            f"motion compresses or stretches cells far beyond the law's range "
                            f"(a ring too small for this annulus? fibres that bear tension only: "
                            f"region.fibre_compression = false)")
            final_ok, stop_reason, t_reached = info.converged, ptc.stop_reason, 1.0
        else:
            start = 0.0
            if resumed is not None and model.p_target != 0.0:  # from the pressure it reached
                share = resumed["pressure_Pa"] / model.p_target
                start = _RAMP_INVERSES[s["ramp"]](min(share, 1.0)) if share > 0 else 0.0
            final_ok, stop_reason, t_reached, load_steps, newton_its = _load_steps(
                model, problem, s, max_steps, load_norm, tight_atol, mass, centre, progress,
                start)
    # (every rank the same: a signal may have reached one after the steps' last check)
    asked = agree_on_stop(comm)
    problem.set_proximal(0.0)
    r_norm, f_norm = problem.residual_norm(), _load_norm(model)
    if abs(model.p_target) < 1e-12:
        f_norm = load_norm  # no pressure: the nominal scale the tolerances used
    rel = r_norm / f_norm if f_norm > 0 else r_norm
    q_max = _max_exponent(model)
    if final_ok and q_max >= MAX_EXPONENT:
        final_ok, stop_reason = False, (f"the exponential law reached its exponent cap "
                                        f"({q_max:.0f}): no physical equilibrium")
    # a pseudo-time run may end on its roundoff floor, above the tolerance (PseudoTransient)
    floor = ptc.floor / f_norm if ptc is not None and ptc.at_floor and f_norm > 0 else 0.0
    converged = bool(final_ok and np.isfinite(rel) and rel <= 10 * max(s["tolerance"], floor))
    if final_ok and not converged:
        stop_reason = (f"equilibrium residual {rel:.3g} of the load exceeds 10 x the tolerance "
                       f"{s['tolerance']:g}")
    result = Result(summary={}, u=u, model=model, out=Path(out) if out else None)
    t_compare = None
    if seq is not None and "_closed" in seq:
        t_compare = time.perf_counter()
        _compare_levels(result, seq, converged)
        t_compare = time.perf_counter() - t_compare
    wall = time.perf_counter() - t_start + t_before
    # disjoint: the point terms' share is taken out of the assembly and SNES times
    pt = model.point_terms
    t_pt, t_lim = (pt.time_s, pt.limit_s) if pt else (0.0, 0.0)
    # SNES's time includes the precheck's step limits; the pseudo-time loop times its solves
    t_linear = ptc.solve_s if ptc is not None else problem.solve_s - t_lim
    timing = {"assembly_s": problem.assembly_s - t_pt, "linear_solve_s": t_linear,
              "contact_s": t_pt + t_lim, "build_s": t_build}
    if t_compare is not None:
        timing["level_change_s"] = t_compare
    if comm.rank == 0 and not converged and not asked:  # (a signal: _interrupted says it)
        log.warning(f"solver stopped short at p = {t_reached * model.p_target / 1e3:.4g} kPa "
                    f"({stop_reason}); the last converged state is kept")
    summary = {
        "converged": converged,
        "wall_time_s": wall,
        "dofs": model.V.dofmap.index_map.size_global * model.V.dofmap.index_map_bs,
        "cells": model.mesh.topology.index_map(2).size_global,
        "load_steps": load_steps,
        "newton_iterations": newton_its,
        "method": method,
        "pressure_Pa": (model.p_target if converged else t_reached * model.p_target),
        "target_pressure_Pa": model.p_target,
        "equilibrium_residual": rel,
        "stop_reason": stop_reason,
        # Ctrl-C or SIGTERM stopped it short (stop_on_interrupt): a study makes it again
        "interrupted": bool(asked and not converged),
        "timing": timing,
    }
    if ptc is not None:
        summary["convexified_tangents"] = convexified
        summary["symmetric_tangents"] = symmetric
        if ptc.weight is not None:  # where a resumed run starts, and how it goes on (_resume)
            scale = model.stabiliser_scale
            summary["pseudo_time"] = {"weight": ptc.weight / scale, "threshold": ptc.k0 / scale,
                                      "symmetric": ptc.symmetric,
                                      "convex_window": ptc.convex_window}
        if ptc.at_floor:  # converged where roundoff alone gives the residual (above tolerance)
            summary["residual_floor"] = floor
            if comm.rank == 0:
                log.info(f"  converged at the roundoff floor: residual {rel:.3g} of the load, "
                         f"above the tolerance {s['tolerance']:g}, is what roundoff of the "
                         f"positions gives at this stiffness ({floor:.3g})")
    if model.motion:
        summary["motion"] = {**model.motion, "ramp_steps": model.ramp_steps,
                             "order": s["motion"], "exponent_capped": capped_stop}
        # the step after which the laws' exponent was no longer capped (MOTION_CAP); None
        # where the run stopped with it capped (its final residual is the true law's all the
        # same; until session 60 such a stop gave its last step here)
        raised = None if capped_stop else cap_raised_at
        if hook is not None:  # the pseudo-time step whose call completed it (None: it did not)
            summary["motion"]["completed_at_step"] = hook.completed_at
            summary["motion"]["cap_raised_at_step"] = raised
        elif resumed is not None:  # complete from the start: in the state resumed
            summary["motion"]["completed_at_step"] = 0
            summary["motion"]["resumed_complete"] = True
            # (0: the law was no longer capped when the run resumed started)
            summary["motion"]["cap_raised_at_step"] = raised if resumed["motion_capped"] else 0
        elif seq is not None and seq.get("motion_complete"):
            # complete from the start: ramped on the coarsest level (coarse_start's records)
            summary["motion"]["completed_at_step"] = 0
            summary["motion"]["on_coarser_level"] = True
    if seq is not None:
        summary["coarse_start"] = seq
    if resumed is not None:
        summary["resumed_from"] = resumed
    result.summary = summary
    # (after a stop signal no finer level follows: this level's state is the one to write)
    if outputs and not (more is not None and not asked and more(result)):
        with _Notice(comm, progress, f"  {'converged' if converged else 'stopped short'}; "
                     "computing stresses, strains and metrics ... (a first run also "
                     "compiles their forms, cached afterwards)").watch():
            write_outputs(result, problem, write=write and out is not None)
    problem.destroy()
    if asked:
        raise _interrupted(result, bool(outputs and write and out is not None), stop)
    return result


def _resume(scene: Scene, model: Model, directory) -> dict:
    """Start from the state an earlier run of this mesh wrote in ``directory``; what summary.json
    ``resumed_from`` records of it (collective)."""
    from mvfem.outputs import read_state

    if model.motion and _method(model) != "pseudo-time":
        raise InputError(f"--resume {directory}: {scene.source} prescribes a boundary motion "
                         "ramped with the load steps from the open state: it cannot resume")
    written = read_state(model, directory)
    went = {"directory": str(directory), "pressure_Pa": float(written.get("pressure_Pa") or 0.0),
            "converged": bool(written.get("converged")),
            "newton_iterations": written.get("newton_iterations"),
            "pseudo_time": written.get("pseudo_time")}
    if model.motion:
        # a motion completed there goes on at its end (_solve); one not completed does not:
        # the path through the motion picks which of the valve's equilibria it closes to, and
        # a run resumed part way (tried in session 58: the share reached and the ramp's
        # increment written, the rim set there, the lifting in the state) took another path
        # to another closure, up to 5.5 mm (mean 0.94 mm) from the uninterrupted run's on the
        # 4 mm pathological valve with a 36 mm ring, where a run from the open state repeats
        # its own to the bit (README, "Resuming a run")
        done = (written.get("motion") or {})
        if done.get("completed_at_step") is None:
            raise InputError(f"--resume {directory}: {scene.source} prescribes a boundary "
                             "motion that the run there had not completed (or had none): run "
                             "it again from the open state (the path through the motion "
                             "picks the closure; part way, a resume would take another)")
        # the laws' exponent still capped there (a run stopped before the capped problem's
        # equilibrium). Not recorded before session 57: then capped where the cap was never
        # raised, though such a stop recorded the cap raised at its last step (a resume with
        # the true law converges too: the 4 mm ring stopped at 120 of 227 steps, in 236)
        went["motion_capped"] = bool(done.get("exponent_capped",
                                          done.get("cap_raised_at_step") is None))
    return went


def _held_mismatch(model: Model) -> float:
    """The largest difference (mm, any component) between a held dof of the state and the
    value the scene's Dirichlet conditions hold it at, as now set (a clamp, a ring's or an
    annulus target's loop, rigid pins). Collective."""
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    gap = model.u.vector.duplicate()
    gap.set(0.0)
    fpetsc.set_bc(gap, model.bcs, x0=model.u.vector, scale=1.0)  # g - u on the held dofs
    off = gap.norm(PETSc.NormType.INFINITY)
    gap.destroy()
    return float(off)


def _interrupted(result: Result, written: bool, stop) -> Interrupted:
    """What Ctrl-C or SIGTERM ended (``stop``, the request of
    :func:`mvfem.solver.stop_on_interrupt`), to raise once the outputs are written."""
    s = result.summary
    where = f"written in {result.out}" if written else "not written"
    if s["converged"]:
        return Interrupted(f"{stop.name} came as the run converged; its results are {where}",
                           result, written, stop.exit_code)
    again = _resume_hint(result) if written else ""
    return Interrupted(f"{s['stop_reason']}; the last accepted state (at "
                       f"{s['pressure_Pa'] / 1e3:.4g} kPa, not converged: residual "
                       f"{s['equilibrium_residual']:.3g} of the load) is {where}{again}",
                       result, written, stop.exit_code)


def _resume_hint(result: Result) -> str:
    """How to go on from the state a run wrote (where it wrote one to start from)."""
    if result.out is None or not (Path(result.out) / "fields.h5").is_file():
        return ""
    motion = (result.summary or {}).get("motion")
    if motion and motion.get("completed_at_step") is None:  # (_resume refuses it)
        return ""
    return f" (--resume {result.out} goes on from it)"


def check_converged(result: Result) -> None:
    """Raise :class:`SolverError` (exit code 3) for a run that stopped short."""
    if not result.converged:
        s = result.summary
        again = f" in {result.out}{_resume_hint(result)}" if result.out is not None else ""
        raise SolverError(f"stopped at {s['pressure_Pa'] / 1e3:.4g} kPa of "
                          f"{s['target_pressure_Pa'] / 1e3:.4g} kPa: {s['stop_reason']}; "
                          f"last converged state written{again}")
