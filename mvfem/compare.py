"""Repair comparison (issue 8): ``mvfem repair-compare SCENE --repairs R1.toml R2.toml ...``.

The unrepaired valve (the scene as written) and each repair are closed at systole (the scene's
pressure) and, unless switched off, opened under a small atrial-side (diastolic) pressure;
every run is one ``mvfem run`` process of the study runner (:mod:`mvfem.study`: resumable,
``processes`` at a time, one line per finished run). Then:

- ``comparison.csv``: one row per case (``COLUMNS``): regurgitant orifice area (with its
  projected and leak-gap parts), coaptation length (stepped, and the continuous trace
  length, which moves less with the solver's path: README "Repairs") and area, tenting
  height, the 95th percentile and the peak of the per-facet radial Cauchy stress over both
  leaflets, chordae
  forces (native and neochordae), tie (clip, suture) forces, on a refined mesh how far its
  last refinement moved the closure (``mesh_move_mean_mm``, ``mesh_move_p95_mm``: the
  systolic run's ``coarse_start`` ``distance_to_finer_mm``, README "Each refined run measures
  its own mesh error"), and from the diastolic run the orifice area and the number of
  separate orifices;
- ``comparison.png``: those numbers as bars, one per case;
- ``shapes.png``: the closed valves side by side, seen from the atrium (radial stress, one
  colour range for all) and from the side (the A2-P2 direction across), and the diastolic
  valves seen from the atrium.

The solver's path can pick the closure: a ring that shrinks the annulus leaves the leaflets
more tissue than the orifice needs, and they can rest in more than one fold (README
"Repairs", "Which closure"). Two options close the cases again at systole along other paths,
the same scene and pressure: ``paths`` (``--paths 10,20,30,40``), each case with a
prescribed motion (a ring, a clip's or sutures' ties, moved papillary tips) with each of
those ``solver.ramp_steps`` (a case without one has no ramp to vary); ``weights``
(``--weights 0.05,0.2,0.4``), every case with each of those ``solver.stabilisation``, the
pseudo-time start weight. The csv then gains, for the regurgitant orifice, both coaptation
lengths and the tenting height, the smallest and largest value over each case's converged
systolic runs (``PATH_COLUMNS``; ``path_runs`` names them); the printed table shows them as
``[min, max]``, comparison.png as a line over each bar, and ``paths.png`` shows each case's
closures side by side (the folds). Differences between repairs within those ranges are not
differences.

Under ``mesh.accuracy`` every case closes on one mesh, the one the case needing the most
refinements needs (:func:`mvfem.study.one_mesh_runs`: the systoles first, to the accuracy;
the result's ``mesh`` and ``comparison.csv`` ``mesh_cells`` say which).

A repair file is a TOML table of scene keys merged into the scene: tables key by key, other
values (numbers, strings, lists such as ``[[repair.clip]]`` or ``chordae.edit``) replace the
scene's. Its ``title`` names the repair (default: the file's stem); file names in it
(``annulus.target``, ``papillary.target``, ``mesh.file``, ...) are relative to it. Every
repair is built (mesh, ring, snapped points, resection) before anything runs: an impossible
repair is one line naming the repair file and key, exit code 2.
"""

from __future__ import annotations

import csv
import io
import math
import re
from pathlib import Path

import numpy as np

from mvfem.errors import InputError
from mvfem.scene import read_toml
from mvfem.units import beyond_float

__all__ = ["COLUMNS", "DIASTOLIC_PRESSURE", "PATH_COLUMNS", "PATH_KEYS", "compare",
           "load_repair", "parse_paths", "parse_weights"]

#: the atrial-side pressure of the diastolic check (Pa): the valve opens; a clip shows its two
#: orifices
DIASTOLIC_PRESSURE = -500.0
COLUMNS = ("case", "title", "systole", "regurgitant_orifice_area_mm2",
           "projected_orifice_area_mm2", "leak_gap_area_mm2", "coaptation_length_mm",
           "coaptation_trace_length_mm", "coaptation_area_mm2", "tenting_height_mm",
           "annulus_area_mm2", "stress_p95_Pa", "stress_max_Pa", "chordae_force_total_N",
           "chordae_force_max_N", "neochord_force_total_N", "tie_force_max_N",
           "mesh_move_mean_mm", "mesh_move_p95_mm", "mesh_cells", "diastole",
           "diastolic_orifice_area_mm2", "diastolic_orifice_count", "diastolic_orifice_areas_mm2",
           "run_dir")
#: the numbers whose spread over the solver's paths ``--paths`` and ``--weights`` measure
PATH_KEYS = ("regurgitant_orifice_area_mm2", "coaptation_length_mm", "coaptation_trace_length_mm",
             "tenting_height_mm")


