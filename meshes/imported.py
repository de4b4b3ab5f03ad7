"""Patient valves from files: a leaflet surface with its annulus and chordae, made into a
:class:`~mvfem.meshes.valve.ValveMesh` that the model treats like a generated valve.

The file (any meshio format, read by :func:`mvfem.meshes.io.read_surface`) holds (CONTRACT.md,
"Imported valves"):

- leaflet cells, triangles or quads (each split in two), with integer cell data ``leaflet``;
  ``labels`` maps its values to leaflet names (default ``{1: "anterior", 2: "posterior"}``,
  what :func:`write_valve_with_chordae` writes); several values may share a name;
- point data ``annulus``, nonzero on the annulus nodes. The annulus edges are the boundary
  edges with both end nodes on the annulus; they must form one closed loop. Every other
  boundary edge is a free edge of the leaflet of its cell;
- optionally line cells: the chordae, which may branch (trees). Each tree is rooted at one
  node with nonzero point data ``papillary`` (a papillary tip; not a leaflet node). Every
  leaflet node the tree reaches is an insertion, tethered straight to the root with the path
  length along the tree from the root as its length. Line nodes off the leaflets are branch
  points. Optional line cell data: ``family`` (0 marginal, 1 strut, 2 basal, -1 not given; the
  segment that reaches an insertion decides; otherwise an insertion on a free edge is marginal,
  any other basal) and ``rest_length`` (mm, a segment's unstretched length where it differs
  from its length in the file; values that are not > 0 mean "its length").

Orientation: the cells are oriented consistently over each edge-connected piece of the
surface, then each piece so that its normals face the atrium (the valve axis from ventricle to
atrium) and the valve's axis (the inside of the open funnel). The ventricle is the side of the
annulus plane where the papillary tips are; without tips, the side the leaflets hang to (with
a warning).

``mesh.refine`` splits the file's triangles before the valve is built, once the file itself
has passed the checks below (:func:`check_surface`): :func:`refine_surface`, each new node at
its edge's midpoint (the file's surface, a finer mesh on it) or, with ``mesh.refine_surface =
"smooth"``, on a smooth surface through the file's nodes.

Lengths are those of the file (mm). Geometry only: numpy and scipy, no physics.
"""

from __future__ import annotations

import logging
import os
import shutil
import tempfile
from dataclasses import dataclass, field

import numpy as np

from .io import (RawSurface, _raise_from_root, _root_or_error, mesh_from_arrays,
                 read_surface)
from .valve import ValveMesh, write_valve

__all__ = ["ImportedValve", "check_plain_surface", "check_surface", "refine_surface",
           "valve_from_file", "valve_from_surface",
           "write_valve_with_chordae", "chord_lengths", "DEFAULT_LABELS", "FAMILY_CODES",
           "FORMATS"]

logger = logging.getLogger(__name__)

#: the farthest a file's node may lie from the origin (mm: a kilometre; beyond it a unit is
#: mistaken, and at 1e200 the areas overflow)
MAX_COORDINATE_MM = 1e6

#: leaflet names of the ``leaflet`` values when a scene gives no ``mesh.labels``
DEFAULT_LABELS = {1: "anterior", 2: "posterior"}
#: file formats that keep the line cells and point data of a valve file (meshio by extension)
FORMATS = (".vtu", ".vtk", ".xdmf")
#: line cell data ``family`` -> chordae family
FAMILY_CODES = {0: "marginal", 1: "strut", 2: "basal"}
_CODE_OF_FAMILY = {v: k for k, v in FAMILY_CODES.items()}
# coincident nodes: closer than this times the bounding-box diagonal
_MERGE = 1e-9


@dataclass
class ImportedValve(ValveMesh):
    """A valve read from a file (see the module docstring).

    Attributes (besides those of :class:`ValveMesh`; ``insertion_closed`` is empty):
        insertion_path_length: (K,) unstretched length of each chord: the path length along
            its tree from the root to the insertion (``rest_length`` data where given), mm.
            The model's chordae rest length is ``length_factor`` x this.
        insertion_tree_length: (K,) the same path length measured on the file's geometry, mm.
    """

    insertion_path_length: np.ndarray = field(default_factory=lambda: np.zeros(0))
    insertion_tree_length: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def insertions(self, family: str | None = None, leaflet: str | None = None) -> np.ndarray:
        """Indices (into ``insertion_points``) of one family and/or one leaflet (by name)."""
        keep = np.ones(len(self.insertion_points), dtype=bool)
        if family is not None:
            keep &= self.insertion_family == family
        if leaflet is not None:
            keep &= self.insertion_leaflet == self.names[leaflet]
        return np.flatnonzero(keep)


def valve_from_file(comm, path: str | os.PathLike, labels: dict[int, str] | None = None
                    ) -> ImportedValve:
    """Read a valve file on rank 0 and distribute it (collective).

    Args:
        comm: MPI communicator.
        path: the file (any meshio format).
        labels: ``leaflet`` value -> leaflet name (default :data:`DEFAULT_LABELS`).

    Raises:
        ValueError: (on every rank) the file cannot be read or is not a valid valve; the
            message names the file and what is wrong.
    """
    path = os.fspath(path)
    raw = _root_or_error(comm, lambda: read_surface(path))
    return valve_from_surface(comm, raw, labels, source=path)


def valve_from_surface(comm, raw: RawSurface | None, labels: dict[int, str] | None = None,
                       source: str = "<surface>") -> ImportedValve:
    """A valve from rank 0's :class:`~mvfem.meshes.io.RawSurface` (other ranks may pass None);
    collective. ``source`` names the file in error messages.

    Raises:
        ValueError: (on every rank) the surface is not a valid valve (see the module docstring).
    """
    built = _root_or_error(comm, lambda: _build(raw, labels, source))
    if comm.rank == 0:
        arrays, extras = built
    else:
        arrays, extras = (None,) * 5, None
    extras = comm.bcast(extras, root=0)
    msh, cell_tags, facet_tags = mesh_from_arrays(comm, *arrays)
    names, info = extras.pop("names"), extras.pop("info")
    return ImportedValve(msh, cell_tags, facet_tags, names, info, **extras)


