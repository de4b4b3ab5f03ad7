"""The report of a study: the paper-style figures and one HTML page, ``report.html``.

The page is self-contained: its figures are embedded as base64 PNG, so it opens from the
disk in any browser with no server (and can be mailed alone); links to the per-run
directories and to results.csv are relative.
"""

from __future__ import annotations

import base64
import html
import math
import os
import time
from pathlib import Path

import numpy as np

from mvfem.figures import LEAFLETS, box_plots, leaflet_values, map_grid, read_fields, view_basis

__all__ = ["build_report", "study_figures", "write_html"]


def _included(row: dict, include_stopped: bool) -> bool:
    return row["status"] == "converged" or (include_stopped and row["status"] == "stopped")


def study_figures(study, out: Path, rows: list[dict]) -> dict:
    """Write the box plots and the maps of the map case into ``out``; returns
    ``{"box": [...], "maps": [...], "pooled": {(leaflet, set): (strain, stress)}, ...}``."""
    out = Path(out)
    by_key = {(r["case"], r["set"]): r for r in rows}
    pooled: dict = {}
    counts: dict = {}
    posterior_sets = {}
    for spec in study.runs:
        row = by_key[(spec.case, spec.set)]
        if spec.posterior_set:
            posterior_sets.setdefault(spec.set, spec.posterior_set)
        if not _included(row, study.include_stopped):
            continue
        values = leaflet_values(spec.dir(out), spec.regions)
        if values is None:
            continue
        for leaf in LEAFLETS:
            strain, stress = values[leaf]
            if len(strain) == 0:
                continue
            k = (leaf, spec.set)
            old = pooled.get(k, (np.zeros(0), np.zeros(0)))
            pooled[k] = (np.concatenate([old[0], strain]), np.concatenate([old[1], stress]))
            counts[k] = counts.get(k, 0) + 1
    note = ("converged and stopped-short runs" if study.include_stopped
            else "converged runs only") + "; n = runs pooled"
    box = box_plots(pooled, study.sets, posterior_sets, counts, out, note=note)
    maps = []
    panels = {"strain": [], "stress": [], "distance": []}
    for spec in (s for s in study.runs if s.case == study.map_case):
        row = by_key[(spec.case, spec.set)]
        if row["status"] not in ("converged", "stopped"):
            continue
        f = read_fields(spec.dir(out))
        if f is None:
            continue
        leaflet_of = np.array([r["leaflet"] for r in spec.regions] + [""], dtype=object)
        cl = leaflet_of[np.clip(f["region"], 0, len(spec.regions))]
        axis, up, centre = view_basis(f["X"], f["u"], f["cells"], cl)
        label = spec.set + ("" if row["status"] == "converged" else " (stopped short)")
        base = {"label": label, "x": f["X"] + f["u"], "cells": f["cells"], "axis": axis,
                "up": up, "centre": centre}
        panels["strain"].append({**base, "values": f["radial_almansi_strain"]})
        panels["stress"].append({**base, "values": f["radial_cauchy_stress_Pa"]})
        dist = spec.dir(out) / "distance.vtu"
        if dist.is_file():
            from mvfem.meshes.io import read_surface

            try:
                raw = read_surface(dist)
                panels["distance"].append({**base, "x": raw.points, "cells": raw.triangles,
                                           "values": raw.cell_data["distance_mm"].ravel()})
            except (ValueError, KeyError):
                pass
    for q in ("strain", "stress", "distance"):
        p = map_grid(panels[q], q, out, f"case {study.map_case}: the closed state per "
                     "parameter set")
        if p is not None:
            maps.append(p)
    return {"box": box, "maps": maps, "pooled": pooled, "counts": counts,
            "posterior_sets": posterior_sets}


def _img(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return (f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'
            f"<figcaption>{html.escape(alt)}</figcaption></figure>")


def _num(v, fmt: str = ".3g") -> str:
    if v is None or v == "":
        return ""
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, (int, float)):
        if isinstance(v, float) and not math.isfinite(v):
            return ""
        return format(v, fmt)
    return html.escape(str(v))


def _table(head: list[str], body: list[list[str]], cls: str = "",
           row_classes: list[str] | None = None) -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    row_classes = row_classes or [""] * len(body)
    rows = "\n".join((f'<tr class="{rc}">' if rc else "<tr>")
                     + "".join(f"<td>{c}</td>" for c in r) + "</tr>"
                     for r, rc in zip(body, row_classes))
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>\n{rows}\n</tbody></table>'