def _bound(key: str, which: str) -> str:
    """``coaptation_length_mm`` -> ``coaptation_length_min_mm`` (``which`` min or max)."""
    base, unit = key.rsplit("_", 1)
    return f"{base}_{which}_{unit}"


#: appended to ``COLUMNS`` (empty without ``--paths`` or ``--weights``): the case's converged
#: systolic runs (``own``, then ``solver.ramp_steps=N``, ``solver.stabilisation=W``) and each
#: PATH_KEY's smallest and largest value over them
PATH_COLUMNS = ("path_runs",) + tuple(_bound(k, w) for k in PATH_KEYS for w in ("min", "max"))
#: the study's set names of the runs along other paths, and the scene key each varies
VARIANTS = {"path-": "solver.ramp_steps", "weight-": "solver.stabilisation"}
COLUMNS = COLUMNS + PATH_COLUMNS
#: keys whose values are file names (resolved against the repair file's directory)
_PATH_KEYS = ("mesh.file", "mesh.annulus", "mesh.papillary", "reference.file",
              "annulus.target", "papillary.target")
_NAME = re.compile(r"[^A-Za-z0-9._-]+")


def load_repair(path: str | Path, scene) -> tuple[str, str, dict]:
    """(name, title, scene changes) of a repair file, validated against ``scene``.

    Raises:
        InputError: one line naming the repair file, the key and the problem.
    """
    path = Path(path)
    raw = read_toml(path, "repair", missing=f"--repairs {path}: no such repair file")
    title = raw.pop("title", path.stem)
    if not isinstance(title, str):
        raise InputError(f"{path}: title: expected a string, got {title!r}")
    if not raw:
        raise InputError(f"{path}: the repair changes nothing (no scene keys)")
    from mvfem.study import _flatten

    changes = _flatten(raw)
    for k in list(changes):
        if k in _PATH_KEYS and isinstance(changes[k], str):
            p = Path(changes[k])
            changes[k] = str(p if p.is_absolute() else (path.resolve().parent / p))
    try:
        scene.with_changes(changes)
    except InputError as e:
        raise InputError(f"{path}: {str(e).split(': ', 1)[-1]}") from None
    name = _NAME.sub("-", path.stem).strip("-") or "repair"
    return name, title, changes


def _check_buildable(scene, label: str) -> dict:
    """Build the repaired model on this process alone (mesh, ring, snapped points,
    resection): its input errors are the repair's. Returns the valve frame for the figures."""
    from mpi4py import MPI

    from mvfem.model import build_model

    try:
        model = build_model(scene, MPI.COMM_SELF)
    except InputError as e:
        text = str(e)
        if text.startswith(scene.source):
            text = text[len(scene.source):].lstrip(": ")
        raise InputError(f"{label}: {text}") from None
    s = model.surface
    return {"frame": np.asarray(getattr(s, "frame", np.eye(3)), dtype=float),
            "centre": np.asarray(getattr(s, "centre", np.zeros(3)), dtype=float),
            "motion": bool(model.motion), "ramp_steps": int(model.ramp_steps),
            "stabilisation": float(model.scene["solver"]["stabilisation"])}


def _parse_values(text, option: str, convert, what: str) -> list:
    """``"a,b,c"`` (or a list) -> the values, in order, without repeats; each ``convert``ed
    and positive, else one line naming ``option``."""
    items = [t.strip() for t in text.split(",")] if isinstance(text, str) else list(text)
    out = []
    for t in items:
        if t == "":
            continue
        try:
            v = convert(t)
        except (TypeError, ValueError):
            v = None
        if v is None or not v > 0 or beyond_float(v) or not math.isfinite(v):
            raise InputError(f"{option}: {text!r}: expected {what} separated by commas")
        if v not in out:
            out.append(v)
    if not out:
        raise InputError(f"{option}: {text!r}: give at least one value")
    return out


def _whole(t) -> int:
    n = int(t)
    if str(n) != str(t).strip():
        raise ValueError(t)
    return n


def parse_paths(text) -> list[int]:
    """``"10,20,30,40"`` (or a list) -> the ``solver.ramp_steps`` values of ``--paths``.

    Raises:
        InputError: one line, when a value is not a positive whole number.
    """
    return _parse_values(text, "--paths", _whole, "solver.ramp_steps values, positive whole "
                         "numbers (e.g. 10,20,30,40),")


def parse_weights(text) -> list[float]:
    """``"0.05,0.2,0.4"`` (or a list) -> the ``solver.stabilisation`` values of ``--weights``.

    Raises:
        InputError: one line, when a value is not a positive number.
    """
    return _parse_values(text, "--weights", float, "solver.stabilisation values, positive "
                         "numbers (e.g. 0.05,0.2,0.4),")


