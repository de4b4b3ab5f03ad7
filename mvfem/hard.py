"""Hard cases (issue 7): scenes that stress the solver and the import, run through the CLI.

Each case is one ``mvfem run`` in its own process with a timeout. What counts as a clean ending
(:func:`verdict`): exit code 0 with a converged, finite summary; exit code 3 with a summary
that says ``"converged": false`` and one ``mvfem: solver stopped: ...`` line on stderr; or, for
the imported meshes that a case damages on purpose, exit code 2 with one ``mvfem: error: ...``
line that names the file. Never a timeout, a traceback, a signal or a NaN in summary.json.

The valve cases use the demo valve on a 4 mm mesh (322 triangles, about 15 s when it converges)
unless the point of the case is the mesh; the imported ones start from the generated valve
written in the import format (:func:`base_valve_file`, 4 mm) and damage it
(:data:`DAMAGE`). ``python scripts/hard_cases.py`` prints the table of the README;
``pytest -m hard`` (tests/test_hard.py) asserts the verdicts.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["CASES", "Case", "Outcome", "base_valve_file", "markdown", "run_case", "verdict"]

DEMO = Path(__file__).parent / "data" / "demo.toml"
#: the valve mesh size of the cases whose point is not the mesh, mm
COARSE = 4.0
ALL_FAMILIES = ("marginal", "strut", "basal")


@dataclass(frozen=True)
class Case:
    """One hard case: a scene (``demo``, a scene file, or an imported valve damaged by
    ``damage``) with ``--set`` changes, a timeout, and whether exit code 2 is a right answer
    (a damaged file that import must reject or repair with a message)."""

    name: str
    what: str
    changes: dict = field(default_factory=dict)
    scene: str = "demo"
    damage: str | None = None
    timeout: float = 300.0
    may_reject: bool = False


def _families(factor: float) -> dict:
    return {f"chordae.{f}.length_factor": factor for f in ALL_FAMILIES}


CASES: list[Case] = [
    Case("cp08-16kPa", "stiffest specimen set CP08 (anterior) at 16 kPa",
         {"region.0.params": "CP08"}),
    Case("cp08-32kPa", "CP08 at twice systolic pressure",
         {"region.0.params": "CP08", "load.pressure": "32 kPa"}),
    Case("cp07-16kPa", "specimen set CP07 (anterior) at 16 kPa", {"region.0.params": "CP07"}),
    Case("cp07-32kPa", "CP07 at 32 kPa", {"region.0.params": "CP07", "load.pressure": "32 kPa"}),
    Case("flat-disk-cp08", "flat stress-free clamped disk, CP08, 16 kPa (zero initial stiffness)",
         {"mesh.size": 1.0, "region.0.params": "CP08"}, scene="disk"),
    Case("chordae-slack-1.5", "all chordae 1.5 x their rest length (very slack)", _families(1.5)),
    Case("chordae-short-0.8", "all chordae 0.8 x their rest length (very short)", _families(0.8)),
    Case("nearly-touching", "imported valve, posterior leaflet moved until its free edge is "
         "0.3 mm from the anterior leaflet", scene="file", damage="nearly-touching"),
    Case("crossing-leaflets", "imported valve whose posterior leaflet passes through the "
         "anterior one (heavy initial penetration)", scene="file", damage="crossing",
         may_reject=True),
    Case("fine-mesh", "demo valve at 1 mm: 3.8x the demo's facets (4385 triangles), "
         "solver.max_steps = 300", {"mesh.size": 1.0, "solver.max_steps": 300}, timeout=600.0),
    Case("fine-mesh-sequenced", "the same, started from its closure on the demo's 2 mm mesh "
         "(solver.coarse_start = 2)",
         {"mesh.size": 1.0, "solver.max_steps": 300, "solver.coarse_start": 2.0}, timeout=600.0),
    Case("fine-mesh-nested", "the demo's 2 mm valve refined once (4x its facets, 4576 "
         "triangles, mesh.refine = 1), closed from the 2 mm closure (solver.nested), "
         "solver.max_steps = 300", {"mesh.size": 2.0, "mesh.refine": 1, "solver.max_steps": 300},
         timeout=600.0),
    Case("slivers", "imported valve with 3 posterior nodes moved to within 1 % of an edge: 3 "
         "slivers (smallest angle 0.55 deg)", scene="file", damage="slivers", may_reject=True),
    Case("inverted", "imported valve with 3 nodes pushed across a neighbour edge (folded, "
         "inverted triangles)", scene="file", damage="inverted", may_reject=True),
    Case("duplicate-nodes", "imported valve with 10 leaflet nodes duplicated (cells of one "
         "side use the copies)", scene="file", damage="duplicates", may_reject=True),
    Case("pressure-100kPa", "100 kPa, six times systolic pressure",
         {"load.pressure": "100 kPa"}),
    Case("prolapse-no-marginal", "marginal chordae family removed (ruptured): prolapse",
         {"chordae.edit": [{"family": "marginal", "rupture": True}]}),
]


# --------------------------------------------------------------------------- imported files
def base_valve_file(path: Path, size: float = COARSE) -> Path:
    """The generated valve (``mvfem mesh valve --size SIZE``) in the import format."""
    if not path.exists():
        subprocess.run([sys.executable, "-m", "mvfem.cli", "mesh", "valve", "--size", str(size),
                        "--out", str(path)], check=True, capture_output=True, env=_env())
    return path


def _leaflet_nodes(raw, value: int) -> np.ndarray:
    return np.unique(raw.triangles[raw.cell_data["leaflet"] == value])


def _interior(raw, nodes: np.ndarray) -> np.ndarray:
    """Nodes off the boundary (neither annulus nor free edge)."""
    from mvfem.meshes.refine import cell_edges

    u, sides = cell_edges(raw.triangles)
    boundary = np.unique(u[np.bincount(sides.ravel(), minlength=len(u)) == 1])
    return np.setdiff1d(nodes, boundary)


def _point_triangle_distance(p, a, b, c) -> np.ndarray:
    """Distances from points ``p`` (n, 3) to triangles ``abc`` (n, 3 each), exact."""
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    h = np.einsum("ij,ij->i", p - a, n)
    y = p - h[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, y - u), n) >= 0
    best = np.where(inside, np.abs(h), np.inf)
    for u, v in ((a, b), (b, c), (c, a)):
        e = v - u
        t = np.clip(np.einsum("ij,ij->i", p - u, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(p - u - t[:, None] * e, axis=1))
    return best


def _gap(X, moved: np.ndarray, tri: np.ndarray) -> float:
    """Smallest distance from the nodes ``moved`` to the triangles ``tri`` (near candidates)."""
    from scipy.spatial import cKDTree

    T = tri
    _, near = cKDTree(X[T].mean(axis=1)).query(X[moved], k=min(8, len(T)))
    i = np.repeat(moved, near.shape[1])
    t = T[near.ravel()]
    return float(_point_triangle_distance(X[i], X[t[:, 0]], X[t[:, 1]], X[t[:, 2]]).min())


def damage_file(kind: str, base: Path, out: Path) -> Path:
    """Write a damaged copy of the valve file ``base`` (see :data:`CASES`)."""
    from mvfem.meshes.io import read_surface, write_raw_surface

    raw = read_surface(base)
    X = raw.points.copy()
    ant, post = _leaflet_nodes(raw, 1), _leaflet_nodes(raw, 2)
    ann = raw.point_data["annulus"] != 0
    post_free = post[~ann[post]]
    # how far below the annulus plane (z = its mean) a node hangs: 0 at the annulus, 1 deepest
    z_ann = X[ann, 2].mean()
    depth = np.clip((z_ann - X[:, 2]) / max(z_ann - X[post_free, 2].min(), 1e-9), 0.0, 1.0)
    anterior_dir = X[ant].mean(axis=0) - X[post].mean(axis=0)
    anterior_dir[2] = 0.0
    anterior_dir /= np.linalg.norm(anterior_dir)
    ant_tri = np.flatnonzero(raw.cell_data["leaflet"] == 1)
    if kind in ("nearly-touching", "crossing"):
        # posterior nodes shifted toward the anterior leaflet in proportion to their depth,
        # the most at the middle of the leaflet, nothing at the commissures
        side = np.cross([0.0, 0.0, 1.0], anterior_dir)
        lateral = (X - X[ann].mean(axis=0)) @ side
        taper = np.clip(1.0 - (lateral / np.abs(lateral[post]).max()) ** 2, 0.0, 1.0)
        weight = depth * taper

        def shifted(a: float) -> np.ndarray:
            Y = X.copy()
            Y[post_free] += a * weight[post_free, None] * anterior_dir
            return Y

        middle = post_free[taper[post_free] > 0.5]
        ant_only = ant_tri[~np.isin(raw.triangles[ant_tri], post).any(axis=1)]
        if kind == "crossing":
            X = shifted(20.0)
        else:  # bisect the shift for a smallest gap of 0.3 mm at the middle
            lo, hi = 0.0, 20.0
            for _ in range(25):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if _gap(shifted(mid), middle, raw.triangles[ant_only]) > 0.3 \
                    else (lo, mid)
            X = shifted(lo)
    elif kind == "slivers":
        # an interior node moved to within 1 % of the edge opposite it in a neighbour triangle
        rng = np.random.default_rng(7)
        for i in rng.choice(_interior(raw, post), 3, replace=False):
            t = raw.triangles[np.any(raw.triangles == i, axis=1)][0]
            a, b = [j for j in t if j != i]
            m = 0.5 * (X[a] + X[b])
            X[i] = m + 0.01 * (X[i] - m)
    elif kind == "inverted":
        # an interior node pushed 40 % past the edge opposite it: that triangle folds over
        rng = np.random.default_rng(11)
        for i in rng.choice(_interior(raw, ant), 3, replace=False):
            t = raw.triangles[np.any(raw.triangles == i, axis=1)][0]
            a, b = [j for j in t if j != i]
            m = 0.5 * (X[a] + X[b])
            X[i] = m - 0.4 * (X[i] - m)
    elif kind == "duplicates":
        # leaflet nodes given a coincident copy; the anterior cells around each use the copy
        rng = np.random.default_rng(3)
        tri = raw.triangles.copy()
        extra, pd = [], {k: list(v) for k, v in raw.point_data.items()}
        for i in rng.choice(_interior(raw, ant), 10, replace=False):
            k = len(X) + len(extra)
            extra.append(X[i].copy())
            for name, values in pd.items():
                values.append(raw.point_data[name][i])
            sel = np.flatnonzero(np.any(tri == i, axis=1))[::2]
            tri[sel] = np.where(tri[sel] == i, k, tri[sel])
        X = np.vstack([X, extra])
        raw.point_data = {k: np.asarray(v) for k, v in pd.items()}
        raw.triangles = tri
    else:
        raise ValueError(f"unknown damage {kind!r}")
    raw.points = X
    write_raw_surface(out, raw)
    return out


def _scene_for(case: Case, workdir: Path) -> tuple[Path, dict]:
    changes = dict(case.changes)
    if case.scene == "demo":
        changes.setdefault("mesh.size", COARSE)
        return DEMO, changes
    if case.scene == "disk":
        scene = workdir / "disk.toml"
        scene.write_text('title = "hard case: flat disk"\n[mesh]\ngenerator = "disk"\n'
                         'radius = 10.0\nsize = 1.0\n[[region]]\nlaw = "mny"\n'
                         'params = "MNY-mean"\n[load]\npressure = "16 kPa"\n[output]\n'
                         'probes = [{ name = "centre", point = [0.0, 0.0, 0.0] }]\n')
        return scene, changes
    base = base_valve_file(workdir.parent / "base_valve.vtu")
    vtu = damage_file(case.damage, base, workdir / f"{case.name}.vtu")
    scene = workdir / f"{case.name}.toml"
    scene.write_text(f'title = "hard case: {case.name}"\n[mesh]\ngenerator = "file"\n'
                     f'file = "{vtu.name}"\nlabels = {{ 1 = "anterior", 2 = "posterior" }}\n'
                     '[[region]]\nlabel = "anterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     '[[region]]\nlabel = "posterior"\nlaw = "mny"\nparams = "MNY-mean"\n'
                     'leaflet = "posterior"\n[load]\npressure = "16 kPa"\n')
    return scene, changes


# --------------------------------------------------------------------------- running
@dataclass
class Outcome:
    """How a case ended."""

    case: Case
    exit_code: int | None  # None: killed at the timeout
    time_s: float
    stdout: str
    stderr: str
    summary: dict | None

    @property
    def message(self) -> str:
        """The line a user sees: the error or stop line on stderr, else the result line."""
        lines = [ln for ln in self.stderr.splitlines() if ln.startswith("mvfem: ")]
        if lines:
            return lines[-1][len("mvfem: "):]
        if self.exit_code is None:
            return f"killed after the {self.case.timeout:g} s timeout"
        out = [ln for ln in self.stdout.splitlines() if ln.startswith(("converged",
                                                                       "NOT converged"))]
        return out[-1] if out else ""

    @property
    def warnings(self) -> list[str]:
        return [ln for ln in self.stderr.splitlines()
                if ln and not ln.startswith(("mvfem: ", " ", "valve", "solver stopped short"))
                and "step" not in ln]


def _env() -> dict:
    from mvfem.relaunch import without_mpi_job

    env = without_mpi_job()  # a case started under mpirun runs as its own serial program
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    root = str(Path(__file__).resolve().parents[1])
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _no_nan(text: str):
    def refuse(c):
        raise ValueError(f"summary.json has {c}")
    return json.loads(text, parse_constant=refuse)


def run_case(case: Case, workdir: Path) -> Outcome:
    """Run ``case`` through ``mvfem run`` in a subprocess (its own process group, killed at
    the timeout) in ``workdir/case.name``."""
    work = Path(workdir) / case.name
    work.mkdir(parents=True, exist_ok=True)
    scene, changes = _scene_for(case, work)
    out = work / "out"
    cmd = [sys.executable, "-m", "mvfem.cli", "run", str(scene), "--out", str(out)]
    for k, v in changes.items():
        cmd += ["--set", f"{k}={_toml(v)}"]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                         env=_env(), start_new_session=True)
    try:
        so, se = p.communicate(timeout=case.timeout)
        code = p.returncode
    except subprocess.TimeoutExpired:
        os.killpg(p.pid, signal.SIGKILL)
        so, se = p.communicate()
        code = None
    dt = time.perf_counter() - t0
    summary = None
    f = out / "summary.json"
    if f.exists():
        try:
            summary = _no_nan(f.read_text())
        except ValueError as e:
            summary = {"_unreadable": str(e)}
    (work / "stdout.txt").write_text(so)
    (work / "stderr.txt").write_text(se)
    return Outcome(case, code, dt, so, se, summary)


def _toml(v) -> str:
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, list):
        return "[" + ", ".join(_toml(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{ " + ", ".join(f"{k} = {_toml(x)}" for k, x in v.items()) + " }"
    return repr(v)


def _finite(obj) -> bool:
    if isinstance(obj, float):
        return math.isfinite(obj)
    if isinstance(obj, dict):
        return all(_finite(v) for v in obj.values())
    if isinstance(obj, list):
        return all(_finite(v) for v in obj)
    return True


def verdict(o: Outcome) -> tuple[bool, str]:
    """(clean ending?, why not)."""
    if o.exit_code is None:
        return False, f"hung: killed at {o.case.timeout:g} s"
    if "Traceback" in o.stderr:
        return False, "traceback on stderr"
    if o.exit_code < 0:
        return False, f"killed by signal {-o.exit_code}"
    if o.exit_code == 2:
        lines = [ln for ln in o.stderr.splitlines() if ln.startswith("mvfem: error: ")]
        if not o.case.may_reject:
            return False, f"input refused: {o.message}"
        return (len(lines) == 1 and o.summary is None,
                "" if len(lines) == 1 else "not one error line")
    if o.exit_code not in (0, 3):
        return False, f"exit code {o.exit_code}"
    s = o.summary
    if s is None or "_unreadable" in s:
        return False, (s or {}).get("_unreadable", "no summary.json")
    if not _finite(s):
        return False, "non-finite number in summary.json"
    if o.exit_code == 0:
        return (s["converged"] is True, "exit 0 but not converged")
    stop = [ln for ln in o.stderr.splitlines() if ln.startswith("mvfem: solver stopped: ")]
    return (s["converged"] is False and len(stop) == 1, "exit 3 without the stop line")


def markdown(outcomes: list[Outcome]) -> str:
    lines = ["| case | what | outcome | exit code | time (s) | message |", "|---|---|---|---:|---:|---|"]
    for o in outcomes:
        ok, why = verdict(o)
        s = o.summary or {}
        kind = {0: "converged", 2: "rejected", 3: "stopped short", None: "HUNG"}.get(
            o.exit_code, f"exit {o.exit_code}")
        extra = []
        if o.exit_code in (0, 3) and s:
            v = s.get("valve") or {}
            if s.get("max_penetration_mm") is not None:
                extra.append(f"penetration {s['max_penetration_mm']:.3g} mm")
            if v.get("coaptation_length_mm") is not None:
                extra.append(f"coaptation {v['coaptation_length_mm']:.3g} mm")
        warn = [w for w in o.warnings if "merged" in w or "warning" in w.lower()]
        msg = o.message.replace("|", "/").replace(f"{Path.cwd()}/", "")
        if extra:
            msg += " (" + ", ".join(extra) + ")"
        if warn:
            msg += "; warned: " + warn[0].replace("|", "/").replace(f"{Path.cwd()}/", "")
        lines.append(f"| {o.case.name} | {o.case.what} | {kind if ok else 'NOT CLEAN: ' + why} "
                     f"| {'-' if o.exit_code is None else o.exit_code} | {o.time_s:.0f} | {msg} |")
    return "\n".join(lines)
