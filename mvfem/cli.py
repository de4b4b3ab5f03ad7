"""The `mvfem` command: a thin layer over the Python API (see CONTRACT.md).

Exit codes: 0 done, 2 bad input (one line on stderr), 3 solver stopped short.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time

from mvfem.errors import InputError, Interrupted, SolverError

__all__ = ["main"]

log = logging.getLogger("mvfem")


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump) and no exit, so main() returns the code."""

    def error(self, message):  # noqa: D401 - argparse API
        raise InputError(f"{self.prog}: {message}")

    def _print_message(self, message, file=None):  # (--help, --version: once under mpirun)
        if _launcher_rank() == 0:
            super()._print_message(message, file)


def _launcher_rank() -> int:
    """This process's rank as mpirun's environment gives it (0 outside mpirun): what the
    command line's own output goes by before MPI is started."""
    import os

    for var in ("OMPI_COMM_WORLD_RANK", "PMIX_RANK", "PMI_RANK"):
        try:
            return int(os.environ[var])
        except (KeyError, ValueError):
            continue
    return 0


class _StderrHandler(logging.StreamHandler):
    """Writes to whatever sys.stderr is at the time (main() may run many times in a process)."""

    def __init__(self):
        super().__init__(sys.stderr)

    @property
    def stream(self):
        return sys.stderr

    @stream.setter
    def stream(self, value):
        pass


def _setup_logging(verbose: bool) -> None:
    from mpi4py import MPI

    level = logging.DEBUG if verbose else logging.INFO
    root = logging.getLogger("mvfem")
    root.setLevel(level if MPI.COMM_WORLD.rank == 0 else logging.WARNING)
    if not root.handlers:
        h = _StderrHandler()
        h.setFormatter(logging.Formatter("%(message)s"))
        root.addHandler(h)
    root.propagate = False
    quiet_jit_logs()


def quiet_jit_logs() -> None:
    """Silence the INFO lines of FFCx JIT builds.

    FFCx calls logging.basicConfig(), and distutils (cffi's compiler) sets the root logger's
    level to INFO at each build; a level on the root *handlers* is left alone by both.
    """
    import ffcx  # noqa: F401  (installs its basicConfig handler first)

    for h in logging.getLogger().handlers:
        h.setLevel(logging.WARNING)
    for name in ("ffcx", "UFL", "ufl"):
        logging.getLogger(name).setLevel(logging.WARNING)


def _say(*args) -> None:
    from mpi4py import MPI

    if MPI.COMM_WORLD.rank == 0:
        print(*args, flush=True)


def _complain(text: str) -> None:
    """``text`` on stderr, once under ``mpirun``: every rank meets the same bad input (the
    scene, the files and the solver's stops are decided alike on every rank), so rank 0
    speaks for them."""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is not None and mpi.Is_initialized():
        rank = mpi.COMM_WORLD.rank
    else:   # (an error of the command line itself, before MPI is started)
        rank = _launcher_rank()
    if rank == 0:
        print(text, file=sys.stderr, flush=True)


def _parse_range(text: str, option: str) -> tuple[float, float]:
    parts = text.split(":")
    try:
        if len(parts) != 2:
            raise ValueError
        return float(parts[0]), float(parts[1])
    except ValueError:
        raise InputError(f"{option}: expected MIN:MAX (e.g. {option}=-0.5:0.5), got {text!r}") from None