def compare(scene_path: str | Path, repairs: list, out: str | Path, processes: int | None = None,
            diastolic: float | None = DIASTOLIC_PRESSURE, changes: dict | None = None,
            progress: bool = True, timeout: float | None = None,
            paths: list | None = None, weights: list | None = None) -> dict:
    """Run the unrepaired scene and each repair; write the comparison (module docstring).

    Args:
        scene_path: the pathological valve's scene file.
        repairs: repair files.
        out: the comparison directory (made by mvfem, or new); resumable.
        processes: runs at a time (default: the cores available).
        diastolic: the pressure (Pa, negative: atrial side) of the diastolic runs; None skips
            them.
        changes: scene changes applied to every case first (``--set``).
        paths: ``solver.ramp_steps`` values (:func:`parse_paths`): each case with a prescribed
            motion is closed again with each one that is not its own (module docstring).
        weights: ``solver.stabilisation`` values (:func:`parse_weights`): each case is closed
            again with each one that is not its own.

    Returns:
        dict with ``rows`` (the table), ``files``, ``counts``, ``moving`` (the cases with a
        prescribed motion, whose closure ``paths`` can vary).
    """
    import hashlib

    from mvfem.outputs import check_out, prepare_out
    from mvfem.scene import load_scene
    from mvfem.study import (Case, RunSpec, Study, _leaflet_of, checked_processes, mesh_line,
                             one_mesh_runs, run_study)

    scene_path = Path(scene_path).resolve()
    base = load_scene(scene_path)
    changes = dict(changes or {})
    if changes:
        base.with_changes(changes)
    if not repairs:
        raise InputError("--repairs: give at least one repair file")
    if processes is not None:
        checked_processes(processes)
    check_out(out)   # (before the repairs' meshes are built: seconds, and their lines)
    if diastolic is not None and not diastolic < 0:
        raise InputError(f"--diastolic: expected a negative (atrial-side) pressure, got "
                         f"{diastolic:g} Pa")
    paths = parse_paths(paths) if paths else []
    weights = parse_weights(weights) if weights else []
    cases = [("unrepaired", "unrepaired", {})]
    for r in repairs:
        name, title, ch = load_repair(r, base.with_changes(changes) if changes else base)
        while name in [c[0] for c in cases]:
            name += "_"
        cases.append((name, title, ch))
    view, built = None, {}
    for name, _title, ch in cases:  # every repair built before anything runs
        built[name] = _check_buildable(base.with_changes({**changes, **ch}),
                                       "the scene" if name == "unrepaired" else
                                       str(repairs[[c[0] for c in cases].index(name) - 1]))
        view = view or built[name]
    phases = [("systole", {})]
    if diastolic is not None:
        phases.append(("diastole", {"load.pressure": float(diastolic)}))
    regions = [{"label": r["label"] or "membrane", "leaflet": _leaflet_of(r),
                "set": r.get("set", "custom")} for r in base["region"]]
    sets = {leaf: next((r["set"] for r in regions if r["leaflet"] == leaf), "")
            for leaf in ("anterior", "posterior")}
    digest = hashlib.sha256(scene_path.read_bytes()).hexdigest()
    runs, study_cases = [], []
    for name, _title, ch in cases:
        study_cases.append(Case(name=name, scene=str(scene_path), changes={**changes, **ch}))
        for phase, extra in phases:
            all_changes = {**changes, **ch, **extra, "output.xdmf": True}
            runs.append(RunSpec(case=name, set=phase, anterior_set=sets["anterior"],
                                posterior_set=sets["posterior"], scene=str(scene_path),
                                changes=all_changes, regions=regions, scene_sha256=digest))
        own = built[name]
        other = ([("path-", n) for n in paths if own["motion"] and n != own["ramp_steps"]]
                 + [("weight-", w) for w in weights if w != own["stabilisation"]])
        for prefix, v in other:  # (no motion: no ramp to vary)
            runs.append(RunSpec(case=name, set=f"{prefix}{v}", anterior_set=sets["anterior"],
                                posterior_set=sets["posterior"], scene=str(scene_path),
                                changes={**changes, **ch, VARIANTS[prefix]: v},
                                regions=regions, scene_sha256=digest))
    def study_of(runs):
        return Study(title=f"repairs of {base['title'] or scene_path.name}", cases=study_cases,
                     sets=list(dict.fromkeys(r.set for r in runs)),  # (variants: where run)
                     processes=processes or 1, timeout_s=timeout,
                     map_case="unrepaired", include_stopped=True, biaxial=False, runs=runs,
                     source=str(scene_path))

    out = prepare_out(out).resolve()
    # under mesh.accuracy every case on one mesh (nothing runs here without a target)
    runs, meshes = one_mesh_runs(
        runs, out, lambda rs: run_study(study_of(rs), out, processes=processes,
                                        progress=progress, report=False, one_mesh=False),
        primary=lambda r: r.set == "systole", group=lambda r: "", label=lambda r: r.case)
    mesh = meshes.get("")
    if mesh and progress:
        import sys

        sys.stderr.write(mesh_line(mesh) + "\n")
    study = study_of(runs)
    res = run_study(study, out, processes=processes, progress=progress, report=False,
                    one_mesh=False)
    titles = {c[0]: c[1] for c in cases}
    rows = _rows(study, out, titles)
    files = [_write_csv(rows, out / "comparison.csv")]
    files += [p for p in (_bars(rows, out / "comparison.png"),
                          _shapes(study, out, view, out / "shapes.png", titles, diastolic),
                          _path_shapes(study, out, view, out / "paths.png", titles))
              if p is not None]
    return {"rows": rows, "files": files, "counts": res, "mesh": mesh,
            "moving": [name for name, _t, _c in cases if built[name]["motion"]]}


