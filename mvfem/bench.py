"""Speed against error (issue 7): reference problems swept over discretisation and solver.

``mvfem bench [--quick] --out DIR`` (or :func:`run_bench`) solves three reference problems at
several settings and measures each quantity of interest against a reference that the code
being timed did not compute at that setting:

- ``foppl``: clamped St Venant-Kirchhoff disk (radius 10 mm, E 400 kPa, nu 1/2, h 1 mm) under a
  1 Pa dead load; centre deflection against Hencky's closed form
  ``w0 = C a (p a / (E h))^(1/3)`` (:func:`mvfem.reference.foppl_hencky`, ODE shooting);
- ``neo-hookean``: clamped neo-Hookean disk (mu 20 kPa, h 1 mm) inflated to 3 kPa by a
  follower pressure; pole height against the axisymmetric membrane solution
  (:func:`mvfem.reference.axisymmetric_inflation`);
- ``valve``: the built-in valve of ``mvfem demo`` closed at 16 kPa, against a much finer run
  of itself, solved first: the demo valve refined twice (nested levels, ``mesh.refine = 2``,
  18,304 triangles, about 0.5 mm; ``--quick``: the 5 mm valve refined once): closed shape
  (area-weighted mean distance, 95th percentile and Hausdorff distance of the predicted closed
  leaflets to the finest closed leaflets, leaflet with leaflet, divided by the finest run's
  largest displacement to make them relative), coaptation length (stepped and the trace
  length), and the 50th and 95th percentiles of each leaflet's radial Cauchy stress.

The sweep varies the mesh size, the element degree (P1, P2: disks only; chordae and contact
need P1), the quadrature degree (P2 only: a P1 membrane on flat facets has a constant integrand
per cell, so any degree is exact) and solver settings (MUMPS LU or GMRES + ILU, the equilibrium
tolerance); the valve also over nested refinement (``mesh.refine``).

Outputs in DIR: ``bench.csv`` (one row per run and quantity, :data:`COLUMNS`), ``bench_pareto.png``
(wall time against relative error, per problem, log-log, Pareto front of the main quantity) and
``bench.md`` (the fastest setting that reaches 1 % and 0.1 % for every problem and quantity).
Wall times are of single runs on whatever the machine is doing at the time; within one run of
the benchmark they compare settings with each other.
"""

from __future__ import annotations

import csv
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from mpi4py import MPI

__all__ = ["COLUMNS", "Setting", "fastest_table", "pareto_plot", "run_bench", "settings"]

RADIUS = 10.0
ORIGIN = [0.0, 0.0, 0.0]
DEMO = Path(__file__).parent / "data" / "demo.toml"
#: the CSV header (one row per run and quantity of interest)
COLUMNS = ["problem", "setting", "mesh_size_mm", "degree", "quadrature_degree", "solver",
           "cells", "dofs", "converged", "newton_iterations", "wall_time_s", "assembly_s",
           "linear_solve_s", "contact_s", "rest_s", "reference_step_s", "quantity", "value",
           "reference", "abs_error", "rel_error", "stop_reason", "refine"]
#: the quantity whose error is the x axis of the Pareto front of each problem
MAIN_QUANTITY = {"foppl": "centre_deflection_mm", "neo-hookean": "pole_height_mm",
                 "valve": "closed_shape_mean"}
#: solver variants: label -> scene changes (solver.*)
SOLVERS = {"lu": {}, "iterative": {"solver.linear_solver": "iterative"},
           "tol1e-6": {"solver.tolerance": 1e-6}, "tol1e-4": {"solver.tolerance": 1e-4}}


@dataclass(frozen=True)
class Setting:
    """One run of the sweep."""

    problem: str
    size: float
    degree: int = 1
    quadrature: int | None = None
    solver: str = "lu"
    reference: bool = False  # the valve's finest run, the reference of the others
    refine: int = 0  # valves: nested uniform refinements of the mesh of size ``size``

    @property
    def label(self) -> str:
        r = f" r{self.refine}" if self.refine else ""
        q = f" q{self.quadrature}" if self.quadrature else ""
        s = "" if self.solver == "lu" else f" {self.solver}"
        return f"h{self.size:g}{r} P{self.degree}{q}{s}"


