"""Mesh refinement of the built-in valve's closure: the closed shape at several mesh sizes
against the finest one.

    mpirun -n 2 python scripts/valve_refinement.py --out results/refinement [--sizes 3,2,1.5,1]

Closes `mvfem demo`'s scene at every size (mm; the free edge gets half of it), writes the
finest closed valve as a surface (closed_<size>.vtu, leaflet cell data) and measures every
coarser closed valve against it with the closed-state error of the `[reference]` scene key
(mean, 95th percentile, Hausdorff, leaflet with leaflet), beside the valve metrics and the
wall time. Prints a table (README, "Mesh refinement") and writes refinement.csv.
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


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/refinement")
    p.add_argument("--sizes", default="3,2,1.5,1", help="mesh sizes, mm (the finest is the "
                   "reference)")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    sizes = sorted({float(s) for s in args.sizes.split(",")})
    out = Path(args.out)
    if comm.rank == 0:
        prepare_out(out)
    comm.Barrier()
    base = mvfem.load_scene(DEMO)
    rows = []
    reference = out / f"closed_{sizes[0]:g}.vtu"
    for size in sizes:
        changes = {"mesh.size": size}
        if size != sizes[0]:
            changes["reference.file"] = str(reference.resolve())
        scene = base.with_changes(changes)
        r = mvfem.solve(scene, out=out / f"size_{size:g}", progress=False)
        if size == sizes[0]:
            closed_surface(r, reference)
        s, v = r.summary, r.summary.get("valve") or {}
        ref = s.get("reference") or {}
        rows.append({"size_mm": size, "cells": s["cells"], "dofs": s["dofs"],
                     "converged": s["converged"], "wall_time_s": round(s["wall_time_s"], 1),
                     "newton_iterations": s["newton_iterations"],
                     "coaptation_length_mm": v.get("coaptation_length_mm"),
                     "tenting_height_mm": v.get("tenting_height_mm"),
                     "regurgitant_orifice_area_mm2": v.get("regurgitant_orifice_area_mm2"),
                     "max_penetration_mm": s.get("max_penetration_mm"),
                     "mean_abs_error_mm": ref.get("mean_abs_error_mm", 0.0),
                     "p95_error_mm": ref.get("p95_error_mm", 0.0),
                     "hausdorff_mm": ref.get("hausdorff_mm", 0.0)})
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
