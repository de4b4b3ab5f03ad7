"""MPI scaling of one closure (issue 7): the same solve on 1 and 2 processes.

One run (collective; prints one JSON line on rank 0 and appends it to --record)::

    mpirun -n 2 python scripts/scaling.py --case disk --size 0.2
    mpirun -n 2 python scripts/scaling.py --case valve --size 1.5
    mpirun -n 2 python scripts/scaling.py --case valve --size 2 --refine 2

Everything (each case under ``mpirun -n 1`` and ``mpirun -n 2``, one run at a time, then the
table of the README; ``--record`` must not exist yet)::

    python scripts/scaling.py --all --record results/scaling.jsonl [--cases disk:0.2,valve:2:2]

Cases: ``disk``, the clamped neo-Hookean disk of the verification (radius 10 mm, mu 20 kPa,
h 1 mm, 3 kPa follower pressure; about 20,000 triangles at size 0.2), and ``valve``, the demo
valve closed at 16 kPa with chordae and contact, at mesh size ``--size`` and refined
``--refine`` times (nested levels, as ``mvfem run`` does; ``valve:SIZE:REFINE`` in ``--cases``).
The disk's probe and the valve's coaptation length are printed so that the runs can be seen
to give the same answer. With ``--all`` each run gets the machine's cores divided by its
processes as OpenBLAS threads (and, as always, as kernel threads): one process has them all,
as a plain ``mvfem run`` does.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

#: the solve timed, not the optional outputs (session 50's runs of the README measured their
#: levels too: about 3 s of 190 refined three times, 1.5 s of it the finest comparison)
DEMO_CHANGES = {"output.xdmf": False, "output.levels": False}


def _scene(case: str, size: float, refine: int = 0):
    import mvfem

    if case == "disk":
        o = [0.0, 0.0, 0.0]
        return mvfem.load_scene({
            "title": "scaling disk", "mesh": {"generator": "disk", "radius": 10.0, "size": size},
            "region": [{"law": "neo-hookean", "params": {"mu": 20e3}, "thickness": 1.0}],
            "fibres": {"centre": o}, "load": {"pressure": 3000.0, "follower": True},
            "output": {"probes": [{"name": "centre", "point": o}], "xdmf": False}})
    demo = Path(mvfem.__file__).parent / "data" / "demo.toml"
    return mvfem.load_scene(demo).with_changes({"mesh.size": size, "mesh.refine": refine,
                                                **DEMO_CHANGES})


def run_one(case: str, size: float, record: str | None, refine: int = 0) -> int:
    import dolfinx  # noqa: F401  (PETSc initialisation is collective)
    from mpi4py import MPI

    from mvfem.cli import quiet_jit_logs
    from mvfem.run import solve

    quiet_jit_logs()
    comm = MPI.COMM_WORLD
    r = solve(_scene(case, size, refine), out=None, comm=comm, progress=False)
    s = r.summary
    if comm.rank == 0:
        t = s["timing"]
        row = {"case": case, "size_mm": size, "refine": refine, "processes": comm.size,
               "threads": int(os.environ.get("OPENBLAS_NUM_THREADS", "0")) or None,
               "cells": s["cells"],
               "dofs": s["dofs"], "converged": s["converged"],
               "stop_reason": s.get("stop_reason") or "",
               "equilibrium_residual": s.get("equilibrium_residual"),
               "newton_iterations": s["newton_iterations"], "wall_time_s": s["wall_time_s"],
               "assembly_s": t["assembly_s"], "linear_solve_s": t["linear_solve_s"],
               "contact_s": t["contact_s"], "build_s": t.get("build_s"),
               "output_s": t.get("output_s"), "reference_step_s": t.get("reference_step_s"),
               "centre_mm": (s["probes"].get("centre") or {}).get("displacement_mm"),
               "coaptation_length_mm": (s.get("valve") or {}).get("coaptation_length_mm"),
               "max_displacement_mm": s["max_displacement_mm"]}
        print(json.dumps(row), flush=True)
        if record:
            with open(record, "a") as f:
                f.write(json.dumps(row) + "\n")
    return 0 if s["converged"] else 3


def _outcome(r: dict) -> str:
    if r["converged"]:
        return "yes"
    res = r.get("equilibrium_residual")
    return ("**no**" + (f", residual {res:.1e} of the load" if res is not None else "")
            + (f": {r['stop_reason']}" if r.get("stop_reason") else ""))


def _key(r: dict) -> tuple:
    return r["case"], r["size_mm"], r.get("refine", 0)


def _name(r: dict) -> str:
    refine = r.get("refine", 0)
    return f"{r['case']} (size {r['size_mm']:g}" + (f", refined {refine}x)" if refine else ")")


def table(rows: list[dict]) -> str:
    lines = [("| case | cells | dofs | processes | converged | Newton its | wall (s) | assembly (s) "
              "| linear solves (s) | contact (s) | speed-up | same answer |"),
             "|---|---:|---:|---:|---|---:|---:|---:|---:|---:|---:|---|"]
    for r in rows:
        base = next((b for b in rows if _key(b) == _key(r) and b["processes"] == 1), None)
        speed = base["wall_time_s"] / r["wall_time_s"] if base else float("nan")
        same = "-"
        if base is not None and r is not base:
            if r["case"] == "disk" and base["centre_mm"] and r["centre_mm"]:
                d = abs(r["centre_mm"][2] - base["centre_mm"][2]) / abs(base["centre_mm"][2])
                same = f"centre deflection differs {d:.1e} relative"
            elif r["coaptation_length_mm"] is not None and base["coaptation_length_mm"]:
                same = (f"coaptation {r['coaptation_length_mm']:.3f} vs "
                        f"{base['coaptation_length_mm']:.3f} mm")
        lines.append(f"| {_name(r)} | {r['cells']} | {r['dofs']} | "
                     f"{r['processes']} | {_outcome(r)} | {r['newton_iterations']} | "
                     f"{r['wall_time_s']:.1f} | {r['assembly_s']:.1f} | {r['linear_solve_s']:.1f}"
                     f" | {r['contact_s']:.1f} | {speed:.2f} | {same} |")
    return "\n".join(lines)


def run_all(record: str, cases: list[tuple[str, float, int]], procs=(1, 2),
            timeout=3600) -> int:
    from mvfem.relaunch import without_mpi_job

    if Path(record).exists():  # (the runs append: an old record would mix into the table)
        print(f"scaling: --record {record}: exists; choose another name", file=sys.stderr)
        return 2
    cores = os.cpu_count() or 1
    Path(record).parent.mkdir(parents=True, exist_ok=True)
    for case, size, refine in cases:
        for n in procs:
            # the cores shared among the processes: one process gets them all (the default of
            # a plain run), two get one each (OpenBLAS's threads otherwise oversubscribe)
            env = without_mpi_job(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
                                  OPENBLAS_NUM_THREADS=str(max(cores // n, 1)))
            cmd = ["mpirun", "--oversubscribe", "-n", str(n), sys.executable, "-u",
                   os.path.abspath(__file__), "--case", case, "--size", str(size),
                   "--refine", str(refine), "--record", os.path.abspath(record)]
            print("$ " + " ".join(cmd), flush=True)
            # stdin from /dev/null: mpirun forwards stdin to rank 0 and waits on it otherwise
            subprocess.run(cmd, env=env, stdin=subprocess.DEVNULL, timeout=timeout, check=False)
    rows = [json.loads(ln) for ln in Path(record).read_text().splitlines() if ln.strip()]
    print("\n" + table(rows))
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--case", choices=("disk", "valve"), default="disk")
    p.add_argument("--size", type=float, help="mesh size, mm (disk 0.2, valve 1.5)")
    p.add_argument("--refine", type=int, default=0,
                   help="valve: times the mesh is refined (nested levels)")
    p.add_argument("--record", help="append the JSON line to this file")
    p.add_argument("--all", action="store_true", help="the cases on 1 and 2 processes")
    p.add_argument("--cases", default="disk:0.2,valve:1.5,valve:2:2",
                   help="with --all: case:size[:refine],... (default disk:0.2,valve:1.5,"
                        "valve:2:2, the last the demo refined twice)")
    args = p.parse_args(argv)
    if args.all:
        try:
            cases = []
            for c in args.cases.split(","):
                name, size, *rest = c.split(":")
                refine = int(rest[0]) if rest else 0
                if name not in ("disk", "valve") or len(rest) > 1 or \
                        (refine and name != "valve"):
                    raise ValueError(c)
                cases.append((name, float(size), refine))
        except ValueError:
            print(f"scaling: --cases {args.cases!r}: expected case:size[:refine],... with case "
                  "disk or valve (refine: the valve only)", file=sys.stderr)
            return 2
        return run_all(args.record or "results/scaling.jsonl", cases)
    if args.refine and args.case != "valve":
        print("scaling: --refine: the valve only (mesh.refine refines generated valves)",
              file=sys.stderr)
        return 2
    size = args.size if args.size is not None else {"disk": 0.2, "valve": 1.5}[args.case]
    return run_one(args.case, size, args.record, args.refine)


if __name__ == "__main__":
    sys.exit(main())
