"""Studies: cases (scenes, generated or imported valves) crossed with parameter sets.

The source paper's results section as one command (``mvfem study STUDY.toml --out DIR``):
every (case, set) pair is run once, each in its own process (``mvfem run`` with its own
``--out DIR/runs/<case>/<set>``), as many at a time as ``processes`` allows. A study file:

.. code-block:: toml

    title = "three valves x eleven sets"
    sets = ["CP01", "MNY-mean"]   # default: the eleven anterior sets of `mvfem materials`
    processes = 2                 # default: the cores this process may use
    timeout = 3600                # seconds per run (default: none)
    map_case = "small"            # the case whose maps the report shows (default: the first)
    include_stopped = false       # box plots also pool runs that stopped short
    biaxial = true                # the canonical biaxial curves (Figs 1-2) in the report

    [[case]]
    name = "small"                # default: the scene file's stem ("demo" for the demo)
    scene = "demo"                # the built-in valve, or a scene file (relative to this file)
    set = { "mesh.size" = 3.0, "mesh.ap_diameter" = 24.0 }   # like `mvfem run --set`
    reference = "closed.vtu"      # optional reference closed surface (relative to this file)

A study *set* is a name. The region that is the anterior leaflet (``leaflet = "anterior"``, or
labelled so, or any region that is neither) gets the anterior set of that name; a posterior
region gets the posterior set of that name where one exists, otherwise the posterior MNY-mean
(the per-specimen posterior sets are not in our sources). The set's law, parameters and
thickness replace the region's; the case's ``set`` changes apply after them.

Resumable: a run is finished when its ``summary.json`` exists (mvfem writes it last and
atomically), converged or not, unless Ctrl-C or SIGTERM stopped it (``"interrupted":
true``: the state it had reached, written on the way out, and a run still to make); a run
that failed (crash, exception, timeout) is recorded in its ``status.json`` with the reason
and is not repeated unless ``retry_failed``. A killed study run again picks up the runs that
did not finish. ``results.csv`` (one row per run) is rebuilt from the per-run files after
every finished run, the figures and ``report.html`` at the end, each written atomically.

A case whose scene asks for ``mesh.accuracy`` has its sets closed on one mesh, the one its set
needing the most refinements needs (:func:`one_mesh_runs`): parameter sets compared on
meshes of their own would carry the meshes' differences.
"""

from __future__ import annotations

import copy
import csv
import io
import json
import math
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any


from mvfem.errors import InputError
from mvfem.relaunch import RETRIES, WITHIN_S, without_mpi_job
from mvfem.scene import read_toml
from mvfem.units import beyond_float

__all__ = ["Study", "Case", "RunSpec", "load_study", "run_study", "one_mesh_runs",
           "mesh_line", "collect_results",
           "write_results_csv", "default_sets", "default_processes", "RESULT_COLUMNS",
           "LEAFLETS", "PERCENTILE_NAMES"]

LEAFLETS = ("anterior", "posterior")
PERCENTILE_NAMES = ("p5", "p25", "median", "p75", "p95")
_PERCENTILES = (5, 25, 50, 75, 95)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")
_TOP = ("title", "sets", "processes", "timeout", "map_case", "include_stopped", "biaxial",
        "case")
_CASE = ("name", "scene", "set", "reference")
#: the posterior set a posterior region uses when the study's set has no posterior version
POSTERIOR_FALLBACK = "MNY-mean"

RESULT_COLUMNS = (
    ["case", "set", "anterior_set", "posterior_set", "status", "converged", "exit_code",
     "reason", "wall_time_s", "elapsed_s", "dofs", "cells", "newton_iterations",
     "equilibrium_residual", "pressure_Pa", "max_displacement_mm", "max_penetration_mm",
     "coaptation_length_mm", "coaptation_area_mm2", "regurgitant_orifice_area_mm2",
     "tenting_height_mm", "reference_mean_abs_error_mm", "reference_p95_error_mm",
     "reference_hausdorff_mm", "mesh_move_mean_mm", "mesh_move_p95_mm"]
    + [f"{leaf}_{q}_{p}" for leaf in LEAFLETS for q in ("radial_strain", "radial_stress_Pa")
       for p in PERCENTILE_NAMES]
    + [f"{leaf}_cells" for leaf in LEAFLETS] + ["run_dir"])


def default_sets() -> list[str]:
    """The eleven parameter sets of the source paper: every anterior set, in table order."""
    from mvfem.materials import parameter_sets

    return [s.name for s in parameter_sets("anterior")]


