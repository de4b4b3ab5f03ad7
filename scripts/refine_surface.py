"""A valve file split on its facets or on a smooth surface, against the generator's own surface.

    python scripts/refine_surface.py [--size 3] [--refine 2] [--pressure 16] [--out F.json]

`mvfem demo`'s valve meshed at ``--size`` mm is written as a valve file (what ``mvfem mesh
valve`` writes: leaflets, annulus, chordae). Three closures at ``--pressure`` kPa, each split
``--refine`` times into nested levels:

- ``generated``: the demo's scene with ``mesh.refine``: the generator places each new node on
  the leaflets' own ruled surface (the reference: the surface the file samples);
- ``facets``: the file with ``mesh.refine`` (``mesh.refine_surface = "facets"``, the default):
  the new nodes at the edges' midpoints, on the file's facets;
- ``smooth``: the same with ``mesh.refine_surface = "smooth"``
  (:func:`mvfem.meshes.refine.smooth_midpoints`).

Prints, for both splits of the file, the new nodes' distances from the ruled surface (the
generator's inversion, ``meshes.valve.surface_distance``), and for each closure its steps
(level by level), wall time, coaptation length, tenting height and, against the generated
closure, the closed leaflets' mean, 95th percentile and largest distance (the scene's
``[reference] file``).
``--out`` writes the rows as JSON (refused if the file exists). Rank 0 speaks; the closures run
under ``mpirun`` too.
"""

from __future__ import annotations

import argparse
import inspect
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from mpi4py import MPI

import mvfem
from mvfem.errors import InputError
from mvfem.scriptargs import errors, existing_out

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"


def surface_distances(raw, times: int, smooth: bool, mesh: dict) -> np.ndarray:
    """Distances (mm) of the new nodes of ``raw`` split ``times`` times from the generated
    valve's ruled surfaces (the generator's defaults with the scene's ``mesh`` keys)."""
    from mvfem.meshes.imported import refine_surface
    from mvfem.meshes.valve import surface_distance, valve

    known = inspect.signature(valve).parameters
    fine = refine_surface(raw, times, smooth=smooth)
    nodes = np.unique(np.asarray(fine.triangles))
    nodes = nodes[nodes >= len(raw.points)]
    return surface_distance(fine.points[nodes], **{k: v for k, v in mesh.items()
                                                   if k in known and v is not None})


def level_steps(summary: dict) -> str:
    """``"a + b + c"``: the pseudo-time steps of each nested level, coarsest first."""
    steps, cs = [summary["newton_iterations"]], summary.get("coarse_start")
    while cs:
        steps.append(cs.get("steps"))
        cs = cs.get("coarser")
    return " + ".join(str(n) for n in reversed(steps))


def closed_distances(summary: dict) -> dict:
    d = summary.get("reference") or {}
    return {k: d.get(k) for k in ("mean_abs_error_mm", "p95_error_mm", "hausdorff_mm")}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--size", type=float, default=3.0, help="the demo's mesh size, mm")
    ap.add_argument("--refine", type=int, default=2, help="times the file is split")
    ap.add_argument("--pressure", type=float, default=16.0, help="kPa")
    ap.add_argument("--out", help="write the rows as JSON here")
    args = ap.parse_args(argv)
    root, error = errors("refine_surface.py")
    if (msg := existing_out(args.out)) is not None:
        return error(msg)
    if not 1 <= args.refine <= 4:
        return error(f"--refine {args.refine}: 1 to 4")

    comm = MPI.COMM_WORLD
    tmp = Path(comm.bcast(tempfile.mkdtemp(prefix="refine_surface_") if root else None))
    try:
        code = _study(args, comm, root, error, tmp)
        comm.Barrier()  # every rank done with the files
        return code
    finally:
        if root:
            shutil.rmtree(tmp, ignore_errors=True)


def _study(args, comm, root: bool, error, tmp: Path) -> int:
    from mvfem.bench import _closed_surface
    from mvfem.meshes.imported import write_valve_with_chordae
    from mvfem.meshes.io import read_surface
    from mvfem.model import build_mesh
    from mvfem.run import solve
    from mvfem.scene import load_scene

    base = load_scene(DEMO)
    path = tmp / f"valve_{args.size:g}.vtu"
    try:
        coarse = base.with_changes({"mesh.size": args.size})
    except InputError as e:
        return error(str(e))
    write_valve_with_chordae(path, build_mesh(coarse, comm))
    comm.Barrier()
    raw = read_surface(path)
    rows = []
    pressure = {"load.pressure": f"{args.pressure:g} kPa", "output.xdmf": False}

    def closure(name: str, scene) -> dict:
        t0 = time.perf_counter()
        r = solve(scene, out=None, comm=comm, progress=False)
        s = r.summary
        v = s.get("valve") or {}
        row = {"run": name, "converged": bool(s["converged"]), "cells": s["cells"],
               "steps": level_steps(s), "wall_s": time.perf_counter() - t0,
               "coaptation_mm": v.get("coaptation_length_mm"),
               "trace_mm": v.get("coaptation_trace_length_mm"),
               "tenting_mm": v.get("tenting_height_mm"), **closed_distances(s)}
        return row, r

    generated = base.with_changes({"mesh.size": args.size, "mesh.refine": args.refine,
                                   **pressure})
    row, r = closure("generated", generated)
    if not row["converged"]:
        return error("the generated valve's closure did not converge")
    ref = tmp / "closed_generated.vtu"
    _closed_surface(r, ref)
    rows.append(row)
    file_mesh = {"generator": "file", "file": str(path), "refine": args.refine}
    for how in ("facets", "smooth"):
        d = surface_distances(raw, args.refine, how == "smooth", base["mesh"]) if root else None
        scene = load_scene({**{k: v for k, v in base.raw.items() if k not in ("mesh", "title")},
                            "mesh": {**file_mesh, "refine_surface": how},
                            "reference": {"file": str(ref)}}).with_changes(pressure)
        row, _ = closure(how, scene)
        if root:
            row.update(new_nodes_off_surface_mean_mm=float(d.mean()),
                       new_nodes_off_surface_p95_mm=float(np.percentile(d, 95)),
                       new_nodes_off_surface_max_mm=float(d.max()))
        rows.append(row)
    if root:
        print(f"demo valve at {args.size:g} mm, split {args.refine} times, {args.pressure:g} kPa\n")
        print("| run | new nodes off the surface: mean / p95 / max (mm) | steps | wall (s) "
              "| coaptation (mm) | trace (mm) | tenting (mm) | closed leaflets from the "
              "generated: mean / p95 / max (mm) |")
        print("|---|---|---:|---:|---:|---:|---:|---|")
        for w in rows:
            off = "-" if "new_nodes_off_surface_mean_mm" not in w else " / ".join(
                f"{w[k]:.4f}" for k in ("new_nodes_off_surface_mean_mm",
                                        "new_nodes_off_surface_p95_mm",
                                        "new_nodes_off_surface_max_mm"))
            far = "-" if w.get("mean_abs_error_mm") is None else " / ".join(
                f"{w[k]:.4f}" for k in ("mean_abs_error_mm", "p95_error_mm", "hausdorff_mm"))
            print(f"| {w['run']} | {off} | {w['steps']} | {w['wall_s']:.1f} | "
                  f"{w['coaptation_mm']:.3f} | {w['trace_mm']:.3f} | {w['tenting_mm']:.3f} "
                  f"| {far} |")
        if args.out:
            Path(args.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
