"""Surface meshes in and out: meshio files <-> numpy arrays <-> distributed dolfinx meshes.

meshio is imported here and nowhere else in mvfem. Files are read and written by one rank
(the caller chooses which); :func:`mesh_from_arrays` and :func:`to_dolfinx` take the arrays
of rank 0 and distribute the mesh over the communicator.
"""

from __future__ import annotations

import os
from contextlib import redirect_stderr, redirect_stdout
from dataclasses import dataclass, field
from io import StringIO

import numpy as np

__all__ = ["RawSurface", "read_surface", "write_surface", "write_raw_surface", "to_dolfinx",
           "mesh_from_arrays", "read_points"]

# gmsh/VTK node order of a 6-node triangle (v0 v1 v2 m01 m12 m20) -> dolfinx's
# (v0 v1 v2, then the midpoint of the edge opposite v0, v1, v2: m12 m20 m01)
_TRI6_TO_DOLFINX = np.array([0, 1, 2, 4, 5, 3])


@dataclass
class RawSurface:
    """A triangulated surface as plain arrays (what :func:`read_surface` returns).

    Attributes:
        points: (N, 3) node coordinates (2-D files get z = 0).
        triangles: (M, 3) node indices; quads are split into two triangles each.
        point_data: name -> array with N rows.
        cell_data: name -> array with M rows (a quad's value repeated for its two triangles).
        lines: (K, 2) node indices of line cells in the file ((0, 2) if none).
        line_data: name -> array with K rows, for the data given on line cells.
    """

    points: np.ndarray
    triangles: np.ndarray
    point_data: dict = field(default_factory=dict)
    cell_data: dict = field(default_factory=dict)
    lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    line_data: dict = field(default_factory=dict)


def read_points(path: str | os.PathLike) -> np.ndarray:
    """(N, 3) points from a CSV file of x, y, z rows (``#`` comments or one header line).

    Raises:
        ValueError: the file is not such a CSV, or holds non-finite values.
    """
    try:
        pts = np.loadtxt(path, delimiter=",", ndmin=2, comments="#")
    except ValueError:
        try:
            pts = np.loadtxt(path, delimiter=",", ndmin=2, skiprows=1)
        except ValueError as e:
            raise ValueError(f"{path}: not a CSV of x, y, z rows ({e})") from None
    if pts.shape[1] != 3:
        raise ValueError(f"{path}: expected x, y, z columns, got {pts.shape[1]}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{path}: non-finite values")
    return pts


