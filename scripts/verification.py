"""Verification table: mvfem against independent references, as markdown.

Runs the cases of ``tests/test_verification.py`` at one or two mesh sizes each and prints,
on rank 0, one row per run: the reference value (``mvfem.reference``: ODE shooting or closed
form, no dolfinx), the mvfem value, the relative error, wall time and Newton iterations; then
the hard starts (every anterior parameter set from the flat disk to 16 kPa)::

    mpirun -n 2 python scripts/verification.py            # two sizes per case
    python scripts/verification.py --quick                # one coarse size per case

Cases (see the test docstrings for the derivations and the expected O(h^2) errors):

- Föppl-Hencky: clamped SVK disk (radius 10 mm, E 400 kPa, nu 1/2, h 1 mm) under a 1 Pa
  dead load, centre deflection vs Hencky's ``w0 = C a (p a/(E h))^(1/3)``;
- neo-Hookean disk (mu 20 kPa, h 1 mm) inflated to 3 kPa by a follower pressure, pole height
  vs the axisymmetric shooting solution;
- octasphere (R 10 mm, h 0.85 mm) under internal pressure, strain ``lambda - 1`` from the mean
  deformed radius vs Laplace's law, for May-Newman-Yin with its fibre term off (a Fung law,
  16 kPa) and neo-Hookean (1.5 kPa).
"""

from __future__ import annotations

import dolfinx  # noqa: F401  (PETSc is initialised collectively on import: before anything else)

import argparse
import sys
import time

from mpi4py import MPI

from mvfem import reference as ref
from mvfem.cli import quiet_jit_logs
from mvfem.fields import mean_deformed_radius
from mvfem.run import solve

RADIUS = 10.0
ORIGIN = [0.0, 0.0, 0.0]


def _disk(region: dict, pressure: float, size: float, follower: bool, solver: dict) -> dict:
    return {"title": "verification", "mesh": {"generator": "disk", "radius": RADIUS, "size": size},
            "region": [region], "fibres": {"centre": ORIGIN},
            "load": {"pressure": pressure, "follower": follower}, "solver": solver,
            "output": {"probes": [{"name": "centre", "point": ORIGIN}]}}


def _centre(result) -> float:
    return float(result.summary["probes"]["centre"]["displacement_mm"][2])


def _strain(result) -> float:
    """Mean deformed radius / R - 1 over the nodes (collective)."""
    return mean_deformed_radius(result.u) / RADIUS - 1.0


def cases(quick: bool):
    """(case label, reference value, unit, scene, measure) for every run."""
    disk_sizes = (1.0,) if quick else (1.0, 0.5)
    levels = (3,) if quick else (3, 4)

    E, nu, h, p = 4e5, 0.5, 1.0, 1.0
    w0 = ref.foppl_hencky(nu).centre_deflection(RADIUS, h, E, p)
    for size in disk_sizes:
        # stabilisation 10: see FH_SOLVER in tests/test_verification.py
        yield (f"Föppl-Hencky, SVK, 1 Pa dead load, centre deflection, disk size {size}", w0,
               "mm", _disk({"law": "svk", "params": {"E": E, "nu": nu}, "thickness": h}, p, size,
                           False, {"stabilisation": 10.0}), _centre)

    mu, h, p = 20e3, 1.0, 3000.0
    inflated = ref.axisymmetric_inflation(ref.neo_hookean(mu), p, RADIUS, h)
    for size in disk_sizes:
        yield (f"neo-Hookean disk, 3 kPa follower, pole height, disk size {size}",
               inflated.centre_deflection, "mm",
               _disk({"law": "neo-hookean", "params": {"mu": mu}, "thickness": h}, p, size,
                     True, {}), _centre)

    h = 0.85
    spheres = [("MNY (c2 = 0)", {"law": "mny", "params": {"c0": 399.0, "c1": 4.325, "c2": 0.0}},
                ref.may_newman_yin(399.0, 4.325, 0.0), 16e3),
               ("neo-Hookean", {"law": "neo-hookean", "params": {"mu": 20e3}},
                ref.neo_hookean(20e3), 1500.0)]
    for name, region, law, p in spheres:
        lam = ref.sphere_stretch(law, RADIUS, h, p)
        for n in levels:
            scene = {"title": "verification",
                     "mesh": {"generator": "octasphere", "radius": RADIUS, "refinements": n},
                     "region": [dict(region, thickness=h)], "load": {"pressure": p}}
            yield (f"Laplace sphere, {name}, {p / 1e3:g} kPa, strain lambda - 1, level {n} "
                   f"({8 * 4 ** n} cells)", lam - 1.0, "", scene, _strain)


ANTERIOR = [("mny", f"CP0{i}") for i in range(1, 9)] + [
    ("mny", "MNY-mean"), ("holzapfel", "Holzapfel"), ("svk", "SVK")]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="one coarse size per case")
    parser.add_argument("--hard-size", type=float, default=1.25,
                        help="disk mesh size of the hard starts (mm), default 1.25")
    args = parser.parse_args(argv)
    quiet_jit_logs()
    comm = MPI.COMM_WORLD
    say = print if comm.rank == 0 else (lambda *a, **k: None)
    t0 = time.perf_counter()
    failures = 0

    say(f"## Verification against independent references ({comm.size} process"
        f"{'es' if comm.size > 1 else ''})\n")
    say("| case | reference | mvfem | relative error | wall time (s) | Newton iterations |")
    say("|---|---:|---:|---:|---:|---:|")
    for label, expected, unit, scene, measure in cases(args.quick):
        r = solve(scene, out=None, comm=comm, progress=False)
        s = r.summary
        value = measure(r)
        u = f" {unit}" if unit else ""
        if s["converged"]:
            shown, err = f"{value:.6g}{u}", f"{(value - expected) / expected:+.2e}"
        else:
            failures += 1
            shown, err = f"not converged ({s['stop_reason']})", "-"
        say(f"| {label} | {expected:.6g}{u} | {shown} | {err} | {s['wall_time_s']:.2f} | "
            f"{s['newton_iterations']} |")

    say(f"\n## Hard starts: flat clamped disk (radius 10 mm, size {args.hard_size:g} mm) to "
        "16 kPa, default solver\n")
    say("| set | converged | equilibrium residual | load steps | Newton iterations | "
        "wall time (s) |")
    say("|---|---|---:|---:|---:|---:|")
    for law, name in ANTERIOR:
        scene = _disk({"law": law, "params": name}, 16e3, args.hard_size, True, {})
        s = solve(scene, out=None, comm=comm, progress=False).summary
        ok = s["converged"] and s["equilibrium_residual"] <= 1e-7
        failures += not ok
        say(f"| {name} | {'yes' if ok else 'NO: ' + s['stop_reason']} | "
            f"{s['equilibrium_residual']:.1e} | {s['load_steps']} | {s['newton_iterations']} | "
            f"{s['wall_time_s']:.2f} |")
    say(f"\ntotal {time.perf_counter() - t0:.1f} s")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