def refine_surface(raw: RawSurface, times: int, smooth: bool = False) -> RawSurface:
    """``times`` uniform 1-to-4 splits of an imported valve surface (``mesh.refine`` of a
    file), each new node at its edge's midpoint: the facets stay the file's, so the surface
    is as the file gives it, with a finer displacement on it (the generated valve places its
    new nodes on its own curved surface instead). With ``smooth`` (``mesh.refine_surface =
    "smooth"``) each new node is on a smooth surface through the nodes instead
    (:func:`mvfem.meshes.refine.smooth_midpoints`: the annulus and the free edges along their
    own curves, the corners where they meet kept). The file's nodes keep their indices (the
    chordae's line cells and the papillary tips are unchanged), each triangle's four
    children take its cell data, and a new node is on the annulus (``annulus`` point data)
    where its edge is a boundary edge with both ends on it; other point data of new nodes
    are zero (``papillary``: the tips are off the leaflets). The coarse levels of a nested
    closure are the file itself and its fewer splits."""
    from .refine import smooth_midpoints, split

    points = np.asarray(raw.points, dtype=np.float64)
    tri = np.asarray(raw.triangles, dtype=np.int64).reshape(-1, 3)
    point_data = {k: np.asarray(v) for k, v in raw.point_data.items()}
    cell_data = {k: np.asarray(v) for k, v in raw.cell_data.items()}
    for _ in range(times):
        n, m = len(points), len(tri)
        edges, children = split(tri, n)
        # each parent's three edges are its middle child's nodes (as meshes.valve's _refine
        # reads them): an edge of one cell is on the boundary
        mids = children[3 * m:] - n
        boundary = np.bincount(mids.ravel(), minlength=len(edges)) == 1
        # the annulus edges: boundary edges with both ends on it
        ring = point_data.get("annulus", np.zeros(n))
        ring = (np.asarray(ring).reshape(n, -1) != 0).any(axis=1)
        ring_edges = boundary & ring[edges[:, 0]] & ring[edges[:, 1]]
        # (a file with non-finite nodes is split flat: the import then names its problem)
        if smooth and np.isfinite(points[np.unique(tri)]).all():
            # a boundary edge is annulus (1) or free edge (0): where they meet is a corner;
            # mids.T holds each cell's three edges, as cell_edges' sides do
            new_points = smooth_midpoints(points, tri, edges, mids.T, ring_edges.astype(int))
        else:
            new_points = 0.5 * (points[edges[:, 0]] + points[edges[:, 1]])
        points = np.vstack([points, new_points])
        for key, v in point_data.items():
            new = np.zeros((len(edges),) + v.shape[1:], dtype=v.dtype)
            if key == "annulus":
                new[ring_edges] = v[edges[ring_edges, 0]]
            point_data[key] = np.concatenate([v, new])
        cell_data = {k: np.concatenate([v] * 4) for k, v in cell_data.items()}
        tri = children
    return RawSurface(points=points, triangles=tri, point_data=point_data, cell_data=cell_data,
                      lines=raw.lines, line_data=raw.line_data)


# --- the valve on rank 0 ---------------------------------------------------------------------

def check_surface(comm, raw: RawSurface | None, labels: dict[int, str] | None = None,
                  source: str = "<surface>") -> None:
    """Raise what :func:`valve_from_surface` would raise for ``raw`` (rank 0's; collective),
    without building a mesh, its warnings or its report: a file checked before it is split
    (``mesh.refine``) is refused in its own nodes and places, not its split's."""
    _root_or_error(comm, lambda: _build(raw, labels, source, report=False))


