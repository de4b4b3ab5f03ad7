"""Distance between a predicted closed valve and a reference closed surface (numpy, scipy).

The closed-state error of the source paper: how far the predicted closed leaflets lie from the
segmented closed valve. Both surfaces are triangle meshes in mm. Distances are exact
point-to-triangle distances (:func:`mvfem.contact.closest_point_on_triangles`), found among
candidate triangles from a KD-tree on the triangle centroids with a radius bound, so that no
closer triangle is missed.

Sampling (a quadrature of the distance over the predicted surface): each predicted triangle
contributes its centroid with half its area and each of its three nodes with a sixth. The value
of a facet is ``(d_a + d_b + d_c) / 6 + d_centroid / 2``, so the mean absolute error is the
area-weighted mean of the facet values. The 95th percentile is taken over the same weighted
samples; the Hausdorff distance is the larger of the two directed maxima, predicted samples to
the reference and reference samples (nodes and centroids) to the prediction.

When the reference has integer cell data ``leaflet`` (names from ``labels``, default
``{1: "anterior", 2: "posterior"}``) and the prediction names its leaflets, each predicted
leaflet is compared with the reference leaflet of the same name (and the other way round);
a leaflet without a namesake is compared with the whole other surface.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["point_triangle_distance", "points_within", "surface_samples", "weighted_percentile",
           "surface_distance", "SurfaceDistance", "read_reference", "ReferenceSurface",
           "reference_outputs", "level_change", "last_move", "level_change_map",
           "DEFAULT_LABELS"]

log = logging.getLogger(__name__)

#: names of the reference's ``leaflet`` values when neither the scene's ``reference.labels``
#: nor ``mesh.labels`` says otherwise (the import format of CONTRACT.md)
DEFAULT_LABELS = {1: "anterior", 2: "posterior"}


def _closest(p, a, b, c):
    """Distances of points ``p`` to triangles ``(a, b, c)``, row-wise (all (m, 3)), by the
    contact's pairs (:func:`mvfem.contact._fast_triangle_distance`: the compiled kernel where
    it loads, 20x faster on the closed levels of the demo refined twice, else numpy)."""
    from mvfem.contact import _fast_triangle_distance

    m = len(p)
    x = np.concatenate([p, a, b, c])
    cells = np.arange(m, 4 * m, dtype=np.int64).reshape(3, m).T
    idx = np.arange(m, dtype=np.int64)
    return _fast_triangle_distance(x, cells, idx, idx)


def point_triangle_distance(points: np.ndarray, x: np.ndarray, tri: np.ndarray,
                            k: int = 8, budget: int = 2_000_000) -> np.ndarray:
    """Distance of each point to the surface of triangles ``tri`` on nodes ``x`` (exact).

    The ``k`` triangles with the nearest centroids are tried first. A triangle further away is
    at least (its centroid distance - the largest circumradius about a centroid) from the
    point, so a point is finished once that bound for the k-th centroid exceeds its best
    distance; the others are tried again with four times as many candidates (all of them at
    the end).

    Args:
        points: (m, 3) query points.
        x: (n, 3) nodes of the surface; tri: (t, 3) node indices.
        budget: largest number of point-triangle pairs evaluated at once (memory).
    Returns:
        (m,) distances, mm.
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    x = np.asarray(x, dtype=float)
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    if len(tri) == 0:
        raise ValueError("the surface has no triangles")
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    cen = (a + b + c) / 3
    r_max = float(np.max([np.linalg.norm(v - cen, axis=1).max() for v in (a, b, c)]))
    tree = cKDTree(cen)
    d = np.full(len(points), np.inf)
    todo = np.arange(len(points))
    k = min(max(k, 1), len(tri))
    while len(todo):
        step = max(1, budget // k)
        unsure = []
        for s in range(0, len(todo), step):
            i = todo[s:s + step]
            dist_c, idx = tree.query(points[i], k=k)
            dist_c, idx = dist_c.reshape(len(i), k), idx.reshape(len(i), k)
            dd = _closest(np.repeat(points[i], k, axis=0), a[idx.ravel()], b[idx.ravel()],
                          c[idx.ravel()]).reshape(len(i), k).min(axis=1)
            d[i] = np.minimum(d[i], dd)
            if k < len(tri):
                unsure.append(i[d[i] > dist_c[:, -1] - r_max])
        todo = np.concatenate(unsure) if unsure else np.zeros(0, dtype=np.int64)
        k = min(4 * k, len(tri))
    return d


def points_within(points: np.ndarray, x: np.ndarray, tri: np.ndarray, within: float,
                  budget: int = 2_000_000) -> np.ndarray:
    """Boolean (m,): whether each point lies within ``within`` (mm) of the surface of triangles
    ``tri`` on nodes ``x``, i.e. ``point_triangle_distance(points, x, tri) <= within``.

    Every point of a triangle is within the triangle's largest vertex distance from its
    centroid, so a triangle whose centroid is farther than ``within`` plus the largest such
    radius cannot be that close: only the pairs inside that reach are measured (exactly).
    :func:`point_triangle_distance` certifies each point's nearest triangle instead, which
    for the points far from the surface means trying every triangle: the coaptation trace's
    samples, most of them far from the other leaflet, took 0.13 s a call on the demo and
    0.36 s refined twice (README, "Valve outputs and metrics").
    """
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=float).reshape(-1, 3)
    near = np.zeros(len(points), dtype=bool)
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    if len(points) == 0 or len(tri) == 0:
        return near
    x = np.asarray(x, dtype=float)
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    cen = (a + b + c) / 3
    r_max = float(np.max([np.linalg.norm(v - cen, axis=1).max() for v in (a, b, c)]))
    reach = float(within) + r_max
    tree = cKDTree(cen)
    # chunks of points whose candidate pairs stay within the budget (a first guess from the
    # density of centroids; a chunk's pairs are measured at once)
    step = max(1, budget // max(1, min(len(tri), 64)))
    for s in range(0, len(points), step):
        q = points[s:s + step]
        pairs = cKDTree(q).sparse_distance_matrix(tree, reach * (1 + 1e-12) + 1e-12,
                                                  output_type="ndarray")
        i, j = pairs["i"].astype(np.int64), pairs["j"].astype(np.int64)
        if len(i) == 0:
            continue
        d = _closest(q[i], a[j], b[j], c[j])
        near[s + np.unique(i[d <= within])] = True
    return near


def surface_samples(x: np.ndarray, tri: np.ndarray):
    """Sample points of a triangle surface: its nodes, then its centroids, with the weights
    of the quadrature above (node: a sixth of each adjacent triangle's area; centroid: half).

    Returns:
        (points (n + t, 3), weights (n + t,), areas (t,)).
    """
    x = np.asarray(x, dtype=float)
    tri = np.asarray(tri, dtype=np.int64).reshape(-1, 3)
    a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    w_node = np.zeros(len(x))
    np.add.at(w_node, tri.ravel(), np.repeat(area / 6, 3))
    return np.vstack([x, (a + b + c) / 3]), np.concatenate([w_node, area / 2]), area


def weighted_percentile(values: np.ndarray, weights: np.ndarray, q: float) -> float:
    """The smallest value whose cumulative weight reaches ``q`` % of the total."""
    values, weights = np.asarray(values, dtype=float), np.asarray(weights, dtype=float)
    keep = weights > 0
    values, weights = values[keep], weights[keep]
    if len(values) == 0:
        return float("nan")
    order = np.argsort(values)
    cum = np.cumsum(weights[order])
    i = int(np.searchsorted(cum, q / 100.0 * cum[-1] * (1 - 1e-12)))
    return float(values[order][min(i, len(values) - 1)])


@dataclass
class SurfaceDistance:
    """What :func:`surface_distance` returns (mm).

    Attributes:
        mean_abs_error_mm: area-weighted mean distance, predicted -> reference.
        p95_error_mm: weighted 95th percentile of the predicted samples' distances.
        hausdorff_mm: symmetric: max of both directed maxima (over the samples).
        max_to_reference_mm / max_to_prediction_mm: the two directed maxima.
        mean_to_prediction_mm: area-weighted mean distance, reference -> predicted.
        facet_mm: (t,) distance value of each predicted triangle (see the module docstring).
        node_mm: (n,) distance of each predicted node.
        compared: "by leaflet" or "whole surface".
    """

    mean_abs_error_mm: float
    p95_error_mm: float
    hausdorff_mm: float
    max_to_reference_mm: float
    max_to_prediction_mm: float
    mean_to_prediction_mm: float
    facet_mm: np.ndarray = field(repr=False)
    node_mm: np.ndarray = field(repr=False)
    compared: str = "whole surface"

    def block(self) -> dict:
        """The ``reference`` block of summary.json (CONTRACT.md keys first)."""
        return {"mean_abs_error_mm": self.mean_abs_error_mm, "p95_error_mm": self.p95_error_mm,
                "hausdorff_mm": self.hausdorff_mm,
                "max_to_reference_mm": self.max_to_reference_mm,
                "max_to_prediction_mm": self.max_to_prediction_mm,
                "mean_to_prediction_mm": self.mean_to_prediction_mm,
                "compared": self.compared}


def _directed(x_from, tri_from, group_from, x_to, tri_to, group_to):
    """Distances of the samples of one surface to the other, each group (leaflet) against its
    namesake (all of the other surface when it has none). Returns (node d, centroid d)."""
    d_node = np.full(len(x_from), np.inf)
    d_cen = np.full(len(tri_from), np.inf)
    cen = x_from[tri_from].mean(axis=1)
    groups = [None] if group_from is None else list(dict.fromkeys(group_from.tolist()))
    for g in groups:
        sel = np.ones(len(tri_from), bool) if g is None else group_from == g
        target = tri_to
        if g is not None and group_to is not None and np.any(group_to == g):
            target = tri_to[group_to == g]
        nodes = np.unique(tri_from[sel])
        # a node shared by two leaflets keeps its distance to the nearer namesake
        d_node[nodes] = np.minimum(d_node[nodes], point_triangle_distance(x_from[nodes], x_to,
                                                                          target))
        d_cen[sel] = point_triangle_distance(cen[sel], x_to, target)
    return d_node, d_cen


def surface_distance(x_pred, tri_pred, x_ref, tri_ref, group_pred=None,
                     group_ref=None) -> SurfaceDistance:
    """Closed-state error of a predicted surface against a reference surface (mm).

    Args:
        x_pred, tri_pred: the predicted (deformed) surface: nodes (n, 3), triangles (t, 3).
        x_ref, tri_ref: the reference surface.
        group_pred, group_ref: optional per-triangle group names (leaflets); a group is
            compared with the other surface's group of the same name.
    """
    x_pred, x_ref = np.asarray(x_pred, float), np.asarray(x_ref, float)
    tri_pred = np.asarray(tri_pred, np.int64).reshape(-1, 3)
    tri_ref = np.asarray(tri_ref, np.int64).reshape(-1, 3)
    by_leaflet = group_pred is not None and group_ref is not None
    gp = np.asarray(group_pred, dtype=object) if by_leaflet else None
    gr = np.asarray(group_ref, dtype=object) if by_leaflet else None
    used_p = np.unique(tri_pred)
    used_r = np.unique(tri_ref)
    dn, dc = _directed(x_pred, tri_pred, gp, x_ref, tri_ref, gr)
    rn, rc = _directed(x_ref, tri_ref, gr, x_pred, tri_pred, gp)
    _, w, area = surface_samples(x_pred, tri_pred)
    d = np.concatenate([np.where(np.isfinite(dn), dn, 0.0), dc])
    facet = dn[tri_pred].sum(axis=1) / 6 + dc / 2
    _, w_ref, _ = surface_samples(x_ref, tri_ref)
    dr = np.concatenate([np.where(np.isfinite(rn), rn, 0.0), rc])
    to_ref = max(float(dn[used_p].max()), float(dc.max()))
    to_pred = max(float(rn[used_r].max()), float(rc.max()))
    return SurfaceDistance(
        mean_abs_error_mm=float((area * facet).sum() / area.sum()),
        p95_error_mm=weighted_percentile(d, w, 95),
        hausdorff_mm=max(to_ref, to_pred),
        max_to_reference_mm=to_ref, max_to_prediction_mm=to_pred,
        mean_to_prediction_mm=float((w_ref * dr).sum() / w_ref.sum()),
        facet_mm=facet, node_mm=np.where(np.isfinite(dn), dn, np.nan),
        compared="by leaflet" if by_leaflet else "whole surface")


# --------------------------------------------------------------------------- reference files
@dataclass
class ReferenceSurface:
    """A reference closed surface read from a file: nodes, triangles and, when the file has
    integer cell data ``leaflet``, the leaflet name of each triangle (else None)."""

    x: np.ndarray
    tri: np.ndarray
    leaflet: np.ndarray | None
    path: str


def read_reference(path, labels: dict | None = None) -> ReferenceSurface:
    """Read a reference surface (any meshio format; quads are split).

    Raises:
        ValueError: unreadable file, no triangles, non-finite points, or ``leaflet`` values
            that ``labels`` does not name.
    """
    from mvfem.meshes.io import read_surface

    raw = read_surface(path)
    labels = labels or DEFAULT_LABELS
    if not np.all(np.isfinite(raw.points)):
        raise ValueError(f"{path}: non-finite point coordinates")
    names = None
    if "leaflet" in raw.cell_data:
        vals = np.asarray(raw.cell_data["leaflet"]).reshape(len(raw.triangles), -1)[:, 0]
        if not np.all(np.isfinite(vals)) or not np.all(vals == np.round(vals)):
            raise ValueError(f"{path}: cell data 'leaflet' must hold integers")
        unknown = sorted({int(v) for v in vals} - set(labels))
        if unknown:
            raise ValueError(f"{path}: cell data 'leaflet' has value {unknown[0]}, which the "
                             f"labels do not name (labels: {labels})")
        names = np.array([labels[int(v)] for v in vals], dtype=object)
    return ReferenceSurface(x=raw.points, tri=raw.triangles, leaflet=names, path=str(path))


def _view_axis(surface, x):
    """Viewing axis and 'up' of a map: the surface's frame when it has one (valves: seen from
    the atrium, anterior up), else the normal of the best-fit plane."""
    axis = getattr(surface, "axis", None)
    if axis is not None:
        axis = np.asarray(axis, float)
        frame = np.asarray(getattr(surface, "frame", np.eye(3)), float)
        up = frame[0] - (frame[0] @ axis) * axis
        if np.linalg.norm(up) > 1e-9:
            return axis / np.linalg.norm(axis), up / np.linalg.norm(up)
    c = x - x.mean(axis=0)
    _, _, vt = np.linalg.svd(c, full_matrices=False)
    axis = vt[2]
    if axis @ np.array([0.0, 0.0, 1.0]) < 0:
        axis = -axis
    return axis, vt[1] if abs(vt[1] @ axis) < 0.9 else vt[0]


def nodal_average(tri: np.ndarray, facet: np.ndarray, n: int) -> np.ndarray:
    """Per-node values from per-facet ones: each node's the plain mean of the values of the
    facets it is a corner of; 0 at a node of no facet."""
    tri = np.asarray(tri, dtype=np.int64)
    total = np.bincount(tri.ravel(), weights=np.repeat(np.asarray(facet, float), 3), minlength=n)
    count = np.bincount(tri.ravel(), minlength=n)
    return np.divide(total, count, out=np.zeros(n), where=count > 0)


def distance_map(x, tri, facet_mm, axis, up, path, title: str,
                 label: str = "distance to the reference surface, mm",
                 smooth: bool = False) -> Path:
    """PNG map of the per-facet distance, seen along ``-axis`` (the atrium for valves).
    ``smooth``: each node coloured by the mean of its facets' values, shaded across the
    facets (Gouraud), instead of each facet by its own value."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    right = np.cross(up, axis)
    c = x.mean(axis=0)
    p2 = np.stack([(x - c) @ right, (x - c) @ up], axis=1)
    order = np.argsort(((x - c) @ axis)[tri].mean(axis=1))
    hi = float(np.percentile(facet_mm, 95)) if len(facet_mm) else 1.0
    fig, ax = plt.subplots(figsize=(6, 5.2), dpi=120)
    if smooth:  # (the triangles drawn in depth order, the nearest last, as the facets are)
        nodal = nodal_average(tri, facet_mm, len(x))
        pc = ax.tripcolor(p2[:, 0], p2[:, 1], tri[order], nodal, shading="gouraud",
                          cmap="magma_r", vmin=0.0, vmax=hi if hi > 0 else 1e-9)
    else:
        pc = PolyCollection(p2[tri[order]], array=facet_mm[order], cmap="magma_r",
                            edgecolors="face", linewidths=0.1)
        pc.set_clim(0.0, hi if hi > 0 else 1e-9)
        ax.add_collection(pc)
    ax.autoscale_view()
    ax.set_aspect("equal")
    ax.set_xlabel("mm")
    ax.set_ylabel("mm")
    ax.set_title(title, fontsize=9)
    fig.colorbar(pc, ax=ax, shrink=0.8, label=label)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path)
    plt.close(fig)
    return path


def _deformed_surface(model):
    """(x deformed (N, 3), triangles, per-triangle leaflet name or None) on rank 0 (None
    elsewhere). Collective."""
    from mvfem.nodal import NodalView

    u = model.u
    if model.V.ufl_element().degree() != 1:
        from dolfinx import fem

        V1 = fem.VectorFunctionSpace(model.mesh, ("Lagrange", 1))
        u1 = fem.Function(V1)
        u1.interpolate(u)
        u = u1
    view = NodalView(u.function_space, cell_tags=model.surface.cell_tags)
    disp = view.gather(u.x.array)
    if model.comm.rank != 0:
        return None
    x = view.X + disp
    groups = None
    named = [r for r in model.regions if r.tag is not None]
    if named:
        raw_regions = model.scene["region"]
        name_of = {}
        for r, raw in zip(model.regions, raw_regions):
            if r.tag is not None:
                name_of[r.tag] = raw.get("leaflet") or r.label
        groups = np.array([name_of.get(int(t), "") for t in view.cell_tag], dtype=object)
    return x, view.cells, groups


def reference_outputs(model, out: Path | None) -> dict:
    """The ``reference`` block of summary.json for a scene with ``[reference] file``; writes
    ``distance.vtu`` (the closed leaflets with cell data ``distance_mm``) and
    ``map_distance.png`` into ``out`` when given. Collective; the same dict on every rank."""
    ref = model.scene["reference"]
    block = None
    surf = _deformed_surface(model)  # collective
    if model.comm.rank == 0:
        labels = ref["labels"] or model.scene["mesh"]["labels"] or DEFAULT_LABELS
        reference = read_reference(ref["file"], labels)
        x, tri, groups = surf
        res = surface_distance(x, tri, reference.x, reference.tri,
                               groups if reference.leaflet is not None else None,
                               reference.leaflet if groups is not None else None)
        block = {**res.block(), "file": str(ref["file"])}
        if out is not None:
            from mvfem.meshes.io import write_surface

            cell_data = {"distance_mm": res.facet_mm}
            if groups is not None:
                codes = {n: i for i, n in enumerate(dict.fromkeys(groups.tolist()))}
                cell_data["leaflet_index"] = np.array([codes[g] for g in groups], np.int32)
            write_surface(Path(out) / "distance.vtu", x, tri,
                          point_data={"distance_mm": np.nan_to_num(res.node_mm)},
                          cell_data=cell_data)
            axis, up = _view_axis(model.surface, x)
            distance_map(x, tri, res.facet_mm, axis, up, Path(out) / "map_distance.png",
                         f"distance to {Path(ref['file']).name}: mean {res.mean_abs_error_mm:.3g}"
                         f" mm, p95 {res.p95_error_mm:.3g} mm, Hausdorff "
                         f"{res.hausdorff_mm:.3g} mm\ncolour range 0 - 95th percentile")
    return model.comm.bcast(block, root=0)


# ---------------------------------------------------------------- one mesh level to the next
def level_change(finer, coarser) -> tuple[dict, np.ndarray]:
    """How far a closure moved from one mesh level to the next finer one (rank 0): the finer
    closed surface's distance to the coarser one (:func:`surface_distance`, each leaflet
    against its namesake where both surfaces name them).

    Args:
        finer, coarser: ``(x, triangles, leaflet names or None)`` of the two closed surfaces,
            as :func:`_deformed_surface` gives them.
    Returns:
        The block of summary.json (``mean_mm``: the finer surface's area-weighted mean
        distance to the coarser one, ``p95_mm``, ``hausdorff_mm``: both ways, ``compared``)
        and the finer surface's per-facet values (mm).
    """
    (xf, tf, gf), (xc, tc, gc) = finer, coarser
    by_leaflet = gf is not None and gc is not None
    d = surface_distance(xf, tf, xc, tc, gf if by_leaflet else None, gc if by_leaflet else None)
    return ({"mean_mm": d.mean_abs_error_mm, "p95_mm": d.p95_error_mm,
             "hausdorff_mm": d.hausdorff_mm, "compared": d.compared}, d.facet_mm)


def last_move(summary: dict | None) -> dict | None:
    """How far a refined run's last refinement moved its closure: the block of
    :func:`level_change` that summary.json keeps as ``coarse_start.distance_to_finer_mm``;
    None for a run on one mesh, one whose levels were not measured, or no summary."""
    return ((summary or {}).get("coarse_start") or {}).get("distance_to_finer_mm")


def level_change_map(surface, finer, facet_mm, block: dict, cells: tuple[int, int],
                     path) -> Path:
    """``map_level_change.png``: the finer closure coloured by its distance to the coarser
    closure (:func:`level_change`), seen as the other maps are: each node by the mean of its
    facets' distances, shaded across the facets. Facet by facet the map alternated: a nested
    level's new nodes (its coarser edges' midpoints) move further than the coarser nodes, so
    the facets at a coarser node and those between them differ (README "Each refined run
    measures its own mesh error")."""
    x, tri, _ = finer
    axis, up = _view_axis(surface, x)
    return distance_map(
        x, tri, facet_mm, axis, up, path,
        f"closure moved by the last refinement ({cells[0]} -> {cells[1]} cells)\n"
        f"mean {block['mean_mm']:.3g}, p95 {block['p95_mm']:.3g}, max "
        f"{block['hausdorff_mm']:.3g} mm; colours 0 - 95th percentile",
        label="distance to the coarser closure, mm (a node: its facets' mean)",
        smooth=True)
