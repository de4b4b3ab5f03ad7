"""The coaptation length of the demo's closure on several meshes, two ways.

    python scripts/coaptation_trace.py [--meshes 5,4,3,2.5,2,1.5,2r1,2r2] [--pressure 16]
                                       [--out trace.json]

Closes `mvfem demo`'s scene on each mesh (a mesh size in mm, ``r<n>`` for that mesh refined
``n`` times, closed through the nested levels) and prints, for each, the summary's
``coaptation_length_mm`` (a segment of the A2-P2 trace, one per cut triangle, counted whole
where both its crossed edges have a coapting node: it moves by a cell's length) and the
continuous length of the same trace within 1.5 contact thicknesses of the other leaflet
(``coaptation_trace_length_mm``, :func:`mvfem.metrics.coapting_trace_length`, the trace
sampled every 0.02 mm), the mean of the two
leaflets and each one. The README's table in "Valve outputs and metrics" (session 39) is its
output. ``--out`` writes the rows as JSON (refused if the file exists).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from mpi4py import MPI

import mvfem
import mvfem.run as run_mod
from mvfem.errors import InputError
from mvfem.scriptargs import errors, existing_out
from mvfem.scene import load_scene

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"


def parse_meshes(text: str) -> list[tuple[float, int]]:
    """``"5,2r1"`` -> ``[(5.0, 0), (2.0, 1)]``; ValueError on anything else."""
    out = []
    for item in text.split(","):
        size, _, refine = item.strip().partition("r")
        out.append((float(size), int(refine) if refine else 0))
        if out[-1][0] <= 0 or out[-1][1] < 0:
            raise ValueError(item)
    return out


def close(size: float, refine: int, pressure_kpa: float) -> dict | None:
    """One closure of the demo on that mesh; its row on rank 0 (None elsewhere)."""
    scene = load_scene(DEMO).with_changes({"mesh.size": size, "mesh.refine": refine,
                                           "load.pressure": f"{pressure_kpa} kPa"})
    t0 = time.perf_counter()
    res = run_mod.solve(scene, progress=False, write=False)
    wall = time.perf_counter() - t0
    if MPI.COMM_WORLD.rank != 0:
        return None
    s, v = res.summary, res.summary["valve"]
    return {"size_mm": size, "refine": refine, "cells": int(s["cells"]),
            "converged": bool(s["converged"]), "wall_s": wall,
            "coaptation_length_mm": v["coaptation_length_mm"],
            "stepped_per_leaflet_mm": v["coaptation_length_per_leaflet_mm"],
            "trace_mm": v["coaptation_trace_length_mm"],
            "trace_per_leaflet_mm": v["coaptation_trace_length_per_leaflet_mm"]}


def table(rows: list[dict]) -> str:
    lines = ["| mesh | cells | converged | `coaptation_length_mm` | continuous | per leaflet, "
             "stepped | per leaflet, continuous |", "|---|---:|---|---:|---:|---|---|"]
    for r in rows:
        mesh = f"{r['size_mm']:g} mm" + (f" refined {r['refine']}x" if r["refine"] else "")
        each = lambda d: " / ".join(f"{v:.2f}" for v in d.values())  # noqa: E731
        lines.append(f"| {mesh} | {r['cells']} | {r['converged']} | "
                     f"{r['coaptation_length_mm']:.2f} | {r['trace_mm']:.2f} | "
                     f"{each(r['stepped_per_leaflet_mm'])} | {each(r['trace_per_leaflet_mm'])} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--meshes", default="5,4,3,2.5,2,1.5,2r1,2r2",
                   help="mesh sizes in mm, r<n> for refined n times, comma-separated")
    p.add_argument("--pressure", type=float, default=16.0, help="kPa")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    a = p.parse_args(argv)
    root, error = errors("coaptation_trace")
    try:
        meshes = parse_meshes(a.meshes)
    except ValueError:
        return error(f"--meshes {a.meshes!r}: not sizes in mm with optional r<refine>")
    if msg := existing_out(a.out):
        return error(msg)
    rows = []
    for size, refine in meshes:
        try:
            row = close(size, refine, a.pressure)
        except InputError as e:
            return error(str(e))
        if root:
            rows.append(row)
            print(f"{size:g} mm, refined {refine}x: {row['cells']} cells, {row['wall_s']:.1f} s",
                  flush=True)
    if root:
        print(table(rows), flush=True)
        if a.out is not None:
            Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