def settings(quick: bool = False) -> list[Setting]:
    """The sweep; the valve's reference (finest) run comes first among the valve settings."""
    S = Setting
    if quick:
        out = []
        for prob in ("foppl", "neo-hookean"):
            out += [S(prob, 2.0), S(prob, 1.0), S(prob, 2.0, degree=2)]
        out += [S("neo-hookean", 0.7), S("neo-hookean", 2.0, degree=2, quadrature=2),
                S("neo-hookean", 1.0, solver="iterative")]
        out += [S("valve", 5.0, refine=1, reference=True), S("valve", 5.0), S("valve", 6.0)]
        return out
    out = []
    for prob in ("foppl", "neo-hookean"):
        out += [S(prob, h) for h in (2.0, 1.4, 1.0, 0.7, 0.5, 0.35)]
        out += [S(prob, h, degree=2) for h in (2.0, 1.4, 1.0, 0.7)]
        out += [S(prob, h, degree=2, quadrature=2) for h in (2.0, 1.0)]
        out += [S(prob, h, degree=2, quadrature=6) for h in (2.0, 1.0)]
        out += [S(prob, h, solver=sv) for h in (1.0, 0.5) for sv in ("iterative", "tol1e-6")]
    # the reference: the target-size valve of issue 7, 4x finer than the demo's 2 mm
    out += [S("valve", 2.0, refine=2, reference=True)]
    out += [S("valve", h) for h in (5.0, 4.0, 3.0, 2.5, 2.0, 1.5)]
    out += [S("valve", 2.0, refine=1)]
    out += [S("valve", 3.0, solver=sv) for sv in ("iterative", "tol1e-6")]
    # the equilibrium tolerance where the closure is fine enough for it to matter
    out += [S("valve", 2.0, solver="tol1e-4"), S("valve", 2.0, refine=1, solver="tol1e-4")]
    return out


# --------------------------------------------------------------------------- problems
def _disk_scene(problem: str, st: Setting) -> dict:
    if problem == "foppl":
        # stabilisation 10: SVK under a 1 Pa load needs a stronger start-up weight (README);
        # the state reported is the unstabilised equilibrium either way
        region = {"law": "svk", "params": {"E": 4e5, "nu": 0.5}, "thickness": 1.0}
        load, solver = {"pressure": 1.0, "follower": False}, {"stabilisation": 10.0}
    else:
        region = {"law": "neo-hookean", "params": {"mu": 20e3}, "thickness": 1.0}
        load, solver = {"pressure": 3000.0, "follower": True}, {}
    solver["degree"] = st.degree
    if st.quadrature:
        solver["quadrature_degree"] = st.quadrature
    # fibres.centre given: every mesh size reuses the same compiled forms
    return {"title": f"bench {problem} {st.label}",
            "mesh": {"generator": "disk", "radius": RADIUS, "size": st.size},
            "region": [region], "fibres": {"centre": ORIGIN}, "load": load, "solver": solver,
            "output": {"probes": [{"name": "centre", "point": ORIGIN}], "xdmf": False}}


def disk_reference(problem: str) -> float:
    """Centre deflection (mm) of the disk problem from :mod:`mvfem.reference` (no dolfinx)."""
    from mvfem import reference as ref

    if problem == "foppl":
        return ref.foppl_hencky(0.5).centre_deflection(RADIUS, 1.0, 4e5, 1.0)
    law = ref.neo_hookean(20e3)
    return ref.axisymmetric_inflation(law, 3000.0, RADIUS, 1.0).centre_deflection


def _closed_surface(result, path: Path) -> float:
    """Write the closed leaflets of ``result`` (rank 0) with cell data ``leaflet`` (1 anterior,
    2 posterior) for the ``[reference] file`` key; returns the largest displacement (mm)."""
    from mvfem.distance import _deformed_surface
    from mvfem.meshes import write_surface

    surf = _deformed_surface(result.model)  # collective
    if result.model.comm.rank == 0:
        x, tri, groups = surf
        codes = np.array([{"anterior": 1, "posterior": 2}.get(g, 3) for g in groups], np.int32)
        write_surface(path, x, tri, cell_data={"leaflet": codes})
    result.model.comm.Barrier()
    return float(result.summary["max_displacement_mm"])


