"""Parametric membrane surfaces made with gmsh: disk, square, sphere, tube.

gmsh runs on rank 0 only; the triangles are oriented there (normal +z for flat shapes, outward
for closed or tubular ones), then distributed over the communicator as a dolfinx mesh (tdim 2,
gdim 3) with named cell and edge tags (:class:`SurfaceMesh`). Lengths in millimetres.
"""

from __future__ import annotations

import json
import logging
import os
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from .io import _raise_from_root, mesh_from_arrays

__all__ = ["SurfaceMesh", "disk", "square", "sphere", "tube"]

logger = logging.getLogger(__name__)

# gmsh element types: 3- and 6-node triangles, 2- and 3-node lines
_TRIANGLE = {1: 2, 2: 9}
_LINE = {1: 1, 2: 8}
# swap v1 and v2 of a gmsh 6-node triangle (v0 v1 v2 m01 m12 m20) and its edge midpoints
_FLIP = {1: np.array([0, 2, 1]), 2: np.array([0, 2, 1, 5, 4, 3])}


@dataclass
class SurfaceMesh:
    """A distributed membrane mesh with named tags.

    Attributes:
        mesh: dolfinx mesh, triangles, tdim 2, gdim 3.
        cell_tags: int32 MeshTags on cells (dim 2), e.g. ``"membrane"``.
        facet_tags: int32 MeshTags on edges (dim 1), e.g. ``"boundary"``, ``"top"``.
        names: group name -> tag value; values are unique over cell and facet groups.
        info: the generator's name and parameters (JSON-serialisable).
    """

    mesh: Any
    cell_tags: Any
    facet_tags: Any
    names: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def cells(self, *names: str) -> np.ndarray:
        """Local indices of the cells in any of the named groups."""
        return _find(self.cell_tags, [self.names[n] for n in names])

    def facets(self, *names: str) -> np.ndarray:
        """Local indices of the edges in any of the named groups."""
        return _find(self.facet_tags, [self.names[n] for n in names])

    def write_info(self, path: str | os.PathLike) -> None:
        """Write ``{"info": ..., "names": ...}`` as JSON (on rank 0 of the mesh's communicator)."""
        if self.mesh.comm.rank == 0:
            with open(path, "w") as f:
                json.dump({"info": self.info, "names": self.names}, f, indent=2)
                f.write("\n")


def _find(tags, values) -> np.ndarray:
    return np.sort(tags.indices[np.isin(tags.values, values)]).astype(np.int32)


def disk(comm, *, radius: float = 10.0, size: float = 0.5,
         centre: Sequence[float] = (0.0, 0.0, 0.0), order: int = 1) -> SurfaceMesh:
    """A flat disk in the plane z = centre[2], normal +z.

    Args:
        comm: MPI communicator (gmsh runs on its rank 0).
        radius: disk radius, mm.
        size: target edge length, mm.
        centre: disk centre, mm.
        order: geometry degree, 1 (straight triangles) or 2 (boundary nodes on the circle).

    Returns:
        Cells tagged ``"membrane"``, the outer circle ``"boundary"``. Every cell is
        counter-clockwise seen from +z: cross(dX/dxi1, dX/dxi2) points along +z.
    """
    c = _point(centre)
    info = {"generator": "disk", "radius": float(radius), "size": float(size), "centre": c,
            "order": int(order)}
    _check_positive(radius=radius, size=size)

    def build(gmsh):
        s = gmsh.model.occ.addDisk(*c, radius, radius)
        gmsh.model.occ.synchronize()
        curves = [t for _, t in gmsh.model.getBoundary([(2, s)], oriented=False)]
        return {"membrane": (2, [s]), "boundary": (1, curves)}

    return _generate(comm, build, _plus_z, size, order, info)