def _build(raw: RawSurface, labels: dict[int, str] | None, where: str, report: bool = True):
    points = np.asarray(raw.points, dtype=np.float64)
    tri = np.asarray(raw.triangles, dtype=np.int64).reshape(-1, 3)
    lines = np.asarray(raw.lines, dtype=np.int64).reshape(-1, 2)
    _check_indices(points, tri, lines, where)

    value_of, file_labels, cell_leaflet = _leaflet_values(raw, labels, where, len(tri))
    if "annulus" not in raw.point_data:
        raise ValueError(f"{where}: no 'annulus' point data (nonzero on the annulus nodes); "
                         f"point data found: {', '.join(sorted(raw.point_data)) or 'none'}")
    on_annulus = _flags(raw.point_data["annulus"], len(points), "annulus", where)
    has_papillary = "papillary" in raw.point_data
    on_papillary = (_flags(raw.point_data["papillary"], len(points), "papillary", where)
                    if has_papillary else np.zeros(len(points), dtype=bool))

    used = np.unique(np.concatenate([tri.ravel(), lines.ravel(), np.flatnonzero(on_papillary)]))
    diag = _check_finite(points, tri, used, where, "leaflet cells")

    said = []  # warnings
    # coincident nodes (e.g. a leaflet saved with its own copy of shared nodes): merged
    rep, merged = _merge_coincident(points, used, _MERGE * diag)
    if merged:
        said.append(f"{where}: merged {merged} coincident node(s) (closer than "
                    f"{_MERGE * diag:.3g} mm)")
        np.maximum.at(on_annulus, rep, on_annulus.copy())
        np.maximum.at(on_papillary, rep, on_papillary.copy())
        tri, lines = rep[tri], rep[lines]

    _check_cells(points, tri, where, diag)
    _check_intersections(points, tri, where)
    slivers = _slivers(points, tri)
    if len(slivers):
        said.append(f"{where}: {len(slivers)} sliver triangle(s) with an angle below "
                    f"{SLIVER_DEG:g} deg (smallest {slivers[0][1]:.2g} deg, at "
                    f"{_at(points[tri[slivers[0][0]]].mean(0))}); kept as they are, but expect "
                    "a poorly conditioned tangent and stresses that are not resolved there")
    edges, edge_tri, counts = _edges(tri)
    bad = counts > 2
    if bad.any():
        e = edges[np.flatnonzero(bad)[0]]
        raise ValueError(f"{where}: {int(bad.sum())} non-manifold edge(s) (in more than two "
                         f"triangles), e.g. the edge at {_at(points[e].mean(0))}")

    # compact the surface nodes; line nodes off the surface keep their file index
    surface_nodes = np.unique(tri)
    local = np.full(len(points), -1, dtype=np.int64)
    local[surface_nodes] = np.arange(len(surface_nodes))
    X = points[surface_nodes]
    cells = local[tri]
    edges = local[edges]
    ann = on_annulus[surface_nodes]

    boundary = counts == 1
    b_edges, b_tri = edges[boundary], edge_tri[boundary, 0]
    is_ann = ann[b_edges].all(axis=1)
    loop = _annulus_loop(X, b_edges[is_ann], ann, where)
    centre, n_plane = _loop_plane(X[loop], where)

    tips_idx = np.flatnonzero(on_papillary)
    tips_idx = tips_idx[np.isin(tips_idx, used) & (rep[tips_idx] == tips_idx)]
    if np.any(local[tips_idx] >= 0):
        k = tips_idx[local[tips_idx] >= 0][0]
        raise ValueError(f"{where}: node {int(k)} at {_at(points[k])} has nonzero 'papillary' "
                         "point data but is a leaflet node (papillary tips are off the leaflets)")
    tips = points[tips_idx]

    area = _areas(X, cells)
    cen = X[cells].mean(axis=1)
    if len(tips):
        axis = -n_plane if (tips.mean(0) - centre) @ n_plane > 0 else n_plane
        ventricle = "papillary tips"
        cells, flipped = _orient(X, cells, axis, centre, where)
    else:
        hang = float(area @ ((cen - centre) @ n_plane))
        if abs(hang) > 1e-6 * diag * area.sum():
            axis = n_plane if hang < 0 else -n_plane
            ventricle = "leaflets hang"
            said.append(f"{where}: no 'papillary' tips; the ventricle is taken on the side of "
                        "the annulus plane the leaflets hang to")
            cells, flipped = _orient(X, cells, axis, centre, where)
        else:  # flat: trust the file's orientation
            cells, flipped = _orient(X, cells, None, centre, where)
            mean_n = _normals(X, cells).sum(axis=0)
            axis = n_plane if mean_n @ n_plane >= 0 else -n_plane
            ventricle = "file orientation"
            said.append(f"{where}: no 'papillary' tips and flat leaflets; the atrium is taken "
                        "on the side the file's triangles face")
    axis = axis / np.linalg.norm(axis)

    # tags: leaflet cells by value; annulus; free edge of each leaflet
    top = max(value_of.values())
    names = dict(value_of)
    names["annulus"] = top + 1
    for i, name in enumerate(value_of):
        names[f"free_edge_{name}"] = top + 2 + i
    edge_values = np.where(is_ann, names["annulus"], 0).astype(np.int32)
    free_of = {v: names[f"free_edge_{n}"] for n, v in value_of.items()}
    edge_values[~is_ann] = [free_of[v] for v in cell_leaflet[b_tri[~is_ann]]]

    frame = _frame(X, cells, cell_leaflet, value_of, loop, centre, axis, area)
    loop = _ccw_from_anterior(X, loop, centre, frame)
    edge_leaflet = _loop_edge_leaflets(loop, b_edges, b_tri, cell_leaflet)
    commissures = _commissures(X, loop, edge_leaflet, value_of, centre, frame)

    free_nodes = np.zeros(len(X), dtype=bool)
    free_nodes[b_edges[~is_ann].ravel()] = True
    ch = _chordae(points, X, lines, local, tips_idx, on_papillary, has_papillary,
                  raw.line_data, cells, cell_leaflet, free_nodes, where)
    muscle = _muscles(tips, centre, frame)

    areas = {n: float(area[cell_leaflet == v].sum()) for n, v in value_of.items()}
    perimeter = float(np.linalg.norm(X[np.roll(loop, -1)] - X[loop], axis=1).sum())
    info = {"generator": "file", "file": where,
            "labels": file_labels,
            "cells": int(len(cells)), "vertices": int(len(X)),
            "nodes_merged": int(merged), "cells_flipped": int(flipped),
            "ventricle_from": ventricle, "leaflet_area_mm2": areas,
            "annulus_nodes": int(len(loop)), "annulus_perimeter_mm": perimeter,
            "papillary_tips": int(len(tips)), "chordae": int(len(ch["points"])),
            "chordae_trees": ch["trees"], "chordae_branch_points": ch["branch_points"]}
    if report:  # only for a valve that is built: an error is the one line a user sees
        for text in said:
            logger.warning(text)
        logger.info("%s: %d cells, %d nodes, %d leaflets, %d chordae from %d tips", where,
                    len(cells), len(X), len(value_of), len(ch["points"]), len(tips))
    extras = {"names": names, "info": info,
              "papillary_tips": tips.reshape(-1, 3), "papillary_muscle": muscle,
              "insertion_points": ch["points"], "insertion_leaflet": ch["leaflet"],
              "insertion_family": ch["family"], "insertion_tip": ch["tip"],
              "insertion_muscle": (muscle[ch["tip"]] if len(ch["tip"])
                                   else np.zeros(0, dtype=np.int32)).astype(np.int32),
              "insertion_path_length": ch["path_length"],
              "insertion_tree_length": ch["tree_length"],
              "axis": axis, "centre": centre, "frame": frame, "commissures": commissures,
              "annulus_curve": X[loop]}
    return (X, cells, cell_leaflet, b_edges, edge_values), extras