def default_processes() -> int:
    """Runs at a time: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not Linux
        return max(1, os.cpu_count() or 1)


def demo_scene_path() -> Path:
    return Path(__file__).parent / "data" / "demo.toml"


# --------------------------------------------------------------------------- definition
@dataclass
class Case:
    """One case: a scene (file or the built-in demo) with changes and an optional reference."""

    name: str
    scene: str                      # absolute path of the scene file
    changes: dict = field(default_factory=dict)   # dotted key -> value
    reference: str | None = None    # absolute path


@dataclass
class RunSpec:
    """One run of a study: a case with a parameter set, as ``mvfem run`` gets it.

    Attributes:
        regions: per ``[[region]]`` of the scene, in order: label, leaflet and the set used
            (the ``region`` cell values of fields.h5 index this list).
        scene_sha256: of the scene file's text, so that an edited scene is a different run
            (code changes are not detected).
        mesh_target_mm: a run made again on its group's mesh (:func:`one_mesh_runs`): the
            ``mesh.accuracy`` target that chose that mesh, which its changes switch off, so
            that a study resumed with another target does not take it for this run. Not
            passed to the run; absent from run.json where None.
    """

    case: str
    set: str
    anterior_set: str
    posterior_set: str
    scene: str
    changes: dict
    regions: list
    scene_sha256: str = ""
    mesh_target_mm: float | None = None

    @property
    def key(self) -> str:
        return f"{self.case}/{self.set}"

    def dir(self, out: Path) -> Path:
        return Path(out) / "runs" / self.case / self.set

    def command(self, out: Path) -> list[str]:
        cmd = [sys.executable, "-m", "mvfem.cli", "run", self.scene, "--out", str(self.dir(out))]
        for k, v in self.changes.items():
            cmd += ["--set", f"{k}={toml_value(v)}"]
        return cmd


@dataclass
class Study:
    """A validated study (see the module docstring)."""

    title: str
    cases: list
    sets: list
    processes: int
    timeout_s: float | None
    map_case: str
    include_stopped: bool
    biaxial: bool
    runs: list
    source: str = "<dict>"

    def as_dict(self) -> dict:
        return {"title": self.title, "source": self.source, "sets": self.sets,
                "processes": self.processes, "timeout_s": self.timeout_s,
                "map_case": self.map_case, "include_stopped": self.include_stopped,
                "biaxial": self.biaxial, "cases": [asdict(c) for c in self.cases],
                "runs": [asdict(r) for r in self.runs]}


def toml_value(v: Any) -> str:
    """A Python value (from TOML) as a TOML literal, for ``mvfem run --set key=value``."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"not a finite number: {v!r}")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a JSON string is a TOML basic string
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{json.dumps(str(k))} = {toml_value(x)}"
                                for k, x in v.items()) + " }"
    raise ValueError(f"cannot pass {type(v).__name__} {v!r} to a scene")


def _flatten(table: dict, prefix: str = "") -> dict:
    """``{"mesh": {"size": 3}}`` and ``{"mesh.size": 3}`` -> ``{"mesh.size": 3}``."""
    out = {}
    for k, v in table.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict) and v:
            out.update(_flatten(v, key + "."))
        else:
            out[key] = v
    return out


def _leaflet_of(region: dict) -> str:
    """The leaflet a scene region is, as scene.py decides which table a set name is read from."""
    if region.get("leaflet"):
        return region["leaflet"]
    return region["label"] if region.get("label") in LEAFLETS else "anterior"


def _set_changes(scene, name: str) -> tuple[dict, list, str, str]:
    """Scene changes that give each region the study set ``name`` (module docstring); and the
    regions' (label, leaflet, set) and the sets the two leaflets use ("" where absent)."""
    from mvfem.materials import get_set

    changes, regions, used = {}, [], {"anterior": "", "posterior": ""}
    for i, r in enumerate(scene["region"]):
        leaflet = _leaflet_of(r)
        if leaflet == "posterior":
            try:
                ps = get_set(name, "posterior")
            except InputError:
                ps = get_set(POSTERIOR_FALLBACK, "posterior")
        else:
            ps = get_set(name, "anterior")
        changes.update({f"region.{i}.law": ps.law, f"region.{i}.params": ps.name,
                        f"region.{i}.thickness": ps.thickness_mm})
        regions.append({"label": r["label"] or "membrane", "leaflet": leaflet, "set": ps.name})
        used[leaflet] = used[leaflet] or ps.name
    return changes, regions, used["anterior"], used["posterior"]