def square(comm, *, side: float = 10.0, size: float = 0.5, centred: bool = False,
           sides: bool = False, order: int = 1) -> SurfaceMesh:
    """A flat square in the xy plane (z = 0), normal +z.

    Args:
        comm: MPI communicator (gmsh runs on its rank 0).
        side: side length, mm.
        size: target edge length, mm.
        centred: False for ``[0, side]^2`` (as :func:`square_patch`), True for
            ``[-side/2, side/2]^2``.
        sides: tag the four sides ``"left"`` (x min), ``"right"``, ``"bottom"`` (y min),
            ``"top"`` separately instead of one ``"boundary"`` group.
        order: geometry degree, 1 or 2.

    Returns:
        Cells tagged ``"membrane"``; boundary edges ``"boundary"`` or the four sides.
    """
    info = {"generator": "square", "side": float(side), "size": float(size),
            "centred": bool(centred), "sides": bool(sides), "order": int(order)}
    _check_positive(side=side, size=size)
    x0 = -0.5 * side if centred else 0.0

    def build(gmsh):
        s = gmsh.model.occ.addRectangle(x0, x0, 0.0, side, side)
        gmsh.model.occ.synchronize()
        curves = [t for _, t in gmsh.model.getBoundary([(2, s)], oriented=False)]
        groups = {"membrane": (2, [s])}
        if not sides:
            groups["boundary"] = (1, curves)
            return groups
        tol = 1e-6 * side
        where = {t: gmsh.model.occ.getCenterOfMass(1, t) for t in curves}
        for name, axis, value in [("left", 0, x0), ("right", 0, x0 + side),
                                  ("bottom", 1, x0), ("top", 1, x0 + side)]:
            groups[name] = (1, [t for t, p in where.items() if abs(p[axis] - value) < tol])
        return groups

    return _generate(comm, build, _plus_z, size, order, info)


def sphere(comm, *, radius: float = 10.0, size: float = 1.0,
           centre: Sequence[float] = (0.0, 0.0, 0.0), order: int = 1) -> SurfaceMesh:
    """A closed sphere, normals outward.

    Args:
        comm: MPI communicator (gmsh runs on its rank 0).
        radius: sphere radius, mm.
        size: target edge length, mm.
        centre: sphere centre, mm.
        order: geometry degree, 1 or 2 (nodes on the sphere).

    Returns:
        Cells tagged ``"membrane"``; no edges tagged (the sphere has no boundary).
        cross(dX/dxi1, dX/dxi2) points away from the centre in every cell.
    """
    c = _point(centre)
    info = {"generator": "sphere", "radius": float(radius), "size": float(size), "centre": c,
            "order": int(order)}
    _check_positive(radius=radius, size=size)

    def build(gmsh):
        v = gmsh.model.occ.addSphere(*c, radius)
        gmsh.model.occ.synchronize()
        surfaces = [t for _, t in gmsh.model.getBoundary([(3, v)], oriented=False)]
        return {"membrane": (2, surfaces)}

    def outward(xc):
        return xc - np.asarray(c)

    return _generate(comm, build, outward, size, order, info)


def tube(comm, *, radius: float = 5.0, length: float = 20.0, size: float = 0.5,
         base: Sequence[float] = (0.0, 0.0, 0.0), order: int = 1) -> SurfaceMesh:
    """An open circular cylinder along +z, normals outward.

    Args:
        comm: MPI communicator (gmsh runs on its rank 0).
        radius: tube radius, mm.
        length: tube length along z, mm.
        size: target edge length, mm.
        base: centre of the bottom circle, mm; the top circle is at ``base + (0, 0, length)``.
        order: geometry degree, 1 or 2 (nodes on the cylinder).

    Returns:
        Cells tagged ``"membrane"``; end circles ``"bottom"`` and ``"top"`` (e.g. to clamp).
        cross(dX/dxi1, dX/dxi2) points away from the axis in every cell.
    """
    b = _point(base)
    info = {"generator": "tube", "radius": float(radius), "length": float(length),
            "size": float(size), "base": b, "order": int(order)}
    _check_positive(radius=radius, length=length, size=size)

    def build(gmsh):
        occ = gmsh.model.occ
        circle = occ.addCircle(*b, radius)
        surfaces = [t for d, t in occ.extrude([(1, circle)], 0.0, 0.0, length) if d == 2]
        occ.synchronize()
        curves = [t for _, t in gmsh.model.getBoundary([(2, s) for s in surfaces],
                                                        oriented=False)]
        z = {t: gmsh.model.occ.getCenterOfMass(1, t)[2] for t in curves}
        tol = 1e-6 * length
        return {"membrane": (2, surfaces),
                "bottom": (1, [t for t in curves if abs(z[t] - b[2]) < tol]),
                "top": (1, [t for t in curves if abs(z[t] - b[2] - length) < tol])}

    def outward(xc):
        d = xc - np.asarray(b)
        d[:, 2] = 0.0
        return d

    return _generate(comm, build, outward, size, order, info)