def _stress(summary: dict, leaflet: str, p: str):
    reg = (summary.get("regions") or {}).get(leaflet) or {}
    return (reg.get("radial_cauchy_stress_Pa") or {}).get(p)


def _valve_quantities(summary: dict) -> dict:
    v = summary.get("valve") or {}
    q = {"coaptation_length_mm": v.get("coaptation_length_mm"),
         "coaptation_trace_length_mm": v.get("coaptation_trace_length_mm")}
    for leaflet in ("anterior", "posterior"):
        for p in ("median", "p95"):
            q[f"{leaflet}_radial_stress_{p}_Pa"] = _stress(summary, leaflet, p)
    return q


# --------------------------------------------------------------------------- running
@dataclass
class _Run:
    setting: Setting
    summary: dict
    quantities: dict = field(default_factory=dict)  # name -> (value, reference, rel_error)


def _rel(value, reference):
    if value is None or reference is None or not math.isfinite(value):
        return None, None
    err = abs(value - reference)
    return err, (err / abs(reference) if reference else None)


def _solve(scene, comm):
    from mvfem.run import solve

    return solve(scene, out=None, comm=comm, progress=False)


def _run_setting(st: Setting, comm, out: Path, valve_ref: dict) -> _Run:
    import mvfem

    changes = dict(SOLVERS[st.solver])
    if st.problem == "valve":
        base = mvfem.load_scene(DEMO)
        # the solve timed, not the optional outputs (fields.xdmf, the levels' measurement)
        changes.update({"mesh.size": st.size, "output.xdmf": False, "output.levels": False})
        if st.refine:
            changes["mesh.refine"] = st.refine
        if not st.reference:
            if "file" not in valve_ref:
                raise RuntimeError("the valve's reference run did not converge")
            changes["reference.file"] = str(valve_ref["file"])
        scene = base.with_changes(changes)
    else:
        scene = mvfem.load_scene(_disk_scene(st.problem, st)).with_changes(changes)
    r = _solve(scene, comm)
    s = r.summary
    run = _Run(st, s)
    if st.problem in ("foppl", "neo-hookean"):
        value = float(s["probes"]["centre"]["displacement_mm"][2]) if s["converged"] else None
        name = MAIN_QUANTITY[st.problem]
        ref_v = disk_reference(st.problem)
        run.quantities[name] = (value, ref_v, *_rel(value, ref_v))
        return run
    q = _valve_quantities(s) if s["converged"] else {}
    if st.reference:
        if s["converged"]:
            tag = f"_r{st.refine}" if st.refine else ""
            path = out / f"valve_reference_h{st.size:g}{tag}.vtu"
            valve_ref["file"] = path.resolve()
            valve_ref["scale"] = _closed_surface(r, path)
            valve_ref["quantities"] = q
        return run
    ref_q = valve_ref["quantities"]
    scale = valve_ref["scale"]
    d = s.get("reference") or {}
    for name, key in (("closed_shape_mean", "mean_abs_error_mm"),
                      ("closed_shape_p95", "p95_error_mm"),
                      ("closed_shape_hausdorff", "hausdorff_mm")):
        value = d.get(key) if s["converged"] else None
        run.quantities[name] = (value, scale, value,
                                None if value is None else value / scale)
    for name, ref_v in ref_q.items():
        value = q.get(name)
        run.quantities[name] = (value, ref_v, *_rel(value, ref_v))
    return run


