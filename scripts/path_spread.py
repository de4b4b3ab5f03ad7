"""How far a closure's numbers move with the solver's path alone.

    python scripts/path_spread.py SCENE [--repair R.toml] [--ramp-steps 10,20,30,40]
                                  [--motion with-pressure[,before-pressure]]
                                  [--set key=value ...] [--out spread.json]

Closes ``SCENE`` (with the repair file merged in, as ``mvfem repair-compare`` merges it) once
for each ``solver.ramp_steps`` and ``solver.motion`` given, one after the other in this
process, and prints one row a run (converged, steps, wall time, regurgitant orifice, stepped
coaptation length, continuous trace length, tenting height) and the spread (largest minus
smallest) of each number over the converged runs. The scene, the pressure and the repair are
the same in every run: only the path to the equilibrium differs. A ring that shrinks the
annulus leaves the leaflets more tissue than the orifice needs, and they can rest in more than
one fold: README "Repairs", "Which closure: the path picks among equilibria" (session 42),
whose table this script makes. Differences between repairs smaller than the spread are not
differences. `mvfem repair-compare ... --paths 10,20,30,40 --weights 0.05,0.2,0.4` makes such
runs for every case of a comparison and reports each number's range (session 46); this
script also varies ``solver.motion``.

Bad input (a missing scene or repair file, a bad key, a list that is not numbers, an
``--out`` that exists) is one line and exit code 2, before any run. Ctrl-C or SIGTERM during a
run stops it at a step boundary; the runs already done are printed (and written to ``--out``,
marked ``"interrupted"``), with one line saying so, and the exit code is 130 or 143.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import mvfem
from mvfem.errors import InputError
from mvfem.scene import parse_set_option

#: the numbers compared (summary.json ``valve`` keys) and their table headings
KEYS = (("regurgitant_orifice_area_mm2", "orifice mm^2"),
        ("coaptation_length_mm", "coaptation mm"),
        ("coaptation_trace_length_mm", "trace mm"),
        ("tenting_height_mm", "tenting mm"))


def closures(scene_path: str, repair: str | None = None, ramp_steps=(10, 20, 30, 40),
             motions=("with-pressure",), changes: dict | None = None,
             runs: list | None = None) -> list[dict]:
    """One record per (motion, ramp_steps): the path, converged, steps, wall time and KEYS.
    Each is appended to ``runs`` (a new list if None) as its run ends, so a caller that is
    interrupted keeps the runs done."""
    scene = mvfem.load_scene(scene_path)
    title = scene.data.get("title") or Path(scene_path).stem
    if repair is not None:
        from mvfem.compare import load_repair

        _, title, repair_changes = load_repair(repair, scene)
        scene = scene.with_changes(repair_changes)
    if changes:
        scene = scene.with_changes(changes)
    runs = [] if runs is None else runs
    for motion in motions:
        for n in ramp_steps:
            t0 = time.perf_counter()
            r = mvfem.solve(scene.with_changes({"solver.ramp_steps": int(n),
                                                "solver.motion": motion}),
                            progress=False, write=False)
            s = r.summary
            v = s.get("valve") or {}
            rec = {"title": title, "motion": motion, "ramp_steps": int(n),
                   "converged": bool(s["converged"]), "steps": s["newton_iterations"],
                   "wall_s": time.perf_counter() - t0,
                   "max_penetration_mm": s.get("max_penetration_mm")}
            rec.update({k: v.get(k) for k, _ in KEYS})
            runs.append(rec)
            print(f"  {motion}, ramp_steps {n}: {'converged' if rec['converged'] else 'stopped'}"
                  f" in {rec['steps']} steps, {rec['wall_s']:.1f} s", file=sys.stderr, flush=True)
    return runs


def spread(runs: list[dict]) -> dict:
    """Largest minus smallest of each KEY over the converged runs (None with fewer than 2)."""
    ok = [r for r in runs if r["converged"]]
    out = {}
    for k, _ in KEYS:
        vals = [r[k] for r in ok if r.get(k) is not None]
        out[k] = max(vals) - min(vals) if len(vals) >= 2 else None
    return out


def table(runs: list[dict]) -> str:
    heads = ["path", "converged", "steps", "wall s", *[h for _, h in KEYS]]
    lines = ["| " + " | ".join(heads) + " |", "|" + "---|" * len(heads)]

    def fmt(v):
        return "-" if v is None else f"{v:.2f}"
    for r in runs:
        lines.append(f"| {r['motion']}, ramp_steps {r['ramp_steps']} | "
                     f"{'yes' if r['converged'] else 'no'} | {r['steps']} | {r['wall_s']:.1f} | "
                     + " | ".join(fmt(r[k]) for k, _ in KEYS) + " |")
    sp = spread(runs)
    lines.append("| spread (converged runs) | | | | " + " | ".join(fmt(sp[k]) for k, _ in KEYS)
                 + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--repair", help="a repair file (TOML of scene keys), as for repair-compare")
    ap.add_argument("--ramp-steps", default="10,20,30,40",
                    help="solver.ramp_steps values, comma-separated (default 10,20,30,40)")
    ap.add_argument("--motion", default="with-pressure",
                    help="solver.motion values, comma-separated (with-pressure, before-pressure)")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scene key for every run, e.g. mesh.size=3")
    ap.add_argument("--out", help="write the runs and the spread as JSON here")
    a = ap.parse_args(argv)
    try:
        try:
            steps = [int(x) for x in a.ramp_steps.split(",") if x.strip()]
        except ValueError:
            raise InputError(f"--ramp-steps: {a.ramp_steps!r} is not a list of whole numbers")
        if not steps or min(steps) < 1:
            raise InputError(f"--ramp-steps: {a.ramp_steps!r}: give positive whole numbers")
        motions = [m.strip() for m in a.motion.split(",") if m.strip()]
        bad = [m for m in motions if m not in ("with-pressure", "before-pressure")]
        if not motions or bad:
            raise InputError(f"--motion: {a.motion!r}: each must be with-pressure or "
                             "before-pressure")
        changes = dict(parse_set_option(kv) for kv in a.set)
        for f in (a.scene, a.repair):
            if f is not None and not Path(f).is_file():
                raise InputError(f"{f}: no such file")
        if a.out and Path(a.out).exists():  # nothing a user wrote is overwritten
            raise InputError(f"--out {a.out}: exists; choose another name")
        runs: list[dict] = []
        stop = None
        try:
            closures(a.scene, a.repair, steps, motions, changes, runs=runs)
        except KeyboardInterrupt as e:  # (mvfem.Interrupted: a signal stopped a run)
            stop = e
    except InputError as e:
        print(f"path_spread: {e}", file=sys.stderr)
        return 2
    if stop is not None:
        print(f"path_spread: {stop or 'interrupted'}; {len(runs)} of "
              f"{len(steps) * len(motions)} runs done", file=sys.stderr)
    if runs:
        print(table(runs))
    if a.out:
        Path(a.out).write_text(json.dumps({"runs": runs, "spread": spread(runs),
                                           "interrupted": stop is not None}, indent=1))
    return 0 if stop is None else getattr(stop, "exit_code", 130)


if __name__ == "__main__":
    sys.exit(main())