# --- gmsh on rank 0 -> oriented arrays -> distributed dolfinx mesh ---------------------------

def _plus_z(xc: np.ndarray) -> np.ndarray:
    return np.broadcast_to(np.array([0.0, 0.0, 1.0]), xc.shape)


def _point(p: Sequence[float]) -> list[float]:
    p = [float(v) for v in p]
    if len(p) != 3:
        raise ValueError(f"expected a 3-D point, got {p}")
    return p


def _check_positive(**values: float) -> None:
    for name, v in values.items():
        if not v > 0:
            raise ValueError(f"{name} must be positive, got {v}")


def _generate(comm, build: Callable, direction: Callable[[np.ndarray], np.ndarray],
              size: float, order: int, info: dict) -> SurfaceMesh:
    """Run ``build`` in gmsh on rank 0, mesh it, orient the cells along ``direction``
    (a function of cell centroids), distribute, and tag."""
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    arrays = names = err = None
    if comm.rank == 0:
        try:
            arrays, names = _mesh_on_root(build, direction, size, order, info["generator"])
        except Exception as exc:  # gmsh raises plain Exception
            err = exc
    _raise_from_root(comm, err)
    names = comm.bcast(names, root=0)
    if comm.rank != 0:
        arrays = (None,) * 5
    msh, cell_tags, facet_tags = mesh_from_arrays(comm, *arrays, order=order)
    return SurfaceMesh(msh, cell_tags, facet_tags, names, dict(info))


def _mesh_on_root(build: Callable, direction: Callable, size: float, order: int, name: str):
    """gmsh model -> physical groups -> mesh -> oriented arrays, and group name -> value."""
    with _gmsh_model(name) as gmsh:
        groups = build(gmsh)
        names = {}
        for value, (group, (dim, tags)) in enumerate(groups.items(), start=1):
            if not tags:
                raise RuntimeError(f"{name}: no gmsh entities for {group!r}")
            gmsh.model.addPhysicalGroup(dim, tags, value)
            gmsh.model.setPhysicalName(dim, value, group)
            names[group] = value
        _set_options(gmsh, {"Mesh.MeshSizeMin": size, "Mesh.MeshSizeMax": size,
                            "Mesh.MeshSizeFromPoints": 0, "Mesh.MeshSizeExtendFromBoundary": 0,
                            "Mesh.Algorithm": 6})
        gmsh.model.mesh.generate(2)
        if order > 1:
            gmsh.model.mesh.setOrder(order)
        arrays = _extract(gmsh, order)
    points, cells = arrays[0], arrays[1]
    flipped = _orient(points, cells, direction, order)
    logger.debug("%s: %d cells, %d vertices, %d cells flipped", name, len(cells), len(points),
                 flipped)
    return arrays, names


def _extract(gmsh, order: int):
    """Physical groups of the current gmsh model -> compact arrays
    ``(points, cells, cell_values, edges, edge_values)`` (nodes renumbered from 0)."""
    etype = {2: _TRIANGLE[order], 1: _LINE[order]}
    width = {2: 3 * order, 1: order + 1}  # nodes per element
    blocks = {2: ([], []), 1: ([], [])}
    for dim, value in gmsh.model.getPhysicalGroups():
        if dim not in blocks:
            continue
        for entity in gmsh.model.getEntitiesForPhysicalGroup(dim, value):
            _, nodes = gmsh.model.mesh.getElementsByType(etype[dim], entity)
            nodes = np.asarray(nodes, dtype=np.int64).reshape(-1, width[dim])
            blocks[dim][0].append(nodes)
            blocks[dim][1].append(np.full(len(nodes), value, dtype=np.int32))
    cells, edges = (np.concatenate(blocks[d][0]) if blocks[d][0]
                    else np.zeros((0, width[d]), dtype=np.int64) for d in (2, 1))
    cell_values, edge_values = (np.concatenate(blocks[d][1]) if blocks[d][1]
                                else np.zeros(0, dtype=np.int32) for d in (2, 1))

    tags, coords, _ = gmsh.model.mesh.getNodes()
    tags = np.asarray(tags, dtype=np.int64)
    coords = np.asarray(coords, dtype=np.float64).reshape(-1, 3)
    used = np.unique(cells)
    sort = np.argsort(tags)
    points = coords[sort[np.searchsorted(tags, used, sorter=sort)]]
    return (points, np.searchsorted(used, cells), cell_values, np.searchsorted(used, edges),
            edge_values)


