"""A sphere from a refined octahedron: structured, with nodes on the three axes.

Unlike the gmsh :func:`~mvfem.meshes.sphere`, the octasphere has nodes at ``(+-R, 0, 0)``,
``(0, +-R, 0)`` and ``(0, 0, +-R)`` exactly, where rigid-body pins can sit without changing a
uniform inflation, and its refinement levels are nested, which makes clean convergence studies.
"""

from __future__ import annotations

import numpy as np

from .generators import SurfaceMesh
from .io import _raise_from_root, mesh_from_arrays
from .refine import split

__all__ = ["octasphere", "octasphere_arrays"]

_OCTAHEDRON_POINTS = np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0],
                               [0.0, -1.0, 0.0], [0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
# each face (x, y, z) with one vertex per axis, counter-clockwise seen from outside
_OCTAHEDRON_CELLS = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                              [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])


def octasphere_arrays(radius: float = 10.0, refinements: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Points and outward-oriented triangles of the octasphere (plain numpy, no MPI).

    Each refinement splits every triangle into four at its edge midpoints, and the new
    midpoints are projected radially onto the sphere (so every node lies on it). Level ``n``
    has ``8 * 4^n`` triangles and ``4^(n+1) + 2`` nodes; edge lengths run from
    ``(pi/2) R / 2^n`` (along the octahedron's edges) to about 1.5 times that.

    Args:
        radius: sphere radius ``R``, mm, centred at the origin.
        refinements: number of 1-to-4 subdivisions of the octahedron (>= 0).

    Returns:
        ``(points, cells)``: (N, 3) float64 and (M, 3) int64, with
        ``cross(x1 - x0, x2 - x0)`` pointing away from the centre in every cell.
    """
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius}")
    if isinstance(refinements, bool) or int(refinements) != refinements or refinements < 0:
        raise ValueError(f"refinements must be a non-negative integer, got {refinements!r}")
    points = _OCTAHEDRON_POINTS.copy()
    cells = _OCTAHEDRON_CELLS.copy()
    for _ in range(int(refinements)):
        points, cells = _split(points, cells)
    # outward orientation (the construction keeps it; enforced here for safety)
    x0, x1, x2 = (points[cells[:, i]] for i in range(3))
    wrong = np.einsum("ij,ij->i", np.cross(x1 - x0, x2 - x0), x0 + x1 + x2) < 0
    cells[wrong] = cells[wrong][:, [0, 2, 1]]
    # the octahedron's vertices stay exact unit vectors: nodes at +-R on each axis exactly
    return float(radius) * points, cells


def _split(points: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """One 1-to-4 subdivision on the unit sphere; shared edges get one midpoint."""
    edges, new = split(cells, len(points))
    mid = points[edges[:, 0]] + points[edges[:, 1]]
    mid /= np.linalg.norm(mid, axis=1)[:, None]
    return np.concatenate([points, mid]), new


def octasphere(comm, *, radius: float = 10.0, refinements: int = 3) -> SurfaceMesh:
    """A closed sphere centred at the origin, from an octahedron refined ``refinements`` times.

    Built on rank 0 (:func:`octasphere_arrays`) and distributed over ``comm``.

    Args:
        comm: MPI communicator.
        radius: sphere radius, mm.
        refinements: 1-to-4 subdivisions of each octahedron face (level n: ``8 * 4^n`` cells,
            edges of ``(pi/2) radius / 2^n`` to about 1.5 times that).

    Returns:
        Cells tagged ``"membrane"``; no edges tagged (the sphere has no boundary). Nodes at
        ``(+-R, 0, 0)``, ``(0, +-R, 0)``, ``(0, 0, +-R)`` exactly; cross(dX/dxi1, dX/dxi2)
        points away from the centre in every cell.
    """
    points = cells = values = err = None
    if comm.rank == 0:
        try:
            points, cells = octasphere_arrays(radius, refinements)
            values = np.ones(len(cells), dtype=np.int32)
        except (ValueError, TypeError) as exc:
            err = exc
    _raise_from_root(comm, err)
    msh, cell_tags, _ = mesh_from_arrays(comm, points, cells, values)
    info = {"generator": "octasphere", "radius": float(radius), "refinements": int(refinements)}
    return SurfaceMesh(mesh=msh, cell_tags=cell_tags, facet_tags=None, names={"membrane": 1},
                       info=info)
