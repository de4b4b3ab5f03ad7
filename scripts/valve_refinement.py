"""Mesh refinement of the built-in valve's closure: the closed shape at several mesh sizes
against the finest one.

    mpirun -n 2 python scripts/valve_refinement.py --out results/refinement [--sizes 3,2,1.5,1]
    python scripts/valve_refinement.py --out results/nested --refine 2 [--open 1]

Closes `mvfem demo`'s scene at every size (mm; the free edge gets half of it), writes the
finest closed valve as a surface (closed_size_<size>.vtu, leaflet cell data) and measures every
coarser closed valve against it with the closed-state error of the `[reference]` scene key
(mean, 95th percentile, Hausdorff, leaflet with leaflet), beside the valve metrics and the
wall time. Prints a table (README, "Mesh refinement") and writes refinement.csv.
``moved_mean_mm`` and ``moved_p95_mm`` are what a nested or sequenced run reports of itself:
how far its closure lies from its next coarser level's (summary.json ``coarse_start``
``distance_to_finer_mm``; README, "Each refined run measures its own mesh error").

With ``--refine N`` the levels are the demo's mesh (``--sizes``: one size) refined 0 to N times
(``mesh.refine``, nested meshes), each closed from the closure of the level below
(``solver.nested``; a level's wall time includes the coarser levels' solves), the finest the
reference (README, "Nested levels"); ``--open L`` also closes the levels up to L from the open
state (``solver.nested = false``).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from mpi4py import MPI

import mvfem
from mvfem.outputs import prepare_out

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"


def closed_surface(result, path: Path) -> None:
    """Write the closed leaflets of ``result`` (rank 0) with their leaflet labels."""
    from mvfem.meshes import write_surface

    model = result.model
    n = model.V.dofmap.index_map.size_local * 3
    x = model.point_terms.positions(result.u.x.array[:n])
    if model.comm.rank == 0:
        write_surface(path, x, model.view.cells, cell_data={"leaflet": model.view.cell_tag})
    model.comm.Barrier()


def _steps(summary: dict) -> str:
    """The coarser levels' pseudo-time steps of a nested solve, coarsest first ("-" if none)."""
    from mvfem.run import coarse_levels

    return "+".join(str(cs["steps"]) for cs in reversed(coarse_levels(summary))) or "-"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/refinement")
    p.add_argument("--sizes", default=None, help="mesh sizes, mm (the finest is the "
                   "reference); default 3,2,1.5,1, or the demo's 2 with --refine")
    p.add_argument("--refine", type=int, default=None, help="levels 0..N of nested refinement "
                   "of one mesh size instead of several sizes")
    p.add_argument("--open", type=int, default=-1, help="with --refine: also close the levels "
                   "up to this one from the open state")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    sizes = sorted({float(s) for s in (args.sizes or ("2" if args.refine is not None
                                                      else "3,2,1.5,1")).split(",")})
    if args.refine is not None and len(sizes) != 1:
        p.error("--refine takes one mesh size")
    out = Path(args.out)
    if comm.rank == 0:
        prepare_out(out)
    comm.Barrier()
    base = mvfem.load_scene(DEMO)
    if args.refine is None:  # the finest first: it is the reference
        runs = [(f"size_{h:g}", {"mesh.size": h}, h) for h in sizes]
    else:
        levels = range(args.refine, -1, -1)
        runs = [(f"refine_{n}", {"mesh.size": sizes[0], "mesh.refine": n}, n) for n in levels]
        runs += [(f"refine_{n}_open", {"mesh.size": sizes[0], "mesh.refine": n,
                                       "solver.nested": False}, n)
                 for n in levels if 0 < n <= args.open]
    rows = []
    reference = out / f"closed_{runs[0][0]}.vtu"
    for name, changes, level in runs:
        if name != runs[0][0]:
            changes["reference.file"] = str(reference.resolve())
        scene = base.with_changes(changes)
        r = mvfem.solve(scene, out=out / name, progress=False)
        if name == runs[0][0]:
            closed_surface(r, reference)
        s, v = r.summary, r.summary.get("valve") or {}
        ref = s.get("reference") or {}
        # what the run itself reports: its closure against the next coarser level's
        moved = (s.get("coarse_start") or {}).get("distance_to_finer_mm") or {}
        t = s["timing"]
        head = ({"size_mm": level} if args.refine is None else
                {"refine": level, "start": "open" if name.endswith("open") or not level
                 else "nested", "coarser_steps": _steps(s)})
        rows.append({**head, "cells": s["cells"], "dofs": s["dofs"],
                     "converged": s["converged"], "wall_time_s": round(s["wall_time_s"], 1),
                     "newton_iterations": s["newton_iterations"],
                     "reference_step_s": round(t["reference_step_s"], 3),
                     "ratio": round(s["wall_time_s"] / t["reference_step_s"]),
                     "contact_pairs": (s.get("contact") or {}).get("active_pairs"),
                     "closest_mm": (s.get("contact") or {}).get("min_distance_mm"),
                     "coaptation_length_mm": v.get("coaptation_length_mm"),
                     "tenting_height_mm": v.get("tenting_height_mm"),
                     "regurgitant_orifice_area_mm2": v.get("regurgitant_orifice_area_mm2"),
                     "max_penetration_mm": s.get("max_penetration_mm"),
                     "mean_abs_error_mm": ref.get("mean_abs_error_mm", 0.0),
                     "p95_error_mm": ref.get("p95_error_mm", 0.0),
                     "hausdorff_mm": ref.get("hausdorff_mm", 0.0),
                     "moved_mean_mm": moved.get("mean_mm"), "moved_p95_mm": moved.get("p95_mm")})
        if comm.rank == 0:
            print(json.dumps(rows[-1]), flush=True)
    if comm.rank == 0:
        with open(out / "refinement.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        keys = list(rows[0])
        print("| " + " | ".join(keys) + " |")
        print("|" + "---|" * len(keys))
        for row in rows:
            print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v)
                                    for v in row.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