# --------------------------------------------------------------------------- table
def _summary(d: Path) -> dict | None:
    import json

    try:
        return json.loads((d / "summary.json").read_text())
    except (OSError, ValueError):
        return None


def _rows(study, out: Path, titles: dict) -> list[dict]:
    from mvfem.distance import last_move
    from mvfem.figures import read_fields

    rows = []
    for case in study.cases:
        row = dict.fromkeys(COLUMNS)
        row.update(case=case.name, title=titles[case.name])
        closed = []  # (label, valve) of the converged systolic runs, its own first
        for spec in study.runs:
            if spec.case != case.name:
                continue
            d = spec.dir(out)
            s = _summary(d)
            status = "missing" if s is None else ("converged" if s.get("converged")
                                                  else "stopped")
            v = (s or {}).get("valve") or {}
            if spec.set == "systole" or _variant(spec.set):
                if status == "converged":
                    closed.append((_label(spec.set), v))
                if spec.set != "systole":
                    continue
            if spec.set == "systole":
                row["systole"] = status
                row["run_dir"] = str(d.relative_to(out))
                for k in ("regurgitant_orifice_area_mm2", "projected_orifice_area_mm2",
                          "leak_gap_area_mm2", "coaptation_length_mm",
                          "coaptation_trace_length_mm", "coaptation_area_mm2",
                          "tenting_height_mm", "annulus_area_mm2"):
                    row[k] = v.get(k)
                ch = v.get("chordae_force_N") or {}
                row["chordae_force_total_N"] = ch.get("total")
                row["chordae_force_max_N"] = ch.get("max")
                row["neochord_force_total_N"] = (ch.get("neochord") or {}).get("total")
                row["mesh_cells"] = (s or {}).get("cells")
                moved = last_move(s)
                if moved:
                    row["mesh_move_mean_mm"] = moved["mean_mm"]
                    row["mesh_move_p95_mm"] = moved["p95_mm"]
                ties = v.get("ties") or {}
                if ties:
                    row["tie_force_max_N"] = max(t["max_force_N"] for t in ties.values())
                f = read_fields(d) if s is not None else None
                if f is not None:
                    stress = f["radial_cauchy_stress_Pa"]
                    row["stress_p95_Pa"] = float(np.percentile(stress, 95))
                    row["stress_max_Pa"] = float(stress.max())
            else:
                row["diastole"] = status
                row["diastolic_orifice_area_mm2"] = v.get("diastolic_orifice_area_mm2")
                row["diastolic_orifice_count"] = v.get("orifice_count")
                areas = v.get("orifice_areas_mm2")
                row["diastolic_orifice_areas_mm2"] = (" ".join(f"{a:.1f}" for a in areas)
                                                     if areas else None)
        if any(r.case == case.name and _variant(r.set) for r in study.runs):
            _path_ranges(row, closed)
        rows.append(row)
    return rows


def _variant(set_name: str) -> str | None:
    """The prefix of a run along another path (``VARIANTS``), None for other runs."""
    return next((p for p in VARIANTS if set_name.startswith(p)), None)


def _label(set_name: str) -> str:
    """``systole`` -> ``own``; ``path-10`` -> ``solver.ramp_steps=10``; ``weight-0.05`` ->
    ``solver.stabilisation=0.05``."""
    p = _variant(set_name)
    return "own" if p is None else f"{VARIANTS[p]}={set_name[len(p):]}"