def read_surface(path: str | os.PathLike) -> RawSurface:
    """Read a triangle/quad surface mesh with meshio (any format meshio knows: .vtu, .vtk, .msh,
    .stl, .obj, .ply, .xdmf, ...).

    Quads ``(a, b, c, d)`` are split into ``(a, b, c)`` and ``(a, c, d)``, which keeps their
    orientation. Cells other than triangles, quads and lines (e.g. vertices, tetrahedra) are
    ignored. Points are kept as in the file, so ``point_data`` stays aligned with them.

    Args:
        path: the file.

    Returns:
        The surface as arrays.

    Raises:
        ValueError: the file is missing, meshio cannot read it, or it has no triangle or quad cells.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise ValueError(f"surface mesh file not found: {path!r}")
    said = StringIO()
    try:
        with redirect_stdout(said), redirect_stderr(said):
            m = meshio.read(path)
    # meshio raises ReadError, KeyError, ValueError, ... by format; 5.0 calls sys.exit(1) when
    # the reader for the extension fails
    except (Exception, SystemExit) as err:
        detail = " ".join(said.getvalue().split()) or f"{type(err).__name__}: {err}"
        raise ValueError(f"cannot read surface mesh {path!r}: {detail}") from err

    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise ValueError(f"surface mesh {path!r}: points of shape {points.shape}, "
                         "expected (N, 2) or (N, 3)")
    if points.shape[1] == 2:
        points = np.column_stack([points, np.zeros(len(points))])

    triangles, lines = [], []
    cell_data: dict[str, list] = {}
    line_data: dict[str, list] = {}
    for i, block in enumerate(m.cells):
        data = {name: np.asarray(values[i]) for name, values in m.cell_data.items()}
        c = np.asarray(block.data, dtype=np.int64)
        if block.type == "triangle":
            triangles.append(c)
            _append(cell_data, data)
        elif block.type == "quad":
            triangles.append(np.stack([c[:, [0, 1, 2]], c[:, [0, 2, 3]]], axis=1).reshape(-1, 3))
            _append(cell_data, {k: np.repeat(v, 2, axis=0) for k, v in data.items()})
        elif block.type == "line":
            lines.append(c)
            _append(line_data, data)
    if not triangles:
        found = ", ".join(sorted({b.type for b in m.cells})) or "none"
        raise ValueError(f"surface mesh {path!r} has no triangle or quad cells "
                         f"(cell types: {found})")

    ntri = sum(len(t) for t in triangles)
    nline = sum(len(c) for c in lines)
    return RawSurface(
        points=points,
        triangles=np.concatenate(triangles),
        point_data={k: np.asarray(v) for k, v in m.point_data.items()},
        cell_data=_complete(cell_data, ntri),
        lines=np.concatenate(lines) if lines else np.zeros((0, 2), dtype=np.int64),
        line_data=_complete(line_data, nline),
    )


def _append(store: dict, data: dict) -> None:
    for name, values in data.items():
        store.setdefault(name, []).append(values)


def _complete(store: dict, n: int) -> dict:
    """Concatenate per-block arrays; drop names not given on every block of that kind."""
    out = {}
    for name, parts in store.items():
        values = np.concatenate(parts)
        if len(values) == n:
            out[name] = values
    return out


def write_surface(path: str | os.PathLike, points: np.ndarray, triangles: np.ndarray,
                  point_data: dict | None = None, cell_data: dict | None = None) -> None:
    """Write a triangle surface with meshio; the format follows the file extension.

    Call it on one rank (it writes the arrays it is given).

    Args:
        path: output file (.vtu, .vtk, .xdmf, .msh, .stl, ...).
        points: (N, 3) coordinates.
        triangles: (M, 3) node indices.
        point_data: name -> array with N rows.
        cell_data: name -> array with M rows.
    """
    import meshio

    mesh = meshio.Mesh(
        np.asarray(points, dtype=np.float64),
        [("triangle", np.asarray(triangles, dtype=np.int64))],
        point_data={k: np.asarray(v) for k, v in (point_data or {}).items()},
        cell_data={k: [np.asarray(v)] for k, v in (cell_data or {}).items()},
    )
    meshio.write(os.fspath(path), mesh)


def write_raw_surface(path: str | os.PathLike, raw: RawSurface) -> None:
    """Write a :class:`RawSurface` (triangles and line cells with their data, point data) with
    meshio: what :func:`read_surface` reads back. Data given only on triangles or only on lines
    is filled with -1 on the other block. Call it on one rank."""
    import meshio

    tri = np.asarray(raw.triangles, dtype=np.int64).reshape(-1, 3)
    lines = np.asarray(raw.lines, dtype=np.int64).reshape(-1, 2)
    cells = [("triangle", tri)] + ([("line", lines)] if len(lines) else [])
    names = list(dict.fromkeys([*raw.cell_data, *raw.line_data]))
    data = {}
    for name in names:
        t = raw.cell_data.get(name)
        ln = raw.line_data.get(name)
        like = t if t is not None else ln
        dtype = np.asarray(like).dtype
        data[name] = [np.asarray(t) if t is not None else np.full(len(tri), -1, dtype)]
        if len(lines):
            data[name].append(np.asarray(ln) if ln is not None
                             else np.full(len(lines), -1, dtype))
    meshio.write(os.fspath(path), meshio.Mesh(
        np.asarray(raw.points, dtype=np.float64), cells,
        point_data={k: np.asarray(v) for k, v in raw.point_data.items()}, cell_data=data))


def to_dolfinx(comm, raw: RawSurface | None, cell_values: np.ndarray | None = None):
    """Build a distributed dolfinx surface mesh (P1 triangles, gdim 3) from rank 0's arrays.

    Args:
        comm: MPI communicator.
        raw: the surface on rank 0 (ignored, may be None, on other ranks).
        cell_values: on rank 0, one integer per triangle of ``raw`` (e.g. leaflet labels), or None.
            Must be None on every rank or on none.

    Returns:
        ``(mesh, cell_tags)``; ``cell_tags`` is None when ``cell_values`` is None.
    """
    points = cells = err = None
    if comm.rank == 0:
        try:
            points, cells = raw.points, raw.triangles
        except AttributeError as e:
            err = TypeError(f"to_dolfinx needs a RawSurface on rank 0, got {type(raw).__name__}")
            err.__cause__ = e
    _raise_from_root(comm, err)
    has_values = comm.bcast(cell_values is not None, root=0)
    msh, cell_tags, _ = mesh_from_arrays(comm, points, cells,
                                         cell_values if has_values else None)
    return msh, (cell_tags if has_values else None)


def mesh_from_arrays(comm, points: np.ndarray | None, cells: np.ndarray | None,
                     cell_values: np.ndarray | None = None, edges: np.ndarray | None = None,
                     edge_values: np.ndarray | None = None, order: int = 1):
    """Distribute a triangle surface given as arrays on rank 0; carry cell and edge tags across.

    Only rank 0's arrays are used (other ranks may pass None). Node indices refer to rows of
    rank 0's ``points``. ``create_mesh`` renumbers and distributes nodes and cells; the tags
    follow through ``dolfinx.io.distribute_entity_data`` (entities given in input node numbers)
    and ``dolfinx.mesh.meshtags_from_entities``, as dolfinx 0.5's own gmsh reader does.

    Args:
        comm: MPI communicator.
        points: (N, 3) coordinates on rank 0.
        cells: (M, 3) triangles (order 1), or (M, 6) in gmsh/VTK node order
            v0 v1 v2 m01 m12 m20 (order 2).
        cell_values: (M,) integer tags, or None (the cell MeshTags is then empty).
        edges: (K, 2) or (K, 3) edges (vertices, then the midpoint for order 2), or None.
        edge_values: (K,) integer tags of ``edges``.
        order: geometry degree, 1 or 2.

    Returns:
        ``(mesh, cell_tags, facet_tags)``: a dolfinx mesh (tdim 2, gdim 3) and two int32
        MeshTags (dimension 2 and 1), empty where no values were given.
    """
    import ufl
    from dolfinx import cpp, io, mesh

    if order not in (1, 2):
        raise ValueError(f"geometry order must be 1 or 2, got {order}")
    nodes_per_cell = 3 if order == 1 else 6
    nodes_per_edge = 2 if order == 1 else 3
    flags = err = None
    if comm.rank == 0:
        try:
            x, c, cv, e, ev = _checked(points, cells, cell_values, edges, edge_values, order)
            flags = (cv is not None, e is not None)
        except (ValueError, TypeError, IndexError) as exc:
            err = exc
    else:
        x = np.zeros((0, 3))
        c = np.zeros((0, nodes_per_cell), dtype=np.int64)
    _raise_from_root(comm, err)
    has_cell_values, has_edges = comm.bcast(flags, root=0)
    if comm.rank != 0:
        cv = np.zeros(0, dtype=np.int32) if has_cell_values else None
        e = np.zeros((0, nodes_per_edge), dtype=np.int64) if has_edges else None
        ev = np.zeros(0, dtype=np.int32) if has_edges else None

    cell = ufl.Cell("triangle", geometric_dimension=3)
    domain = ufl.Mesh(ufl.VectorElement("Lagrange", cell, order))
    msh = mesh.create_mesh(comm, c, x, domain)
    tdim = msh.topology.dim

    msh.topology.create_connectivity(tdim, 0)
    if has_cell_values:
        ent, val = io.distribute_entity_data(_cpp_mesh(msh), tdim, c, cv)
        cell_tags = mesh.meshtags_from_entities(msh, tdim, cpp.graph.AdjacencyList_int32(ent),
                                                val.astype(np.int32))
    else:
        cell_tags = mesh.meshtags(msh, tdim, np.zeros(0, dtype=np.int32),
                                  np.zeros(0, dtype=np.int32))
    cell_tags.name = "cell_tags"

    msh.topology.create_connectivity(tdim - 1, tdim)
    if has_edges:
        ent, val = io.distribute_entity_data(_cpp_mesh(msh), tdim - 1, e, ev)
        facet_tags = mesh.meshtags_from_entities(msh, tdim - 1, cpp.graph.AdjacencyList_int32(ent),
                                                 val.astype(np.int32))
    else:
        facet_tags = mesh.meshtags(msh, tdim - 1, np.zeros(0, dtype=np.int32),
                                   np.zeros(0, dtype=np.int32))
    facet_tags.name = "facet_tags"
    return msh, cell_tags, facet_tags


def _checked(points, cells, cell_values, edges, edge_values, order: int):
    """Rank 0's arrays as contiguous float64/int64/int32, cells in dolfinx node order."""
    nodes_per_cell, nodes_per_edge = 3 * order, order + 1
    x = np.ascontiguousarray(np.asarray(points, dtype=np.float64))
    if x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {x.shape}")
    c = np.asarray(cells, dtype=np.int64)
    if c.ndim != 2 or c.shape[1] != nodes_per_cell:
        raise ValueError(f"order-{order} cells must have shape (M, {nodes_per_cell}), "
                         f"got {c.shape}")
    if len(c) == 0 or c.min() < 0 or c.max() >= len(x):
        raise ValueError(f"cells must be non-empty and index the {len(x)} points")
    if order == 2:
        c = c[:, _TRI6_TO_DOLFINX]
    cv = None if cell_values is None else np.asarray(cell_values, dtype=np.int32).ravel()
    if cv is not None and len(cv) != len(c):
        raise ValueError(f"{len(cv)} cell values for {len(c)} cells")
    if (edges is None) != (edge_values is None):
        raise ValueError("edges and edge_values must be given together")
    e = ev = None
    if edges is not None:
        e = np.asarray(edges, dtype=np.int64).reshape(-1, nodes_per_edge)
        ev = np.asarray(edge_values, dtype=np.int32).ravel()
        if len(e) != len(ev):
            raise ValueError(f"{len(ev)} edge values for {len(e)} edges")
    return x, np.ascontiguousarray(c), cv, e, ev