def _cmd_biaxial(args) -> int:
    from mvfem.biaxial import run_biaxial, strain_grid
    from mvfem.materials import LEAFLETS, get_set
    from mvfem.outputs import prepare_out

    smin, smax = _parse_range(args.strain, "--strain")
    leaflets = LEAFLETS if args.leaflet is None else (args.leaflet,)
    sets = tuple(s.strip() for s in args.sets.split(",") if s.strip()) if args.sets else None
    strain_grid(smin, smax, args.points)  # validate before touching the output directory
    for leaflet in leaflets:
        for name in sets or ():
            get_set(name, leaflet)
    # a few thousand point evaluations: rank 0 does them all; the others only wait. dolfinx is
    # imported everywhere first because PETSc initialisation is collective.
    import dolfinx  # noqa: F401
    from mpi4py import MPI

    comm = MPI.COMM_WORLD
    outcome = None
    if comm.rank == 0:
        try:
            out = prepare_out(args.out)
            t0 = time.perf_counter()
            res = run_biaxial(out, leaflets=leaflets, strain_min=smin, strain_max=smax,
                              points=args.points, sets=sets)
        except InputError as e:
            outcome = str(e)
    outcome = comm.bcast(outcome, root=0)
    if outcome:
        raise InputError(outcome)
    if comm.rank != 0:
        return 0
    _say(f"biaxial: {res['rows']} states, {len(res['curves'])} curves in "
         f"{time.perf_counter() - t0:.1f} s")
    if res["overflow"]:
        _say(f"  {res['overflow']} stresses exceed float64 (exponential laws at large "
             "strains) and are left empty in the CSV")
    for f in res["files"]:
        _say(f"  wrote {f}")
    return 0


def _cmd_materials(args) -> int:
    from mvfem.forms import law_parameters
    from mvfem.materials import LEAFLETS, MISSING, parameter_sets

    leaflets = LEAFLETS if args.leaflet is None else (args.leaflet,)
    for leaflet in leaflets:
        _say(f"{leaflet} leaflet")
        _say(f"  {'set':<10} {'law':<10} {'parameters':<42} {'h (mm)':>6}  {'checked':<8} source")
        for s in parameter_sets(leaflet):
            units = {"E": " Pa", "c0": " Pa", "mu": " Pa"}
            p = ", ".join(f"{k} = {s.params[k]:g}{units.get(k, '')}" for k in law_parameters(s.law))
            _say(f"  {s.name:<10} {s.law:<10} {p:<42} {s.thickness_mm:>6.2f}  "
                 f"{'yes' if s.verified else 'NO':<8} {s.source}")
        if leaflet in MISSING:
            names, why = MISSING[leaflet]
            _say(f"  {names[0]}..{names[-1]}: not available: {why}")
        _say("")
    return 0


def level_lines(s: dict) -> list[str]:
    """The terminal's lines on a nested or sequenced run's levels (summary.json ``s``), coarsest
    first: their cells and how far each refinement moved the closure, then (a valve) each
    level's metrics; none where a level did not record them."""
    from mvfem.run import coarse_levels

    levels = coarse_levels(s)[::-1]
    if not levels or any("distance_to_finer_mm" not in lv for lv in levels):
        return []
    d = [lv["distance_to_finer_mm"] for lv in levels]
    lines = [f"mesh levels {' / '.join(str(lv['cells']) for lv in levels + [s])} cells: each "
             "refinement moved the closure by " + " / ".join(f"{x['mean_mm']:.3g}" for x in d)
             + " mm on average (p95 " + " / ".join(f"{x['p95_mm']:.3g}" for x in d) + " mm)"]
    if s.get("valve") and all(lv.get("valve") for lv in levels):
        def seq(key, unit):
            vals = [lv["valve"].get(key) for lv in levels] + [s["valve"].get(key)]
            return " / ".join("n/a" if x is None else f"{x:.3g}" for x in vals) + f" {unit}"

        lines.append(f"  by level: coaptation length {seq('coaptation_length_mm', 'mm')}, "
                     f"trace {seq('coaptation_trace_length_mm', 'mm')}; tenting "
                     f"{seq('tenting_height_mm', 'mm')}; orifice "
                     f"{seq('regurgitant_orifice_area_mm2', 'mm2')}")
    return lines