def _path_ranges(row: dict, closed: list) -> None:
    """Set ``row``'s PATH_COLUMNS from ``closed``, the (label, valve summary) of the case's
    converged systolic runs, its own first."""
    if not closed:
        return
    row["path_runs"] = " ".join(label for label, _ in closed)
    for k in PATH_KEYS:
        vals = [float(v[k]) for _, v in closed if v.get(k) is not None
                and math.isfinite(float(v[k]))]
        if vals:
            row[_bound(k, "min")], row[_bound(k, "max")] = min(vals), max(vals)


def _fmt(v) -> str:
    if v is None:
        return ""
    if isinstance(v, float):
        return "" if not math.isfinite(v) else f"{v:.6g}"
    return str(v)


def _write_csv(rows: list[dict], path: Path) -> Path:
    import os

    buf = io.StringIO()
    w = csv.writer(buf)
    w.writerow(COLUMNS)
    for r in rows:
        w.writerow([_fmt(r.get(c)) for c in COLUMNS])
    tmp = path.with_name(path.name + ".part")
    tmp.write_text(buf.getvalue())
    os.replace(tmp, path)
    return path


def table_text(rows: list[dict]) -> str:
    """The comparison as a Markdown table (what the CLI prints and README quotes)."""
    cols = [("case", "case", "{}"), ("systole", "systole", "{}"),
            ("regurgitant_orifice_area_mm2", "orifice mm2", "{:.1f}"),
            ("coaptation_length_mm", "coapt. length mm", "{:.2f}"),
            ("coaptation_trace_length_mm", "coapt. trace mm", "{:.2f}"),
            ("coaptation_area_mm2", "coapt. area mm2", "{:.0f}"),
            ("tenting_height_mm", "tenting mm", "{:.2f}"),
            ("mesh_move_mean_mm", "mesh move mm", "{:.3f}"),
            ("stress_p95_Pa", "stress p95 kPa", "k{:.0f}"),
            ("stress_max_Pa", "stress max kPa", "k{:.0f}"),
            ("chordae_force_total_N", "chordae N", "{:.2f}"),
            ("neochord_force_total_N", "neochordae N", "{:.2f}"),
            ("tie_force_max_N", "tie max N", "{:.2f}"),
            ("diastole", "diastole", "{}"),
            ("diastolic_orifice_area_mm2", "diastolic orifice mm2", "{:.0f}"),
            ("diastolic_orifice_count", "orifices", "{}")]
    lines = ["| " + " | ".join(c[1] for c in cols) + " |",
             "|" + "|".join("---" for _ in cols) + "|"]
    for r in rows:
        cells = []
        for key, _, f in cols:
            v = r.get(key)
            if v is None:
                cells.append("-")
            elif f.startswith("k"):
                cells.append(f[1:].format(v / 1e3))
            else:
                cells.append(f.format(v))
            if key in PATH_KEYS and r.get(_bound(key, "min")) is not None:
                cells[-1] += (f" [{f.format(r[_bound(key, 'min')])}, "
                              f"{f.format(r[_bound(key, 'max')])}]")
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- figures
def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _bars(rows: list[dict], path: Path) -> Path | None:
    plt = _plt()
    panels = [("regurgitant_orifice_area_mm2", "regurgitant orifice area (mm$^2$)", 1.0),
              ("coaptation_length_mm", "coaptation length (mm)", 1.0),
              ("coaptation_area_mm2", "coaptation area (mm$^2$)", 1.0),
              ("tenting_height_mm", "tenting height (mm)", 1.0),
              ("stress_p95_Pa", "radial Cauchy stress, 95th pct. (kPa)", 1e-3),
              ("stress_max_Pa", "radial Cauchy stress, peak (kPa)", 1e-3),
              ("chordae_force_total_N", "chordae + neochordae force (N)", 1.0),
              ("diastolic_orifice_area_mm2", "diastolic orifice area (mm$^2$)", 1.0)]
    names = [r["case"] for r in rows]
    fig, axes = plt.subplots(2, 4, figsize=(15, 7), dpi=110)
    colours = ["0.45"] + [f"C{i}" for i in range(len(rows) - 1)]
    for ax, (key, label, scale) in zip(axes.ravel(), panels):
        vals = np.array([np.nan if r.get(key) is None else r[key] * scale for r in rows])
        ax.bar(range(len(rows)), np.nan_to_num(vals), color=colours)
        # --paths, --weights: the range over the solver's paths, a line over the bar
        lo, hi = (np.array([np.nan if key not in PATH_KEYS or r.get(_bound(key, w)) is None
                            else r[_bound(key, w)] * scale for r in rows]) for w in ("min", "max"))
        ranged = np.isfinite(lo)
        if ranged.any():
            x = np.flatnonzero(ranged)
            ax.vlines(x, lo[ranged], hi[ranged], color="k", linewidth=1.2)
            for y in (lo[ranged], hi[ranged]):
                ax.hlines(y, x - 0.12, x + 0.12, color="k", linewidth=1.2)
        ax.axhline(0.0, color="k", linewidth=0.6)
        ax.set_title(label, fontsize=10)
        ax.set_xticks(range(len(rows)))
        ax.set_xticklabels(names, rotation=30, ha="right", fontsize=8)
        everything = np.concatenate([vals, lo, hi])
        top = np.nanmax(np.abs(everything)) if np.isfinite(everything).any() else 1.0
        ax.set_ylim(min(0.0, np.nanmin(everything) * 1.15) if np.isfinite(everything).any()
                    else 0.0, 1.18 * top if top > 0 else 1.0)
        status_key = "diastole" if key == "diastolic_orifice_area_mm2" else "systole"
        for i, r in enumerate(rows):
            words = []
            if not np.isfinite(vals[i]):
                words.append("n/a")
            else:
                words.append(f"{vals[i]:.0f}" if abs(vals[i]) >= 100 else f"{vals[i]:.3g}")
            if key == "diastolic_orifice_area_mm2" and r.get("diastolic_orifice_count"):
                n = r["diastolic_orifice_count"]
                words.append(f"{n} orifice{'s' if n != 1 else ''}")
            if r.get(status_key) not in (None, "converged"):
                words.append(f"({r.get(status_key)})")
            ax.annotate("\n".join(words), (i, np.nanmax([vals[i], hi[i], 0.0])),
                        ha="center", va="bottom", fontsize=7,
                        color="red" if r.get(status_key) not in (None, "converged") else "k")
    legend = "; ".join(f"{r['case']} = {r['title']}" for r in rows if r["title"] != r["case"])
    paths = any(r.get("path_runs") for r in rows)
    fig.suptitle("repairs compared: systole at the scene's pressure; diastolic orifice under "
                 "an atrial-side pressure" + ("; lines over the bars: the range over the "
                                              "solver's paths (--paths, --weights)" if paths
                                              else "")
                 + (f"\n{legend}" if legend else ""), fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)
    return path