def load_study(study: str | Path | dict, base_dir: str | Path | None = None) -> Study:
    """Read and validate a study (a TOML file or a dict; paths in a dict are relative to
    ``base_dir``, default the working directory). Every run's scene is validated too.

    Raises:
        InputError: one line naming the study file, the key and the problem.
    """
    from mvfem.materials import get_set
    from mvfem.scene import load_scene

    if isinstance(study, dict):
        raw, source = copy.deepcopy(study), "<dict>"
        base = Path(base_dir or ".").resolve()
    else:
        path = Path(study)
        source = str(path)
        raw = read_toml(path, "study")
        base = path.resolve().parent

    def bad(key: str, message: str):
        return InputError(f"{source}: {key}: {message}")

    unknown = sorted(set(raw) - set(_TOP))
    if unknown:
        raise bad(unknown[0], f"unknown key (known: {', '.join(_TOP)})")
    title = raw.get("title", "")
    if not isinstance(title, str):
        raise bad("title", f"expected a string, got {title!r}")
    sets = raw.get("sets", default_sets())
    if not isinstance(sets, list) or not sets or not all(isinstance(s, str) for s in sets):
        raise bad("sets", f"expected a list of parameter set names, got {sets!r}")
    canonical = []
    for i, s in enumerate(sets):
        try:
            canonical.append(get_set(s, "anterior").name)
        except InputError as e:
            raise bad(f"sets[{i}]", str(e)) from None
    dup = [s for s in canonical if canonical.count(s) > 1]
    if dup:
        raise bad("sets", f"set {dup[0]!r} is listed twice")
    processes = raw.get("processes", default_processes())
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise bad("processes", f"expected a positive integer, got {processes!r}")
    timeout = raw.get("timeout")
    if timeout is not None and (isinstance(timeout, bool) or not isinstance(timeout, (int, float))
                                or beyond_float(timeout) or not math.isfinite(timeout)
                                or timeout <= 0):
        raise bad("timeout", f"expected a positive number of seconds, got {timeout!r}")
    flags = {}
    for key, default in (("include_stopped", False), ("biaxial", True)):
        flags[key] = raw.get(key, default)
        if not isinstance(flags[key], bool):
            raise bad(key, f"expected true or false, got {flags[key]!r}")
    cases_raw = raw.get("case")
    if cases_raw is None:
        raise bad("case", "at least one [[case]] is required")
    if isinstance(cases_raw, dict):
        cases_raw = [cases_raw]
    if not isinstance(cases_raw, list) or not cases_raw:
        raise bad("case", "expected [[case]] tables")
    cases, runs = [], []
    for i, c in enumerate(cases_raw):
        where = f"case[{i}]"
        if not isinstance(c, dict):
            raise bad(where, f"expected a table, got {c!r}")
        unknown = sorted(set(c) - set(_CASE))
        if unknown:
            raise bad(f"{where}.{unknown[0]}", f"unknown key (known: {', '.join(_CASE)})")
        scene = c.get("scene")
        if not isinstance(scene, str) or not scene.strip():
            raise bad(f"{where}.scene",
                      "required: a scene file, or \"demo\" for the built-in valve")
        if scene == "demo":
            scene_path = demo_scene_path()
        else:
            scene_path = (Path(scene) if Path(scene).is_absolute() else base / scene).resolve()
            if not scene_path.is_file():
                raise bad(f"{where}.scene", f"no such scene file: {scene_path}")
        name = c.get("name", "demo" if scene == "demo" else scene_path.stem)
        if not isinstance(name, str) or not _NAME.match(name):
            raise bad(f"{where}.name", f"expected letters, digits, '.', '_' or '-' (a directory "
                      f"name), got {name!r}")
        if name in (k.name for k in cases):
            raise bad(f"{where}.name", f"case name {name!r} is used twice (give each case a name)")
        changes = c.get("set", {})
        if not isinstance(changes, dict):
            raise bad(f"{where}.set", f"expected a table of scene changes such as "
                      f"{{ \"mesh.size\" = 3.0 }}, got {changes!r}")
        changes = _flatten(changes)
        for k, v in changes.items():
            try:
                toml_value(v)
            except ValueError as e:
                raise bad(f"{where}.set.{k}", str(e)) from None
        ref = c.get("reference")
        if ref is not None:
            if not isinstance(ref, str) or not ref.strip():
                raise bad(f"{where}.reference", f"expected a file name, got {ref!r}")
            ref_path = (Path(ref) if Path(ref).is_absolute() else base / ref).resolve()
            if not ref_path.is_file():
                raise bad(f"{where}.reference", f"no such file: {ref_path}")
            ref = str(ref_path)
        case = Case(name=name, scene=str(scene_path), changes=changes, reference=ref)
        try:
            base_scene = load_scene(scene_path)
        except InputError as e:
            raise bad(f"{where}.scene", str(e)) from None
        import hashlib

        digest = hashlib.sha256(scene_path.read_bytes()).hexdigest()
        for s in canonical:
            set_changes, regions, ant, post = _set_changes(base_scene, s)
            all_changes = {**set_changes, **changes, "output.xdmf": True}
            if ref is not None:
                all_changes["reference.file"] = ref
            try:
                base_scene.with_changes(all_changes)
            except InputError as e:
                raise bad(where, f"({name}, set {s}): {e}") from None
            runs.append(RunSpec(case=name, set=s, anterior_set=ant, posterior_set=post,
                                scene=str(scene_path), changes=all_changes, regions=regions,
                                scene_sha256=digest))
        cases.append(case)
    map_case = raw.get("map_case", cases[0].name)
    if map_case not in [c.name for c in cases]:
        raise bad("map_case", f"{map_case!r} is not a case (cases: "
                  f"{', '.join(c.name for c in cases)})")
    return Study(title=title, cases=cases, sets=canonical, processes=processes,
                 timeout_s=float(timeout) if timeout is not None else None, map_case=map_case,
                 include_stopped=flags["include_stopped"], biaxial=flags["biaxial"], runs=runs,
                 source=source)


# --------------------------------------------------------------------------- files
def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(text)
    os.replace(tmp, path)


def checked_processes(processes) -> int:
    """``--processes`` as a count of runs at a time: an :class:`InputError` below 1."""
    processes = int(processes)
    if processes < 1:
        raise InputError(f"--processes: must be at least 1, got {processes}")
    return processes


