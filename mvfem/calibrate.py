"""Calibrate scene parameters (chordal length factors) against a reference closed surface.

Issue 9, item 2: find the values of a few scene keys (``chordae.marginal.length_factor``, ...)
that minimise the mean distance between the predicted closed leaflets and a reference closed
surface (``summary["reference"]["mean_abs_error_mm"]`` of :mod:`mvfem.distance`). Each
evaluation is one :func:`mvfem.solve` into ``DIR/evals/NNN`` from the open valve; with
``warm=True`` from the last converged evaluation instead, 2-5 x faster but path dependent: the
closed valve with contact has more than one equilibrium, and on the synthetic truth (README)
the warm-started solves landed 0.27-0.29 mm from the truth's closed state where cold solves
reproduce it. One parameter: scipy's bounded Brent (``minimize_scalar``); several:
Nelder-Mead with bounds. The start is always evaluated first (the "before" error, and the check
that the reference overlaps the valve).

Outputs: ``evaluations.csv`` (every evaluation) and ``calibration.json`` (fitted values, error
before and after, time, and the held-apart quantities coaptation length and tenting height,
compared with the reference's own ``summary.json`` when one lies next to the reference file).
"""

from __future__ import annotations

import csv
import json
import logging
import time
from pathlib import Path
from typing import Callable

import numpy as np
from mpi4py import MPI

from mvfem.errors import InputError

__all__ = ["calibrate", "parse_fit", "parse_bounds", "parse_start", "OVERLAP_MM"]

log = logging.getLogger(__name__)
#: a start whose mean distance to the reference exceeds this does not overlap the valve, mm
OVERLAP_MM = 10.0
#: a reference surface this many times larger or smaller across than the open valve is not
#: the same valve closed (a file in metres: 1000 x smaller; in cm, 10 x), refused before any
#: solve; a part of a leaflet may be a few times smaller
EXTENT_RATIO = 8.0
#: default bounds of every fitted key (a chordal length factor)
DEFAULT_BOUNDS = (0.8, 1.4)
#: the optimisers stop when the parameters are known to this (absolute)
XATOL = 2e-3
#: pseudo-time steps of one evaluation unless the scene says (the 4 mm demo closes in ~200;
#: a stall near contact would otherwise run to the solver's 1500)
MAX_STEPS = 500
HELD_APART = ("coaptation_length_mm", "tenting_height_mm", "regurgitant_orifice_area_mm2")


def parse_fit(text: str) -> list[str]:
    keys = [k.strip() for k in text.split(",") if k.strip()]
    if not keys:
        raise InputError(f"--fit {text!r}: expected one or more scene keys, e.g. "
                         "chordae.marginal.length_factor")
    if len(set(keys)) != len(keys):
        raise InputError(f"--fit {text!r}: a key is given twice")
    return keys


def _floats(text: str, option: str) -> list[str]:
    return [t.strip() for t in text.split(",")]


def parse_bounds(text: str | None, n: int) -> list[tuple[float, float]]:
    """``"0.8:1.4,0.9:1.2"`` (one per key, or one for all) -> [(lo, hi), ...]."""
    if text is None:
        return [DEFAULT_BOUNDS] * n
    items = _floats(text, "--bounds")
    if len(items) == 1:
        items = items * n
    if len(items) != n:
        raise InputError(f"--bounds {text!r}: {len(items)} ranges for {n} --fit keys")
    out = []
    for item in items:
        try:
            lo, hi = (float(v) for v in item.split(":"))
        except ValueError:
            raise InputError(f"--bounds {text!r}: expected MIN:MAX per key (e.g. 0.8:1.4), got "
                             f"{item!r}") from None
        if not (np.isfinite(lo) and np.isfinite(hi)) or lo >= hi:
            raise InputError(f"--bounds {item}: lower bound must be below the upper; no value "
                             "satisfies it")
        out.append((lo, hi))
    return out


def parse_start(text: str | None, n: int, bounds, defaults) -> list[float]:
    if text is None:
        start = [min(max(d, lo), hi) for d, (lo, hi) in zip(defaults, bounds)]
    else:
        items = _floats(text, "--start")
        if len(items) != n:
            raise InputError(f"--start {text!r}: {len(items)} values for {n} --fit keys")
        try:
            start = [float(v) for v in items]
        except ValueError:
            raise InputError(f"--start {text!r}: expected numbers") from None
    for v, (lo, hi) in zip(start, bounds):
        if not lo <= v <= hi:
            raise InputError(f"--start {v:g}: outside the bounds {lo:g}:{hi:g}")
    return start