#: the leaflets' colours in the figures of shapes (anterior blue, posterior red)
LEAFLET_COLOURS = np.array([[0.55, 0.7, 0.95, 1.0], [0.95, 0.65, 0.55, 1.0]])


def _projection(view: dict | None):
    """``project(x, kind)``: points ``x`` (n, 3) in the valve's frame ``view`` as 2-D
    coordinates and a depth (n,): ``kind`` "top", seen from the atrium with the anterior
    side up (the anterolateral commissure on the left); "side", the anterior side right and
    the atrium up."""
    frame = view["frame"] if view else np.eye(3)
    centre = view["centre"] if view else np.zeros(3)
    ant, lat, axis = frame[0], frame[1], frame[2]
    right = -lat

    def project(x, kind):
        if kind == "top":
            return (np.stack([(x - centre) @ right, (x - centre) @ ant], axis=1),
                    (x - centre) @ axis)
        return np.stack([(x - centre) @ ant, (x - centre) @ axis], axis=1), (x - centre) @ lat

    return project


def _limits(pts: np.ndarray) -> tuple:
    """(lower, upper) corners of the 2-D points ``pts``, padded by 4 % of the larger span."""
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 0.04 * (hi - lo).max()
    return lo - pad, hi + pad


def _panel(ax, limits: tuple, first: bool) -> None:
    """A figure panel in mm on ``limits`` (equal aspect), y labels only in the ``first``
    column."""
    ax.set_aspect("equal")
    ax.set_xlim(limits[0][0], limits[1][0])
    ax.set_ylim(limits[0][1], limits[1][1])
    ax.tick_params(labelsize=7)
    if not first:
        ax.set_yticklabels([])


def _section(x: np.ndarray, cells: np.ndarray, view: dict | None) -> np.ndarray:
    """The trace of the triangles ``cells`` (into ``x``) in the long-axis plane through the
    valve's centre spanned by its anterior direction and axis (A2-P2, where the metrics read
    the coaptation length and the tenting: :func:`mvfem.metrics._section`): (k, 2, 2)
    segments, each two points as (anterior coordinate, height along the axis), mm."""
    from mvfem.metrics import _section as trace

    frame = view["frame"] if view else np.eye(3)
    centre = view["centre"] if view else np.zeros(3)
    ant, lat, axis = frame[0], frame[1], frame[2]
    seg, _ = trace(x, cells, np.zeros(len(x), dtype=bool), centre, lat)
    seg = seg - centre
    return np.stack([seg @ ant, seg @ axis], axis=-1)