def check_plain_surface(raw: RawSurface, where: str,
                        labels: dict[int, str] | None = None) -> None:
    """Raise what a surface file without an annulus cannot be solved on, as a valve file's
    import does (:func:`_build`): cells naming nodes not in the file, nodes with non-finite
    coordinates, no extent, degenerate (zero-area) or duplicate triangles, 'leaflet' cell
    data that are not integers or, where ``labels`` are given, that they do not name (cells
    of such a value would be in no region)."""
    points = np.asarray(raw.points, dtype=np.float64)
    tri = np.asarray(raw.triangles, dtype=np.int64).reshape(-1, 3)
    _check_indices(points, tri, np.zeros((0, 2), dtype=np.int64), where)
    diag = _check_finite(points, tri, np.unique(tri), where, "cells")
    _check_cells(points, tri, where, diag)
    if "leaflet" in raw.cell_data:
        if labels:
            _leaflet_values(raw, labels, where, len(tri))
        else:
            _leaflet_ints(raw, where, len(tri))


def _leaflet_ints(raw: RawSurface, where: str, ntri: int) -> np.ndarray:
    """The file's 'leaflet' cell data, one integer a triangle (refused if not integers)."""
    values = np.asarray(raw.cell_data["leaflet"]).reshape(ntri, -1)[:, 0]
    if not np.issubdtype(values.dtype, np.number) or not np.all(np.isfinite(values)) \
            or not np.all(values == np.round(values)):
        raise ValueError(f"{where}: 'leaflet' cell data must be integers")
    return values.astype(np.int64)


def _check_indices(points, tri, lines, where: str) -> None:
    for name, c in (("cells", tri), ("line cells", lines)):
        if len(c) and (c.min() < 0 or c.max() >= len(points)):
            raise ValueError(f"{where}: {name} refer to nodes that are not in the file")


def _check_finite(points, tri, used, where: str, cells: str) -> float:
    """The diagonal of the cells' bounding box, once the ``used`` nodes are finite and the
    cells have an extent."""
    finite = np.isfinite(points[used]).all(axis=1)
    if not finite.all():
        raise ValueError(f"{where}: {int(np.sum(~finite))} node(s) have non-finite coordinates "
                         f"(first: node {int(used[~finite][0])})")
    far = np.abs(points[used]).max(axis=1, initial=0.0) > MAX_COORDINATE_MM
    if far.any():   # (1e200 overflowed in the checks below: a message without the file's name)
        raise ValueError(f"{where}: {int(far.sum())} node(s) lie farther than "
                         f"{MAX_COORDINATE_MM:g} mm from the origin (first: node "
                         f"{int(used[far][0])}); coordinates are in mm")
    diag = float(np.linalg.norm(np.ptp(points[np.unique(tri)], axis=0))) if len(tri) else 0.0
    if not diag > 0:
        raise ValueError(f"{where}: the {cells} have no extent")
    return diag


def _leaflet_values(raw: RawSurface, labels, where: str, ntri: int):
    """(leaflet name -> tag value, the file's values present -> names, per-triangle tag
    value)."""
    if "leaflet" not in raw.cell_data:
        found = ", ".join(sorted(raw.cell_data)) or "none"
        raise ValueError(f"{where}: no 'leaflet' cell data (an integer leaflet label on every "
                         f"triangle or quad); cell data found: {found}")
    values = _leaflet_ints(raw, where, ntri)
    given = labels is not None
    labels = DEFAULT_LABELS if labels is None else {int(k): str(v) for k, v in labels.items()}
    present = np.unique(values)
    missing = [int(v) for v in present if int(v) not in labels]
    if missing:
        known = ", ".join(f"{k} = {v!r}" for k, v in sorted(labels.items()))
        hint = "mesh.labels" if given else "the default labels (give mesh.labels)"
        raise ValueError(f"{where}: 'leaflet' value {missing[0]} "
                         f"({int(np.sum(values == missing[0]))} cells) is not in {hint}: "
                         f"{{{known}}}")
    value_of: dict[str, int] = {}
    for v in present:  # a name given to several values takes the smallest
        value_of.setdefault(labels[int(v)], int(v))
    for name in value_of:
        if name == "annulus" or name.startswith("free_edge_"):
            raise ValueError(f"{where}: leaflet name {name!r} is reserved for edge tags")
    cell_leaflet = np.array([value_of[labels[int(v)]] for v in values], dtype=np.int32) \
        if len(values) else np.zeros(0, dtype=np.int32)
    return value_of, {int(v): labels[int(v)] for v in present}, cell_leaflet


def _flags(data, n: int, name: str, where: str) -> np.ndarray:
    a = np.asarray(data)
    if a.shape[0] != n:
        raise ValueError(f"{where}: '{name}' point data has {a.shape[0]} values for {n} nodes")
    a = a.reshape(n, -1)[:, 0].astype(np.float64)
    return np.isfinite(a) & (a != 0)