_CSS = """
body { font-family: sans-serif; margin: 1.5em; color: #222; max-width: 1500px; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 12px; margin: 0.6em 0; }
th, td { border: 1px solid #bbb; padding: 2px 6px; text-align: right; }
th { background: #eee; } td:nth-child(-n+3) { text-align: left; }
tr.failed td { background: #fde2e2; } tr.stopped td { background: #fff4d6; }
tr.pending td { color: #888; }
figure { display: inline-block; margin: 0.5em; vertical-align: top; }
figure img { max-width: 100%; border: 1px solid #ddd; }
figcaption { font-size: 12px; color: #555; max-width: 900px; }
p.note { font-size: 13px; color: #444; max-width: 1100px; }
"""


def write_html(study, out: Path, rows: list[dict], figs: dict, biaxial: list[Path]) -> Path:
    """Write ``report.html`` (atomically) and return its path."""
    out = Path(out)
    counts = {k: sum(r["status"] == k for r in rows) for k in
              ("converged", "stopped", "failed", "pending")}
    parts = [(f"<!DOCTYPE html><html lang=\"en\"><head><meta charset=\"utf-8\">"
              f"<title>{html.escape(study.title or 'mvfem study')}</title>"
              f"<style>{_CSS}</style></head><body>"),
             f"<h1>{html.escape(study.title or 'mvfem study')}</h1>",
             (f"<p>Study file <code>{html.escape(study.source)}</code>; {len(study.cases)} cases "
              f"x {len(study.sets)} parameter sets = {len(rows)} runs: "
              f"<b>{counts['converged']} converged</b>, {counts['stopped']} stopped short, "
              f"{counts['failed']} failed, {counts['pending']} not run. Written "
              f"{time.strftime('%Y-%m-%d %H:%M')} by mvfem; one row per run in "
              f"<a href=\"results.csv\">results.csv</a>.</p>")]
    parts.append("<h2>Cases</h2>")
    from mvfem.study import demo_scene_path

    body = []
    for c in study.cases:
        scene = ("demo (the built-in valve)" if Path(c.scene) == demo_scene_path().resolve()
                 else os.path.relpath(c.scene, out))
        body.append([html.escape(c.name), html.escape(scene),
                     html.escape(", ".join(f"{k} = {v}" for k, v in c.changes.items())),
                     html.escape(os.path.relpath(c.reference, out)) if c.reference else ""])
    parts.append(_table(["case", "scene", "changes", "reference surface"], body))
    parts.append('<p class="note">A study set is a name: the anterior leaflet gets the anterior '
                 "set of that name; the posterior leaflet the posterior set of that name where "
                 "one exists (MNY-mean, Holzapfel, SVK), otherwise the posterior MNY-mean: the "
                 "per-specimen posterior sets of the source paper are not in our sources "
                 "(<code>mvfem materials</code>). The posterior literature sets are not yet "
                 "checked against their original papers.</p>")

    parts.append("<h2>Radial stress and strain per leaflet (cf. the paper's Figs 5-6)</h2>")
    parts += [_img(p, {"box_stress": "Per-facet radial Cauchy stress per leaflet and set, all "
                       "cases pooled (log axis).",
                       "box_strain": "Per-facet radial Almansi strain per leaflet and set, all "
                       "cases pooled."}[p.stem]) for p in figs["box"]]
    parts.append(_set_table(study, rows, figs))

    parts.append(f"<h2>Maps of case {html.escape(study.map_case)} (cf. Figs 3-4)</h2>")
    if figs["maps"]:
        parts += [_img(p, {"maps_strain": "Radial Almansi strain of the closed state, one panel "
                           "per set, common colour range.",
                           "maps_stress": "Radial Cauchy stress (log10 Pa), one panel per set, "
                           "common colour range.",
                           "maps_distance": "Distance of the predicted closed leaflets to the "
                           "reference surface (mm)."}[p.stem]) for p in figs["maps"]]
    else:
        parts.append("<p>No finished run of this case.</p>")

    if any(r["reference_mean_abs_error_mm"] is not None for r in rows):
        parts.append("<h2>Closed-state error against the reference surfaces</h2>")
        body = [[html.escape(r["case"]), html.escape(r["set"]), html.escape(r["status"]),
                 _num(r["reference_mean_abs_error_mm"]), _num(r["reference_p95_error_mm"]),
                 _num(r["reference_hausdorff_mm"])]
                for r in rows if r["reference_mean_abs_error_mm"] is not None]
        parts.append(_table(["case", "set", "status", "mean abs error (mm)", "p95 (mm)",
                             "Hausdorff (mm)"], body))
        parts.append('<p class="note">Point-to-triangle distances from the predicted closed '
                     "leaflets to the reference (leaflet with leaflet when the reference has "
                     "cell data <code>leaflet</code>), sampled at nodes and facet centroids and "
                     "area-weighted; Hausdorff is symmetric (also reference to prediction).</p>")

    if biaxial:
        parts.append("<h2>Canonical biaxial curves of the parameter sets (cf. Figs 1-2)</h2>")
        parts += [_img(p, f"Biaxial curves, {p.stem.split('_')[-1]} leaflet sets "
                       "(mvfem biaxial).") for p in biaxial]

    parts.append("<h2>Runs</h2>")
    parts.append(_run_table(rows))
    parts.append("</body></html>\n")
    path = out / "report.html"
    tmp = path.with_name(path.name + ".part")
    tmp.write_text("\n".join(parts), encoding="utf-8")
    os.replace(tmp, path)
    return path