def valve_line(s: dict) -> str:
    """The terminal's line on a valve's closure (summary.json ``s`` with ``valve``): the
    stepped coaptation length with the continuous trace length beside it (the first jumps
    by tenths of a millimetre between meshes and paths, the second moves smoothly: README
    "Valve outputs and metrics"), the coaptation area, orifice, tenting and penetration."""
    v = s["valve"]
    fmt = lambda x, unit: "n/a" if x is None else f"{x:.3g} {unit}"  # noqa: E731
    return (f"coaptation length {fmt(v.get('coaptation_length_mm'), 'mm')} (trace "
            f"{fmt(v.get('coaptation_trace_length_mm'), 'mm')}), area "
            f"{fmt(v.get('coaptation_area_mm2'), 'mm2')}; regurgitant orifice "
            f"{fmt(v.get('regurgitant_orifice_area_mm2'), 'mm2')}; tenting "
            f"{fmt(v.get('tenting_height_mm'), 'mm')}; max penetration "
            f"{fmt(s.get('max_penetration_mm'), 'mm')} (closest approach "
            f"{fmt((s.get('contact') or {}).get('min_distance_mm'), 'mm')})")


def accuracy_line(acc: dict) -> str:
    """The terminal's line on ``mesh.accuracy`` (summary.json ``accuracy``)."""
    moved = "" if acc["moved_mm"] is None else (
        f" (the last refinement moved the closure by {acc['moved_mm']:.3g} mm)")
    if acc["met"]:
        return f"mesh.accuracy {acc['target_mm']:g} mm: met refined {acc['refine']} time(s){moved}"
    why = ", the most mesh.refine allows" if acc["refine"] == acc["most_refine"] else \
        ", a level stopped short"
    return (f"mesh.accuracy {acc['target_mm']:g} mm: NOT met; stopped refined {acc['refine']} "
            f"time(s){moved}{why}")


#: ``--resume`` of ``mvfem run`` and ``mvfem demo``
_RESUME_HELP = ("start from the state an earlier run of the same mesh wrote in DIR (one that "
                "stopped short, was stopped by Ctrl-C, or ran at another pressure); DIR may "
                "be --out")


def _solve_and_report(scene_path, changes, out, resume=None) -> int:
    """Solve a scene (with ``--set`` changes) into ``out`` (from the state an earlier run wrote
    in ``resume``); report on the terminal; exit 3 when the solver stopped short. Shared by
    ``mvfem run`` and ``mvfem demo``."""
    from mvfem.run import check_converged, solve
    from mvfem.scene import load_scene, parse_set_option

    scene = load_scene(scene_path)
    if changes:
        scene = scene.with_changes(dict(parse_set_option(t) for t in changes))
    stopped = None
    try:
        result = solve(scene, out=out, progress=True, resume=resume)
    except Interrupted as e:  # Ctrl-C, SIGTERM: the state reached is reported as any other
        if not e.written:
            raise
        result, stopped = e.result, e
    s = result.summary
    _say(f"{'converged' if s['converged'] else 'NOT converged'}: {s['pressure_Pa'] / 1e3:g} kPa, "
         f"{s['load_steps']} load steps, {s['newton_iterations']} Newton iterations, "
         f"{s['wall_time_s']:.1f} s; max displacement {s['max_displacement_mm']:.4g} mm")
    if s.get("valve"):
        _say(valve_line(s))
    for line in level_lines(s):
        _say(line)
    if s.get("accuracy"):
        _say(accuracy_line(s["accuracy"]))
    from mvfem.outputs import RUN_FILES

    written = sorted(n for n in RUN_FILES if (out / n).is_file()) if out.is_dir() else []
    _say(f"wrote {out}: {', '.join(written)}")
    if stopped is not None:
        raise stopped
    check_converged(result)
    return 0


def _cmd_run(args) -> int:
    from pathlib import Path

    out = Path(args.out) if args.out else Path("results") / Path(args.scene).stem
    return _solve_and_report(args.scene, args.set, out, args.resume)


def _cmd_demo(args) -> int:
    from pathlib import Path

    return _solve_and_report(Path(__file__).parent / "data" / "demo.toml", args.set,
                             Path(args.out), args.resume)


#: what ``mvfem mesh KIND`` generates
MESH_KINDS = ("valve", "disk", "square", "sphere", "octasphere", "tube")