def _merge_coincident(points, used, tol):
    """(representative of every node, number of nodes merged into another)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    rep = np.arange(len(points))
    pairs = cKDTree(points[used]).query_pairs(tol, output_type="ndarray")
    if len(pairs) == 0:
        return rep, 0
    n = len(used)
    g = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    first = np.full(comp.max() + 1, np.iinfo(np.int64).max)
    np.minimum.at(first, comp, used)
    rep[used] = first[comp]
    return rep, int(np.sum(rep[used] != used))


def _areas(X, cells):
    return 0.5 * np.linalg.norm(_normals(X, cells), axis=1)


def _normals(X, cells):
    """Cross products of the cell tangents (twice the area along the unit normal)."""
    x = X[cells]
    return np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])


#: smallest angle of a triangle below which import warns (a sliver), degrees
SLIVER_DEG = 5.0


def _slivers(points, tri) -> list[tuple[int, float]]:
    """(triangle, smallest angle in degrees) of the slivers, smallest first."""
    x = points[tri]
    ang = np.empty((len(tri), 3))
    for k in range(3):
        a, b = x[:, (k + 1) % 3] - x[:, k], x[:, (k + 2) % 3] - x[:, k]
        c = np.einsum("ij,ij->i", a, b) / (np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1))
        ang[:, k] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
    small = ang.min(axis=1)
    bad = np.flatnonzero(small < SLIVER_DEG)
    return [(int(t), float(small[t])) for t in bad[np.argsort(small[bad])]]


def _check_intersections(points, tri, where: str) -> None:
    """Refuse a surface that passes through itself: an edge crossing the interior of a
    triangle it shares no node with (a folded or inverted triangle, or one leaflet through
    another). The open valve must be free of crossings: contact only keeps apart surfaces
    that start apart (the crossing tests ignore pairs that were close in the open valve)."""
    from scipy.spatial import cKDTree

    from .refine import cell_edges

    edges = cell_edges(tri)[0]
    if len(edges) == 0:
        return
    x = points[tri]
    cen = x.mean(axis=1)
    radius = np.linalg.norm(x - cen[:, None], axis=2).max()
    p, q = points[edges[:, 0]], points[edges[:, 1]]
    half = 0.5 * np.linalg.norm(q - p, axis=1).max()
    near = cKDTree(cen).query_ball_point(0.5 * (p + q), half + radius)
    ei = np.repeat(np.arange(len(edges)), [len(n) for n in near])
    ti = np.fromiter((t for n in near for t in n), dtype=np.int64, count=len(ei))
    share = (tri[ti] == edges[ei, :1]).any(axis=1) | (tri[ti] == edges[ei, 1:]).any(axis=1)
    ei, ti = ei[~share], ti[~share]
    a, b, c = (points[tri[ti, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    dp = np.einsum("ij,ij->i", p[ei] - a, n)
    dq = np.einsum("ij,ij->i", q[ei] - a, n)
    scale = np.linalg.norm(n, axis=1) * np.linalg.norm(q[ei] - p[ei], axis=1)
    # strictly on both sides (a shared plane or an end on the triangle is not a crossing)
    crosses = (dp * dq < 0) & (np.minimum(np.abs(dp), np.abs(dq)) > 1e-9 * scale)
    t = np.where(crosses, dp / np.where(crosses, dp - dq, 1.0), 0.0)
    y = p[ei] + t[:, None] * (q[ei] - p[ei])
    inside = crosses.copy()
    for u, v in ((a, b), (b, c), (c, a)):
        inside &= np.einsum("ij,ij->i", np.cross(v - u, y - u), n) > 0
    if inside.any():
        k = np.flatnonzero(inside)
        raise ValueError(f"{where}: the leaflet surface passes through itself: {len(k)} edge(s) "
                         "cross a triangle they share no node with (folded or inverted "
                         "triangles, or leaflets through each other), e.g. at "
                         f"{_at(y[k[0]])}")


def _check_cells(points, tri, where: str, diag: float) -> None:
    repeated = (tri[:, 0] == tri[:, 1]) | (tri[:, 1] == tri[:, 2]) | (tri[:, 0] == tri[:, 2])
    area = _areas(points, tri)
    degenerate = repeated | (area <= 1e-12 * diag * diag)
    if degenerate.any():
        k = np.flatnonzero(degenerate)[0]
        raise ValueError(f"{where}: {int(degenerate.sum())} degenerate (zero-area) triangle(s), "
                         f"e.g. at {_at(points[tri[k]].mean(0))}")
    key = np.sort(tri, axis=1)
    _, first, count = np.unique(key, axis=0, return_index=True, return_counts=True)
    if np.any(count > 1):
        k = first[np.argmax(count > 1)]
        raise ValueError(f"{where}: {int(np.sum(count - 1))} duplicate triangle(s) (the same "
                         f"three nodes twice), e.g. at {_at(points[tri[k]].mean(0))}")


def _edges(tri):
    """Unique edges (E, 2) (smaller node first), the first two triangles of each ((E, 2),
    -1 where there is one), and the number of triangles of each."""
    half = tri[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    key = np.sort(half, axis=1)
    edges, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    owner = np.repeat(np.arange(len(tri)), 3)
    order = np.argsort(inv, kind="stable")
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    edge_tri = np.full((len(edges), 2), -1, dtype=np.int64)
    edge_tri[:, 0] = owner[order[start]]
    two = counts >= 2
    edge_tri[two, 1] = owner[order[start[two] + 1]]
    return edges, edge_tri, counts


def _orient(X, cells, axis, centre, where: str):
    """Consistent orientation over each edge-connected piece; with ``axis``, each piece turned
    to face the atrium and the valve axis (area-weighted n . (axis + inward) > 0). Returns
    (cells, number of cells flipped)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, connected_components

    cells = cells.copy()
    n = len(cells)
    half = cells[:, [[0, 1], [1, 2], [2, 0]]].reshape(-1, 2)
    key = np.sort(half, axis=1)
    forward = half[:, 0] < half[:, 1]
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    order = np.argsort(inv, kind="stable")
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    inner = start[counts == 2]
    h0, h1 = order[inner], order[inner + 1]
    t0, t1 = h0 // 3, h1 // 3
    # same direction along the shared edge: one of the two must be flipped relative to the other
    same = (forward[h0] == forward[h1]).astype(np.int8)
    g = coo_matrix((same + 1, (t0, t1)), shape=(n, n)).tocsr()
    g = g + g.T
    ncomp, comp = connected_components(g, directed=False)
    flip = np.zeros(n, dtype=bool)
    for root in np.unique(comp, return_index=True)[1]:
        seq, pred = breadth_first_order(g, root, directed=False, return_predecessors=True)
        parity = np.asarray(g[seq[1:], pred[seq[1:]]]).ravel() - 1
        for t, p, s in zip(seq[1:], pred[seq[1:]], parity):
            flip[t] = flip[p] ^ bool(s)
    f1 = flip[t0] ^ flip[t1]
    if np.any(f1 != same.astype(bool)):
        k = t0[np.flatnonzero(f1 != same.astype(bool))[0]]
        raise ValueError(f"{where}: the leaflet surface is not orientable (a Moebius-like twist "
                         f"near {_at(X[cells[k]].mean(0))})")
    if axis is not None:
        nrm = _normals(X, cells)
        nrm[flip] *= -1
        d = X[cells].mean(axis=1) - centre
        inward = -(d - np.outer(d @ axis, axis))
        norm = np.linalg.norm(inward, axis=1)
        inward = np.divide(inward, norm[:, None], out=np.zeros_like(inward),
                           where=norm[:, None] > 0)
        score = np.einsum("ij,ij->i", nrm, axis + inward)  # area-weighted (|nrm| = 2 area)
        per = np.bincount(comp, weights=score, minlength=ncomp)
        flip ^= per[comp] < 0
    else:  # keep the orientation most of the file's area has in each piece
        area = _areas(X, cells)
        kept = np.bincount(comp, weights=np.where(flip, -area, area), minlength=ncomp)
        flip ^= kept[comp] < 0
    cells[flip] = cells[flip][:, [0, 2, 1]]
    return cells, int(flip.sum())