def _set_table(study, rows, figs) -> str:
    head = ["set", "anterior set", "posterior set", "runs", "converged", "stopped", "failed",
            "mean coaptation length (mm)"]
    for leaf in LEAFLETS:
        head += [f"{leaf} strain median", f"{leaf} strain p95", f"{leaf} stress median (kPa)",
                 f"{leaf} stress p95 (kPa)"]
    body = []
    for s in study.sets:
        mine = [r for r in rows if r["set"] == s]
        ok = [r for r in mine if _included(r, study.include_stopped)]
        coap = [r["coaptation_length_mm"] for r in ok if r["coaptation_length_mm"] is not None]
        line = [html.escape(s), html.escape(mine[0]["anterior_set"] or ""),
                html.escape(figs["posterior_sets"].get(s, "")), str(len(mine)),
                str(sum(r["status"] == "converged" for r in mine)),
                str(sum(r["status"] == "stopped" for r in mine)),
                str(sum(r["status"] == "failed" for r in mine)),
                _num(float(np.mean(coap))) if coap else ""]
        for leaf in LEAFLETS:
            v = figs["pooled"].get((leaf, s))
            if v is None or not len(v[0]):
                line += ["", "", "", ""]
            else:
                line += [_num(float(np.median(v[0]))), _num(float(np.percentile(v[0], 95))),
                         _num(float(np.median(v[1])) / 1e3),
                         _num(float(np.percentile(v[1], 95)) / 1e3)]
        body.append(line)
    return ("<p>Per parameter set, the facets of all included runs pooled:</p>"
            + _table(head, body))


def _run_table(rows) -> str:
    head = ["case", "set", "status", "wall time (s)", "Newton its", "coaptation length (mm)",
            "coaptation area (mm2)", "orifice (mm2)", "tenting (mm)"]
    for leaf in LEAFLETS:
        head += [f"{leaf} strain median", f"{leaf} strain p95", f"{leaf} stress median (kPa)",
                 f"{leaf} stress p95 (kPa)"]
    head += ["ref. mean (mm)", "reason", "files"]
    body = []
    for r in rows:
        line = [html.escape(r["case"]), html.escape(r["set"]), html.escape(r["status"]),
                _num(r["wall_time_s"] if r["wall_time_s"] is not None else r["elapsed_s"], ".1f"),
                _num(r["newton_iterations"], "d") if r["newton_iterations"] is not None else "",
                _num(r["coaptation_length_mm"]), _num(r["coaptation_area_mm2"]),
                _num(r["regurgitant_orifice_area_mm2"]), _num(r["tenting_height_mm"])]
        for leaf in LEAFLETS:
            sm, sp = r[f"{leaf}_radial_strain_median"], r[f"{leaf}_radial_strain_p95"]
            tm, tp = r[f"{leaf}_radial_stress_Pa_median"], r[f"{leaf}_radial_stress_Pa_p95"]
            line += [_num(sm), _num(sp), _num(tm / 1e3) if tm is not None else "",
                     _num(tp / 1e3) if tp is not None else ""]
        line += [_num(r["reference_mean_abs_error_mm"]), html.escape(r["reason"] or ""),
                 f'<a href="{html.escape(r["run_dir"])}/">{html.escape(r["run_dir"])}</a>']
        body.append(line)
    return _table(head, body, cls="runs", row_classes=[r["status"] for r in rows])


def build_report(study, out: Path, rows: list[dict]) -> tuple[list[Path], Path]:
    """Figures and report.html of a study directory; returns (figure paths, report path)."""
    out = Path(out)
    figs = study_figures(study, out, rows)
    biaxial = [out / "biaxial" / f"biaxial_{leaf}.png" for leaf in LEAFLETS]
    biaxial = [p for p in biaxial if p.is_file()] if study.biaxial else []
    report = write_html(study, out, rows, figs, biaxial)
    return figs["box"] + figs["maps"], report
