"""All the paper-style figures from one study of generated valves.

    mpirun -n 2 python scripts/paper_figures.py --out results/paper [--quick] [--size 3]
        [--cases default,small,patient] [--sets CP01,MNY-mean] [--processes 2]

The study (mvfem.study): generated valves of several annulus sizes and saddle heights, and
the valve on the patient annulus of ../shared/data/kaiser_normal1, crossed with the eleven
parameter sets of the source paper; each run once, resumable (run the same command again after
an interruption), as many runs at a time as there are cores. Rank 0 orchestrates; the runs are
separate processes (one core each), the other ranks only wait. Writes into --out:

- box_stress.png, box_strain.png: per-leaflet box plots of radial stress and strain per set
  over all cases (the paper's Figs 5-6);
- maps_strain.png, maps_stress.png: the maps of the default valve, one panel per set (Figs 3-4);
- biaxial/biaxial_anterior.png, biaxial/biaxial_posterior.png: the canonical biaxial curves
  (Figs 1-2);
- results.csv (one row per run), report.html (everything on one page), runs/<case>/<set>/.

--quick: two cases (default and patient annulus) at mesh size 5 mm with two sets, for a smoke
test (about half a minute on two cores).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent

#: healthy-adult ranges of ../shared/data/README.md: AP 24-31 mm, commissural 28-39 mm,
#: saddle height 4-7 mm (defaults 28, 37, 6)
CASES = [
    {"name": "default", "scene": "demo", "set": {}},
    {"name": "small", "scene": "demo",
     "set": {"mesh.ap_diameter": 24.0, "mesh.commissural_diameter": 32.0}},
    {"name": "large", "scene": "demo",
     "set": {"mesh.ap_diameter": 31.0, "mesh.commissural_diameter": 39.0}},
    {"name": "flat-saddle", "scene": "demo", "set": {"mesh.saddle_height": 3.0}},
    {"name": "patient", "scene": str(HERE / "scenes" / "valve_patient.toml"), "set": {}},
]


def build_study(size: float, quick: bool, sets: list[str] | None, processes: int | None,
                cases: list[str] | None = None) -> dict:
    names = cases or (["default", "patient"] if quick else [c["name"] for c in CASES])
    unknown = sorted(set(names) - {c["name"] for c in CASES})
    if unknown:
        raise SystemExit(f"paper_figures: --cases: unknown case {unknown[0]!r} (known: "
                         f"{', '.join(c['name'] for c in CASES)})")
    cases = [c for c in CASES if c["name"] in names]
    study = {"title": f"generated valves x parameter sets (mesh size {size:g} mm)",
             "map_case": "default", "biaxial": True,
             "case": [{**c, "set": {**c["set"], "mesh.size": size}} for c in cases]}
    if sets:
        study["sets"] = sets
    elif quick:
        study["sets"] = ["MNY-mean", "SVK"]
    if processes:
        study["processes"] = processes
    return study


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", required=True, help="study directory")
    p.add_argument("--quick", action="store_true", help="2 cases x 2 sets at mesh size 5 mm")
    p.add_argument("--size", type=float, help="mesh size, mm (default 3; 5 with --quick)")
    p.add_argument("--sets", help="comma-separated sets (default: the eleven)")
    p.add_argument("--processes", type=int, help="runs at a time (default: the cores)")
    p.add_argument("--cases", help="comma-separated subset of the cases: "
                   + ", ".join(c["name"] for c in CASES))
    args = p.parse_args(argv)

    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    code = 0
    # mpirun binds each rank to a core: the runs may use the cores of all ranks on this node
    import os

    node = comm.Split_type(MPI.COMM_TYPE_SHARED)
    cpus = set().union(*node.allgather(os.sched_getaffinity(0)))
    node.Free()
    if comm.rank == 0:
        from mvfem.errors import InputError
        from mvfem.study import run_study

        size = args.size or (5.0 if args.quick else 3.0)
        sets = [s.strip() for s in args.sets.split(",")] if args.sets else None
        cases = [c.strip() for c in args.cases.split(",")] if args.cases else None
        try:
            res = run_study(build_study(size, args.quick, sets, args.processes or len(cpus),
                                        cases), args.out, progress=True, cpus=cpus)
        except InputError as e:
            print(f"paper_figures: error: {e}", file=sys.stderr, flush=True)
            code = 2
        else:
            print(f"{res['runs']} runs: {res['converged']} converged, {res['stopped']} stopped "
                  f"short, {res['failed']} failed; {res['wall_time_s']:.0f} s", flush=True)
            for f in [res["results"], res["report"], *res["figures"]]:
                print(f"  wrote {f}", flush=True)
            for f in sorted(Path(args.out, "biaxial").glob("*.png")):
                print(f"  wrote {f}", flush=True)
    # the other ranks wait without spinning a core (a plain barrier busy-polls under OpenMPI)
    req = comm.Ibarrier()
    while not req.Test():
        time.sleep(0.2)
    return comm.bcast(code, root=0)


if __name__ == "__main__":
    sys.exit(main())