def _annulus_loop(X, ann_edges, ann_nodes, where: str) -> np.ndarray:
    """Annulus nodes in loop order (one closed loop), checked."""
    n_flagged = int(ann_nodes.sum())
    if n_flagged < 3:
        raise ValueError(f"{where}: only {n_flagged} leaflet node(s) have nonzero 'annulus' "
                         "point data; the annulus needs at least 3")
    if len(ann_edges) < 3:
        raise ValueError(f"{where}: the annulus nodes form {len(ann_edges)} boundary edge(s); "
                         "the annulus must be one closed loop of boundary edges")
    nodes, deg = np.unique(ann_edges, return_counts=True)
    off = np.setdiff1d(np.flatnonzero(ann_nodes), nodes)
    if len(off):
        raise ValueError(f"{where}: {len(off)} node(s) with nonzero 'annulus' point data are "
                         f"not on an annulus edge (a boundary edge between two annulus nodes), "
                         f"e.g. at {_at(X[off[0]])}")
    if np.any(deg != 2):
        k = nodes[np.flatnonzero(deg != 2)[0]]
        kind = "ends" if deg[nodes == k][0] == 1 else "branches"
        raise ValueError(f"{where}: the annulus edges do not form one closed loop: it {kind} "
                         f"at {_at(X[k])}")
    nbr: dict[int, list[int]] = {}
    for a, b in ann_edges.tolist():
        nbr.setdefault(a, []).append(b)
        nbr.setdefault(b, []).append(a)
    path = [int(nodes[0])]
    prev = -1
    while True:
        a, b = nbr[path[-1]]
        nxt = b if a == prev else a
        if nxt == path[0]:
            break
        prev = path[-1]
        path.append(nxt)
    if len(path) != len(nodes):
        raise ValueError(f"{where}: the annulus edges form several separate loops (one has "
                         f"{len(path)} of the {len(nodes)} annulus nodes); there must be one")
    return np.array(path)


def _loop_plane(loop_x: np.ndarray, where: str):
    """(centroid, unit normal) of a closed polyline, both weighted by arc length (so that
    unevenly spaced nodes do not tilt the plane): the normal is the least principal axis of
    the second moment of the curve about its centroid."""
    a, b = loop_x, np.roll(loop_x, -1, axis=0)
    seg = np.linalg.norm(b - a, axis=1)
    c = (0.5 * (a + b) * seg[:, None]).sum(0) / seg.sum()
    a, b = a - c, b - c
    # integral of x x^T over each straight segment
    m = (np.einsum("k,ki,kj->ij", seg, a, a) + np.einsum("k,ki,kj->ij", seg, b, b)) / 3.0 \
        + (np.einsum("k,ki,kj->ij", seg, a, b) + np.einsum("k,ki,kj->ij", seg, b, a)) / 6.0
    w, v = np.linalg.eigh(m)
    if w[1] < 1e-12 * w[2]:
        raise ValueError(f"{where}: the annulus nodes are collinear")
    return c, v[:, 0]


def _frame(X, cells, cell_leaflet, value_of, loop, centre, axis, area):
    """Rows: anterior (toward the anterior leaflet's centroid, in the annulus plane),
    commissural (axis x anterior), axis."""
    if "anterior" in value_of:
        target = value_of["anterior"]
    else:
        target = min(value_of.values())
    sel = cell_leaflet == target
    c = (X[cells[sel]].mean(axis=1) * area[sel, None]).sum(0) / area[sel].sum()
    e1 = c - centre
    e1 -= (e1 @ axis) * axis
    radius = np.linalg.norm(X[loop] - centre, axis=1).mean()
    if np.linalg.norm(e1) < 1e-3 * radius:  # centroid on the axis: the annulus's short axis
        d = X[loop] - centre
        d -= np.outer(d @ axis, axis)
        e1 = np.linalg.svd(d, full_matrices=False)[2][1]
        e1 -= (e1 @ axis) * axis
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    return np.array([e1, e2, axis])


def _ccw_from_anterior(X, loop, centre, frame):
    """The loop counter-clockwise about the axis, starting nearest the anterior half-axis."""
    d = X[loop] - centre
    u, v = d @ frame[0], d @ frame[1]
    if np.sum(u * np.roll(v, -1) - np.roll(u, -1) * v) < 0:
        loop = loop[::-1]
        u, v = u[::-1], v[::-1]
    return np.roll(loop, -int(np.argmin(np.abs(np.arctan2(v, u)))))


