"""Where a nested closure's time goes, level by level.

    python scripts/level_costs.py --refine 2 --pressures 16,16.5,17 [--size 2] [--history]
                                  [--out costs.json]

Closes `mvfem demo`'s scene (mesh ``--size``, mm) refined ``--refine`` times, each level from
the closure of the level below (``solver.nested``), at each pressure (kPa), one after the
other in this process, and prints for every pseudo-time solve (a level; a level restarted
from the open state is a second row): how it started (the closure below as moved, smoothed
where it crossed, scaled back, or the open state), its dofs, steps, refused steps, growths of
the matrix's pattern (each a new symbolic analysis), updates solved with the symmetric tangent,
convexified re-solves, updates solved with the projected blocks at once (``ahead``:
``PseudoTransient.convex_window``), and its wall time with the linear solves, the assembly
(residuals, tangents, energies, the load's work) and the point terms (contact, chordae,
hinges) in it;
then the run's total and the closed coaptation. ``--history`` also prints the finest level's
steps (weight ``k``, the update's fraction ``alpha``, residual, accepted). ``--hot`` also
records, at each accepted step of every level, where the residual is: the share of ``|F|^2``
held by the 50 largest nodal forces, the median nodal force, and the largest nodal move of the
step (mm); and each level's largest nodal distance between its start and its end (README,
"Where the finest level's steps go"). ``--out`` writes all of it as JSON.

The runs of README "Nested levels" (sessions 31-32) were made with this breakdown. Paths move
with roundoff by tens of percent (README, "Solving"), so compare codes on several pressures,
and per step.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

import mvfem
import mvfem.run as run_mod
from mvfem.errors import InputError
from mvfem.scriptargs import add_demo_levels, errors, existing_out
from mvfem.scene import load_scene
from mvfem.solver import PseudoTransient

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"

#: the rows of the solves of the current run
LEVELS: list[dict] = []
#: --hot: where the residual is at each accepted step
HOT = False
#: the nodal forces whose share of |F|^2 --hot records
TOP = 50


class Recorded(PseudoTransient):
    """A pseudo-time solve that records what it cost (the run's solves are made as these)."""

    def run(self):
        pb = self.problem
        pt = pb.point_terms
        a0, g0, p0 = pb.assembly_s, pb.regrowths, (pt.time_s if pt is not None else 0.0)
        hot, inner = [], self.on_step
        if HOT:
            gather = pt.view.gather  # (N, 3) nodal values on rank 0, None elsewhere
            start = gather(pb.u.vector.array_r)
            last = [start]

            def on_step(rec, ptc):
                # at an accepted step b holds F at the new state (its residual was the last
                # evaluated) and u that state (the load's work leaves it there to roundoff)
                if rec.accepted:
                    f, u = gather(pb.b.array_r), gather(pb.u.vector.array_r)
                    if f is not None:
                        n2 = np.sum(f * f, axis=1)
                        top = np.sort(n2)[::-1][:TOP].sum()
                        hot.append({"step": rec.step, "top_share": float(top / max(n2.sum(),
                                                                                    1e-300)),
                                    "median_force": float(np.median(np.sqrt(n2))),
                                    "largest_move_mm": float(np.linalg.norm(u - last[0],
                                                                            axis=1).max())})
                        last[0] = u
                if inner is not None:
                    inner(rec, ptc)
            self.on_step = on_step
        t0 = time.perf_counter()
        try:
            return super().run()
        finally:
            h = self.history
            extra = {}
            if HOT:
                end = gather(pb.u.vector.array_r)
                extra = {"hot": hot, "start_to_end_mm": None if end is None else
                         float(np.linalg.norm(end - start, axis=1).max())}
            LEVELS.append({
                "dofs": int(pb.x.getSize()), "steps": len(h),
                "refused": sum(not r.accepted for r in h), "growths": pb.regrowths - g0,
                "symmetric": self.symmetric_solves, "convexified": self.convexified,
                "ahead": self.convexified_ahead,
                "wall_s": time.perf_counter() - t0, "linear_s": self.solve_s,
                "assembly_s": pb.assembly_s - a0,
                "point_terms_s": (pt.time_s if pt is not None else 0.0) - p0,
                # a residual not evaluated (the potential rose, Newton's regime): None
                "history": [{"k": r.weight, "alpha": r.alpha,
                             "residual": None if np.isnan(r.residual) else r.residual,
                             "accepted": r.accepted} for r in h], **extra})


def close(refine: int, size: float, pressure_kpa: float) -> dict:
    """One nested closure of the demo; its levels' rows and the run's summary numbers."""
    scene = load_scene(DEMO).with_changes({"mesh.size": size, "mesh.refine": refine,
                                           "load.pressure": f"{pressure_kpa} kPa"})
    LEVELS.clear()
    t0 = time.perf_counter()
    res = run_mod.solve(scene, progress=False, write=False)
    s = res.summary
    return {"pressure_kPa": pressure_kpa, "refine": refine, "size_mm": size,
            "wall_s": time.perf_counter() - t0, "converged": bool(s["converged"]),
            "newton_iterations": s["newton_iterations"], "load_steps": s["load_steps"],
            "coaptation_mm": s["valve"]["coaptation_length_mm"],
            "coarse_start": s.get("coarse_start"), "levels": list(LEVELS)}


def starts(rec: dict) -> list[str]:
    """How each level started, coarsest first (summary.json ``coarse_start``, nested): "open",
    "moved" (the closure below as moved), "smoothed (k)" (smoothed where it crossed, k
    sweeps: ``sequence.unfold``), "x s" (scaled back toward the open state) or "open (...)"
    where the moved state was refused; one per level only where each level is one solve."""
    out = ["open"]
    for cs in reversed(run_mod.coarse_levels(rec)):
        if not cs.get("used"):
            out.append("open (refused)")
        elif cs.get("unfolded"):
            out.append(f"smoothed ({cs['unfolded']})")
        elif cs.get("scale", 1.0) != 1.0:
            out.append(f"x {cs['scale']:g}")
        else:
            out.append("moved")
    return out if len(out) == len(rec["levels"]) else [""] * len(rec["levels"])


def table(rec: dict, history: bool) -> str:
    lines = [f"refine {rec['refine']}, {rec['size_mm']} mm, {rec['pressure_kPa']} kPa: "
             f"{rec['wall_s']:.1f} s, converged {rec['converged']}, coaptation "
             f"{rec['coaptation_mm']:.6f} mm", "",
             "| start | dofs | steps | refused | growths | symmetric | convexified | ahead | "
             "wall (s) | linear solves (s) | assembly (s) | point terms (s) | a step (s) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for lv, start in zip(rec["levels"], starts(rec)):
        lines.append(f"| {start} | {lv['dofs']} | {lv['steps']} | {lv['refused']} | "
                     f"{lv['growths']} | "
                     f"{lv['symmetric']} | {lv['convexified']} | {lv['ahead']} | "
                     f"{lv['wall_s']:.2f} | "
                     f"{lv['linear_s']:.2f} | {lv['assembly_s']:.2f} | "
                     f"{lv['point_terms_s']:.2f} | {lv['wall_s'] / max(lv['steps'], 1):.3f} |")
    if history and rec["levels"]:
        last = rec["levels"][-1]
        hot = {d["step"]: d for d in last.get("hot", [])}
        head = "| step | k | alpha | residual | accepted |"
        rule = "|---:|---:|---:|---:|---|"
        if "hot" in last:
            head += f" top {TOP} share of F^2 | median nodal force | largest move (mm) |"
            rule += "---:|---:|---:|"
        lines += ["", head, rule]
        for i, h in enumerate(last["history"], 1):
            r = "-" if h["residual"] is None else f"{h['residual']:.3g}"  # not evaluated
            row = f"| {i} | {h['k']:.3g} | {h['alpha']:.3g} | {r} | {h['accepted']} |"
            if "hot" in last:
                d = hot.get(i)
                row += (f" {d['top_share']:.3f} | {d['median_force']:.2g} | "
                        f"{d['largest_move_mm']:.2g} |" if d else " | | |")
            lines.append(row)
        if "hot" in last:
            lines += ["", f"finest level: start to end at most {last['start_to_end_mm']:.4g} mm"]
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_demo_levels(p)
    p.add_argument("--history", action="store_true", help="the finest level's steps too")
    p.add_argument("--hot", action="store_true",
                   help="where the residual is at each accepted step (see above)")
    p.add_argument("--out", default=None, help="write the records as JSON here")
    a = p.parse_args(argv)
    root, error = errors("level_costs")   # (under mpirun: rank 0 prints and writes)
    try:
        pressures = [float(v) for v in a.pressures.split(",")]
    except ValueError:
        return error(f"--pressures {a.pressures!r}: not numbers")
    if msg := existing_out(a.out):
        return error(msg)
    global HOT
    HOT = a.hot
    run_mod.PseudoTransient = Recorded
    records = []
    for pressure in pressures:
        try:
            rec = close(a.refine, a.size, pressure)
        except InputError as e:
            return error(str(e))
        records.append(rec)
        if root:
            print(table(rec, a.history), "\n", flush=True)
    if a.out is not None and root:
        Path(a.out).write_text(json.dumps(records, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