def _shapes(study, out: Path, view: dict | None, path: Path, titles: dict | None = None,
            diastolic: float | None = None) -> Path | None:
    """The closed (and diastolic) valves side by side: one length scale per row (mm), one
    colour range (radial stress, 5-95th percentile over every closed valve)."""
    import textwrap

    from matplotlib.collections import PolyCollection

    from mvfem.figures import read_fields

    plt = _plt()
    phases = [p for p in study.sets if p in ("systole", "diastole")]  # (not other paths')
    cases = [c.name for c in study.cases]
    titles = titles or {}
    data = {}
    for spec in study.runs:
        if spec.set not in phases:
            continue
        f = read_fields(spec.dir(out))
        if f is not None:
            data[(spec.case, spec.set)] = f
    if not data:
        return None
    project = _projection(view)
    stresses = [np.log10(np.clip(f["radial_cauchy_stress_Pa"], 1.0, None))
                for (c, p), f in data.items() if p == "systole"]
    lo, hi = (np.percentile(np.concatenate(stresses), [5, 95]) if stresses else (0.0, 1.0))
    kinds = [("systole", "top"), ("systole", "side")]
    if len(phases) > 1:
        kinds.append(("diastole", "top"))
    row_names = ["systole, seen from the atrium\n(anterior up), mm",
                 "systole, side view\n(anterior right, atrium up), mm"]
    if len(phases) > 1:
        row_names.append("diastole" + (f" ({diastolic:g} Pa)" if diastolic is not None else "")
                         + ",\nseen from the atrium, mm")

    # one length scale per row: the same limits in every panel of it
    limits = []
    for phase, kind in kinds:
        pts = [project(f["X"] + f["u"], kind)[0] for (c, p), f in data.items() if p == phase]
        if pts:
            limits.append(_limits(np.concatenate(pts)))
        else:
            limits.append((np.zeros(2), np.ones(2)))
    spans = [hi_ - lo_ for lo_, hi_ in limits]
    heights = [sp[1] / sp[0] for sp in spans]
    width = 3.4
    fig, axes = plt.subplots(len(kinds), len(cases),
                             figsize=(width * len(cases) + 1.6,
                                      sum(width * h for h in heights) + 1.6),
                             dpi=110, squeeze=False,
                             gridspec_kw={"height_ratios": heights})
    pc_last = None
    for j, case in enumerate(cases):
        for i, (phase, kind) in enumerate(kinds):
            ax = axes[i, j]
            _panel(ax, limits[i], j == 0)
            f = data.get((case, phase))
            if i == 0:
                ax.set_title("\n".join(textwrap.wrap(titles.get(case, case), 28)), fontsize=9)
            if j == 0:
                ax.set_ylabel(row_names[i], fontsize=8)
            if f is None:
                ax.text(0.5, 0.5, "no result", ha="center", transform=ax.transAxes)
                continue
            spec = next(r for r in study.runs if r.case == case and r.set == phase)
            s = _summary(spec.dir(out)) or {}
            if not s.get("converged"):
                ax.text(0.02, 0.02, "not converged: last state", transform=ax.transAxes,
                        fontsize=7, color="red")
            x = f["X"] + f["u"]
            cells = f["cells"]
            leaflet = np.where(f["region"] == 0, 0, 1)
            p2, d = project(x, kind)
            order = np.argsort(d[cells].mean(axis=1))
            if phase == "systole" and kind == "top":
                v = np.log10(np.clip(f["radial_cauchy_stress_Pa"], 1.0, None))
                pc = PolyCollection(p2[cells[order]], array=v[order], cmap="viridis",
                                    edgecolors="face", linewidths=0.1)
                pc.set_clim(lo, hi if hi > lo else lo + 1e-9)
                pc_last = pc
            else:
                pc = PolyCollection(p2[cells[order]], facecolors=LEAFLET_COLOURS[leaflet[order]],
                                    edgecolors="k", linewidths=0.1)
            ax.add_collection(pc)
    if pc_last is not None:
        fig.colorbar(pc_last, ax=axes[0, :].tolist(), shrink=0.9, pad=0.02,
                     label="radial Cauchy stress\n(log10 Pa; 5-95 % of all cases)")
    fig.suptitle("closed valves, same scale in each row (top row: radial stress, one colour "
                 "range for all; other rows: blue anterior, red posterior)", fontsize=10)
    fig.savefig(path)
    plt.close(fig)
    return path