def _cmd_mesh(args) -> int:
    from pathlib import Path

    import numpy as np
    from mpi4py import MPI

    from mvfem.meshes import write_surface
    from mvfem.meshes.valve import ValveMesh
    from mvfem.model import build_mesh
    from mvfem.scene import load_scene, parse_set_option

    out = Path(args.out)
    from_scene = args.kind.lower().endswith(".toml")
    if not from_scene and args.kind not in MESH_KINDS:
        raise InputError(f"mvfem mesh: {args.kind!r} is neither a kind ({', '.join(MESH_KINDS)})"
                         " nor a scene file (.toml)")
    options = {"size": args.size, "radius": args.radius, "side": args.side,
               "length": args.length, "refinements": args.refinements}
    if from_scene:
        given = [f"--{k}" for k, v in options.items() if v is not None]
        if given:
            raise InputError(f"mvfem mesh {args.kind}: {', '.join(given)} "
                             f"{'applies' if len(given) == 1 else 'apply'} to a generated "
                             "kind; change the scene's mesh with --set mesh.KEY=VALUE")
    elif args.set:
        raise InputError("mvfem mesh: --set applies to a scene file (mvfem mesh SCENE.toml)")
    if out.suffix.lower() not in (".vtu", ".vtk", ".xdmf", ".msh", ".stl", ".ply", ".obj"):
        raise InputError(f"--out {out}: unknown mesh format {out.suffix!r} (use .vtu, .xdmf, ...)")
    # every file the command writes: the mesh, its info and, for .xdmf, meshio's heavy data
    targets = [out, Path(str(out) + ".json")]
    if out.suffix.lower() == ".xdmf":
        targets.append(out.with_suffix(".h5"))
    try:
        taken = [t for t in targets if t.exists() or t.is_symlink()]
    except OSError as e:   # (a name too long to look up)
        raise InputError(f"--out {out}: cannot be written ({e.strerror or e})") from None
    if taken and not args.force:
        what = "exists" if taken[0] == out else f"would replace {taken[0]}, which exists"
        raise InputError(f"--out {out}: {what}; choose another name or pass --force")
    if from_scene:
        scene = load_scene(args.kind)
        if args.set:
            scene = scene.with_changes(dict(parse_set_option(t) for t in args.set))
    else:
        m = {"generator": args.kind, **options}
        try:
            scene = load_scene({"mesh": {k: v for k, v in m.items() if v is not None},
                                "region": [{"law": "neo-hookean", "params": {"mu": 1.0},
                                            "thickness": 1.0}]})
        except InputError as e:  # name the option, not the scene key
            raise InputError(str(e).replace("<dict>: mesh.", "--")) from None
    keeps_lines = out.suffix.lower() in (".vtu", ".vtk", ".xdmf")
    no_lines = (f"--out {out}: a valve file keeps its chordae as line cells: use .vtu, .vtk "
                "or .xdmf")
    if scene["mesh"]["generator"] == "valve" and not keeps_lines:  # (before meshing it)
        raise InputError(no_lines)
    try:
        surface = build_mesh(scene, MPI.COMM_SELF, meshing=True)
    except InputError as e:
        if from_scene:
            raise
        raise InputError(str(e).replace("<dict>: mesh.", "--")) from None
    valve = isinstance(surface, ValveMesh)  # generated, or a file with an annulus
    if valve and not keeps_lines:
        raise InputError(no_lines)
    # under mpirun every rank has made the same mesh and passed the same checks (none may
    # find the file rank 0 is writing); rank 0 writes
    MPI.COMM_WORLD.Barrier()
    if MPI.COMM_WORLD.rank != 0:
        return 0
    msh = surface.mesh
    x = msh.geometry.x
    cells = msh.geometry.dofmap.array.reshape(-1, 3)
    tags = np.zeros(len(cells), dtype=np.int32)
    if surface.cell_tags is not None:
        tags[surface.cell_tags.indices] = surface.cell_tags.values
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        if valve:  # the import format of CONTRACT.md: leaflets, annulus, chordae
            from mvfem.meshes.imported import write_valve_with_chordae

            write_valve_with_chordae(out, surface)
        else:
            write_surface(out, x, cells, cell_data={"region": tags})
        surface.write_info(str(out) + ".json")
    except OSError as e:   # (a parent that is a file, no permission, a read-only disk)
        for t in targets:  # leave nothing half-made of what was not there before
            if t not in taken and t.is_file():
                t.unlink()
        where = f" {e.filename}" if e.filename and str(e.filename) != str(out) else ""
        raise InputError(f"--out {out}:{where} cannot be written ({e.strerror or e})") from None
    _say(f"wrote {out} ({len(cells)} triangles, {len(x)} nodes) and {out}.json")
    return 0


