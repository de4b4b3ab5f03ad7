"""Variants of the pseudo-time control on the finest level of a nested closure, each from the
same transferred start.

    python scripts/level_variants.py --refine 2 --pressures 16,16.5 base: \\
        mg2:min_growth=2 kf64:k_first_x=64 [--size 2] [--out variants.json]

Closes `mvfem demo`'s scene (mesh ``--size``, mm) refined ``--refine`` times (nested levels)
at each pressure (kPa). The coarser levels are closed once; the finest level is then solved
once per variant, every time from the same transferred state, with the Fung laws' exponent
cap as it started and the matrix made anew (``SNESProblem.reset_pattern``): the first variant
repeated takes its path again bit for bit. A variant is ``NAME:FIELD=VALUE,...`` with fields
of :class:`mvfem.solver.PseudoTransient` (``min_growth``, ``max_growth``, ``reject``,
``shrink``, ``backtracks``, ``convex_window``, ...) set for the finest level only, and
``k_first_x``: the first weight as a multiple of the level's start weight ``k0`` (the runs
use 16, ``mvfem.run.NESTED_FIRST_WEIGHT``); ``NAME:`` alone is the control as it is. The
run goes on from the last variant's closure. Prints, per pressure, a row per variant: its
steps, refused steps, convergence, wall time and linear solves, and the largest and the
root-mean-square nodal distance of its closure from the first variant's; then each variant's
totals. ``--out`` writes the rows as JSON (an existing file is refused).

Why: these paths move by tens of percent with roundoff and with any change of the control
(README, "Solving"), so a control is judged on many pressures, and the coarser levels, the
same for every variant, are closed once. The finest level alone of the demo refined twice
takes 11-34 s a variant. Session 45's knobs, measured with it, are in "Tried in session 45
and dropped" ("Nested levels").
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

import mvfem
import mvfem.run as run_mod
from mvfem.errors import InputError
from mvfem.scriptargs import add_demo_levels, errors, existing_out
from mvfem.solver import PseudoTransient

DEMO = Path(mvfem.__file__).parent / "data" / "demo.toml"

#: what a run reports (the run goes on with the last variant's)
REPORTS = {"history", "stop_reason", "solve_s", "convexified", "convexified_ahead",
           "symmetric_solves", "floor", "at_floor"}
#: what every variant keeps: the problem and the hooks
HOOKS = {"problem", "on_step", "ramp"}
#: the fields a variant may set, with their defaults (their types read the values)
FIELDS = {f.name: f.default for f in dataclasses.fields(PseudoTransient)
          if f.name not in REPORTS | HOOKS}


def parse_variant(spec: str) -> tuple[str, dict]:
    """``NAME:FIELD=VALUE,...`` -> (name, {field: value}); ValueError with the reason."""
    name, _, rest = spec.partition(":")
    if not name:
        raise ValueError(f"{spec!r}: no name before ':'")
    opts = {}
    for item in filter(None, rest.split(",")):
        field, eq, value = item.partition("=")
        if not eq:
            raise ValueError(f"{spec!r}: {item!r} is not FIELD=VALUE")
        if field == "k_first_x":
            kind = float
        elif field not in FIELDS:
            raise ValueError(f"{spec!r}: PseudoTransient has no field {field!r} a variant may "
                             f"set (one of {', '.join(sorted(FIELDS))}, k_first_x)")
        else:
            default = FIELDS[field]
            kind = type(default) if isinstance(default, (bool, int, float)) else float
        try:
            if kind is bool:
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                opts[field] = value.lower() in ("true", "1")
            elif value.lower() == "none" and FIELDS.get(field, 0) is None:
                opts[field] = None
            else:
                opts[field] = kind(value)
        except ValueError:
            raise ValueError(f"{spec!r}: {field} = {value!r} is not a {kind.__name__}") from None
    return name, opts


class _Finest:
    """What the finest level's variants need: the model built first by a run (the scene's
    own; its coarser levels are built after it), whether its solve was varied already (a
    second solve with the true law after a closure under the exponent cap, rare, is not) and
    the rows of its variants."""

    model = None
    pressure = None
    varied = False
    variants: list = []
    rows: list = []


class Varied(PseudoTransient):
    """The run's pseudo-time solves; on the finest model's, each variant from its start."""

    def run(self):
        model = _Finest.model
        if model is None or self.problem.u is not model.u or _Finest.varied:
            return super().run()
        _Finest.varied = True
        pb = self.problem
        start = pb.u.vector.copy()
        cap = float(model.exponent_cap.value)
        base = {name: getattr(self, name) for name in (*FIELDS, *HOOKS)}
        n_owned = model.V.dofmap.index_map.size_local * 3
        first = None
        last = info = None
        for name, opts in _Finest.variants:
            start.copy(pb.u.vector)
            pb.u.x.scatter_forward()
            model.exponent_cap.value = cap
            pb.reset_pattern()
            o = dict(opts)
            if "k_first_x" in o:
                o["k_first"] = o.pop("k_first_x") * base["k0"]
            ptc = PseudoTransient(**{**base, **o})
            t0 = time.perf_counter()
            info = ptc.run()
            wall = time.perf_counter() - t0
            x = model.view.gather(model.u.x.array[:n_owned])
            dist = rms = None
            if x is not None:
                if first is None:
                    first = x.copy()
                d = np.linalg.norm(x - first, axis=1)
                dist, rms = float(d.max(initial=0.0)), float(np.sqrt(np.mean(d * d)))
            _Finest.rows.append({
                "pressure_kPa": _Finest.pressure, "variant": name, "options": opts,
                "steps": len(ptc.history), "refused": len(ptc.history) - ptc.accepted_steps,
                "converged": bool(info.converged), "wall_s": wall, "linear_s": ptc.solve_s,
                "residual": float(info.residual_norm), "distance_mm": dist, "rms_mm": rms})
            last = ptc
        start.destroy()
        # the run goes on from the last variant's closure, as if it had been the only one
        for name in REPORTS:
            setattr(self, name, getattr(last, name))
        return info


def _build(scene, comm):
    model = _BUILD(scene, comm)
    if _Finest.model is None:
        _Finest.model = model
    return model


_BUILD = run_mod.build_model


def close(size: float, refine: int, pressure_kpa: float) -> None:
    """The nested closure at one pressure, its finest level once per variant."""
    scene = mvfem.load_scene(DEMO).with_changes(
        {"mesh.size": size, "mesh.refine": refine, "load.pressure": f"{pressure_kpa} kPa"})
    _Finest.model, _Finest.pressure, _Finest.varied = None, pressure_kpa, False
    run_mod.build_model, run_mod.PseudoTransient = _build, Varied
    try:
        run_mod.solve(scene, progress=False, write=False)
    finally:
        run_mod.build_model, run_mod.PseudoTransient = _BUILD, PseudoTransient
        _Finest.model = None


def table(rows: list[dict]) -> str:
    lines = ["| pressure (kPa) | variant | steps | refused | converged | wall (s) | "
             "linear solves (s) | largest / rms distance from the first (mm) |",
             "|---:|---|---:|---:|---|---:|---:|---:|"]
    for r in rows:
        d = "-" if r["distance_mm"] is None else \
            f"{r['distance_mm']:.2e} / {r['rms_mm']:.2e}"
        lines.append(f"| {r['pressure_kPa']:g} | {r['variant']} | {r['steps']} | "
                     f"{r['refused']} | {r['converged']} | {r['wall_s']:.1f} | "
                     f"{r['linear_s']:.1f} | {d} |")
    return "\n".join(lines)


def totals(rows: list[dict]) -> str:
    lines = ["| variant | steps | refused | wall (s) | converged |", "|---|---:|---:|---:|---|"]
    for name in dict.fromkeys(r["variant"] for r in rows):
        mine = [r for r in rows if r["variant"] == name]
        lines.append(f"| {name} | {sum(r['steps'] for r in mine)} | "
                     f"{sum(r['refused'] for r in mine)} | "
                     f"{sum(r['wall_s'] for r in mine):.1f} | "
                     f"{sum(r['converged'] for r in mine)}/{len(mine)} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("variants", nargs="+", help="NAME:FIELD=VALUE,... (NAME: alone: as it is)")
    add_demo_levels(p)
    p.add_argument("--out", default=None, help="write the rows as JSON here")
    a = p.parse_args(argv)
    root, error = errors("level_variants")
    try:
        pressures = [float(v) for v in a.pressures.split(",")]
    except ValueError:
        return error(f"--pressures {a.pressures!r}: not numbers")
    if a.refine < 1:
        return error(f"--refine {a.refine}: the finest level must be a nested one (1 or more)")
    try:
        variants = [parse_variant(v) for v in a.variants]
    except ValueError as e:
        return error(f"variant {e}")
    names = [n for n, _ in variants]
    if len(set(names)) != len(names):
        return error(f"variant names repeat: {', '.join(names)}")
    if msg := existing_out(a.out):
        return error(msg)
    _Finest.variants, _Finest.rows = variants, []
    for pressure in pressures:
        done = len(_Finest.rows)
        try:
            close(a.size, a.refine, pressure)
        except InputError as e:
            return error(str(e))
        if root:
            print(table(_Finest.rows[done:]), "\n", flush=True)
    if root:
        print(totals(_Finest.rows), flush=True)
        if a.out is not None:
            Path(a.out).write_text(json.dumps(_Finest.rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
