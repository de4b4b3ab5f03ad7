"""Factorisation time of a closed valve's tangent: MUMPS's LU of the exact tangent against its
LDL^T of the symmetric part (``SNESProblem.symmetric_solver``, the pseudo-time updates'
solver), and how far the two updates differ.

    python scripts/symmetric_tangent.py [--refine 2] [--size MM] [--repeats 3]
                                        [--weights 1e4,1e2,1,1e-2]

Closes the demo valve (its mesh size, or ``--size``) refined ``--refine`` times
(``mvfem.solve``, nested levels), then at
its closed state, for each pseudo-time weight ``k`` (x the model's stabiliser scale), times
the linear solve of ``(K + k M) du = -F`` both ways: the first one (MUMPS's analysis, numeric
factorisation and solve) and the median of ``--repeats`` numeric refactorisations and solves
(the tangent assembled again, so the matrix changed; the pattern did not). ``F`` is the
residual of the closed state moved by 0.05 mm along a smooth field, so that the update is not
roundoff. Prints a markdown row per weight (README, "Nested levels"): the times, their ratio,
the relative difference of the two updates, and the cosine of each update with ``-F``
(positive: a descent direction of the potential). Serial only.
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    from dolfinx.fem import petsc as fpetsc
    from petsc4py import PETSc

    from mvfem.model import lumped_mass
    from mvfem.run import solve
    from mvfem.scene import load_scene
    from mvfem.solver import SNESProblem

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--refine", type=int, default=2)
    p.add_argument("--size", type=float, help="mesh size (mm) instead of the demo's")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--weights", default="1e4,1e2,1,1e-2")
    args = p.parse_args(argv)
    scene = load_scene(Path(__file__).parents[1] / "mvfem" / "data" / "demo.toml")
    changes = {"mesh.refine": args.refine}
    if args.size is not None:
        changes["mesh.size"] = args.size
    scene = scene.with_changes(changes)
    res = solve(scene, progress=True, write=False)
    m = res.model
    pb = SNESProblem(m.residual, m.u, m.bcs, prefix="symtan_", point_terms=m.point_terms,
                     potential=m.energy, load=m.load_form, sparsity=m.sparsity)
    mass = lumped_mass(m)
    pb.set_proximal(0.0, weights=mass, centre=m.u.vector.copy())
    x = m.u.vector.copy()
    X = m.V.tabulate_dof_coordinates()[:, :3]
    move = np.stack([np.sin(0.2 * X[:, 1]), np.cos(0.15 * X[:, 0]),
                     np.sin(0.1 * (X[:, 0] + X[:, 1]))], axis=1).ravel()[: x.array.size]
    x.array[:] += 0.05 * move
    fpetsc.set_bc(x, m.bcs, scale=0.0)  # (the clamped dofs stay at zero)
    pb.evaluate_residual(x)
    rhs = pb.b.copy()
    rhs.scale(-1.0)
    lu, ldl = pb.snes.getKSP(), pb.symmetric_solver()
    print(f"{res.summary['cells']} cells, {res.summary['dofs']} dofs; "
          f"closed in {res.summary['wall_time_s']:.1f} s")
    print("| weight k (x stabiliser) | LU first / repeated (s) | LDL^T first / repeated (s) "
          "| repeated ratio | update difference | cosine with -F, LU / LDL^T |")
    print("|---:|---|---|---:|---:|---|")
    for w in (float(s) for s in args.weights.split(",")):
        k = w * m.stabiliser_scale
        out = {}
        for name, ksp in (("lu", lu), ("ldl", ldl)):
            pb.evaluate_tangent(x, k, symmetric=name == "ldl")
            # a fresh pattern state: the first solve analyses the matrix again
            pb.A.setPreallocationCSR(pb.A.getValuesCSR())
            pb.A.setOption(PETSc.Mat.Option.NEW_NONZERO_ALLOCATION_ERR, False)
            pb.evaluate_tangent(x, k, symmetric=name == "ldl")
            du = rhs.duplicate()
            times = []
            for i in range(1 + args.repeats):  # the first analyses the matrix
                if i:
                    pb.evaluate_tangent(x, k, symmetric=name == "ldl")
                t0 = time.perf_counter()
                ksp.setOperators(pb.A)
                ksp.solve(rhs, du)
                times.append(time.perf_counter() - t0)
            out[name] = (times[0], statistics.median(times[1:]), du)
        d = out["lu"][2].copy()
        d.axpy(-1.0, out["ldl"][2])
        dots = [rhs.dot(out[n][2]) / (rhs.norm() * out[n][2].norm()) for n in ("lu", "ldl")]
        print(f"| {w:g} | {out['lu'][0]:.3f} / {out['lu'][1]:.3f} | {out['ldl'][0]:.3f} / "
              f"{out['ldl'][1]:.3f} | {out['ldl'][1] / out['lu'][1]:.2f} | "
              f"{d.norm() / out['lu'][2].norm():.2e} | {dots[0]:.4f} / {dots[1]:.4f} |",
              flush=True)
    pb.destroy()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
