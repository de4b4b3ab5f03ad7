"""Start-up robustness and linear-solver choice on the clamped disk, every anterior set.

Each set inflates a flat, stress-free 10 mm disk to 16 kPa with the direct (MUMPS) and the
iterative (GMRES + block-Jacobi ILU) linear solver; prints one markdown table row per run and
the totals. Run as ``python scripts/solver_options.py [SIZE]`` or under ``mpirun -n 2``
(default SIZE 0.5 mm, 2944 triangles).
"""

from __future__ import annotations

import sys
import time

import dolfinx  # noqa: F401  (PETSc initialisation is collective: every rank imports it)
from mpi4py import MPI

from mvfem.cli import quiet_jit_logs
from mvfem.materials import parameter_sets
from mvfem.run import solve


def main(size: float = 0.5) -> None:
    quiet_jit_logs()
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    say("| linear solver | set | converged | load steps | Newton iterations | max displacement (mm) "
        "| equilibrium residual | wall time (s) |")
    say("|---|---|---|---|---|---|---|---|")
    totals = {}
    for linear in ("lu", "iterative"):
        for ps in parameter_sets("anterior"):
            scene = {"title": f"disk {ps.name}",
                     "mesh": {"generator": "disk", "radius": 10.0, "size": size},
                     "region": [{"law": ps.law, "params": ps.name}],
                     "solver": {"linear_solver": linear}}
            t0 = time.perf_counter()
            s = solve(scene, comm=comm, progress=False).summary
            dt = time.perf_counter() - t0
            ok, it, tt = totals.get(linear, (0, 0, 0.0))
            totals[linear] = (ok + s["converged"], it + s["newton_iterations"], tt + dt)
            say(f"| {linear} | {ps.name} | {s['converged']} | {s['load_steps']} | "
                f"{s['newton_iterations']} | {s['max_displacement_mm']:.6f} | "
                f"{s['equilibrium_residual']:.1e} | {dt:.1f} |", flush=True)
    for linear, (ok, it, tt) in totals.items():
        say(f"{linear}: {ok} converged, {it} Newton iterations, {tt:.1f} s")


if __name__ == "__main__":
    main(*(float(a) for a in sys.argv[1:2]))
