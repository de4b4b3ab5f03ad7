"""The valve cases of the README ("The valve", measured): the built-in healthy valve, a flail
posterior segment, a dilated annulus, lengthened marginal chordae, the patient annulus and an
imported valve, each closed at 16 kPa; one table row per case.

    python scripts/valve_cases.py --out results/cases [--only demo,flail] [--set key=value]
    mpirun -n 2 python scripts/valve_cases.py --out results/cases2 --only demo

Writes every run's outputs under OUT/<case>/ and the table as cases.csv; prints the rows as
they finish and the markdown table at the end.
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
from mvfem.scene import parse_set_option

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"
SCENES = Path(__file__).parent / "scenes"
FLAIL = [{"leaflet": "posterior", "between": [0.2, 0.8], "rupture": True}]

CASES = {
    "demo": (DEMO, {}),
    "flail": (DEMO, {"chordae.edit": FLAIL}),
    "dilated": (SCENES / "valve_dilated.toml", {}),
    "prolapse": (SCENES / "valve_prolapse.toml", {}),
    "patient": (SCENES / "valve_patient.toml", {}),
    "imported": (SCENES / "valve_imported.toml", {}),
}


def row(case: str, s: dict) -> dict:
    v = s.get("valve") or {}
    t = s.get("timing") or {}
    return {"case": case, "cells": s["cells"], "ranks": MPI.COMM_WORLD.size,
            "converged": s["converged"], "wall_time_s": round(s["wall_time_s"], 1),
            "contact_s": round(t.get("contact_s", float("nan")), 1),
            "newton_iterations": s["newton_iterations"],
            "residual": s.get("equilibrium_residual"),
            "orifice_mm2": v.get("regurgitant_orifice_area_mm2"),
            "projected_mm2": v.get("projected_orifice_area_mm2"),
            "leak_gap_mm2": v.get("leak_gap_area_mm2"),
            "annulus_mm2": v.get("annulus_area_mm2"),
            "coaptation_length_mm": v.get("coaptation_length_mm"),
            "coaptation_area_mm2": v.get("coaptation_area_mm2"),
            "tenting_mm": v.get("tenting_height_mm"),
            "chordae_N": (v.get("chordae_force_N") or {}).get("total"),
            "penetration_mm": s.get("max_penetration_mm"),
            "closest_mm": (s.get("contact") or {}).get("min_distance_mm")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default="results/cases")
    p.add_argument("--only", default=",".join(CASES), help="comma-separated cases: "
                   + ", ".join(CASES))
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="scene change for every case (e.g. mesh.size=1.5)")
    args = p.parse_args(argv)
    comm = MPI.COMM_WORLD
    out = Path(args.out)
    if comm.rank == 0:
        prepare_out(out)
    comm.Barrier()
    rows = []
    for case in args.only.split(","):
        path, changes = CASES[case]
        changes = dict(changes)
        changes.update(parse_set_option(t) for t in args.set)
        scene = mvfem.load_scene(path).with_changes(changes)
        r = mvfem.solve(scene, out=out / case, progress=False)
        rows.append(row(case, r.summary))
        if comm.rank == 0:
            print(json.dumps(rows[-1]), flush=True)
    if comm.rank == 0:
        with open(out / "cases.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        print("| " + " | ".join(rows[0]) + " |")
        print("|" + "---|" * len(rows[0]))
        for r_ in rows:
            print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v)
                                    for v in r_.values()) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