def _read_json(path: Path) -> dict | None:
    """The JSON object in ``path``; None where there is none (no file, not JSON, or JSON
    that is not an object: a summary.json edited by hand to ``[1, 2]`` was an
    AttributeError traceback)."""
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def _spec_record(spec: RunSpec) -> dict:
    rec = asdict(spec)
    if rec["mesh_target_mm"] is None:  # (the run.json of every other run, as before it)
        del rec["mesh_target_mm"]
    return json.loads(json.dumps(rec))  # as it reads back from run.json


def run_state(spec: RunSpec, out: Path) -> str:
    """``done`` (summary.json of this very run exists, not one a signal stopped short),
    ``failed`` (recorded), or ``todo``."""
    d = spec.dir(out)
    if _read_json(d / "run.json") != _spec_record(spec):
        return "todo"  # never run, or run with other settings: its files are not this run's
    summary = _read_json(d / "summary.json") if (d / "summary.json").is_file() else None
    if summary is not None and not summary.get("interrupted"):
        return "done"  # (one a signal stopped short wrote its state: to do)
    status = _read_json(d / "status.json")
    if status and status.get("status") == "failed":
        return "failed"
    return "todo"


def _child_env() -> dict:
    """The environment of a run: no MPI job of ours (a study started under mpirun must not hand
    its MPI environment to the runs), an isolated MPI singleton (no orted daemon and session
    directory per run: many of those at once on one machine), one BLAS thread per process."""
    env = without_mpi_job()
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    env.setdefault("OMP_NUM_THREADS", "1")
    env["OMPI_MCA_ess_singleton_isolated"] = "1"
    return env


def _die_with_parent(parent: int, cpus: set | None):
    """preexec_fn: the run gets SIGTERM when the study process dies (Linux), so that a killed
    study leaves no orphan writing into its directory; and it may use all of ``cpus`` (a study
    under mpirun is bound to one core, which its runs would otherwise share)."""
    def hook():
        try:
            import ctypes

            ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
        if cpus:
            try:
                os.sched_setaffinity(0, cpus)
            except (OSError, AttributeError):
                pass
        if os.getppid() != parent:  # the study died before prctl
            os._exit(1)
    return hook


def _last_line(path: Path) -> str:
    """The last line a run wrote to its log (not the command line the study put first)."""
    try:
        with open(path, "rb") as f:
            f.seek(0, os.SEEK_END)
            f.seek(max(0, f.tell() - 8192))
            lines = [ln.strip() for ln in f.read().decode(errors="replace").splitlines()]
    except OSError:
        return ""
    lines = [ln for ln in lines if ln and not ln.startswith("$ ")]
    return lines[-1] if lines else ""


class _Lock:
    """An exclusive advisory lock on a file (released when every holder closes it or dies)."""

    def __init__(self, path: Path):
        import fcntl

        self.fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(self.fd)
            raise BlockingIOError(str(path)) from None
        os.ftruncate(self.fd, 0)
        os.write(self.fd, f"{os.getpid()}\n".encode())

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


@dataclass
class _Running:
    spec: RunSpec
    proc: subprocess.Popen
    started: float
    started_wall: float
    log: Any
    lock: _Lock


class _Interrupted(Exception):
    pass


def _hms(seconds: float | None) -> str:
    if seconds is None or not math.isfinite(seconds):
        return "--:--:--"
    s = round(max(seconds, 0))
    return f"{s // 3600:02d}:{s % 3600 // 60:02d}:{s % 60:02d}"


class _Progress:
    """One line per finished run on stderr; on a terminal also a bar redrawn in place."""

    def __init__(self, total: int, enabled: bool):
        self.total, self.enabled = total, enabled
        self.tty = enabled and sys.stderr.isatty()
        self.bar_shown = False

    def line(self, text: str) -> None:
        if not self.enabled:
            return
        if self.bar_shown:
            sys.stderr.write("\r\033[K")
            self.bar_shown = False
        sys.stderr.write(text + "\n")
        sys.stderr.flush()

    def bar(self, done: int, running: int, eta: float | None) -> None:
        if not self.tty:
            return
        width = 30
        filled = int(width * done / max(self.total, 1))
        sys.stderr.write(f"\r\033[K[{'#' * filled}{'.' * (width - filled)}] {done}/{self.total}"
                         f", {running} running, ETA {_hms(eta)}")
        sys.stderr.flush()
        self.bar_shown = True


def _at(spec: RunSpec, refine: int, target: float) -> RunSpec:
    """``spec`` on the mesh refined ``refine`` times, chosen for the accuracy ``target`` (mm),
    without a target of its own (after its other keys: a repair that sets the mesh is compared
    on the common one all the same)."""
    from dataclasses import replace

    return replace(spec, changes={**spec.changes, "mesh.refine": int(refine),
                                  "mesh.accuracy": False}, mesh_target_mm=float(target))