def _not_under_mpirun(command: str) -> None:
    """``command`` runs each of its cases as an ``mvfem run`` process of its own, so under
    ``mpirun -n N`` (N > 1) every rank would run the whole job into the same directory: one
    rank ran it while another met its lock, exited 2 unheard (rank 0 speaks for all) and had
    mpirun abort the job. Refused on every rank, before anything is written."""
    from mpi4py import MPI

    size = MPI.COMM_WORLD.size
    if size > 1:
        raise InputError(f"mvfem {command}: runs each case as a process of its own "
                         f"(--processes at a time); start it without mpirun, not on {size} "
                         "ranks")


def _cmd_study(args) -> int:
    from pathlib import Path

    from mvfem.study import load_study, run_study

    _not_under_mpirun("study")
    study = load_study(args.study)  # everything validated before DIR is touched
    out = Path(args.out) if args.out else Path("results") / Path(args.study).stem
    res = run_study(study, out, processes=args.processes, retry_failed=args.retry_failed,
                    progress=True)  # one line per run and the totals on stderr
    _say(f"wrote {res['results']}" + (f", {res['report']}" if res["report"] else "")
         + "".join(f", {p.name}" for p in res["figures"]))
    return 0


def _cmd_repair_compare(args) -> int:
    from pathlib import Path

    from mvfem.compare import compare, parse_paths, parse_weights, table_text
    from mvfem.scene import parse_set_option
    from mvfem.units import PRESSURE, parse_quantity

    _not_under_mpirun("repair-compare")

    diastolic = None
    if not args.no_diastole:
        try:
            diastolic = parse_quantity(args.diastolic, PRESSURE, "Pa")
        except ValueError as e:
            raise InputError(f"--diastolic: {e}") from None
    changes = dict(parse_set_option(t) for t in (args.set or []))
    paths = parse_paths(args.paths) if args.paths is not None else None
    weights = parse_weights(args.weights) if args.weights is not None else None
    out = Path(args.out) if args.out else Path("results") / f"{Path(args.scene).stem}-repairs"
    res = compare(args.scene, args.repairs, out, processes=args.processes, diastolic=diastolic,
                  changes=changes, progress=True, paths=paths, weights=weights)
    _say(table_text(res["rows"]))
    if res["mesh"]:
        from mvfem.study import mesh_line

        _say(mesh_line(res["mesh"]))
    if any(r.get("path_runs") for r in res["rows"]):
        _say("[min, max]: over each case's converged systolic runs along the solver's paths "
             "(comparison.csv path_runs names them)")
    elif res["moving"] and not (paths or weights):
        _say(f"{', '.join(res['moving'])}: a prescribed motion (ring, ties); where the leaflets "
             "can fold, the closure depends on the solver's path: --paths 10,20,30,40 "
             "--weights 0.05,0.2,0.4 gives each number's range (README, Repairs)")
    _say(f"wrote {', '.join(str(p) for p in res['files'])}")
    return 0