def _rows(run: _Run) -> list[dict]:
    st, s = run.setting, run.summary
    t = s.get("timing") or {}
    parts = [t.get(k, 0.0) or 0.0 for k in ("assembly_s", "linear_solve_s", "contact_s")]
    q_deg = st.quadrature or (1 if st.degree == 1 else 2 * st.degree)
    common = {"problem": st.problem, "setting": st.label, "mesh_size_mm": st.size,
              "degree": st.degree, "quadrature_degree": q_deg, "solver": st.solver,
              "cells": s["cells"], "dofs": s["dofs"], "converged": bool(s["converged"]),
              "newton_iterations": s["newton_iterations"],
              "wall_time_s": s["wall_time_s"], "assembly_s": parts[0],
              "linear_solve_s": parts[1], "contact_s": parts[2],
              "rest_s": s["wall_time_s"] - sum(parts),
              "reference_step_s": t.get("reference_step_s"),
              "stop_reason": s.get("stop_reason") or "", "refine": st.refine}
    if not run.quantities:  # the valve's reference run
        return [dict(common, quantity="reference run", value=None, reference=None,
                     abs_error=None, rel_error=None)]
    return [dict(common, quantity=name, value=v, reference=r, abs_error=a, rel_error=e)
            for name, (v, r, a, e) in run.quantities.items()]


def _fmt(v):
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.10g}"
    return str(v)


def write_csv(rows: list[dict], path: Path) -> None:
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=COLUMNS)
        w.writeheader()
        for row in rows:
            w.writerow({k: _fmt(row.get(k)) for k in COLUMNS})


def read_csv(path: Path) -> list[dict]:
    """bench.csv back as dicts with numbers (empty cells None)."""
    out = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            r = {}
            for k, v in row.items():
                if v == "":
                    r[k] = None
                elif k in ("problem", "setting", "solver", "quantity", "stop_reason"):
                    r[k] = v
                elif k == "converged":
                    r[k] = v == "True"
                else:
                    r[k] = float(v)
            out.append(r)
    return out