def _path_shapes(study, out: Path, view: dict | None, path: Path,
                 titles: dict | None = None) -> Path | None:
    """``--paths``, ``--weights``: for each case closed along several paths, one row of its
    systolic closures, its own path first, cut by the long-axis plane through A2-P2
    (anterior right, atrium up: the fold, as an echo's long-axis view shows it) over the
    valve seen from the atrium, all on one length scale (mm), each titled with its path,
    coaptation length and tenting height: the folds the paths end in. None when no case has
    runs along other paths."""
    import textwrap

    from matplotlib.collections import LineCollection, PolyCollection

    from mvfem.figures import read_fields

    rows = []   # (case, [(label, fields, summary)])
    for case in study.cases:
        specs = [r for r in study.runs if r.case == case.name
                 and (r.set == "systole" or _variant(r.set))]
        if len(specs) < 2:
            continue
        runs = []
        for spec in specs:
            f, s = read_fields(spec.dir(out)), _summary(spec.dir(out))
            if f is not None and s is not None:
                runs.append((_label(spec.set), f, s))
        if runs:
            rows.append((case.name, runs))
    if not rows:
        return None
    plt = _plt()
    project = _projection(view)
    kinds = ("section", "top")
    sections = {(case, j, side): _section(f["X"] + f["u"],
                                          f["cells"][(f["region"] != 0) == side], view)
                for case, runs in rows for j, (_, f, _) in enumerate(runs) for side in (0, 1)}
    limits = {}
    for kind in kinds:
        if kind == "section":
            pts = np.concatenate([seg.reshape(-1, 2) for seg in sections.values()]
                                 + [np.zeros((1, 2))])
        else:
            pts = np.concatenate([project(f["X"] + f["u"], kind)[0] for _, runs in rows
                                  for _, f, _ in runs])
        limits[kind] = _limits(pts)
    spans = {k: limits[k][1] - limits[k][0] for k in kinds}
    width = 3.2
    ncol = max(len(runs) for _, runs in rows)
    heights = [spans[k][1] / spans[k][0] for _ in rows for k in kinds]
    fig, axes = plt.subplots(len(heights), ncol, squeeze=False, dpi=110,
                             figsize=(width * ncol + 1.2, 0.8 * width * sum(heights) + 0.5
                                      * len(rows) + 1.0),
                             gridspec_kw={"height_ratios": heights}, constrained_layout=True)
    titles = titles or {}
    for i, (case, runs) in enumerate(rows):
        for j in range(ncol):
            for m, kind in enumerate(kinds):
                ax = axes[2 * i + m, j]
                if j >= len(runs):
                    ax.axis("off")
                    continue
                n, f, s = runs[j]
                _panel(ax, limits[kind], j == 0)
                if j == 0:
                    ax.set_ylabel("\n".join(textwrap.wrap(titles.get(case, case), 22))
                                  + ("\nA2-P2 section, mm" if kind == "section"
                                     else "\nfrom the atrium, mm"), fontsize=8)
                if m == 0:
                    v = s.get("valve") or {}
                    words = ["its own settings" if n == "own" else n.replace("solver.", "")]
                    if v.get("coaptation_length_mm") is not None:
                        words.append(f"coaptation {v['coaptation_length_mm']:.2f} mm")
                    if v.get("tenting_height_mm") is not None:
                        words[-1] += f", tenting {v['tenting_height_mm']:.2f} mm"
                    if not s.get("converged"):
                        words.append("not converged: last state")
                    ax.set_title("\n".join(words), fontsize=8,
                                 color="k" if s.get("converged") else "red")
                if kind == "section":
                    for side in (0, 1):
                        ax.add_collection(LineCollection(sections[(case, j, side)],
                                                         colors=LEAFLET_COLOURS[side],
                                                         linewidths=2.0))
                    continue
                leaflet = np.where(f["region"] == 0, 0, 1)
                x = f["X"] + f["u"]
                cells = f["cells"]
                p2, d = project(x, kind)
                order = np.argsort(d[cells].mean(axis=1))
                ax.add_collection(PolyCollection(p2[cells[order]],
                                                 facecolors=LEAFLET_COLOURS[leaflet[order]],
                                                 edgecolors="k", linewidths=0.1))
    fig.suptitle("each case closed along the solver's paths (--paths: solver.ramp_steps, "
                 "--weights: solver.stabilisation), "
                 "one length scale; blue anterior, red posterior\nthe long-axis section "
                 "through A2-P2 (anterior right, atrium up) over the valve seen from the atrium",
                 fontsize=10)
    fig.savefig(path)
    plt.close(fig)
    return path