def _loop_edge_leaflets(loop, b_edges, b_tri, cell_leaflet):
    """Leaflet tag of each loop edge (loop[i], loop[i+1])."""
    of = {(min(a, b), max(a, b)): cell_leaflet[t] for (a, b), t in zip(b_edges.tolist(), b_tri)}
    nxt = np.roll(loop, -1)
    return np.array([of[(min(a, b), max(a, b))] for a, b in zip(loop.tolist(), nxt.tolist())])


def _commissures(X, loop, edge_leaflet, value_of, centre, frame):
    """(2, 3): where the annulus passes from one leaflet to another (the two ends of the
    anterior leaflet when there are more than two such points); with fewer than two, the
    annulus nodes farthest along +- the commissural axis. The +commissural one first."""
    prev = np.roll(edge_leaflet, 1)
    change = np.flatnonzero(prev != edge_leaflet)  # node loop[i] between edge i-1 and edge i
    if len(change) > 2 and "anterior" in value_of:
        a = value_of["anterior"]
        ends = change[(prev[change] == a) | (edge_leaflet[change] == a)]
        change = ends if len(ends) >= 2 else change
    if len(change) >= 2:
        pts = X[loop[change]]
        if len(change) > 2:  # the two farthest apart
            dist = np.linalg.norm(pts[:, None] - pts[None], axis=2)
            i, j = np.unravel_index(np.argmax(dist), dist.shape)
            pts = pts[[i, j]]
        else:
            pts = pts[:2]
    else:
        s = (X[loop] - centre) @ frame[1]
        pts = X[loop[[int(np.argmax(s)), int(np.argmin(s))]]]
    if (pts[0] - centre) @ frame[1] < (pts[1] - centre) @ frame[1]:
        pts = pts[::-1]
    return np.array(pts, dtype=float)


def _muscles(tips, centre, frame):
    """Muscle index of each tip (0 on the +commissural side, 1 on the other), as the
    generator assigns patient tips."""
    if len(tips) == 0:
        return np.zeros(0, dtype=np.int32)
    y = (tips - centre) @ frame[1]
    if len(tips) == 1:
        return np.array([0 if y[0] >= 0 else 1], dtype=np.int32)
    mid = 0.5 * (y.min() + y.max())
    return np.where(y >= mid, 0, 1).astype(np.int32)


def _chordae(points, X, lines, local, tips_idx, on_papillary, has_papillary, line_data,
             cells, cell_leaflet, free_nodes, where: str) -> dict:
    """Reduce the chordal trees to one tether per insertion (see the module docstring)."""
    empty = {"points": np.zeros((0, 3)), "leaflet": np.zeros(0, dtype=np.int32),
             "family": np.zeros(0, dtype="<U8"), "tip": np.zeros(0, dtype=np.int32),
             "path_length": np.zeros(0), "tree_length": np.zeros(0), "trees": 0,
             "branch_points": 0}
    if len(lines) == 0:
        return empty
    if not has_papillary:
        raise ValueError(f"{where}: {len(lines)} line cells (chordae) but no 'papillary' point "
                         "data to root them (nonzero on the papillary tips)")
    seg_len = np.linalg.norm(points[lines[:, 1]] - points[lines[:, 0]], axis=1)
    if np.any(lines[:, 0] == lines[:, 1]):
        k = np.flatnonzero(lines[:, 0] == lines[:, 1])[0]
        raise ValueError(f"{where}: a chordae line cell has zero length (both ends at "
                         f"{_at(points[lines[k, 0]])})")
    rest = seg_len.copy()
    if "rest_length" in line_data:
        given = np.asarray(line_data["rest_length"], dtype=float).reshape(len(lines), -1)[:, 0]
        rest = np.where(given > 0, given, seg_len)
    codes = np.full(len(lines), -1)
    if "family" in line_data:
        codes = np.asarray(line_data["family"]).reshape(len(lines), -1)[:, 0]
        ok = np.isin(codes, [-1, *FAMILY_CODES])
        if not ok.all():
            raise ValueError(f"{where}: line cell data 'family' must be 0 (marginal), 1 (strut), "
                             f"2 (basal) or -1 (not given), got {codes[~ok][0]!r}")
        codes = codes.astype(np.int64)
    key = np.sort(lines, axis=1)
    _, count = np.unique(key, axis=0, return_counts=True)
    if np.any(count > 1):
        raise ValueError(f"{where}: a chordae line cell is given twice (a cycle)")

    nbr: dict[int, list[tuple[int, int]]] = {}
    for s, (a, b) in enumerate(lines.tolist()):
        nbr.setdefault(a, []).append((b, s))
        nbr.setdefault(b, []).append((a, s))
    tip_number = {int(t): i for i, t in enumerate(tips_idx)}
    seen: set[int] = set()
    out = []  # (segment reaching the insertion, insertion node, tip, path, tree length, code)
    trees = branch = 0
    for start in sorted(nbr):
        if start in seen:
            continue
        comp, stack = [], [start]
        seen.add(start)
        while stack:
            v = stack.pop()
            comp.append(v)
            for w, _ in nbr[v]:
                if w not in seen:
                    seen.add(w)
                    stack.append(w)
        n_edges = sum(len(nbr[v]) for v in comp) // 2
        near = _at(points[comp[0]])
        if n_edges != len(comp) - 1:
            raise ValueError(f"{where}: the chordae lines near {near} form a cycle (a chordal "
                             "tree must not close on itself)")
        roots = [v for v in comp if on_papillary[v]]
        if not roots:
            raise ValueError(f"{where}: a chordal tree near {near} has no root: none of its "
                             f"{len(comp)} nodes has nonzero 'papillary' point data")
        if len(roots) > 1:
            raise ValueError(f"{where}: chordae lines connect {len(roots)} papillary roots (at "
                             f"{_at(points[roots[0]])} and {_at(points[roots[1]])}); each tree "
                             "needs exactly one")
        root = roots[0]
        trees += 1
        for v in comp:
            if v != root and local[v] < 0:
                if len(nbr[v]) == 1:
                    raise ValueError(f"{where}: a chord ends in space at {_at(points[v])} "
                                     "(neither a leaflet node nor a papillary tip)")
                branch += 1
        # walk from the root: path lengths
        path = {root: 0.0}
        tree = {root: 0.0}
        stack = [root]
        while stack:
            v = stack.pop()
            for w, s in nbr[v]:
                if w in path:
                    continue
                path[w] = path[v] + rest[s]
                tree[w] = tree[v] + seg_len[s]
                stack.append(w)
                if local[w] >= 0:
                    out.append((s, w, tip_number[root], path[w], tree[w], int(codes[s])))
    if not out:
        return {**empty, "trees": trees, "branch_points": branch}
    out.sort()
    node = np.array([local[w] for _, w, *_ in out])
    leaflet = np.empty(len(node), dtype=np.int32)
    for i, k in enumerate(node):  # the leaflet most of the node's cells belong to
        vals, n = np.unique(cell_leaflet[(cells == k).any(axis=1)], return_counts=True)
        leaflet[i] = vals[np.argmax(n)]
    family = np.array([FAMILY_CODES[c] if c >= 0 else ("marginal" if free_nodes[k] else "basal")
                       for (*_, c), k in zip(out, node)])
    return {"points": X[node], "leaflet": leaflet, "family": family,
            "tip": np.array([o[2] for o in out], dtype=np.int32),
            "path_length": np.array([o[3] for o in out]),
            "tree_length": np.array([o[4] for o in out]),
            "trees": trees, "branch_points": branch}