def one_mesh_runs(runs: list, out: Path, run, primary=lambda r: True,
                  group=lambda r: r.case, label=lambda r: r.set) -> tuple[list, dict]:
    """Runs that ask for ``mesh.accuracy``, each group of them on one mesh: the mesh the run
    needing the most refinements needs (README "One mesh for every case").

    A group's target and most refinements are its first primary run's scene's. Each primary
    run of a group with a target runs first (``run``: the study runner over some runs), to the
    accuracy, and stops where its own last refinement moved its closure by at most the target
    (summary.json ``accuracy``). The most refinements a group's primary runs needed is its
    mesh: the primary runs that stopped coarser run again on it, and its other runs run on it,
    all without a target of their own (:func:`_at`). A run made again keeps its directory; on
    a resumed study it is recognised by its run.json (:func:`run_state`, which records the
    target that chose its mesh), not run to the accuracy again; resumed with another target,
    it runs to the accuracy again like the others. A run that left no accuracy record (it
    failed) counts as needing the most refinements its scene allows (``mesh.refine``) and
    runs again on the group's mesh.

    Args:
        runs: :class:`RunSpec` list.
        out: the study directory.
        run: called with a list of runs: runs them (the study runner).
        primary: which runs choose the mesh (a comparison: the systoles; a study: all).
        group: runs of one key share a mesh (a comparison: all; a study: each case's sets).
        label: a run's name in the record's ``needed``.

    Returns:
        The runs as they are to run, and per group with a target its record: ``target_mm``,
        ``refine``, ``most_refine``, ``needed`` (label -> refinements; None for a run made
        again on the mesh before, whose own need is not known), ``not_met`` (the labels of the
        runs that missed the target at the most refinements allowed, or stopped short).
    """
    from mvfem.scene import load_scene

    targets = {}
    for r in runs:
        if primary(r) and group(r) not in targets:
            mesh = load_scene(r.scene).with_changes(r.changes)["mesh"]
            targets[group(r)] = (mesh["accuracy"], int(mesh["refine"]))
    groups = {g for g, (target, _) in targets.items() if target is not None}
    if not groups:
        return runs, {}
    chosen = [r for r in runs if primary(r) and group(r) in groups]
    again = {}  # id -> the refinements of a run made again on its group's mesh before
    for r in chosen:
        k = ((_read_json(r.dir(out) / "run.json") or {}).get("changes") or {}).get("mesh.refine")
        if isinstance(k, int) and run_state(_at(r, k, targets[group(r)][0]), out) == "done":
            again[id(r)] = k
    first = [r for r in chosen if id(r) not in again]
    if first:
        run(first)
    closed, short = {}, set()  # id -> where its run to the accuracy stopped; target missed
    for r in first:
        acc = (_read_json(r.dir(out) / "summary.json") or {}).get("accuracy")
        if acc:
            closed[id(r)] = int(acc["refine"])
            if not acc.get("met"):
                short.add(id(r))
    records = {}
    for g in sorted(groups, key=str):
        mine = [r for r in chosen if group(r) == g]
        needed = {id(r): again.get(id(r), closed.get(id(r), targets[g][1])) for r in mine}
        records[g] = {"target_mm": float(targets[g][0]), "refine": max(needed.values()),
                      "most_refine": targets[g][1],
                      "needed": {label(r): None if id(r) in again else needed[id(r)]
                                 for r in mine},
                      "not_met": [label(r) for r in mine if id(r) in short]}
    kept = {id(r) for r in first if closed.get(id(r)) == records[group(r)]["refine"]}
    return [r if group(r) not in groups or id(r) in kept else
            _at(r, records[group(r)]["refine"], records[group(r)]["target_mm"])
            for r in runs], records


def mesh_line(record: dict, what: str = "") -> str:
    """The line saying which mesh runs that ask for ``mesh.accuracy`` share (a record of
    :func:`one_mesh_runs`); ``what`` names the group."""
    needed = ", ".join(f"{k} {'-' if v is None else v}" for k, v in record["needed"].items())
    short = record.get("not_met")
    return (f"mesh.accuracy {record['target_mm']:g} mm{what}: refinements each run needed: "
            f"{needed}; every run is on the mesh refined {record['refine']} time(s) "
            "(mesh move: each run's last refinement there)"
            + (f"; NOT met by {', '.join(short)}" if short else ""))