def _lookup(data: dict, dotted: str):
    node = data
    for part in dotted.split("."):
        if isinstance(node, list):
            try:
                node = node[int(part)]
            except (ValueError, IndexError):
                return None
        elif isinstance(node, dict) and part in node:
            node = node[part]
        else:
            return None
    return node


class _Budget(Exception):
    """The evaluation budget is spent."""


def _remove_earlier_calibration(out: Path) -> None:
    """An earlier calibration's files in ``out`` (a directory mvfem made): its
    ``calibration.json``, ``evaluations.csv`` and evaluations ``evals/NNN`` (their run files
    and marker; a directory left with anything else in it stays), so that a shorter
    calibration into the same directory leaves none of the earlier one's evaluations beside
    its own."""
    from mvfem.outputs import MARKER, RUN_FILES, remove_earlier_files

    remove_earlier_files(out, ("calibration.json", "evaluations.csv"))
    for d in sorted((out / "evals").glob("[0-9][0-9][0-9]")):
        if d.is_dir() and (d / MARKER).exists():
            remove_earlier_files(d, RUN_FILES + (MARKER,))
            try:
                d.rmdir()
            except OSError:   # (not empty: not only an evaluation's files)
                pass


def calibrate(scene, reference: str | Path, fit: list[str], out: str | Path,
              bounds: list[tuple[float, float]] | None = None,
              start: list[float] | None = None, max_evals: int = 30, warm: bool = False,
              grid: int | None = None, say: Callable[[str], None] | None = None,
              comm=MPI.COMM_WORLD) -> dict:
    """Fit the scene keys ``fit`` so that the closed valve matches ``reference``.

    Collective on ``comm``. Validates everything before writing anything. With ``grid = N``
    the ``N ** len(fit)`` points of a regular grid over the bounds are evaluated first and
    the local optimiser starts from the best of them (the start too), with steps of half the
    grid spacing: the closed valve with contact has more than one equilibrium, and the
    distance has narrow wells (README, Calibration) that a local search from afar misses.

    Raises:
        InputError: missing or unreadable reference, unknown or non-numeric key, empty bounds,
            start outside the bounds, a reference that does not overlap the valve, a grid
            larger than the evaluation budget.
    Returns:
        The content of ``calibration.json``.
    """
    import scipy.optimize as so

    from mvfem.outputs import prepare_out_on_root, write_json
    from mvfem.run import solve
    from mvfem.scene import load_scene

    t0 = time.perf_counter()
    say = say or (lambda s: None)
    rank0 = comm.rank == 0
    scene = load_scene(scene)
    ref = Path(reference)
    if not ref.is_file():
        raise InputError(f"--reference {ref}: no such file")
    ref = ref.resolve()
    n = len(fit)
    bounds = bounds or [DEFAULT_BOUNDS] * n
    defaults = []
    for key in fit:
        try:  # an unknown key fails validation, with the scene's message
            changed = scene.with_changes({key: 1.0})
        except InputError as e:
            raise InputError(f"--fit {key}: {e}") from None
        v = _lookup(changed.data, key)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise InputError(f"--fit {key}: not a numeric scene key")
        v = _lookup(scene.data, key)
        defaults.append(float(v) if isinstance(v, (int, float)) and not isinstance(v, bool)
                        else 1.0)
    start = start if start is not None else parse_start(None, n, bounds, defaults)
    parse_start(",".join(repr(v) for v in start), n, bounds, defaults)  # inside the bounds

    def scene_at(x) -> object:
        changes = {k: float(v) for k, v in zip(fit, x)}
        changes["reference.file"] = str(ref)
        if scene["solver"]["max_steps"] is None:
            changes["solver.max_steps"] = MAX_STEPS
        try:
            return scene.with_changes(changes)
        except InputError as e:
            raise InputError(f"--fit/--reference: {e}") from None

    if grid is not None and grid < 2:
        raise InputError(f"--grid {grid}: expected 2 or more points per key")
    if grid is not None and grid ** n + 1 > max_evals:
        raise InputError(f"--grid {grid}: {grid}^{n} + 1 = {grid ** n + 1} evaluations with the "
                         f"start, more than --max-evals {max_evals}")
    scene_at(start)  # the reference reads, the keys take numbers: before anything is written
    for key, ends in zip(fit, bounds):  # every value the search may try is one the scene takes
        for end in ends:
            try:
                scene.with_changes({key: float(end)})
            except InputError as e:
                raise InputError(f"--bounds {ends[0]:g}:{ends[1]:g}: {key} = {end:g} "
                                 f"is not a value the scene takes "
                                 f"({str(e).rsplit(': ', 1)[-1]})") from None
    _check_overlap(scene, ref, comm)
    out = Path(out)
    prepare_out_on_root(out, comm)
    if rank0:
        _remove_earlier_calibration(out)
    comm.Barrier()
    rows: list[dict] = []
    cache: dict[tuple, float] = {}
    warm_u = [None]
    best = {"error": np.inf}

    def evaluate(x) -> float:
        x = [float(v) for v in np.atleast_1d(x)]
        key = tuple(round(v, 12) for v in x)
        if key in cache:
            return cache[key]
        if len(rows) >= max_evals:
            raise _Budget
        i = len(rows)
        t = time.perf_counter()
        r = solve(scene_at(x), out=out / "evals" / f"{i:03d}", comm=comm, progress=False,
                  initial=warm_u[0] if warm else None)
        wall = time.perf_counter() - t
        s = r.summary
        rf = s.get("reference") or {}
        err = float(rf.get("mean_abs_error_mm", np.inf))
        v = s.get("valve") or {}
        row = {"index": i, **{k: val for k, val in zip(fit, x)}, "mean_abs_error_mm": err,
               "p95_error_mm": rf.get("p95_error_mm"), "hausdorff_mm": rf.get("hausdorff_mm"),
               "converged": bool(s["converged"]),
               "equilibrium_residual": s.get("equilibrium_residual"), "wall_time_s": round(wall, 2),
               "warm_start": warm_u[0] is not None and warm,
               **{h: v.get(h) for h in HELD_APART}}
        rows.append(row)
        if s["converged"]:
            warm_u[0] = r.u.x.array.copy()
        if rank0:
            _write_csv(out / "evaluations.csv", rows)
        params = ", ".join(f"{k.split('.')[-2] if k.count('.') else k}={val:.4f}"
                           for k, val in zip(fit, x))
        say(f"eval {i:3d}: {params}: mean error {err:.4f} mm"
            f"{'' if s['converged'] else ' (NOT converged)'}, {wall:.1f} s")
        if i == 0 and not err <= OVERLAP_MM:
            raise InputError(f"--reference {ref}: does not overlap the valve: mean distance "
                             f"{err:.3g} mm at the start (more than {OVERLAP_MM:g} mm)")
        # a run that stopped short keeps its error: the end-game stalls near contact leave a
        # state within ~1e-4 of the load of equilibrium (README), whose shape is meaningful
        value = err
        cache[key] = value
        if value < best["error"]:
            best.update(error=value, x=x, row=row, summary=s)
        return value

    evaluate(start)
    before = rows[0]
    message = ""
    local_start, local_bounds, step = list(start), bounds, [0.1 * (hi - lo) for lo, hi in bounds]
    if grid is not None:
        axes = [np.linspace(lo, hi, grid) for lo, hi in bounds]
        for x in np.array(np.meshgrid(*axes, indexing="ij")).reshape(n, -1).T:
            evaluate(x)
        local_start = list(best["x"])
        step = [0.5 * (hi - lo) / (grid - 1) for lo, hi in bounds]
        # one key: Brent within a grid spacing either side of the best grid point
        local_bounds = [(max(lo, v - 2 * h), min(hi, v + 2 * h))
                        for v, h, (lo, hi) in zip(local_start, step, bounds)]
        say(f"grid of {grid ** n}: best {', '.join(f'{v:.4f}' for v in local_start)} "
            f"({best['error']:.4f} mm); local search from there")
    try:
        if n == 1:
            res = so.minimize_scalar(evaluate, bounds=local_bounds[0], method="bounded",
                                     options={"xatol": XATOL, "maxiter": max_evals})
        else:
            # a step down where a step up would leave the bounds (a grid point on an edge)
            simplex = [local_start] + [
                [v + ((h if v + h <= hi else -h) if j == k else 0.0)
                 for k, (v, h, (lo, hi)) in enumerate(zip(local_start, step, bounds))]
                for j in range(n)]
            simplex = np.clip(np.array(simplex), [b[0] for b in bounds], [b[1] for b in bounds])
            res = so.minimize(evaluate, local_start, method="Nelder-Mead", bounds=bounds,
                              options={"xatol": XATOL, "fatol": 1e-3, "maxfev": max_evals,
                                       "initial_simplex": simplex})
        message = str(res.message)
    except _Budget:
        message = f"stopped at the evaluation budget ({max_evals})"
    after = best["row"]
    result = {
        "scene": scene.source, "reference": str(ref), "fit": fit, "bounds": bounds,
        "start": dict(zip(fit, start)), "fitted": dict(zip(fit, best["x"])),
        "error_before_mm": {k: before[k] for k in ("mean_abs_error_mm", "p95_error_mm",
                                                   "hausdorff_mm")},
        "error_after_mm": {k: after[k] for k in ("mean_abs_error_mm", "p95_error_mm",
                                                 "hausdorff_mm")},
        "converged": after["converged"], "best_evaluation": after["index"],
        "evaluations": len(rows), "optimiser": "minimize_scalar bounded" if n == 1
        else "Nelder-Mead with bounds", "optimiser_message": message,
        "warm_start": warm, "grid": grid, "time_s": round(time.perf_counter() - t0, 1),
        "held_apart": _held_apart(after, ref),
    }
    if rank0:
        write_json(result, out / "calibration.json")
    comm.Barrier()
    say(f"calibrate: {', '.join(f'{k} = {v:.4f}' for k, v in result['fitted'].items())}; mean "
        f"error {before['mean_abs_error_mm']:.4f} -> {after['mean_abs_error_mm']:.4f} mm in "
        f"{len(rows)} evaluations, {result['time_s']:.0f} s")
    if not after["converged"]:  # (its error is a state's short of equilibrium: say so)
        done = sum(r["converged"] for r in rows)
        say(f"  the best evaluation ({after['index']}) did NOT converge (equilibrium residual "
            f"{after['equilibrium_residual']:.3g} of the load); {done} of {len(rows)} "
            "evaluations converged (evaluations.csv)")
    return result