def _at(x) -> str:
    return "(" + ", ".join(f"{float(c):.4g}" for c in np.ravel(x)) + ")"


# --- writing ---------------------------------------------------------------------------------

def chord_lengths(valve: ValveMesh) -> np.ndarray:
    """The unstretched length of each chord of ``valve`` (before the scene's length factor),
    as ``mvfem.model`` takes it: an imported valve's path lengths; for a generated valve the
    distance from the tip to where the designed closed valve puts the insertion
    (``insertion_closed``); otherwise the distance from the tip to the insertion."""
    anchor = valve.papillary_tips[valve.insertion_tip]
    length = getattr(valve, "insertion_path_length", None)
    if length is not None and len(length) == len(anchor):
        return np.asarray(length, dtype=float)
    target = getattr(valve, "insertion_closed", None)
    if target is None or len(target) != len(anchor):
        target = valve.insertion_points
    return np.linalg.norm(target - anchor, axis=1)


def write_valve_with_chordae(path: str | os.PathLike, valve: ValveMesh) -> None:
    """Write ``valve`` as an imported-valve file with its chordae: what
    :func:`mvfem.meshes.valve.write_valve` writes (cell data ``leaflet``, point data
    ``annulus``), plus the papillary tips (point data ``papillary`` = 1) and one straight line
    cell per chord from its tip to its insertion, with line cell data ``family`` (0 marginal,
    1 strut, 2 basal) and ``rest_length`` (:func:`chord_lengths`), so that the valve read back
    by :func:`valve_from_file` has the same chordae.

    Collective over the mesh's communicator; rank 0 writes.

    Raises:
        ValueError: the format (by extension) is not one of :data:`FORMATS`, which keep line
            cells and point data.
    """
    import meshio
    from scipy.spatial import cKDTree

    if os.path.splitext(os.fspath(path))[1].lower() not in FORMATS:
        raise ValueError(f"{os.fspath(path)}: a valve file needs line cells and point data: "
                         f"use {', '.join(FORMATS)}")
    comm = valve.mesh.comm
    tmp = tempfile.mkdtemp(prefix="mvfem-valve-") if comm.rank == 0 else None
    err = None
    try:
        write_valve(os.path.join(tmp, "valve.vtu") if tmp else "unused.vtu", valve)
        if comm.rank == 0:
            raw = read_surface(os.path.join(tmp, "valve.vtu"))
            X, tri = raw.points, raw.triangles
            tips = np.asarray(valve.papillary_tips, dtype=float).reshape(-1, 3)
            dist, node = cKDTree(X).query(np.asarray(valve.insertion_points).reshape(-1, 3))
            scale = float(np.linalg.norm(np.ptp(X, axis=0)))
            if np.any(dist > 1e-9 * scale):
                raise ValueError("write_valve_with_chordae: an insertion point is not a mesh node")
            k = len(node)
            lines = np.column_stack([len(X) + np.asarray(valve.insertion_tip), node])
            codes = np.array([_CODE_OF_FAMILY.get(str(f), -1) for f in valve.insertion_family],
                             dtype=np.int32)
            points = np.vstack([X, tips])
            papillary = np.concatenate([np.zeros(len(X)), np.ones(len(tips))]).astype(np.int32)
            annulus = np.concatenate([raw.point_data["annulus"],
                                      np.zeros(len(tips))]).astype(np.int32)
            cells = [("triangle", tri)]
            data = {"leaflet": [raw.cell_data["leaflet"].astype(np.int32)],
                    "family": [np.full(len(tri), -1, dtype=np.int32)],
                    "rest_length": [np.zeros(len(tri))]}
            if k:
                cells.append(("line", lines.astype(np.int64)))
                data["leaflet"].append(np.zeros(k, dtype=np.int32))
                data["family"].append(codes)
                data["rest_length"].append(chord_lengths(valve))
            meshio.write(os.fspath(path), meshio.Mesh(
                points, cells, point_data={"annulus": annulus, "papillary": papillary},
                cell_data=data))
    except Exception as exc:  # noqa: BLE001 - shared with every rank below
        err = exc
    finally:
        if tmp:
            shutil.rmtree(tmp, ignore_errors=True)
    _raise_from_root(comm, err if comm.rank == 0 else None)
    if err is not None:
        raise err