def run_study(study: Study | str | Path | dict, out: str | Path, processes: int | None = None,
              retry_failed: bool = False, progress: bool = True, report: bool = True,
              cpus: set[int] | None = None, one_mesh: bool = True) -> dict:
    """Run every (case, set) of ``study`` not yet finished in ``out``; then results.csv, the
    figures and report.html.

    Args:
        study: a :class:`Study`, a study file or a dict (validated first, nothing written on
            bad input).
        out: the study directory (made by mvfem, or new).
        processes: runs at a time (default: the study's ``processes``).
        retry_failed: run again the runs recorded as failed.
        progress: one line per finished run on stderr.
        report: write the figures and report.html at the end.
        cpus: the CPUs the runs may use (default: this process's); a script under mpirun,
            whose ranks are bound to one core each, passes the union of its ranks'.
        one_mesh: the sets of a case whose scene asks for ``mesh.accuracy`` all close on
            one mesh, the one the set needing the most refinements needs
            (:func:`one_mesh_runs`; those runs first); False runs the runs as they are.

    Returns:
        A dict: counts per status (converged, stopped, failed, pending), ``ran`` (runs made
        now), ``skipped`` (finished before), ``results`` (results.csv), ``report``, ``figures``,
        ``meshes`` (per case under ``mesh.accuracy``, its mesh's record: :func:`one_mesh_runs`).

    Raises:
        InputError: bad study or output directory, or another study running in ``out``.
    """
    from mvfem.outputs import prepare_out, write_json

    if not isinstance(study, Study):
        study = load_study(study)
    processes = checked_processes(study.processes if processes is None else processes)
    out = prepare_out(out).resolve()
    meshes = {}
    if one_mesh:  # (before this call's lock: the first runs are a call of their own)
        from dataclasses import replace

        runs, meshes = one_mesh_runs(study.runs, out, lambda rs: run_study(
            replace(study, runs=rs), out, processes=processes, retry_failed=retry_failed,
            progress=progress, report=False, cpus=cpus, one_mesh=False))
        study = replace(study, runs=runs)
        for case, record in meshes.items():
            if progress:
                sys.stderr.write(mesh_line(record, f" ({case})") + "\n")
    try:
        study_lock = _Lock(out / ".study.lock")
    except BlockingIOError:
        raise InputError(f"--out {out}: another mvfem study is running in this directory") from None
    t0 = time.perf_counter()
    try:
        write_json(study.as_dict(), out / "study.json")
        todo, skipped = [], 0
        for spec in study.runs:
            state = run_state(spec, out)
            if state == "done" or (state == "failed" and not retry_failed):
                skipped += 1
            else:
                todo.append(spec)
        total = len(study.runs)
        prog = _Progress(total, progress)
        grid = (f"{len(study.cases)} cases x {len(study.sets)} sets"
                if total == len(study.cases) * len(study.sets) else
                f"{len(study.cases)} cases; {', '.join(study.sets)}")
        prog.line(f"study {study.title or study.source}: {total} runs ({grid}), "
                  f"{skipped} finished before, {len(todo)} to run"
                  + (f", {min(processes, len(todo))} at a time; logs in {out / 'runs'}"
                     if todo else ""))
        ran = _schedule(study, out, todo, processes, prog, skipped, total, cpus)
        rows = collect_results(study, out)
        write_results_csv(rows, out / "results.csv")
        result = {k: sum(r["status"] == k for r in rows)
                  for k in ("converged", "stopped", "failed", "pending")}
        result.update({"runs": total, "ran": ran, "skipped": skipped,
                       "results": out / "results.csv", "report": None, "figures": [],
                       "meshes": meshes})
        if report:
            from mvfem.report import build_report

            if study.biaxial:
                _biaxial(out, prog)
            result["figures"], result["report"] = build_report(study, out, rows)
        result["wall_time_s"] = time.perf_counter() - t0
        prog.line(f"study: {total} runs: {result['converged']} converged, {result['stopped']} "
                  f"stopped short, {result['failed']} failed ({ran} run now, {skipped} before) "
                  f"in {_hms(result['wall_time_s'])}")
        return result
    finally:
        study_lock.release()


def _launch(spec: RunSpec, out: Path, cpus: set | None = None) -> _Running | None:
    """Start one run (None when an earlier study's orphan still holds its directory)."""
    from mvfem.outputs import prepare_out, remove_earlier_files, write_json

    d = spec.dir(out)
    prepare_out(d)
    try:
        lock = _Lock(d / ".run.lock")
    except BlockingIOError:
        return None
    # the old files go first, so that a study killed now cannot take them for this run's
    remove_earlier_files(d, ("summary.json", "status.json"))
    write_json(_spec_record(spec), d / "run.json")
    log = open(d / "run.log", "w")
    log.write("$ " + " ".join(_quote(a) for a in spec.command(out)) + "\n")
    log.flush()
    proc = subprocess.Popen(spec.command(out), stdout=log, stderr=subprocess.STDOUT,
                            stdin=subprocess.DEVNULL, env=_child_env(), pass_fds=(lock.fd,),
                            preexec_fn=_die_with_parent(os.getpid(), cpus))
    return _Running(spec, proc, time.perf_counter(), time.time(), log, lock)


def _quote(a: str) -> str:
    import shlex

    return shlex.quote(a)


#: exit codes of a run stopped from outside (Ctrl-C, SIGTERM): not a failure of the run, which
#: the next invocation of the study makes again
_INTERRUPTED = (130, 143, -signal.SIGINT, -signal.SIGTERM)

#: how many times a run that exits 1 at start-up without a word (_silent_start_exit) is started
#: again before the exit is recorded as its failure: the Makefile's and the suite's count
_RETRIES = RETRIES


def _silent_start_exit(r: _Running, out: Path, within_s: float = WITHIN_S) -> bool:
    """The run ended within ``within_s`` of its start without a word of its own: no summary,
    no Python traceback and no ``mvfem:`` line in its log (a line or two from MPI or a library
    may be there)."""
    d = r.spec.dir(out)
    if time.perf_counter() - r.started > within_s or (d / "summary.json").exists():
        return False
    r.log.flush()
    try:
        lines = (d / "run.log").read_text(errors="replace").strip().splitlines()[1:]
    except OSError:
        return False
    return not any(ln.startswith(("Traceback", "mvfem:")) or "Error" in ln for ln in lines)


