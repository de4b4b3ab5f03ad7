"""PNG maps of per-facet radial strain and stress on the closed valve (cf. the source paper's
Figs 3-4): the closed leaflets seen from the atrium, colour range the 5th-95th percentile of
each quantity, stress on a log10 Pa scale. Rendered off-screen with matplotlib (Agg)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["valve_maps"]


def _view_basis(surface):
    frame = np.asarray(getattr(surface, "frame", np.eye(3)), dtype=float)
    axis = np.asarray(getattr(surface, "axis", frame[2]), dtype=float)
    # seen from the atrium: anterior up, anterolateral commissure on the left (surgeon's view)
    up = frame[0] - (frame[0] @ axis) * axis
    up /= np.linalg.norm(up)
    right = np.cross(up, axis)
    return right, up, axis


def _leaflet_places(p2, cells, cell_tag, surface):
    """(name, 2-D point) for each leaflet of the view: its facets' area-weighted centroid,
    where its name is written on the maps."""
    names = getattr(surface, "names", {}) or {}
    if cell_tag is None or not len(cells):
        return []
    tri = p2[cells]
    area = 0.5 * np.abs(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]))
    out = []
    for name in ("anterior", "posterior"):
        sel = np.asarray(cell_tag) == names.get(name, -1)
        if sel.any() and area[sel].sum() > 0:
            out.append((name, (tri[sel].mean(axis=1) * area[sel, None]).sum(0)
                        / area[sel].sum()))
    return out


def valve_maps(x, cells, cell_tag, values: dict, surface, out) -> list[Path]:
    """Write ``map_radial_strain.png`` and ``map_radial_stress.png``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    right, up, axis = _view_basis(surface)
    c = np.asarray(getattr(surface, "centre", x.mean(axis=0)), dtype=float)
    p2 = np.stack([(x - c) @ right, (x - c) @ up], axis=1)
    depth = ((x - c) @ axis)[cells].mean(axis=1)
    order = np.argsort(depth)  # painter's algorithm: the atrial-most facets drawn last
    stress = np.asarray(values["radial_cauchy_stress_Pa"])
    items = [("radial_strain", "radial Almansi strain", np.asarray(values["radial_almansi_strain"])),
             ("radial_stress", "radial Cauchy stress, log10 Pa",
              np.log10(np.clip(stress, 1.0, None)))]
    paths = []
    ring = getattr(surface, "annulus_curve", None)
    for key, label, v in items:
        lo, hi = np.percentile(v, [5, 95])
        fig, ax = plt.subplots(figsize=(6, 5.2), dpi=120)
        pc = PolyCollection(p2[cells[order]], array=v[order], cmap="viridis",
                            edgecolors="face", linewidths=0.1)
        pc.set_clim(lo, hi if hi > lo else lo + 1e-12)
        ax.add_collection(pc)
        if ring is not None and len(ring):
            r2 = np.stack([(ring - c) @ right, (ring - c) @ up], axis=1)
            ax.plot(*np.vstack([r2, r2[:1]]).T, "k-", lw=0.8)
        for name, at in _leaflet_places(p2, cells, cell_tag, surface):
            ax.text(*at, name, ha="center", va="center", fontsize=8,
                    bbox={"boxstyle": "round", "fc": "white", "ec": "none", "alpha": 0.7})
        ax.autoscale_view()
        ax.set_aspect("equal")
        ax.set_xlabel("mm (anterolateral commissure left)")
        ax.set_ylabel("mm (anterior up)")
        clipped = int(np.sum(stress < 1.0)) if key == "radial_stress" else 0
        note = (f"\n{clipped} facets under 1 Pa (radial compression) drawn at 1 Pa"
                if clipped else "")
        ax.set_title(f"closed valve seen from the atrium: {label}\n"
                     f"colour: 5th-95th percentile of both leaflets [{lo:.3g}, {hi:.3g}]"
                     f"{note}", fontsize=8)
        fig.colorbar(pc, ax=ax, shrink=0.8, label=label)
        fig.tight_layout()
        path = Path(out) / f"map_{key}.png"
        fig.savefig(path)
        plt.close(fig)
        paths.append(path)
    return paths