def _cmd_bench(args) -> int:
    import dolfinx  # noqa: F401  (PETSc initialisation is collective: before anything else)

    from mvfem.bench import run_bench

    problems = None
    if args.problems:
        problems = tuple(p.strip() for p in args.problems.split(",") if p.strip())
        known = ("foppl", "neo-hookean", "valve")
        bad = [p for p in problems if p not in known]
        if bad:
            raise InputError(f"--problems: unknown problem {bad[0]!r} (known: {', '.join(known)})")
    res = run_bench(args.out, quick=args.quick, problems=problems, say=_say)
    _say("")
    _say(res["table"])
    _say(f"\nbench: {len(res['rows'])} rows in {res['time_s']:.1f} s; wrote "
         + ", ".join(str(f) for f in res["files"]))
    return 0


def _cmd_calibrate(args) -> int:
    import dolfinx  # noqa: F401  (PETSc initialisation is collective: before anything else)
    from mpi4py import MPI

    from mvfem.calibrate import calibrate, parse_bounds, parse_fit, parse_start
    from mvfem.scene import load_scene

    fit = parse_fit(args.fit)
    bounds = parse_bounds(args.bounds, len(fit))
    start = parse_start(args.start, len(fit), bounds, [1.0] * len(fit)) if args.start else None
    if args.max_evals < 1:
        raise InputError(f"--max-evals {args.max_evals}: expected at least 1")
    scene = load_scene(args.scene)
    say = _say if MPI.COMM_WORLD.rank == 0 else (lambda s: None)
    res = calibrate(scene, args.reference, fit, args.out, bounds=bounds, start=start,
                    max_evals=args.max_evals, warm=args.warm_start, grid=args.grid, say=say)
    h = res["held_apart"]
    for q, v in h["fitted"].items():
        r = (h.get("reference") or {}).get(q)
        _say(f"  held apart {q}: {'n/a' if v is None else f'{v:.3g}'}"
             + ("" if r is None else f" (reference {r:.3g})"))
    _say(f"wrote {args.out}/calibration.json, evaluations.csv, evals/")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of `mvfem` (exposed for documentation and tests)."""
    p = _Parser(prog="mvfem", description="Mitral valve closure with hyperelastic membranes.")
    p.add_argument("-v", "--verbose", action="store_true", help="debug output")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)

    b = sub.add_parser("biaxial", help="the four canonical biaxial curves of every parameter set")
    b.add_argument("--leaflet", choices=("anterior", "posterior"),
                   help="one leaflet's sets (default: both)")
    b.add_argument("--sets", help="comma-separated set names (default: all of the leaflet)")
    b.add_argument("--strain", default="-0.5:0.5",
                   help="imposed strain range MIN:MAX, as --strain=-0.5:0.5 (default)")
    b.add_argument("--points", type=int, default=101, help="strain values per curve (101)")
    b.add_argument("--out", default="results/biaxial", help="output directory")
    b.set_defaults(func=_cmd_biaxial)

    r = sub.add_parser("run", help="run one scene (TOML)")
    r.add_argument("scene", help="scene file")
    r.add_argument("--out", help="output directory (default: results/<scene name>)")
    r.add_argument("--set", action="append", metavar="KEY.PATH=VALUE",
                   help="change a scene value, e.g. --set load.pressure='\"120 mmHg\"' (repeatable)")
    r.add_argument("--resume", metavar="DIR", help=_RESUME_HELP)
    r.set_defaults(func=_cmd_run)

    d = sub.add_parser("demo", help="close the built-in parametric valve (MNY mean, 16 kPa)")
    d.add_argument("--out", default="results/demo", help="output directory (default results/demo)")
    d.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="change a key of the built-in scene, e.g. --set mesh.size=1.0")
    d.add_argument("--resume", metavar="DIR", help=_RESUME_HELP)
    d.set_defaults(func=_cmd_demo)

    g = sub.add_parser("mesh", help="write a generated mesh, or a scene's (any meshio format)")
    g.add_argument("kind", metavar="KIND|SCENE.toml",
                   help=f"{', '.join(MESH_KINDS)}; or a scene file: the mesh it runs on (a "
                        "valve's refined levels, a resection, a file's split), a valve with "
                        "its chordae")
    g.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="change a key of the scene, e.g. --set mesh.refine=1")
    g.add_argument("--out", required=True, help="mesh file, e.g. disk.vtu")
    g.add_argument("--size", type=float, help="target edge length, mm")
    g.add_argument("--radius", type=float, help="disk, sphere, tube radius, mm")
    g.add_argument("--side", type=float, help="square side, mm")
    g.add_argument("--length", type=float, help="tube length, mm")
    g.add_argument("--refinements", type=int, help="octasphere subdivisions")
    g.add_argument("--force", action="store_true", help="replace an existing file")
    g.set_defaults(func=_cmd_mesh)

    st = sub.add_parser("study", help="cases x parameter sets, resumable: results.csv, figures, "
                        "report.html")
    st.add_argument("study", help="study file (TOML)")
    st.add_argument("--out", help="study directory (default: results/<study name>)")
    st.add_argument("--processes", type=int, help="runs at a time (default: the study's "
                    "processes, else the cores available)")
    st.add_argument("--retry-failed", action="store_true",
                    help="run again the runs recorded as failed")
    st.set_defaults(func=_cmd_study)

    rc = sub.add_parser("repair-compare", help="the unrepaired valve and each repair: "
                        "comparison.csv, comparison.png, shapes.png")
    rc.add_argument("scene", help="the pathological valve's scene file (TOML)")
    rc.add_argument("--repairs", nargs="+", required=True, metavar="REPAIR.toml",
                    help="repair files: scene keys merged into the scene (README, Repairs)")
    rc.add_argument("--out", help="comparison directory (default: results/<scene>-repairs)")
    rc.add_argument("--processes", type=int, help="runs at a time (default: 1)")
    rc.add_argument("--diastolic", default="-500 Pa",
                    help="atrial-side pressure of the diastolic runs (default '-500 Pa')")
    rc.add_argument("--no-diastole", action="store_true", help="systolic runs only")
    rc.add_argument("--set", action="append", metavar="KEY.PATH=VALUE",
                    help="change a scene value in every case, e.g. --set mesh.size=4.0")
    rc.add_argument("--paths", metavar="N,N,...",
                    help="close each case with a prescribed motion again with each of these "
                    "solver.ramp_steps (e.g. 10,20,30,40): comparison.csv gains the range of "
                    "orifice, coaptation and tenting over the solver's paths")
    rc.add_argument("--weights", metavar="W,W,...",
                    help="close every case (with a prescribed motion or not) again with each "
                    "of these solver.stabilisation, the pseudo-time start weight (default 0.1; "
                    "e.g. 0.05,0.2,0.4): more paths in the same ranges")
    rc.set_defaults(func=_cmd_repair_compare)
    be = sub.add_parser("bench", help="speed against error on reference problems: bench.csv, "
                        "bench_pareto.png, bench.md")
    be.add_argument("--quick", action="store_true", help="the small sweep (about a minute)")
    be.add_argument("--out", default="results/bench", help="output directory (default "
                    "results/bench)")
    be.add_argument("--problems", help="comma-separated subset of foppl, neo-hookean, valve")
    be.set_defaults(func=_cmd_bench)

    ca = sub.add_parser("calibrate", help="fit chordal length factors (or other scene keys) to "
                        "a reference closed surface: calibration.json, evaluations.csv")
    ca.add_argument("scene", help="scene file (TOML)")
    ca.add_argument("--reference", required=True, help="reference closed surface (any meshio "
                    "format, cell data 'leaflet')")
    ca.add_argument("--fit", required=True, help="comma-separated scene keys, e.g. "
                    "chordae.marginal.length_factor,chordae.basal.length_factor")
    ca.add_argument("--bounds", help="MIN:MAX per key, comma-separated, or one for all "
                    "(default 0.8:1.4)")
    ca.add_argument("--start", help="start values, comma-separated (default: the scene's)")
    ca.add_argument("--max-evals", type=int, default=30, help="solves at most (default 30)")
    ca.add_argument("--grid", type=int, help="first evaluate N points per key on a regular "
                    "grid over the bounds (N^keys solves, within --max-evals) and search "
                    "locally from the best")
    ca.add_argument("--warm-start", action="store_true", help="start each solve from the last "
                    "converged one (faster, but path dependent: see README)")
    ca.add_argument("--out", required=True, help="output directory")
    ca.set_defaults(func=_cmd_calibrate)

    m = sub.add_parser("materials", help="list parameter sets with law, values, thickness, source")
    m.add_argument("--leaflet", choices=("anterior", "posterior"))
    m.set_defaults(func=_cmd_materials)
    return p


def _import_gmsh_before_mpi() -> None:
    """Import gmsh before MPI starts. gmsh's module runs ``ldconfig -p`` in a child process
    (ctypes.util.find_library) when imported; under an OpenMPI singleton (no mpirun) that
    child's exit, after MPI_Init, made `mvfem run` exit with code 1 and no message about one
    time in two (seen in the hard cases, issue 7: strace shows exit_group(1) right after the
    ldconfig child's SIGCHLD).

    gmsh 4.8's module also sets SIGINT to its system default when imported (restored by
    ``gmsh.finalize()``): Ctrl-C then killed the process outright, until the first mesh was
    made. The handler before the import is put back: a study's Ctrl-C killed the study
    without its cleanup (its runs died with it, results.csv not rebuilt), and a run of an
    imported mesh (no gmsh session) could not stop at its next step (session 56)."""
    import sys

    if "mpi4py.MPI" in sys.modules:
        return
    import importlib.util

    if importlib.util.find_spec("gmsh") is not None:  # no gmsh: nothing to race with
        from mvfem.meshes.generators import _sigint_kept

        with _sigint_kept():
            import gmsh  # noqa: F401


def main(argv: list[str] | None = None) -> int:
    """Run `mvfem` with ``argv`` (default: sys.argv[1:]); returns the exit code."""
    from mvfem.outputs import given_back_if_unused

    _import_gmsh_before_mpi()
    try:
        args = build_parser().parse_args(argv)
        _setup_logging(args.verbose)
        _no_empty_options(args)
        with given_back_if_unused():   # (an --out claimed, then an input error: not left)
            return args.func(args)
    except InputError as e:
        _complain(f"mvfem: error: {e}")
        return 2
    except SolverError as e:
        _complain(f"mvfem: solver stopped: {e}")
        return 3
    except KeyboardInterrupt as e:  # (Interrupted: what a solve stopped by a signal wrote)
        _complain(f"mvfem: {e}" if str(e) else "mvfem: interrupted")
        return getattr(e, "exit_code", 130)
    except Exception:
        _abort_the_job()
        raise


#: options whose empty value ("--out ''", "--sets ''") would otherwise mean their default
_NAMED_BY_OPTIONS = {"out": "a directory or file", "sets": "set names",
                     "problems": "problem names"}


def _no_empty_options(args) -> None:
    """An option given an empty value is an input error: a script's empty variable after
    --out wrote to the default results/NAME, and after --sets or --problems ran them all."""
    for name, what in _NAMED_BY_OPTIONS.items():
        v = getattr(args, name, None)
        if isinstance(v, str) and not v.strip(" ,"):
            raise InputError(f"--{name}: empty; give {what}")


def _abort_the_job() -> None:
    """Under mpirun, an unexpected exception on one rank ends the whole job (``MPI_Abort``,
    exit code 1) after printing its traceback, instead of leaving the other ranks waiting for
    that rank in a collective call until someone kills the job; a serial run just raises it.
    (Input errors and solver stops are said collectively by every rank and end normally.)"""
    mpi = sys.modules.get("mpi4py.MPI")
    if mpi is None or mpi.COMM_WORLD.size == 1:
        return
    import traceback

    traceback.print_exc()
    sys.stderr.flush()
    mpi.COMM_WORLD.Abort(1)


if __name__ == "__main__":
    sys.exit(main())