def _raise_from_root(comm, err: BaseException | None) -> None:
    """Collective: re-raise rank 0's error ``err`` (None: no error) on every rank, so that a
    failure of work done on rank 0 only does not leave the other ranks waiting."""
    said = comm.bcast(None if err is None else f"{type(err).__name__}: {err}", root=0)
    if said is None:
        return
    if comm.rank == 0:
        raise err
    raise RuntimeError(f"rank 0 failed: {said}")


def _root_or_error(comm, work):
    """Collective: run ``work`` on rank 0 and return its result there (None elsewhere); its
    ValueError (bad input) is raised on every rank with the same message, any other error as
    :func:`_raise_from_root` does."""
    result = err = None
    if comm.rank == 0:
        try:
            result = work()
        except Exception as exc:  # noqa: BLE001 - re-raised on every rank below (gmsh
            err = exc             # raises plain Exception)
    bad = comm.bcast(str(err) if isinstance(err, ValueError) else None, root=0)
    if bad is not None:
        if comm.rank == 0:
            raise err
        raise ValueError(bad)
    _raise_from_root(comm, err)
    return result


def _cpp_mesh(msh):
    """The C++ mesh behind a dolfinx Python mesh (``_mesh`` in 0.5, ``_cpp_object`` later)."""
    for attr in ("_mesh", "_cpp_object"):
        if hasattr(msh, attr):
            return getattr(msh, attr)
    return msh