# --------------------------------------------------------------------------- reports
def fastest_table(rows: list[dict], thresholds=(1e-2, 1e-3)) -> str:
    """Markdown: per problem and quantity, the fastest converged setting whose relative error
    is within each threshold."""
    lines = ["| problem | quantity | runs | smallest error (setting) | "
             + " | ".join(f"fastest to {t:.1%}" for t in thresholds) + " |",
             "|---|---|---:|---|" + "---|" * len(thresholds)]
    keys = list(dict.fromkeys((r["problem"], r["quantity"]) for r in rows
                              if r["rel_error"] is not None or r["quantity"] != "reference run"))
    for prob, qty in keys:
        if qty == "reference run":
            continue
        sel = [r for r in rows if r["problem"] == prob and r["quantity"] == qty
               and r["converged"] and r["rel_error"] is not None]
        if not sel:
            lines.append(f"| {prob} | {qty} | 0 | - |" + " - |" * len(thresholds))
            continue
        best = min(sel, key=lambda r: r["rel_error"])
        cells = []
        for t in thresholds:
            ok = [r for r in sel if r["rel_error"] <= t]
            if ok:
                f = min(ok, key=lambda r: r["wall_time_s"])
                cells.append(f"{f['setting']}: {f['wall_time_s']:.2f} s ({f['rel_error']:.2e})")
            else:
                cells.append("none in the sweep")
        lines.append(f"| {prob} | {qty} | {len(sel)} | {best['rel_error']:.2e} "
                     f"({best['setting']}) | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def _front(points):
    """Indices of the Pareto-optimal (error, time) points, by increasing error."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best_t = [], math.inf
    for i in order:
        if points[i][1] < best_t:
            front.append(i)
            best_t = points[i][1]
    return front


def pareto_plot(rows: list[dict], path: Path) -> Path:
    """Wall time against relative error, one panel per problem (log-log); every quantity a
    marker, the main quantity's points coloured by element degree and solver, its Pareto front
    a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problems = list(dict.fromkeys(r["problem"] for r in rows))
    fig, axes = plt.subplots(1, len(problems), figsize=(5.2 * len(problems), 4.4), dpi=110,
                             squeeze=False)
    markers = "osD^v<>p*h"
    for ax, prob in zip(axes[0], problems):
        sel = [r for r in rows if r["problem"] == prob and r["converged"]
               and r["rel_error"] is not None and r["rel_error"] > 0]
        qtys = list(dict.fromkeys(r["quantity"] for r in sel))
        main = MAIN_QUANTITY.get(prob, qtys[0] if qtys else None)
        for k, q in enumerate(qtys):
            pts = [r for r in sel if r["quantity"] == q]
            if q == main:
                # one colour per setting apart from the mesh size (degree, quadrature, solver)
                kind = lambda r: r["setting"].split(" ", 1)[1]
                for name in dict.fromkeys(kind(r) for r in pts):
                    g = [r for r in pts if kind(r) == name]
                    ax.scatter([r["rel_error"] for r in g], [r["wall_time_s"] for r in g],
                               marker=markers[k % len(markers)], s=36, zorder=3,
                               label=f"{q}: {name}")
                xy = [(r["rel_error"], r["wall_time_s"]) for r in pts]
                fr = _front(xy)
                ax.plot([xy[i][0] for i in fr], [xy[i][1] for i in fr], "k-", lw=0.8,
                        zorder=2, label="Pareto front")
                for i in fr:
                    ax.annotate(pts[i]["setting"], xy[i], fontsize=6, xytext=(3, 3),
                                textcoords="offset points")
            else:
                ax.scatter([r["rel_error"] for r in pts], [r["wall_time_s"] for r in pts],
                           marker=markers[k % len(markers)], s=18, alpha=0.55,
                           facecolors="none", edgecolors="0.3", label=q)
        for t in (1e-2, 1e-3):
            ax.axvline(t, color="0.7", ls=":", lw=0.8)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("relative error")
        ax.set_ylabel("wall time, s")
        ax.set_title(prob, fontsize=10)
        ax.legend(fontsize=6, loc="best")
        ax.grid(True, which="both", lw=0.3, alpha=0.5)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


def run_bench(out: str | Path, quick: bool = False, comm=MPI.COMM_WORLD,
              problems: tuple[str, ...] | None = None, say=None) -> dict:
    """Run the sweep into ``out`` (collective). Returns {"rows", "files", "table", "time_s"}.

    Args:
        out: output directory (refused if it holds files mvfem did not write).
        quick: the small sweep (disks at 2, 1 and 0.7 mm, the valve at 6 and 5 mm against the
            5 mm valve refined once).
        problems: only these problems (default all: foppl, neo-hookean, valve).
        say: a callable for one progress line per run (rank 0), or None.
    """
    from mvfem.outputs import prepare_out_on_root, remove_earlier_files

    t0 = time.perf_counter()
    out = Path(out)
    prepare_out_on_root(out, comm)
    if comm.rank == 0:   # an earlier benchmark's files (another sweep's reference among them)
        remove_earlier_files(out, ["bench.csv", "bench.md", "bench_pareto.png"]
                             + [p.name for p in out.glob("valve_reference_h*.vtu")])
    comm.Barrier()
    todo = [st for st in settings(quick) if problems is None or st.problem in problems]
    rows: list[dict] = []
    valve_ref: dict = {}
    for i, st in enumerate(todo):
        if st.problem == "valve" and not st.reference and "file" not in valve_ref:
            continue  # no reference: the valve rows would have no error
        run = _run_setting(st, comm, out, valve_ref)
        rows += _rows(run)
        if say and comm.rank == 0:
            s = run.summary
            main = run.quantities.get(MAIN_QUANTITY[st.problem])
            err = "" if not main or main[3] is None else f"  error {main[3]:.2e}"
            say(f"[{i + 1}/{len(todo)}] {st.problem:<11s} {st.label:<18s} {s['cells']:6d} cells "
                f"{'converged' if s['converged'] else 'STOPPED  '} {s['newton_iterations']:5d} it "
                f"{s['wall_time_s']:7.2f} s{err}")
    files, table = [], ""
    if comm.rank == 0:
        write_csv(rows, out / "bench.csv")
        table = fastest_table(rows)
        ref = next((st.label for st in todo if st.reference), "")
        note = ("Relative errors: disks against closed-form/ODE references; the valve against "
                f"its finest run, {ref} (closed-shape distances divided by that run's largest "
                "displacement).")
        (out / "bench.md").write_text(f"{table}\n\n{note}\n")
        pareto_plot(rows, out / "bench_pareto.png")
        files = [out / "bench.csv", out / "bench_pareto.png", out / "bench.md"]
    comm.Barrier()
    return {"rows": rows, "files": files, "table": table, "time_s": time.perf_counter() - t0}
