"""Paper-style figures of a study, from the per-run files (matplotlib, off-screen).

- box plots of the per-facet radial Cauchy stress (log axis) and radial Almansi strain, per
  leaflet, one box per parameter set with the facets of every case pooled (the source paper's
  Figs 5-6): ``box_stress.png``, ``box_strain.png``;
- maps of one case, one panel per set on a common colour range (Figs 3-4):
  ``maps_strain.png``, ``maps_stress.png`` (and ``maps_distance.png`` when the case has a
  reference surface).

The per-facet values come from each run's ``fields.h5`` (cell data ``radial_almansi_strain``,
``radial_cauchy_stress_Pa``, ``region``; ``region`` indexes the scene's ``[[region]]`` list).
Boxes span the 25th-75th percentiles with the median; whiskers the 5th and 95th percentiles
(the percentiles of summary.json); no outliers drawn.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

__all__ = ["read_fields", "leaflet_values", "view_basis", "box_plots", "map_grid",
           "LEAFLETS"]

LEAFLETS = ("anterior", "posterior")
_cache: dict = {}


def read_fields(run_dir: str | Path) -> dict | None:
    """Reference nodes, displacement, triangles and per-cell fields of a run (None without
    fields.h5). Cached while the file is unchanged."""
    import h5py

    path = Path(run_dir) / "fields.h5"
    try:
        st = path.stat()
    except OSError:
        return None
    key = (str(path), st.st_mtime_ns, st.st_size)
    if key in _cache:
        return _cache[key]
    try:
        with h5py.File(path, "r") as f:
            fn = f["Function"]
            data = {"X": f["Mesh/mesh/geometry"][:], "cells": f["Mesh/mesh/topology"][:],
                    "u": fn["displacement/0"][:]}
            for name in ("radial_almansi_strain", "radial_cauchy_stress_Pa", "region"):
                data[name] = fn[f"{name}/0"][:].ravel()
    except (OSError, KeyError):
        return None
    data["region"] = np.rint(data["region"]).astype(int)
    if len(_cache) > 64:
        _cache.clear()
    _cache[key] = data
    return data


def leaflet_values(run_dir, regions: list) -> dict | None:
    """``{leaflet: (strain, stress)}`` per-facet arrays of a run (regions: the run's
    ``RunSpec.regions``), or None when the run has no fields."""
    f = read_fields(run_dir)
    if f is None:
        return None
    leaflet_of = np.array([r["leaflet"] for r in regions] + [""], dtype=object)
    reg = np.where((f["region"] >= 0) & (f["region"] < len(regions)), f["region"], len(regions))
    lf = leaflet_of[reg]
    return {leaf: (f["radial_almansi_strain"][lf == leaf], f["radial_cauchy_stress_Pa"][lf == leaf])
            for leaf in LEAFLETS}


def view_basis(X, u, cells, cell_leaflet=None):
    """(axis, up, centre) of a map, from the run's data alone.

    The axis is the normal of the plane through the clamped nodes (displacement below 1e-9 of
    the largest; all nodes when fewer than three are), pointing where the surface moved on
    average (for a valve the atrium: pressure pushes from ventricle to atrium); the view looks along -axis. Up is
    toward the anterior leaflet's centroid when there is one, else the first in-plane
    principal direction.
    """
    X, u = np.asarray(X, float), np.asarray(u, float)
    norm = np.linalg.norm(u, axis=1)
    fixed = norm <= 1e-9 * max(float(norm.max(initial=0.0)), 1e-300)
    P = X[fixed] if fixed.sum() >= 3 else X
    centre = P.mean(axis=0)
    _, _, vt = np.linalg.svd(P - centre, full_matrices=False)
    axis = vt[2] if len(vt) == 3 else np.array([0.0, 0.0, 1.0])
    if u.mean(axis=0) @ axis < 0:
        axis = -axis
    up = None
    if cell_leaflet is not None and np.any(cell_leaflet == "anterior"):
        a = X[np.unique(cells[cell_leaflet == "anterior"])].mean(axis=0) - centre
        a -= (a @ axis) * axis
        if np.linalg.norm(a) > 1e-9 * (1 + np.abs(X).max()):
            up = a / np.linalg.norm(a)
    if up is None:
        up = vt[0] - (vt[0] @ axis) * axis
        up /= np.linalg.norm(up)
    return axis, up, centre


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _stats(values: np.ndarray, label: str) -> dict:
    p5, q1, med, q3, p95 = np.percentile(values, [5, 25, 50, 75, 95])
    return {"label": label, "whislo": p5, "q1": q1, "med": med, "q3": q3, "whishi": p95,
            "fliers": []}


def box_plots(pooled: dict, sets: list, posterior_sets: dict, runs: dict, out: Path,
              note: str = "") -> list[Path]:
    """``box_stress.png`` and ``box_strain.png``.

    Args:
        pooled: ``{(leaflet, set): (strain array, stress array)}`` over all cases.
        sets: the study's sets (box order).
        posterior_sets: study set -> the posterior set it used (for the tick labels).
        runs: ``{(leaflet, set): number of runs pooled}``.
    """
    plt = _plt()
    paths = []
    for key, index, ylabel, log in (
            ("stress", 1, "radial Cauchy stress (Pa, log scale)", True),
            ("strain", 0, "radial Almansi strain", False)):
        fig, axes = plt.subplots(1, 2, figsize=(13, 5.2), dpi=110, sharey=log)
        for ax, leaf in zip(axes, LEAFLETS):
            stats, dropped = [], 0
            positions = []
            fallback = sorted({posterior_sets[s] for s in sets
                               if posterior_sets.get(s) not in (None, "", s)})
            for i, s in enumerate(sets):
                tick = s if leaf == "anterior" or posterior_sets.get(s) in (None, "", s) \
                    else f"{s}*"
                v = pooled.get((leaf, s), (np.zeros(0), np.zeros(0)))[index]
                v = v[np.isfinite(v)]
                if log:
                    dropped += int((v <= 0).sum())
                    v = v[v > 0]
                if len(v):
                    stats.append(_stats(v, f"{tick}\nn={runs.get((leaf, s), 0)}"))
                    positions.append(i + 1)
            if stats:
                ax.bxp(stats, positions=positions, showfliers=False, widths=0.6,
                       medianprops={"color": "C3"})
            ax.set_xticks(range(1, len(sets) + 1))
            ax.set_xticklabels([next((st["label"] for st, p in zip(stats, positions)
                                      if p == i + 1), f"{s}\n(no runs)")
                                for i, s in enumerate(sets)], fontsize=7, rotation=0)
            ax.set_xlim(0.3, len(sets) + 0.7)
            if log:
                ax.set_yscale("log")
            ax.set_ylabel(ylabel)
            if leaf == "posterior" and fallback:
                ax.set_xlabel(f"* the posterior leaflet used the posterior {', '.join(fallback)}: "
                              "the per-specimen posterior sets are not in our sources",
                              fontsize=8)
            ax.grid(True, axis="y", which="major", alpha=0.4)
            title = f"{leaf} leaflet"
            if log and dropped:
                title += f" ({dropped} facets with stress <= 0 not shown)"
            ax.set_title(title, fontsize=10)
        fig.suptitle(f"Per-facet radial {'Cauchy stress' if log else 'Almansi strain'} of the "
                     "closed valve, all cases pooled per parameter set; box 25-75 %, median, "
                     "whiskers 5-95 %" + (f"\n{note}" if note else ""), fontsize=10)
        fig.tight_layout()
        path = Path(out) / f"box_{key}.png"
        _save(fig, path)
        plt.close(fig)
        paths.append(path)
    return paths


def _save(fig, path: Path) -> None:
    """Save atomically (a browser or the next study never reads half a PNG)."""
    import os

    tmp = path.with_name(path.stem + ".part.png")
    fig.savefig(tmp)
    os.replace(tmp, path)


def map_grid(panels: list, quantity: str, out: Path, title: str) -> Path | None:
    """One figure with a map per panel on a common colour range (5th-95th percentile of all).

    Args:
        panels: dicts with ``label``, ``x`` (deformed nodes), ``cells``, ``values`` (per
            cell), ``axis``, ``up``, ``centre``.
        quantity: "strain", "stress" (log10 Pa) or "distance" (mm).
    """
    from matplotlib.collections import PolyCollection

    if not panels:
        return None
    plt = _plt()
    label = {"strain": "radial Almansi strain", "stress": "radial Cauchy stress, log10 Pa",
             "distance": "distance to the reference, mm"}[quantity]
    vals = []
    for p in panels:
        v = np.asarray(p["values"], float)
        if quantity == "stress":
            v = np.log10(np.clip(v, 1.0, None))
        vals.append(v)
    every = np.concatenate([v[np.isfinite(v)] for v in vals]) if vals else np.zeros(1)
    lo, hi = np.percentile(every, [5, 95]) if len(every) else (0.0, 1.0)
    if quantity == "distance":
        lo = 0.0
    if hi <= lo:
        hi = lo + 1e-12
    n = len(panels)
    ncol = min(4, n)
    nrow = math.ceil(n / ncol)
    fig, axes = plt.subplots(nrow, ncol, figsize=(3.4 * ncol + 1.2, 3.2 * nrow + 0.8), dpi=100,
                             squeeze=False)
    cmap = "magma_r" if quantity == "distance" else "viridis"
    pc = None
    for ax, p, v in zip(axes.flat, panels, vals):
        axis, up, c = (np.asarray(p[k], float) for k in ("axis", "up", "centre"))
        right = np.cross(up, axis)
        x = np.asarray(p["x"], float)
        cells = np.asarray(p["cells"])
        p2 = np.stack([(x - c) @ right, (x - c) @ up], axis=1)
        order = np.argsort(((x - c) @ axis)[cells].mean(axis=1))  # atrial-most drawn last
        pc = PolyCollection(p2[cells[order]], array=v[order], cmap=cmap, edgecolors="face",
                            linewidths=0.1)
        pc.set_clim(lo, hi)
        ax.add_collection(pc)
        ax.autoscale_view()
        ax.set_aspect("equal")
        ax.set_title(p["label"], fontsize=9)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.suptitle(f"{title}: {label}\ncommon colour range [{lo:.3g}, {hi:.3g}] (5th-95th "
                 "percentile of all panels)\nmm, seen along the axis from the side the surface "
                 "moved to (a valve: from the atrium, anterior up)", fontsize=9)
    fig.tight_layout(rect=(0, 0, 0.88, 1))
    cax = fig.add_axes((0.89, 0.15, 0.015, 0.7))
    fig.colorbar(pc, cax=cax, label=label)
    path = Path(out) / f"maps_{quantity}.png"
    _save(fig, path)
    plt.close(fig)
    return path