def _orient(points: np.ndarray, cells: np.ndarray, direction, order: int) -> int:
    """Flip (in place) the cells whose normal cross(x1 - x0, x2 - x0) points against
    ``direction(centroid)``; return how many were flipped."""
    x0, x1, x2 = (points[cells[:, i]] for i in range(3))
    normal = np.cross(x1 - x0, x2 - x0)
    wrong = np.einsum("ij,ij->i", normal, direction((x0 + x1 + x2) / 3.0)) < 0
    cells[wrong] = cells[wrong][:, _FLIP[order]]
    return int(wrong.sum())


# --- gmsh session ------------------------------------------------------------------------------

def _gmsh_initialized(gmsh) -> bool:
    if hasattr(gmsh, "isInitialized"):  # gmsh >= 4.9
        return bool(gmsh.isInitialized())
    # gmsh 4.8 has no isInitialized(): before the first initialize() API calls print an error
    # and return defaults (no models), after finalize() they raise; initialize() makes a model.
    # Keep the error message off the terminal.
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
            try:
                return len(gmsh.model.list()) > 0
            except Exception:
                return False
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@contextmanager
def _sigint_kept():
    """Put the SIGINT handler back as it was (main thread only): gmsh 4.8's module sets SIGINT
    to the system default when imported, and ``gmsh.finalize()`` sets it to whatever handler
    was there at that import, whatever the program has installed since. In a process that
    imported gmsh under another handler (the test suite's workers: a test's own), each mesh
    made later put that handler back, and a later test's Ctrl-C could find it instead of
    Python's (session 58: the likely cause of three fresh-cache suites in a row failing
    ``test_a_run_killed_while_its_outputs_are_made_leaves_a_state_to_resume``, its SIGINT
    not heard)."""
    import signal
    import threading

    main = threading.current_thread() is threading.main_thread()
    before = signal.getsignal(signal.SIGINT) if main else None
    try:
        yield
    finally:
        if before is not None:  # (None: a handler not installed from Python; left alone)
            signal.signal(signal.SIGINT, before)


@contextmanager
def _gmsh_model(name: str):
    """A fresh, quiet gmsh model. Initialise gmsh if needed and finalise it afterwards; if the
    caller had gmsh running, leave it running with its model and options as they were. The
    caller's SIGINT handler is kept through gmsh's import and finalisation
    (:func:`_sigint_kept`)."""
    with _sigint_kept():
        import gmsh

    started = not _gmsh_initialized(gmsh)
    if started:
        with _sigint_kept():
            gmsh.initialize(readConfigFiles=False)
        previous, saved = None, {}
    else:
        previous = gmsh.model.getCurrent()
        saved = {k: gmsh.option.getNumber(k) for k in _OPTIONS}
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add(f"mvfem_{name}")
        yield gmsh
    finally:
        if started:
            with _sigint_kept():
                gmsh.finalize()
        else:
            gmsh.model.remove()
            if previous:
                gmsh.model.setCurrent(previous)
            for k, v in saved.items():
                gmsh.option.setNumber(k, v)


_OPTIONS = ("General.Terminal", "Mesh.MeshSizeMin", "Mesh.MeshSizeMax", "Mesh.MeshSizeFromPoints",
            "Mesh.MeshSizeExtendFromBoundary", "Mesh.Algorithm")


def _set_options(gmsh, options: dict) -> None:
    for k, v in options.items():
        gmsh.option.setNumber(k, v)