def _finish(r: _Running, out: Path, rc: int | None, reason: str | None = None) -> dict | None:
    """Record a run that ended: status.json from its exit code and summary (None: the run was
    interrupted from outside and stays to do)."""
    from mvfem.outputs import write_json

    d = r.spec.dir(out)
    r.log.close()
    summary = _read_json(d / "summary.json")
    elapsed = time.perf_counter() - r.started
    # (a run stopped by Ctrl-C or SIGTERM writes the state it reached, summary.json "interrupted")
    stopped = summary is None or bool(summary.get("interrupted"))
    if reason is None and stopped and rc in _INTERRUPTED:
        r.lock.release()
        return None
    if reason is None and summary is not None:
        status = "converged" if summary.get("converged") else "stopped"
        reason = "" if status == "converged" else str(summary.get("stop_reason", ""))
    else:
        status = "failed"
        if reason is None:
            reason = _last_line(d / "run.log")
            if rc is not None and rc < 0:
                try:
                    reason = f"killed by {signal.Signals(-rc).name}" + (f"; {reason}" if reason
                                                                        else "")
                except ValueError:
                    pass
            reason = reason or f"exit code {rc} with no output"
        (d / "summary.json").unlink(missing_ok=True)
    rec = {"status": status, "exit_code": rc, "reason": reason, "elapsed_s": elapsed,
           "started": r.started_wall, "finished": time.time(), "pid": r.proc.pid}
    write_json(rec, d / "status.json")
    r.lock.release()
    return rec


