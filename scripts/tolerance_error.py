"""The equilibrium tolerance of a nested valve closure: time saved against distance moved.

    python scripts/tolerance_error.py --refine 2 --pressures 16,16.5 --tolerances 1e-4,1e-5
                                      [--size 2] [--out tolerance.json]

Closes `mvfem demo`'s scene (mesh ``--size``, mm) refined ``--refine`` times (nested levels)
at each pressure (kPa), first at the scene's default ``solver.tolerance`` (1e-8 of the load),
then at each of ``--tolerances``, one run after the other in this process. The tolerance is
the scene's own (finest) level's: the coarser levels are closed to the default whatever the
scene sets (``mvfem.run._coarse_start``), so every run of one pressure takes the same path
through them and the looser runs stop the finest level earlier on that path. Prints a
markdown row per run: the steps of each level (coarsest first), the wall time, the
equilibrium residual, and against the default's closure the largest and the root-mean-square
distance of the nodes (mm) and the change of the coaptation trace length (mm). ``--out``
writes the rows as JSON (an existing file is refused).

What the distances are worth: the closure of the demo refined once is 0.026 mm from the demo
refined twice on average (`make bench`), so a tolerance whose distance is far below the
mesh's own error is a speed setting (README, "The scene's tolerance is its own level's").
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import mvfem
from mvfem.errors import InputError
from mvfem.scriptargs import add_demo_levels, errors, existing_out

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"


def level_steps(summary: dict) -> list[int]:
    """The Newton steps of each level of a run, coarsest first (summary ``coarse_start``)."""
    from mvfem.run import coarse_levels

    return [cs["steps"] for cs in reversed(coarse_levels(summary))] + \
        [summary["newton_iterations"]]


def close(size: float, refine: int, pressure_kpa: float, tolerance: float | None):
    """One closure; its row and its nodal positions' displacement (rank 0, (N, 3))."""
    from mvfem.run import solve

    changes = {"mesh.size": size, "mesh.refine": refine, "load.pressure": f"{pressure_kpa} kPa"}
    if tolerance is not None:
        changes["solver.tolerance"] = tolerance
    scene = mvfem.load_scene(DEMO).with_changes(changes)
    t0 = time.perf_counter()
    res = solve(scene, progress=False, write=False)
    wall = time.perf_counter() - t0
    s = res.summary
    u = res.model.point_terms.view.gather(res.model.u.vector.array_r)
    row = {"pressure_kPa": pressure_kpa, "tolerance": scene["solver"]["tolerance"],
           "converged": bool(s["converged"]), "steps": level_steps(s), "wall_s": wall,
           "equilibrium_residual": s["equilibrium_residual"],
           "trace_length_mm": s["valve"]["coaptation_trace_length_mm"]}
    return row, u


def table(rows: list[dict]) -> str:
    lines = ["| pressure (kPa) | tolerance | steps (levels) | wall (s) | residual | largest "
             "distance (mm) | rms distance (mm) | trace length change (mm) |",
             "|---:|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        d = "-" if r.get("max_mm") is None else f"{r['max_mm']:.2e}"
        rms = "-" if r.get("rms_mm") is None else f"{r['rms_mm']:.2e}"
        dt = "-" if r.get("trace_change_mm") is None else f"{r['trace_change_mm']:+.2e}"
        lines.append(f"| {r['pressure_kPa']:g} | {r['tolerance']:g} | "
                     f"{' + '.join(str(n) for n in r['steps'])} | {r['wall_s']:.1f} | "
                     f"{r['equilibrium_residual']:.2g} | {d} | {rms} | {dt} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_demo_levels(p)
    p.add_argument("--tolerances", default="1e-4,1e-5", help="comma-separated, each looser "
                   "than the default 1e-8")
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    a = p.parse_args(argv)
    root, error = errors("tolerance_error")
    try:
        pressures = [float(v) for v in a.pressures.split(",")]
        tolerances = [float(v) for v in a.tolerances.split(",")]
    except ValueError:
        return error(f"--pressures {a.pressures!r} / --tolerances {a.tolerances!r}: not numbers")
    if not all(t > 0 for t in tolerances):
        return error(f"--tolerances {a.tolerances!r}: must be positive")
    if msg := existing_out(a.out):
        return error(msg)
    rows = []
    for pressure in pressures:
        try:
            ref, u_ref = close(a.size, a.refine, pressure, None)
            rows.append(ref)
            for tol in tolerances:
                row, u = close(a.size, a.refine, pressure, tol)
                if root:
                    d = np.linalg.norm(u - u_ref, axis=1)
                    row.update(max_mm=float(d.max()), rms_mm=float(np.sqrt(np.mean(d * d))),
                               trace_change_mm=row["trace_length_mm"] - ref["trace_length_mm"])
                rows.append(row)
        except InputError as e:
            return error(str(e))
        if root:
            print(table([r for r in rows if r["pressure_kPa"] == pressure]), "\n", flush=True)
    if a.out is not None and root:
        Path(a.out).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