def _check_overlap(scene, ref: Path, comm) -> None:
    """Refuse, before any solve, a reference whose bounding box misses the open valve's
    (enlarged by :data:`OVERLAP_MM`): the closed leaflets lie within the open valve's reach."""
    from mvfem.distance import read_reference
    from mvfem.model import build_mesh

    logging.disable(logging.INFO)  # the mesh is built again by the first solve: no log twice
    try:
        x = build_mesh(scene, comm).mesh.geometry.x
    finally:
        logging.disable(logging.NOTSET)
    lo = comm.allreduce(x.min(axis=0) if len(x) else np.full(3, np.inf), op=MPI.MIN)
    hi = comm.allreduce(x.max(axis=0) if len(x) else np.full(3, -np.inf), op=MPI.MAX)
    r = read_reference(ref).x
    rlo, rhi = r.min(axis=0), r.max(axis=0)
    size, ref_size = float(np.linalg.norm(hi - lo)), float(np.linalg.norm(rhi - rlo))
    if not size / EXTENT_RATIO <= ref_size <= size * EXTENT_RATIO:  # (a solve would say so)
        raise InputError(f"--reference {ref}: its extent, {ref_size:.3g} mm across, is not "
                         f"that of the open valve, {size:.3g} mm, within a factor of "
                         f"{EXTENT_RATIO:g} (are its coordinates in mm?)")
    if np.any(rlo > hi + OVERLAP_MM) or np.any(rhi < lo - OVERLAP_MM):
        raise InputError(f"--reference {ref}: does not overlap the valve: its bounding box "
                         f"{np.round(rlo, 1).tolist()}..{np.round(rhi, 1).tolist()} mm lies "
                         f"more than {OVERLAP_MM:g} mm outside the open valve's "
                         f"{np.round(lo, 1).tolist()}..{np.round(hi, 1).tolist()} mm")


def _held_apart(row: dict, ref: Path) -> dict:
    """Quantities not fitted: the fitted run's, and the reference's when its summary.json is
    next to the reference file."""
    out = {"fitted": {h: row.get(h) for h in HELD_APART}}
    summary = ref.parent / "summary.json"
    if summary.is_file():
        try:
            v = json.loads(summary.read_text()).get("valve") or {}
        except (OSError, ValueError):
            v = {}
        out["reference"] = {h: v.get(h) for h in HELD_APART}
        out["difference"] = {h: (row[h] - v[h]) if row.get(h) is not None
                             and v.get(h) is not None else None for h in HELD_APART}
        out["reference_summary"] = str(summary)
    return out


def _write_csv(path: Path, rows: list[dict]) -> None:
    tmp = path.with_name(path.name + ".part")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
