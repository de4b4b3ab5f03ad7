"""Structured triangulations of flat patches, for verification (no gmsh needed)."""

from __future__ import annotations

import numpy as np

__all__ = ["square_patch"]


def square_patch(comm, n: int = 4, size: float = 1.0, frame: np.ndarray | None = None,
                 diagonal: str = "alternate"):
    """A square membrane of ``n x n`` cells split into triangles, lying in a plane in 3-D.

    Args:
        comm: MPI communicator; the mesh is built on rank 0 and distributed.
        n: cells per side.
        size: side length, mm.
        frame: orthonormal 3x3 matrix whose first two columns span the plane (identity: xy).
        diagonal: "right", "left" or "alternate" (crossed pattern, no preferred direction).

    Returns:
        A dolfinx mesh (tdim 2, gdim 3) of the square ``[0, size]^2`` in the frame's plane.
    """
    import ufl
    from dolfinx import mesh

    Q = np.eye(3) if frame is None else np.asarray(frame, dtype=float)
    if comm.rank == 0:
        s = np.linspace(0.0, size, n + 1)
        X, Y = np.meshgrid(s, s, indexing="xy")
        points = np.column_stack([X.ravel(), Y.ravel()]) @ Q[:, :2].T
        cells = []
        for j in range(n):
            for i in range(n):
                v0, v1 = j * (n + 1) + i, j * (n + 1) + i + 1
                v2, v3 = v0 + n + 1, v1 + n + 1
                flip = diagonal == "left" or (diagonal == "alternate" and (i + j) % 2)
                cells += [[v0, v1, v3], [v0, v3, v2]] if not flip else [[v0, v1, v2], [v1, v3, v2]]
        cells = np.array(cells, dtype=np.int64)
    else:
        points = np.zeros((0, 3))
        cells = np.zeros((0, 3), dtype=np.int64)
    cell = ufl.Cell("triangle", geometric_dimension=3)
    domain = ufl.Mesh(ufl.VectorElement("Lagrange", cell, 1))
    return mesh.create_mesh(comm, cells, points, domain)