def _stop(proc: subprocess.Popen, grace: float = 5.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _schedule(study: Study, out: Path, todo: list, processes: int, prog: _Progress,
              skipped: int, total: int, cpus: set | None = None) -> int:
    """Run ``todo`` with at most ``processes`` at a time; returns how many ran."""
    queue = list(todo)
    running: list[_Running] = []
    waiting: list[RunSpec] = []     # held by an orphan of an earlier study: retried later
    said_waiting: set[str] = set()
    retried: dict[str, int] = {}    # silent start-up exits per run, started again
    durations: dict[str, list[float]] = {}
    done = skipped
    ran = 0

    def on_signal(signum, frame):
        raise _Interrupted(signal.Signals(signum).name)

    old = None
    try:
        old = signal.signal(signal.SIGTERM, on_signal)
    except ValueError:  # not the main thread
        pass
    try:
        while queue or running or waiting:
            while queue and len(running) < processes:
                spec = queue.pop(0)
                if spec.key in said_waiting and run_state(spec, out) == "done":
                    done += 1  # an earlier study's run finished it meanwhile
                    prog.line(f"[{done}/{total}] {spec.case} {spec.set} finished by the "
                              "earlier study's run")
                    continue
                r = _launch(spec, out, cpus)
                if r is None:
                    waiting.append(spec)
                    if spec.key not in said_waiting:
                        said_waiting.add(spec.key)
                        prog.line(f"  {spec.key}: still running from an earlier study; waiting")
                else:
                    running.append(r)
            if waiting and not queue and len(running) < processes:
                queue, waiting = waiting, []
                time.sleep(1.0)
            time.sleep(0.2)
            for r in list(running):
                rc = r.proc.poll()
                reason = None
                if rc is None:
                    if study.timeout_s and time.perf_counter() - r.started > study.timeout_s:
                        _stop(r.proc)
                        rc = r.proc.returncode
                        reason = f"timed out after {study.timeout_s:g} s"
                    else:
                        continue
                running.remove(r)
                if rc == 1 and reason is None and retried.get(r.spec.key, 0) < _RETRIES \
                        and _silent_start_exit(r, out):
                    # about one run in 150 (six at once) exits 1 at start-up with no output at
                    # all (no Python traceback: between PETSc's start and the first gmsh call;
                    # README, Studies); it is started again, up to _RETRIES times
                    retried[r.spec.key] = retried.get(r.spec.key, 0) + 1
                    r.log.close()
                    r.lock.release()
                    prog.line(f"  {r.spec.key}: exit code 1 with no output at start-up; "
                              f"started again ({retried[r.spec.key]} of {_RETRIES})")
                    queue.insert(0, r.spec)
                    continue
                rec = _finish(r, out, rc, reason)
                if rec is None:  # stopped from outside: the study is being interrupted
                    prog.line(f"  {r.spec.key}: interrupted (exit code {rc}); not recorded")
                    queue.insert(0, r.spec)
                    continue
                ran += 1
                done += 1
                if rec["status"] != "failed":
                    durations.setdefault(r.spec.case, []).append(rec["elapsed_s"])
                write_results_csv(collect_results(study, out), out / "results.csv")
                eta = _eta(durations, queue + waiting, running, processes)
                prog.line(f"[{done}/{total}] {r.spec.case} {r.spec.set} {rec['status']}  "
                          f"{rec['elapsed_s']:.1f} s  ETA {_hms(eta)}"
                          + (f"  ({rec['reason']})" if rec["status"] == "failed" else ""))
            prog.bar(done, len(running), _eta(durations, queue + waiting, running, processes))
    except (KeyboardInterrupt, _Interrupted):
        prog.line(f"study interrupted: stopping {len(running)} run(s); run the same command "
                  "again to go on")
        for r in running:
            _stop(r.proc)
            r.log.close()
            r.lock.release()
        running = []
        write_results_csv(collect_results(study, out), out / "results.csv")
        raise KeyboardInterrupt from None
    finally:
        for r in running:  # an unexpected error: leave no run behind
            _stop(r.proc)
            r.lock.release()
        if old is not None:
            signal.signal(signal.SIGTERM, old)
    return ran


def _eta(durations: dict, queued: list, running, processes: int) -> float | None:
    """Seconds left: each run to go takes the mean time of the finished runs of its case (of
    all finished runs when none of its case has finished), shared among the processes."""
    every = [t for ts in durations.values() for t in ts]
    if not every:
        return None
    overall = sum(every) / len(every)

    def mean(case):
        ts = durations.get(case)
        return sum(ts) / len(ts) if ts else overall

    now = time.perf_counter()
    left = (sum(max(mean(r.spec.case) - (now - r.started), 0.0) for r in running)
            + sum(mean(s.case) for s in queued))
    return left / max(min(processes, len(queued) + len(running)), 1)


def _biaxial(out: Path, prog: _Progress) -> None:
    """The canonical biaxial curves of every set (Figs 1-2), once per study directory."""
    d = out / "biaxial"
    if all((d / f).is_file() for f in ("biaxial.csv", "biaxial_anterior.png",
                                       "biaxial_posterior.png")):
        return
    cmd = [sys.executable, "-m", "mvfem.cli", "biaxial", "--out", str(d)]
    r = subprocess.run(cmd, capture_output=True, text=True, env=_child_env())
    if r.returncode != 0:
        prog.line(f"  biaxial curves failed: {(r.stderr.strip().splitlines() or ['?'])[-1]}")


# --------------------------------------------------------------------------- results
def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


def collect_results(study: Study, out: str | Path) -> list[dict]:
    """One row per run (``RESULT_COLUMNS``), from the per-run files in ``out``."""
    from mvfem.distance import last_move
    from mvfem.figures import leaflet_values

    out = Path(out)
    rows = []
    for spec in study.runs:
        d = spec.dir(out)
        row = dict.fromkeys(RESULT_COLUMNS)
        row.update(case=spec.case, set=spec.set, anterior_set=spec.anterior_set,
                   posterior_set=spec.posterior_set, run_dir=str(d.relative_to(out)))
        state = run_state(spec, out)
        status = _read_json(d / "status.json") if state != "todo" else None
        if state == "todo":
            row["status"] = "pending"
        elif state == "failed":
            row.update(status="failed", converged=False, exit_code=status.get("exit_code"),
                       reason=status.get("reason", ""), elapsed_s=status.get("elapsed_s"))
        else:
            s = _read_json(d / "summary.json")
            row.update(status="converged" if s.get("converged") else "stopped",
                       converged=bool(s.get("converged")),
                       exit_code=(status or {}).get("exit_code", 0 if s.get("converged") else 3),
                       reason="" if s.get("converged") else s.get("stop_reason", ""),
                       elapsed_s=(status or {}).get("elapsed_s"))
            for k in ("wall_time_s", "dofs", "cells", "newton_iterations", "equilibrium_residual",
                      "pressure_Pa", "max_displacement_mm", "max_penetration_mm"):
                row[k] = s.get(k)
            v = s.get("valve") or {}
            for k in ("coaptation_length_mm", "coaptation_area_mm2",
                      "regurgitant_orifice_area_mm2", "tenting_height_mm"):
                row[k] = v.get(k)
            ref = s.get("reference") or {}
            for k in ("mean_abs_error_mm", "p95_error_mm", "hausdorff_mm"):
                row[f"reference_{k}"] = ref.get(k)
            # a refined run: how far its last refinement moved the closure (README, "Each
            # refined run measures its own mesh error"), beside its error against the reference
            moved = last_move(s) or {}
            row["mesh_move_mean_mm"] = moved.get("mean_mm")
            row["mesh_move_p95_mm"] = moved.get("p95_mm")
            values = leaflet_values(d, spec.regions)
            if values is not None:
                import numpy as np

                for leaf in LEAFLETS:
                    strain, stress = values[leaf]
                    row[f"{leaf}_cells"] = len(strain) if getattr(spec, f"{leaf}_set") else None
                    for q, arr in (("radial_strain", strain), ("radial_stress_Pa", stress)):
                        if len(arr):
                            for p, x in zip(PERCENTILE_NAMES, np.percentile(arr, _PERCENTILES)):
                                row[f"{leaf}_{q}_{p}"] = float(x)
        rows.append(row)
    return rows


def write_results_csv(rows: list[dict], path: str | Path) -> Path:
    """results.csv, atomically (a reader never sees half a file)."""
    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(RESULT_COLUMNS)
    for r in rows:
        w.writerow([_fmt(r.get(c)) for c in RESULT_COLUMNS])
    path = Path(path)
    _write_atomic(path, buf.getvalue())
    return path
